"""Stage-1 training: losses, the optimisation loop, checkpoints and resume (§3.1-3.2, §3.5).

Loss (Eq. 8-12): L = L1 colour + w_eik (|grad f| - 1)^2 + w_smooth |log s(x) - log s(x + n)|
+ w_normal |n(x) - grad f / |grad f||, n ~ N(0, eps^2), grad f by central differences.
The regularisers are evaluated on a subset of the ray samples plus uniform points in the box.

Determinism: every step draws its randomness from a generator seeded with (seed, step), so a run
killed and resumed from a checkpoint retraces the uninterrupted run exactly (on the CPU).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from shells.cameras import subpixel_offsets
from shells.config import Config, TrainConfig
from shells.datasets import Dataset, load_dataset
from shells.errors import InputError, atomic_write, read_json, write_json
from shells.fields.hashgrid import HashGrid
from shells.fields.network import ShellField
from shells.metrics import psnr
from shells.render.volume import render_image, render_rays
from shells.run import RunDir

REG_POINTS = 4096  # points per step for the Eikonal, normal and smoothness terms


# ---------------------------------------------------------------------------------------------
# Field, optimiser, schedule
# ---------------------------------------------------------------------------------------------

def build_field(cfg: Config, aabb: torch.Tensor, device: torch.device) -> ShellField:
    torch.manual_seed(cfg.train.seed)
    return ShellField(cfg.field, aabb.to(device)).to(device)


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


def set_lr(opt: torch.optim.Optimizer, factor: float) -> None:
    for g in opt.param_groups:
        g["lr"] = g["base_lr"] * factor


def step_generator(seed: int, step: int, device: torch.device) -> torch.Generator:
    return torch.Generator(device=device).manual_seed(seed * 1_000_003 + step)


# ---------------------------------------------------------------------------------------------
# Losses
# ---------------------------------------------------------------------------------------------

def regularisers(field: ShellField,
                 points: torch.Tensor,  # [M, 3] world points
                 fd_eps: float,
                 smooth_eps: float,
                 gen: torch.Generator,
                 ) -> dict[str, torch.Tensor]:
    """Eikonal (Eq. 10), kernel smoothness (Eq. 11) and normal (Eq. 12) terms on `points`."""
    grad = field.sdf_gradient_fd(points, fd_eps)  # [M, 3]
    gnorm = grad.norm(dim=-1)
    eikonal = ((gnorm - 1.0) ** 2).mean()
    geo = field.geometry(points)
    target = grad.detach() / gnorm.detach().clamp_min(1e-6)[:, None]
    normal = (geo["normal"] - target).norm(dim=-1).mean()
    noise = torch.randn(points.shape, generator=gen, device=points.device) * smooth_eps
    s_near = field.kernel(points + noise)
    smooth = (torch.log(geo["s"]) - torch.log(s_near)).abs().mean()
    return {"eikonal": eikonal, "normal": normal, "smooth": smooth}


def reg_points(field: ShellField, ray_points: torch.Tensor, n: int,
               gen: torch.Generator) -> torch.Tensor:
    """Half from the ray samples (where the image loss acts), half uniform in the box."""
    flat = ray_points.detach().reshape(-1, 3)
    pick = torch.randint(0, flat.shape[0], (n // 2,), generator=gen, device=flat.device)
    lo, hi = field.aabb[0], field.aabb[1]
    uni = lo + (hi - lo) * torch.rand(n - n // 2, 3, generator=gen, device=flat.device)
    return torch.cat([flat[pick], uni])


def sample_pixel_rays(data: Dataset, batch_rays: int, spp: int, gen: torch.Generator,
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A random batch of training pixels and their rays: ``batch_rays // spp`` pixels (flat
    indices [P] into the split's images) with ``spp`` jittered sub-pixel rays each
    (origins, unit directions [P * spp, 3] on the CPU, a pixel's rays contiguous)."""
    n_views, H, W = data.images.shape[:3]
    n = max(1, batch_rays // spp)
    idx = torch.randint(0, n_views * H * W, (n,), generator=gen, device=gen.device)
    cam, rem = idx // (H * W), idx % (H * W)
    # one ray stays at the pixel centre, drawing no random numbers (runs made before spp
    # existed are reproduced bit for bit)
    off = subpixel_offsets(spp, gen if spp > 1 else None, n, device=idx.device)  # [P, spp, 2]
    px = ((rem % W).float()[:, None] + off[..., 0]).reshape(-1)
    py = ((rem // W).float()[:, None] + off[..., 1]).reshape(-1)
    cam = cam[:, None].expand(n, spp).reshape(-1)
    o, d = data.cameras.rays(cam.cpu(), px.cpu(), py.cpu())
    return idx, o, d


def train_step(field: ShellField, opt: torch.optim.Optimizer, data: Dataset,
               pixels: torch.Tensor, tc: TrainConfig, step: int,
               background: torch.Tensor) -> dict[str, float]:
    """One optimisation step on a random batch of pixels; returns scalar logs."""
    device = pixels.device
    gen = step_generator(tc.seed, step, device)
    spp = tc.pixel_samples
    idx, o, d = sample_pixel_rays(data, tc.batch_rays, spp, gen)
    o, d = o.to(device), d.to(device)
    target = pixels[idx]
    out = render_rays(field, o, d, tc.n_samples, tc.n_importance, background, gen)
    pred = out["color"].reshape(len(idx), spp, 3).mean(1)  # box filter
    color = (pred - target).abs().mean()
    reg = regularisers(field, reg_points(field, out["points"], REG_POINTS, gen),
                       tc.fd_eps, tc.smooth_eps, gen)
    loss = (color + tc.eikonal_weight * reg["eikonal"] + tc.kernel_smooth_weight * reg["smooth"]
            + tc.normal_weight * reg["normal"])
    set_lr(opt, lr_factor(step, tc.iters, tc.warmup_iters, tc.lr_final_factor))
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    with torch.no_grad():
        mse = ((pred.clamp(0, 1) - target) ** 2).mean().item()
    return {"loss": loss.item(), "color_l1": color.item(),
            "eikonal": reg["eikonal"].item(), "normal": reg["normal"].item(),
            "smooth": reg["smooth"].item(), "psnr": -10.0 * math.log10(max(mse, 1e-10))}


# ---------------------------------------------------------------------------------------------
# Checkpoints
# ---------------------------------------------------------------------------------------------

def save_checkpoint(path: Path, field: ShellField, opt: torch.optim.Optimizer, step: int,
                    cfg: Config, extra: dict[str, Any] | None = None) -> None:
    state = {"step": step, "field": field.state_dict(), "optimizer": opt.state_dict(),
             "config": cfg.to_dict(), "aabb": field.aabb.detach().cpu(), **(extra or {})}
    atomic_write(path, lambda p: torch.save(state, p))


def read_checkpoint(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise InputError(f"{path}: no checkpoint; run shells-train first (or pass the right RUN)")
    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # corrupt or foreign file
        raise InputError(f"{path}: unreadable checkpoint ({type(exc).__name__}); retrain")


def load_field(run_dir: str | Path, device: str | torch.device = "cpu",
               stage: str = "latest") -> tuple[ShellField, Config]:
    """The trained field of a run: stage 'stage1', 'stage2' or 'latest' (stage 2 if present)."""
    run = RunDir(run_dir)
    if stage not in ("latest", "stage1", "stage2"):
        raise InputError(f"stage '{stage}': expected latest, stage1 or stage2")
    path = run.checkpoint
    if stage == "stage2" or (stage == "latest" and run.finetune_checkpoint.is_file()):
        path = run.finetune_checkpoint
    ckpt = read_checkpoint(path)
    cfg = Config.from_dict(ckpt["config"], str(path))
    field = ShellField(cfg.field, ckpt["aabb"]).to(device)
    field.load_state_dict(ckpt["field"])
    field.eval()
    return field, cfg


# ---------------------------------------------------------------------------------------------
# Evaluation and the loop
# ---------------------------------------------------------------------------------------------

def evaluate(field: ShellField, data: Dataset, tc: TrainConfig, max_views: int = 0,
             device: torch.device | None = None) -> dict[str, Any]:
    """Full-ray test PSNR (deterministic sample placement) over the views of `data`."""
    device = device or field.aabb.device
    bg = torch.tensor(data.background, device=device)
    n = len(data.cameras) if max_views <= 0 else min(max_views, len(data.cameras))
    scores = []
    for i in range(n):
        o, d = data.cameras.pixel_rays(i, tc.pixel_samples)
        img = render_image(field, o.to(device), d.to(device), tc.n_samples, tc.n_importance, bg)
        pred = img["color"].reshape(-1, tc.pixel_samples, 3).mean(1)  # box filter
        pred = pred.reshape(data.images.shape[1:]).cpu()
        scores.append(psnr(pred.numpy(), data.images[i].numpy()))
    return {"psnr": float(sum(scores) / len(scores)), "psnr_per_view": scores, "n_views": n}


def train(data_dir: str | Path, run_dir: str | Path, cfg: Config, device: torch.device,
          downscale: int = 1, resume: bool = False, progress: bool = True,
          stop_at: int | None = None, evaluate_test: bool = True,
          iters: int | None = None) -> dict[str, Any]:
    """Stage-1 training. On resume, the run's saved config is used (`iters` may extend it).

    `stop_at` ends early after that step (used to test kill/resume).
    """
    run = RunDir(run_dir)
    if resume:
        meta = read_json(run.run_json, "run description (run.json)")
        data_dir, downscale = meta["data"], meta["downscale"]
        ckpt = read_checkpoint(run.checkpoint)
        cfg = Config.from_dict(ckpt["config"], str(run.checkpoint))
        if ckpt["step"] >= (iters or cfg.train.iters):
            raise InputError(f"{run.checkpoint}: already trained {ckpt['step']} steps; pass a "
                             f"larger --iters to continue")
    elif run.checkpoint.exists():
        raise InputError(f"{run.checkpoint}: the run already has a checkpoint; pass --resume to "
                         f"continue it or choose another --out")
    subpixel_offsets(cfg.train.pixel_samples)  # a non-square count fails here, before any write
    data = load_dataset(data_dir, "train", downscale=downscale, background=cfg.train.background)
    tc = cfg.train
    if iters is not None:
        tc.iters = iters
    field = build_field(cfg, data.aabb, device)
    opt = make_optimizer(field, tc.lr, tc.lr_mlp)
    start = 0
    if resume:
        field.load_state_dict(ckpt["field"])
        opt.load_state_dict(ckpt["optimizer"])
        start = ckpt["step"]
        _truncate_log(run.train_log, start)
    else:
        run.root.mkdir(parents=True, exist_ok=True)
        write_json(run.run_json, {"data": str(Path(data_dir).resolve()), "downscale": downscale,
                                  "device": str(device)})
        write_json(run.config, cfg.to_dict())
    pixels = data.images.reshape(-1, 3).to(device)
    background = torch.tensor(tc.background, device=device, dtype=torch.float32)
    end = tc.iters if stop_at is None else min(stop_at, tc.iters)
    bar = tqdm(total=tc.iters, initial=start, disable=not progress, desc="stage 1",
               unit="step", dynamic_ncols=True)
    t0, last = time.perf_counter(), None
    field.train()
    for step in range(start, end):
        last = train_step(field, opt, data, pixels, tc, step, background)
        done = step + 1
        rays_s = tc.batch_rays * (done - start) / (time.perf_counter() - t0)
        bar.update(1)
        bar.set_postfix(loss=f"{last['loss']:.4f}", psnr=f"{last['psnr']:.2f}",
                        rays_s=f"{rays_s:.0f}")
        if done % tc.log_every == 0 or done == end:
            _append_log(run.train_log, {"step": done, **last, "rays_per_s": rays_s,
                                        "elapsed_s": time.perf_counter() - t0})
        if done % tc.checkpoint_every == 0 or done == end:
            save_checkpoint(run.checkpoint, field, opt, done, cfg)
    bar.close()
    summary: dict[str, Any] = {"step": end, "train_seconds": time.perf_counter() - t0,
                               "last": last}
    if evaluate_test and end == tc.iters:
        field.eval()
        try:
            test = load_dataset(data_dir, "test", downscale=downscale, background=tc.background)
        except InputError:
            test = None  # a data set without a test split: nothing to score
        if test is not None:
            summary["test"] = evaluate(field, test, tc, tc.eval_max_views, device)
        write_json(run.root / "train_summary.json", summary)
    return summary


def _append_log(path: Path, record: dict[str, Any]) -> None:
    with open(path, "a") as fh:
        fh.write(json.dumps(record) + "\n")


def _truncate_log(path: Path, step: int) -> None:
    """Drop log records past the checkpoint being resumed (they will be redone)."""
    if not path.is_file():
        return
    keep = [ln for ln in path.read_text().splitlines()
            if ln.strip() and json.loads(ln).get("step", 0) <= step]
    atomic_write(path, lambda p: p.write_text("".join(k + "\n" for k in keep)))
