"""The optimisation loop every training stage runs (stage 1, stage 2, and any later stage).

A stage supplies its field, an Adam optimiser (`make_optimizer`), its schedule and a step
function ``step(gen) -> (loss, logs)`` that draws a batch with the step's generator and returns
the loss tensor and scalar logs (``loss`` and ``psnr`` at least). The loop owns the rest, the
same way for every stage:

* learning rate: linear warm-up over ``warmup`` steps, then cosine decay to ``final`` x the base
  rate of each parameter group (`lr_factor`);
* randomness: step k draws from a generator seeded with (seed, k) on the training device, so a
  run killed and resumed from a checkpoint retraces the uninterrupted run exactly;
* exact resume: from a checkpoint dict (field, optimiser, step); log records past it dropped;
* tqdm progress (loss, psnr, rays/s), a JSON-lines record every ``log_every`` steps and at the
  end, an atomic checkpoint every ``checkpoint_every`` steps and at the end;
* the summary: steps, seconds, rays/s and the last record.

A step whose loss has no gradient (stage 2: every ray of the batch missed the band) changes
nothing but is logged and counted.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import torch
from tqdm.auto import tqdm

from shells.config import Config
from shells.errors import InputError
from shells.fields.hashgrid import HashGrid
from shells.fields.network import ShellField
from shells.run import append_log, save_checkpoint, truncate_log

StepFn = Callable[[torch.Generator], tuple[torch.Tensor, dict[str, float]]]


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

    @classmethod
    def of(cls, name: str, section: Any) -> "Schedule":
        return cls(name=name, iters=section.iters, warmup=section.warmup_iters,
                   final=section.lr_final_factor, seed=section.seed,
                   rays_per_step=section.batch_rays, checkpoint_every=section.checkpoint_every,
                   log_every=section.log_every)


def make_optimizer(field: ShellField, lr_grid: float, lr_mlp: float) -> torch.optim.Adam:
    """Adam with two groups: hash tables (high lr, as Instant-NGP) and MLP weights."""
    grid_ids = {id(p) for m in field.modules() if isinstance(m, HashGrid) for p in m.parameters()}
    grid = [p for p in field.parameters() if id(p) in grid_ids]
    mlp = [p for p in field.parameters() if id(p) not in grid_ids]
    return torch.optim.Adam([{"params": grid, "lr": lr_grid, "base_lr": lr_grid},
                             {"params": mlp, "lr": lr_mlp, "base_lr": lr_mlp}],
                            betas=(0.9, 0.99), eps=1e-15)


def lr_factor(step: int, iters: int, warmup: int, final: float) -> float:
    """Linear warm-up over `warmup` steps, then cosine decay from 1 to `final`."""
    if step < warmup:
        return (step + 1) / warmup
    p = min(1.0, (step - warmup) / max(1, iters - warmup))
    return final + (1.0 - final) * 0.5 * (1.0 + math.cos(math.pi * p))


def step_generator(seed: int, step: int, device: torch.device) -> torch.Generator:
    return torch.Generator(device=device).manual_seed(seed * 1_000_003 + step)


def psnr_of(mse: float) -> float:
    return -10.0 * math.log10(max(mse, 1e-10))


def optimise(field: ShellField, opt: torch.optim.Optimizer, cfg: Config, sched: Schedule,
             step: StepFn,
             checkpoint: Path,  # where the stage's checkpoint goes
             log: Path,  # the stage's JSON-lines log
             device: torch.device,
             resume: dict[str, Any] | None = None,  # checkpoint dict to continue from
             stop_at: int | None = None,  # end after this step (kill/resume tests)
             progress: bool = True) -> dict[str, Any]:
    """Run steps [start, end) of the schedule; returns the summary (step, seconds, rays_per_s,
    last, finished). ``cfg`` is what the checkpoints store with the field."""
    start = 0
    if resume is not None:
        start = int(resume["step"])
        if start >= sched.iters:
            raise InputError(f"{checkpoint}: already trained {start} steps; pass a larger "
                             f"--iters to continue")
        field.load_state_dict(resume["field"])
        opt.load_state_dict(resume["optimizer"])
        truncate_log(log, start)
    end = sched.iters if stop_at is None else min(stop_at, sched.iters)
    bar = tqdm(total=sched.iters, initial=start, disable=not progress, desc=sched.name,
               unit="step", dynamic_ncols=True)
    t0, last, rays_s = time.perf_counter(), None, 0.0
    field.train()
    for k in range(start, end):
        gen = step_generator(sched.seed, k, device)
        factor = lr_factor(k, sched.iters, sched.warmup, sched.final)
        for g in opt.param_groups:
            g["lr"] = g["base_lr"] * factor
        opt.zero_grad(set_to_none=True)
        loss, last = step(gen)
        if loss.requires_grad:
            loss.backward()
            opt.step()
        done = k + 1
        elapsed = time.perf_counter() - t0
        rays_s = sched.rays_per_step * (done - start) / elapsed
        bar.update(1)
        bar.set_postfix(loss=f"{last['loss']:.4f}", psnr=f"{last['psnr']:.2f}",
                        rays_s=f"{rays_s:.0f}")
        if done % sched.log_every == 0 or done == end:
            append_log(log, {"step": done, **last, "rays_per_s": rays_s, "elapsed_s": elapsed})
        if done % sched.checkpoint_every == 0 or done == end:
            save_checkpoint(checkpoint, field, opt, done, cfg)
    bar.close()
    field.eval()
    return {"step": end, "seconds": time.perf_counter() - t0, "rays_per_s": rays_s,
            "last": last, "finished": end == sched.iters}
