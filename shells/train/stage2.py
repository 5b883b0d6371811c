"""Stage 2: fine-tune the field inside the narrow band, colour loss only (§3.5, Procedure 4).

Rays are cast against the fixed shells and rendered by the differentiable torch band renderer
(`shells.render.band.render_band_rays`: the Dr.Jit renderer's ray casting, sample placement
and solid-end rule), and the field is trained with the colour loss alone (L1 unless
`finetune.color_loss` says "l2"). The steps run in `shells.train.loop.optimise`; the checkpoint
goes to RUN/finetune.pt (stage 1's checkpoint.pt is left untouched), with resume. Runs on the
CPU (llvm_ad_rgb) or on CUDA (cuda_ad_rgb): the Mitsuba variant follows the torch device
unless `render.variant` names one.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from shells import distributed
from shells.config import FinetuneConfig, RenderConfig, override_config
from shells.data.datasets import Dataset, load_dataset
from shells.device import mitsuba_variant, torch_device
from shells.errors import InputError
from shells.files import write_json
from shells.fields.network import ShellField
from shells.train.loop import Schedule, color_loss, join, make_optimizer, optimise, psnr_of
from shells.render.band import render_band_rays
from shells.render.raycast import ShellScene
from shells.run import RunDir, field_from_checkpoint, load_shells, read_checkpoint, read_run


def stage2_step(field: ShellField, scene: ShellScene, data: Dataset, pixels: torch.Tensor,
                fc: FinetuneConfig, rc: RenderConfig, background: torch.Tensor,
                gen: torch.Generator) -> tuple[torch.Tensor, dict[str, float]]:
    """Colour loss (`finetune.color_loss`) of one shard of a step (``batch_rays / shards``
    random rays drawn with ``gen``) rendered in the band, and its logs."""
    idx, o, d = data.sample_pixel_rays(fc.batch_rays // fc.shards, fc.pixel_samples, gen)
    out = render_band_rays(field, scene, o, d, rc, background)
    pred = out["color"].reshape(len(idx), fc.pixel_samples, 3).mean(1)  # box filter
    target = pixels[idx]
    loss = color_loss(pred, target, fc.color_loss)
    mse = ((pred.detach().clamp(0, 1) - target) ** 2).mean().item()
    return loss, {"loss": loss.item(), "psnr": psnr_of(mse),
                  "spp": out["spp"].float().mean().item() * fc.pixel_samples}  # per pixel


def finetune(run_dir: str | Path, iters: int | None = None, resume: bool = False,
             progress: bool = True, stop_at: int | None = None,
             config: str | Path | None = None,
             device: str | torch.device | None = None,
             shells: str = "fine") -> dict[str, Any]:
    """Stage-2 fine-tuning of a run that has a stage-1 checkpoint and shells.

    ``config``: a JSON file with ``finetune`` / ``render`` sections overriding the run's; the
    result is stored with the stage-2 checkpoint (and used by renders of stage 2).
    ``device``: torch device (default: CUDA when available); ``shells``: 'fine' (RUN/shells) or
    'lod' (RUN/shells/lod, shells-lod), recorded in the stage-2 log's summary.
    """
    run = RunDir(run_dir)
    meta = read_run(run)
    if not run.outer.is_file():
        raise InputError(f"{run.outer}: no shells; run shells-extract {run.root} first")
    dev = distributed.rank_device(device if isinstance(device, torch.device)
                                  else torch_device(device))
    ckpt = None
    if resume:
        ckpt = read_checkpoint(run, "stage2")
        field, cfg = field_from_checkpoint(ckpt, str(run.checkpoint("stage2")), dev)
    else:
        if run.checkpoint("stage2").exists():
            raise InputError(f"{run.checkpoint('stage2')}: stage 2 already ran; pass --resume "
                             f"to continue it, or delete the file to start over")
        field, cfg = field_from_checkpoint(read_checkpoint(run, "stage1"),
                                           str(run.checkpoint("stage1")), dev)
    override_config(cfg, config, ("finetune", "render"), "shells-finetune")
    if iters is not None:
        cfg.update({"finetune": {"iters": iters}}, "--iters")
    w = join(cfg, "finetune", ckpt is None, dev)
    fc, rc = cfg.finetune, cfg.render
    scene = load_shells(run, mitsuba_variant(rc.variant, dev), shells)
    data = load_dataset(meta["data"], "train", downscale=int(meta["downscale"]),
                        background=cfg.data.background)
    opt = make_optimizer(field, fc.lr, fc.lr_mlp)
    pixels = data.images.reshape(-1, 3).to(dev)
    background = torch.tensor(cfg.data.background, dtype=torch.float32, device=dev)
    summary = optimise(field, opt, cfg, Schedule.of("stage 2", fc),
                       lambda gen: stage2_step(field, scene, data, pixels, fc, rc, background,
                                               gen),
                       run.checkpoint("stage2"), run.log("stage2"), dev, resume=ckpt,
                       stop_at=stop_at, progress=progress)
    summary["shells"] = shells
    if summary["finished"] and w.main:  # the summary marks a finished stage 2
        write_json(run.summary("stage2"), summary)
    return summary

