"""Stage 1: the field trained by full-ray NeuS volume rendering and its losses (§3.1-3.2, §3.5).

Loss (Eq. 8-12): L = L1 colour + w_eik (|grad f| - 1)^2 + w_smooth |log s(x) - log s(x + n)|
+ w_normal |n(x) - grad f / |grad f||, n ~ N(0, eps^2), grad f by central differences.
The regularisers are evaluated on a subset of the ray samples plus uniform points in the box.

The steps run in `shells.loop.optimise` (schedule, progress, logs, checkpoints, exact resume);
the run directory is read and written through `shells.run`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from shells import distributed
from shells.config import Config, TrainConfig
from shells.datasets import Dataset, load_dataset
from shells.errors import InputError, write_json
from shells.fields.network import ShellField
from shells.loop import Schedule, join, make_optimizer, optimise, psnr_of
from shells.metrics import psnr
from shells.render.volume import render_volume_image, render_volume_rays
from shells.run import RunDir, read_checkpoint, read_run, write_run

REG_POINTS = 4096  # points per step for the Eikonal, normal and smoothness terms


def build_field(cfg: Config, aabb: torch.Tensor, device: torch.device) -> ShellField:
    torch.manual_seed(cfg.train.seed)
    return ShellField(cfg.field, aabb.to(device)).to(device)


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


def stage1_step(field: ShellField, data: Dataset, pixels: torch.Tensor, tc: TrainConfig,
                background: torch.Tensor, gen: torch.Generator,
                ) -> tuple[torch.Tensor, dict[str, float]]:
    """Loss of one shard of a step (``batch_rays / shards`` random rays drawn with ``gen``) and
    its scalar logs."""
    spp = tc.pixel_samples
    idx, o, d = data.sample_pixel_rays(tc.batch_rays // tc.shards, spp, gen)
    target = pixels[idx]
    out = render_volume_rays(field, o, d, tc.n_samples, tc.n_importance, background, gen)
    pred = out["color"].reshape(len(idx), spp, 3).mean(1)  # box filter
    color = (pred - target).abs().mean()
    reg = regularisers(field, reg_points(field, out["points"], REG_POINTS // tc.shards, gen),
                       tc.fd_eps, tc.smooth_eps, gen)
    loss = (color + tc.eikonal_weight * reg["eikonal"] + tc.kernel_smooth_weight * reg["smooth"]
            + tc.normal_weight * reg["normal"])
    with torch.no_grad():
        mse = ((pred.clamp(0, 1) - target) ** 2).mean().item()
    return loss, {"loss": loss.item(), "color_l1": color.item(),
                  "eikonal": reg["eikonal"].item(), "normal": reg["normal"].item(),
                  "smooth": reg["smooth"].item(), "psnr": psnr_of(mse)}


# ---------------------------------------------------------------------------------------------
# Evaluation and the stage
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
        img = render_volume_image(field, o.to(device), d.to(device), tc.n_samples,
                                  tc.n_importance, bg)
        pred = img["color"].reshape(-1, tc.pixel_samples, 3).mean(1)  # box filter
        pred = pred.reshape(data.images.shape[1:]).cpu()
        scores.append(psnr(pred.numpy(), data.images[i].numpy()))
    return {"psnr": float(sum(scores) / len(scores)), "psnr_per_view": scores, "n_views": n}


def train(data_dir: str | Path | None, run_dir: str | Path, cfg: Config, device: torch.device,
          downscale: int = 1, resume: bool = False, progress: bool = True,
          stop_at: int | None = None, evaluate_test: bool = True,
          iters: int | None = None) -> dict[str, Any]:
    """Stage-1 training. On resume, the run's saved config is used (`iters` may extend it).

    `stop_at` ends early after that step (used to test kill/resume).
    """
    run = RunDir(run_dir)
    ckpt = None
    if resume:
        meta = read_run(run)
        data_dir, downscale = meta["data"], int(meta["downscale"])
        ckpt = read_checkpoint(run, "stage1")
        cfg = Config.from_dict(ckpt["config"], str(run.checkpoint()))
    elif run.checkpoint().exists():
        raise InputError(f"{run.checkpoint()}: the run already has a checkpoint; pass --resume "
                         f"to continue it or choose another --out")
    if iters is not None:
        cfg.update({"train": {"iters": iters}}, "--iters")
    device = distributed.rank_device(device)
    w = join(cfg, "train", ckpt is None, device)  # before anything is written
    tc = cfg.train
    data = load_dataset(data_dir, "train", downscale=downscale, background=cfg.data.background)
    field = build_field(cfg, data.aabb, device)
    opt = make_optimizer(field, tc.lr, tc.lr_mlp)
    if ckpt is None and w.main:
        write_run(run, data_dir, downscale, str(device), cfg)
    pixels = data.images.reshape(-1, 3).to(device)
    background = torch.tensor(cfg.data.background, device=device, dtype=torch.float32)
    summary = optimise(field, opt, cfg, Schedule.of("stage 1", tc),
                       lambda gen: stage1_step(field, data, pixels, tc, background, gen),
                       run.checkpoint("stage1"), run.log("stage1"), device, resume=ckpt,
                       stop_at=stop_at, progress=progress)
    if summary["finished"] and evaluate_test and w.main:
        try:
            test = load_dataset(data_dir, "test", downscale=downscale,
                                background=cfg.data.background)
        except InputError:
            test = None  # a data set without a test split: nothing to score
        if test is not None:
            summary["test"] = evaluate(field, test, tc, tc.eval_max_views, device)
        write_json(run.summary("stage1"), summary)
    return summary
