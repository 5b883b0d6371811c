"""The optimisation loop every training stage runs (stage 1, stage 2, and any later stage).

A stage supplies its field, an Adam optimiser (`shells.train.optim.make_optimizer`), its
schedule and a shard loss
``shard_loss(gen) -> (loss, logs)`` that draws ``batch_rays / shards`` rays with the generator
it is given and returns their loss tensor and scalar logs (``loss`` and ``psnr`` at least). The
loop owns the rest, the same way for every stage:

* learning rate: linear warm-up over ``warmup`` steps, then cosine decay to ``final`` x the base
  rate of each parameter group (`lr_factor`);
* randomness: a step's rays come in ``shards`` shards; shard k of step t draws from a generator
  seeded with (seed, t, k) on the training device, so a run killed and resumed from a
  checkpoint retraces the uninterrupted run exactly, and the rays of a step do not depend on
  how many processes share them;
* data parallel (torchrun, `shells.distributed`): rank r of N computes shards r, r + N, ...;
  DistributedDataParallel averages the gradients, so N ranks and one process give the same
  step up to float rounding (one process computes the mean of the shard losses itself);
  rank 0 alone shows progress and writes logs and checkpoints;
* exact resume: from a checkpoint dict (field, optimiser, step), with any N dividing
  ``shards``; log records past it dropped;
* tqdm progress (loss, psnr, rays/s), a JSON-lines record every ``log_every`` steps and at the
  end, an atomic checkpoint every ``checkpoint_every`` steps and at the end;
* the summary: steps, seconds, rays/s and the last record.

A step whose loss has no gradient on any rank (stage 2: every ray of the batch missed the band)
changes nothing but is logged and counted.
"""

from __future__ import annotations

import contextlib
import inspect
import math
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import torch

from shells import distributed
from shells.config import COLOR_LOSSES, Config
from shells.errors import InputError, Interrupted
from shells.fields.network import ShellField
from shells.progress import tqdm
from shells.run import append_log, load_field_state, save_checkpoint, truncate_log

ShardLoss = Callable[[torch.Generator], tuple[torch.Tensor, dict[str, float]]]


@dataclass
class Schedule:
    """What the loop needs to know of a stage's config section (TrainConfig, FinetuneConfig)."""

    name: str  # progress-bar label, e.g. "stage 1"
    iters: int  # last step of the schedule
    warmup: int  # linear warm-up steps
    final: float  # learning-rate factor at the last step
    seed: int  # generator seed of every step
    rays_per_step: int  # for the rays/s figure
    checkpoint_every: int
    log_every: int
    shards: int = 1  # the step's rays come in this many independently drawn shards

    @classmethod
    def of(cls, name: str, section: Any) -> "Schedule":
        return cls(name=name, iters=section.iters, warmup=section.warmup_iters,
                   final=section.lr_final_factor, seed=section.seed,
                   rays_per_step=section.batch_rays, checkpoint_every=section.checkpoint_every,
                   log_every=section.log_every, shards=section.shards)


def lr_factor(step: int, iters: int, warmup: int, final: float) -> float:
    """Linear warm-up over `warmup` steps, then cosine decay from 1 to `final`."""
    if step < warmup:
        return (step + 1) / warmup
    p = min(1.0, (step - warmup) / max(1, iters - warmup))
    return final + (1.0 - final) * 0.5 * (1.0 + math.cos(math.pi * p))


def step_generator(seed: int, step: int, device: torch.device,
                   shard: int = 0) -> torch.Generator:
    """The generator of shard ``shard`` of step ``step`` (shard 0: the stream of runs made
    before shards existed).

    The CPU generator (mt19937) keeps only the low 32 bits of its seed, so the shards must
    differ there: shard k adds k x SHARD_STRIDE, an odd constant whose multiples (mod 2^32) lie
    far from every step offset a run reaches (shard k of step t would meet shard 0 of step
    t + k x SHARD_STRIDE mod 2^32, a billion steps away for k = 1, 2; nearly 2 million for
    k < 1024). A stride of 2^32 or a multiple of it (e.g. 2^40) would be dropped on the CPU, and
    the shards of a step would draw the same rays."""
    return torch.Generator(device=device).manual_seed(seed * 1_000_003 + step
                                                      + shard * SHARD_STRIDE)


SHARD_STRIDE = 0x9E3779B1  # 2^32 / golden ratio, odd: `step_generator`


def psnr_of(mse: float) -> float:
    return -10.0 * math.log10(max(mse, 1e-10))


