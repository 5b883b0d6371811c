"""Stage 2: fine-tune the field inside the narrow band, colour loss only (§3.5, Procedure 4).

Rays are cast against the fixed shells and sampled with exactly the renderer's placement
(`shells.render.sampler.band_samples`, one implementation); the field is evaluated on the valid
samples only, composited with the same NeuS alpha, and trained with the L1 colour loss. The
checkpoint goes to RUN/finetune.pt (stage 1's checkpoint.pt is left untouched), with resume.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from shells.cameras import subpixel_offsets
from shells.config import FinetuneConfig, RenderConfig
from shells.datasets import Dataset, load_dataset
from shells.errors import InputError, read_json, write_json
from shells.fields.network import ShellField
from shells.fields.neus import composite, neus_alpha
from shells.render.raycast import ShellScene
from shells.render.sampler import band_samples
from shells.run import RunDir
from shells.training import (_append_log, _truncate_log, load_field, lr_factor, make_optimizer,
                             read_checkpoint, sample_pixel_rays, save_checkpoint, set_lr,
                             step_generator)


def render_band(field: ShellField, scene: ShellScene,
                origins: torch.Tensor,  # [R, 3]
                dirs: torch.Tensor,  # [R, 3] unit
                rc: RenderConfig,
                background: torch.Tensor,  # [3]
                ) -> dict[str, torch.Tensor]:
    """Differentiable torch rendering of rays with narrow-band samples: color [R, 3], spp [R]."""
    t, delta, mask, solid = band_samples(scene, origins, dirs, rc)  # [R, S] x 3, [R]
    t, delta, mask, solid = t.clone(), delta.clone(), mask.clone(), solid.clone()  # own them
    R, S = t.shape
    pts = origins[:, None] + t[..., None] * dirs[:, None]  # [R, S, 3]
    d = dirs[:, None].expand(R, S, 3)
    sdf = torch.zeros(R, S)
    s = torch.ones(R, S)
    cos = torch.zeros(R, S)
    rgb = torch.zeros(R, S, 3)
    if mask.any():
        out = field(pts[mask], d[mask])
        sdf = sdf.masked_scatter(mask, out["sdf"])
        s = s.masked_scatter(mask, out["s"])
        cos = cos.masked_scatter(mask, (out["normal"] * d[mask]).sum(-1))
        rgb = rgb.masked_scatter(mask[..., None].expand(R, S, 3), out["rgb"])
    alpha = neus_alpha(sdf, s, cos, delta) * mask
    # a ray that reached M- ends on its last sample (the renderer's solid_end_colour)
    last = rgb[torch.arange(R), (mask.sum(-1) - 1).clamp_min(0)]  # [R, 3]
    end = torch.where(solid[:, None], last, background.expand(R, 3))
    color, weights, opacity = composite(alpha, rgb, end)
    return {"color": color, "opacity": opacity, "spp": mask.sum(-1)}


def finetune_step(field: ShellField, opt: torch.optim.Optimizer, scene: ShellScene,
                  data: Dataset, pixels: torch.Tensor, fc: FinetuneConfig, rc: RenderConfig,
                  step: int, background: torch.Tensor) -> dict[str, float]:
    gen = step_generator(fc.seed, step, torch.device("cpu"))
    idx, o, d = sample_pixel_rays(data, fc.batch_rays, fc.pixel_samples, gen)
    out = render_band(field, scene, o, d, rc, background)
    pred = out["color"].reshape(len(idx), fc.pixel_samples, 3).mean(1)  # box filter
    target = pixels[idx]
    loss = (pred - target).abs().mean()
    set_lr(opt, lr_factor(step, fc.iters, 0, 0.1))
    opt.zero_grad(set_to_none=True)
    if loss.requires_grad:  # a batch of rays that all miss the band has nothing to train
        loss.backward()
        opt.step()
    mse = ((pred.detach().clamp(0, 1) - target) ** 2).mean().item()
    return {"loss": loss.item(), "psnr": -10.0 * torch.log10(torch.tensor(max(mse, 1e-10))).item(),
            "spp": out["spp"].float().mean().item() * fc.pixel_samples}  # samples per pixel


def finetune(run_dir: str | Path, iters: int | None = None, resume: bool = False,
             progress: bool = True, stop_at: int | None = None,
             config: str | Path | None = None) -> dict[str, Any]:
    """Stage-2 fine-tuning of a run that has a stage-1 checkpoint and shells (CPU).

    ``config``: a JSON file with ``finetune`` / ``render`` sections overriding the run's; the
    result is stored with the stage-2 checkpoint (and used by renders of stage 2).
    """
    from shells.config import override_config
    from shells.render.run import load_shells

    run = RunDir(run_dir)
    meta = read_json(run.run_json, "run description (run.json); run shells-train first")
    if not run.outer.is_file():
        raise InputError(f"{run.outer}: no shells; run shells-extract {run.root} first")
    if resume:
        ckpt = read_checkpoint(run.finetune_checkpoint)
        field, cfg = load_field(run.root, stage="stage2")
    else:
        if run.finetune_checkpoint.exists():
            raise InputError(f"{run.finetune_checkpoint}: stage 2 already ran; pass --resume to "
                             f"continue it, or delete the file to start over")
        field, cfg = load_field(run.root, stage="stage1")
    override_config(cfg, config, ("finetune", "render"), "shells-finetune")
    fc, rc = cfg.finetune, cfg.render
    subpixel_offsets(fc.pixel_samples)  # a non-square count fails here, before any write
    if iters is not None:
        fc.iters = iters
    scene = load_shells(run, "llvm_ad_rgb")
    data = load_dataset(meta["data"], "train", downscale=int(meta.get("downscale", 1)),
                        background=tuple(rc.background))
    opt = make_optimizer(field, fc.lr, fc.lr_mlp)
    start = 0
    if resume:
        opt.load_state_dict(ckpt["optimizer"])
        start = ckpt["step"]
        if start >= fc.iters:
            raise InputError(f"{run.finetune_checkpoint}: already at step {start}; pass a larger "
                             f"--iters to continue")
        _truncate_log(run.finetune_log, start)
    field.train()
    pixels = data.images.reshape(-1, 3)
    background = torch.tensor(rc.background, dtype=torch.float32)
    end = fc.iters if stop_at is None else min(stop_at, fc.iters)
    bar = tqdm(total=fc.iters, initial=start, disable=not progress, desc="stage 2", unit="step",
               dynamic_ncols=True)
    t0, last = time.perf_counter(), None
    for step in range(start, end):
        last = finetune_step(field, opt, scene, data, pixels, fc, rc, step, background)
        done = step + 1
        bar.update(1)
        bar.set_postfix(loss=f"{last['loss']:.4f}", psnr=f"{last['psnr']:.2f}",
                        spp=f"{last['spp']:.1f}")
        if done % fc.log_every == 0 or done == end:
            _append_log(run.finetune_log, {"step": done, **last,
                                           "elapsed_s": time.perf_counter() - t0})
        if done % fc.checkpoint_every == 0 or done == end:
            save_checkpoint(run.finetune_checkpoint, field, opt, done, cfg)
    bar.close()
    summary = {"step": end, "seconds": time.perf_counter() - t0, "last": last}
    if end == fc.iters:  # the summary marks a finished stage 2
        write_json(run.root / "finetune_summary.json", summary)
    return summary