def color_loss(pred: torch.Tensor, target: torch.Tensor, kind: str) -> torch.Tensor:
    """The colour term of a stage's loss over [N, 3] pixels: "l1" the mean |pred - target|
    (NeuS), "l2" the mean squared error (Instant-NGP; what PSNR scores), "rmse" its square
    root (a pixel pulls in proportion to its error, as under "l2", with the overall size of
    "l1": mean |e| / rms(e) <= 1)."""
    diff = pred - target
    if kind == "l1":
        return diff.abs().mean()
    if kind == "l2":
        return (diff * diff).mean()
    if kind == "rmse":
        return torch.sqrt((diff * diff).mean() + 1e-12)
    raise ValueError(f"unknown colour loss {kind!r}; valid: {COLOR_LOSSES}")


def join(cfg: Config, section: str, fresh: bool, device: torch.device) -> distributed.World:
    """This process's place in the job (`shells.distributed.world`) for the stage whose config
    section is ``section`` ("train", "finetune"): a fresh run under torchrun with the default
    single shard takes one shard per process (stored in ``cfg``); N processes must divide the
    shards. Call it before the stage writes anything."""
    w = distributed.world(device)
    if fresh and w.size > 1 and getattr(cfg, section).shards == 1:
        cfg.update({section: {"shards": w.size}}, f"torchrun ({w.size} processes)")
    _check_shards({"train": "stage 1", "finetune": "stage 2"}.get(section, section),
                  getattr(cfg, section).shards, w)
    return w


def _check_shards(name: str, shards: int, w: distributed.World) -> None:
    if shards % w.size:
        raise InputError(f"{name}: {shards} ray shards per step cannot be shared by {w.size} "
                         f"processes; run a number of processes that divides it")


class _Shard(torch.nn.Module):
    """One shard's loss as a module: what DistributedDataParallel wraps (its forward is the
    shard loss; the field's parameters are its parameters)."""

    def __init__(self, field: ShellField, shard_loss: ShardLoss) -> None:
        super().__init__()
        self.field = field
        self.shard_loss = shard_loss

    def forward(self, gen: torch.Generator) -> tuple[torch.Tensor, dict[str, float]]:
        return self.shard_loss(gen)


def optimise(field: ShellField, opt: torch.optim.Optimizer, cfg: Config, sched: Schedule,
             shard_loss: ShardLoss,
             checkpoint: Path,  # where the stage's checkpoint goes
             log: Path,  # the stage's JSON-lines log
             device: torch.device,
             resume: dict[str, Any] | None = None,  # checkpoint dict to continue from
             stop_at: int | None = None,  # end after this step (kill/resume tests)
             progress: bool = True,
             before_step: Callable[[int], None] | None = None,
             state: Any = None,
             after_step: Callable[[int, float], None] | None = None,
             ) -> dict[str, Any]:
    """Run steps [start, end) of the schedule; returns the summary (step, seconds, wall_s,
    rays_per_s, samples_per_s, last, finished). ``cfg`` is what the checkpoints store with the
    field. ``seconds`` is this sitting's time, ``wall_s`` the stage's over all its sittings
    (kept in the checkpoints; up to the checkpoint a sitting resumed from).

    ``before_step(k)`` runs on every rank before step k's shards (a stage's schedule of its
    own, e.g. rebuilding an occupancy grid); ``state`` (an object with ``state_dict`` /
    ``load_state_dict``, e.g. that grid) is stored in the checkpoints and restored on resume.
    A shard's logs may report ``rays`` and ``samples`` it used (else ``rays_per_step`` /
    ``shards`` rays are counted). ``after_step(k, wall_s)`` runs on every rank after step k's
    update (k counted from 1)."""
    w = distributed.world(device)
    _check_shards(sched.name, sched.shards, w)
    start, wall0 = 0, 0.0
    if resume is not None:
        start, wall0 = int(resume["step"]), float(resume.get("wall_s", 0.0))
        if start >= sched.iters:
            raise InputError(f"{checkpoint}: already trained {start} steps; pass a larger "
                             f"--iters to continue")
        load_field_state(field, resume["field"], str(checkpoint))
        fresh_kernels = [{"fused": g["fused"], "foreach": g["foreach"]} for g in opt.param_groups]
        try:
            opt.load_state_dict(resume["optimizer"])
        except (ValueError, KeyError) as exc:
            raise InputError(f"{checkpoint}: the optimiser state does not fit the field ({exc});"
                             " the checkpoint is of another architecture: re-train") from None
        # the kernel make_optimizer chose, not the saved one (runs saved before fused Adam)
        for g, kernel in zip(opt.param_groups, fresh_kernels):
            g.update(kernel)
        if state is not None and resume.get("extra") is not None:
            state.load_state_dict(resume["extra"])
    if w.main:  # records past the checkpoint (or of an attempt stopped before the first one)
        truncate_log(log, start)
    mine = list(range(w.rank, sched.shards, w.size))  # this rank's shards
    shard = _Shard(field, shard_loss)
    model: torch.nn.Module = shard
    if w.size > 1:
        from torch.nn.parallel import DistributedDataParallel

        # the field's buffers (box, grid constants) are equal on every rank: no sync per step
        params = inspect.signature(DistributedDataParallel.__init__).parameters
        quiet = ({"forward_sync_buffers": False} if "forward_sync_buffers" in params
                 else {"broadcast_buffers": False})
        model = DistributedDataParallel(
            shard, device_ids=[device.index] if device.type == "cuda" else None, **quiet)
    end = sched.iters if stop_at is None else min(stop_at, sched.iters)
    bar = tqdm(total=sched.iters, initial=start, disable=not (progress and w.main),
               desc=sched.name, unit="step", dynamic_ncols=True)
    t0, last, rays_s, saved = time.perf_counter(), None, 0.0, start
    rays, samples = 0.0, 0.0
    field.train()
    k = start
    try:
        for k in range(start, end):
            if before_step is not None:
                before_step(k)
            gens = [step_generator(sched.seed, k, device, j) for j in mine]
            factor = lr_factor(k, sched.iters, sched.warmup, sched.final)
            for g in opt.param_groups:
                g["lr"] = g["base_lr"] * factor
            opt.zero_grad(set_to_none=True)
            last, any_grad = _accumulate(model, gens, field, w.size > 1)
            if distributed.any_rank(any_grad, device):
                opt.step()
            last = distributed.mean_of(last, device)
            done = k + 1
            elapsed = time.perf_counter() - t0
            rays += last["rays"] * sched.shards if "rays" in last else sched.rays_per_step
            samples += last.get("samples", 0.0) * sched.shards
            rays_s = rays / elapsed
            bar.update(1)
            bar.set_postfix(loss=f"{last['loss']:.4f}", psnr=f"{last['psnr']:.2f}",
                            rays_s=f"{rays_s:.0f}")
            if after_step is not None:
                after_step(done, wall0 + time.perf_counter() - t0)
            if w.main and (done % sched.log_every == 0 or done == end):
                rec = {"step": done, **last, "rays_per_s": rays_s, "elapsed_s": elapsed,
                       "wall_s": wall0 + elapsed}
                if samples:
                    rec["samples_per_s"] = samples / elapsed
                append_log(log, rec)
            if done % sched.checkpoint_every == 0 or done == end:
                if w.main:
                    save_checkpoint(checkpoint, field, opt, done, cfg,
                                    None if state is None else state.state_dict(),
                                    wall0 + time.perf_counter() - t0)
                saved = done
    except KeyboardInterrupt:
        raise Interrupted(f"{sched.name} interrupted at step {k + 1}; {_intact(checkpoint, saved)}",
                          status=130) from None
    except RuntimeError as exc:
        if w.size == 1:
            raise
        why = re.sub(r"^\[[^\]]*\]\s*", "", str(exc).splitlines()[0] if str(exc) else "")
        why = why.split(". ")[0][:80] or type(exc).__name__
        raise Interrupted(f"{sched.name}: rank {w.rank} of {w.size} lost the other processes at "
                          f"step {k + 1} ({why}); {_intact(checkpoint, saved)}") from None
    finally:
        bar.close()
    field.eval()
    seconds = time.perf_counter() - t0
    summary = {"step": end, "seconds": seconds, "wall_s": wall0 + seconds, "rays_per_s": rays_s,
               "last": last, "finished": end == sched.iters}
    if samples:
        summary["samples_per_s"] = samples / max(seconds, 1e-9)
    return summary


def _accumulate(model: torch.nn.Module, gens: list[torch.Generator], field: ShellField,
                ddp: bool) -> tuple[dict[str, float], bool]:
    """Gradient of the mean loss of this rank's shards, one shard at a time (each shard's loss
    scaled by 1 / shards-per-rank and back-propagated at once: the sum in the gradients is the
    same, term for term, as DistributedDataParallel's sum over ranks). Returns the mean logs and
    whether any shard had a gradient.

    Under DDP every shard back-propagates (a shard without gradient adds zeros) so that all
    ranks take part in the gradient all-reduce; only the last shard synchronises."""
    logs: list[dict[str, float]] = []
    any_grad = False
    for i, gen in enumerate(gens):
        last = i == len(gens) - 1
        sync = model.no_sync() if ddp and not last else contextlib.nullcontext()
        with sync:
            loss, rec = model(gen)
            logs.append(rec)
            any_grad |= loss.requires_grad
            if not loss.requires_grad:
                if not ddp:
                    continue
                loss = loss + sum(p.reshape(-1)[0] * 0.0 for p in field.parameters())
            (loss if len(gens) == 1 else loss / len(gens)).backward()
    if len(logs) == 1:
        return logs[0], any_grad
    return {k: sum(r[k] for r in logs) / len(logs) for k in logs[0]}, any_grad


def _intact(checkpoint: Path, step: int) -> str:
    if step == 0:
        return "no checkpoint was written yet; start again"
    return f"the checkpoint of step {step} ({checkpoint}) is intact; continue with --resume"
