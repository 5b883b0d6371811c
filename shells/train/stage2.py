"""Stage 2: fine-tune the field inside the narrow band (§3.5, Procedure 4).

Rays are cast against the fixed shells and rendered by the differentiable torch band renderer
(`shells.render.band.render_band_rays`: the Dr.Jit renderer's ray casting, sample placement
and solid-end rule), and the field is trained with the colour loss (L1 unless
`finetune.color_loss` says "l2") and the anchor (`anchor_term`). The colour loss reaches the
field only in the band, but the hash tables and MLPs it moves are shared with the space
outside M+, where the kernel size then drifts (floaters in every renderer but the band's;
BENCHMARKS.md, lego 800x800); the anchor holds f and s outside M+ at the stage-1 field's
values. The steps run in `shells.train.loop.optimise`; the checkpoint goes to RUN/finetune.pt
(stage 1's checkpoint.pt is left untouched), with resume. Runs on the CPU (llvm_ad_rgb) or on
CUDA (cuda_ad_rgb): the Mitsuba variant follows the torch device unless `render.variant` names
one.
"""

from __future__ import annotations

import copy
import sys
from pathlib import Path
from typing import Any

import torch

from shells import distributed
from shells.config import FinetuneConfig, RenderConfig, override_config
from shells.data.datasets import Dataset, load_dataset
from shells.device import mitsuba_variant, torch_device
from shells.errors import InputError
from shells.files import write_json
from shells.fields.contraction import uncontract
from shells.fields.hashgrid import HashGrid
from shells.fields.network import ShellField
from shells.progress import tqdm
from shells.train.health import band_check
from shells.train.loop import Schedule, color_loss, join, optimise, psnr_of
from shells.train.optim import make_optimizer, use_hashgrid
from shells.render.band import render_band_rays
from shells.render.raycast import ShellScene
from shells.run import RunDir, field_from_checkpoint, load_shells, read_checkpoint, read_run


ANCHOR_DIR = (0.267, 0.535, 0.802)  # the outside test's ray direction, off every axis
MAX_CONTRACTED = 1.99  # unbounded fields: anchor points nearer to infinity are not drawn


def outside_outer(scene: ShellScene, x: torch.Tensor  # [N, 3] world points
                  ) -> torch.Tensor:  # [N] bool
    """Which points lie outside M+: a ray from the point whose first hit is not the outer
    shell's back face (an exit) nor the inner shell (`ShellScene.intervals` with one peel:
    such a hit closes an interval)."""
    d = x.new_tensor(ANCHOR_DIR)
    d = (d / d.norm()).expand_as(x).contiguous()
    return scene.intervals(x, d, 1).torch()["count"].to(x.device) == 0


def anchor_points(field: ShellField, n: int, gen: torch.Generator
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Uniform points of the field's box: field-space z [M, 3] and world x [M, 3] (the same
    tensor for a bounded field; an unbounded field's z beyond MAX_CONTRACTED are dropped)."""
    lo, hi = field.aabb[0], field.aabb[1]
    z = lo + (hi - lo) * torch.rand(n, 3, generator=gen, device=lo.device)
    sim = field.similarity
    if sim is None:
        return z, z
    y = sim.to_unit(z)
    keep = torch.linalg.vector_norm(y, dim=-1) < MAX_CONTRACTED
    return z[keep], sim.to_world(uncontract(y[keep]))


def anchor_term(sdf: torch.Tensor, s: torch.Tensor,  # [M] the field at anchor points
                sdf1: torch.Tensor, s1: torch.Tensor,  # [M] the stage-1 field there
                side: float) -> torch.Tensor:
    """mean |log s - log s1| + |f - f1| / side (side: the field box's longest side)."""
    return ((torch.log(s) - torch.log(s1)).abs().mean() + (sdf - sdf1).abs().mean() / side)


def box_side(field: ShellField) -> float:
    return float((field.aabb[1] - field.aabb[0]).max())


def anchor_targets(field: ShellField, stage1: ShellField, scene: ShellScene, n: int,
                   gen: torch.Generator) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The anchor's points of a step: those of ``n`` uniform ones of the field's box
    (`anchor_points`) that lie outside M+, as world points [M, 3], and the frozen stage-1
    field there (its geometry, no gradient); None, None when none lies outside."""
    _, x = anchor_points(field, n, gen)
    x = x[outside_outer(scene, x)]
    if len(x) == 0:
        return None, None
    with torch.no_grad():
        return x, stage1.geometry(x)


def anchor_loss(field: ShellField, stage1: ShellField, scene: ShellScene, n: int,
                gen: torch.Generator) -> torch.Tensor:
    """The anchor (`anchor_term`) of ``field`` against the frozen ``stage1`` at the points
    `anchor_targets` draws, evaluated on its own (the step evaluates them in the band's
    batch)."""
    x, g1 = anchor_targets(field, stage1, scene, n, gen)
    if x is None:
        return field.aabb.new_zeros(())
    g = field.geometry(x)
    return anchor_term(g["sdf"], g["s"], g1["sdf"], g1["s"], box_side(field))


def frozen(stage1: ShellField) -> ShellField:
    """The stage-1 field as the anchor holds it: no gradients, and hash-grid lookups in torch
    (a step's few anchor points take a third of the time of Dr.Jit's kernel launch)."""
    stage1.requires_grad_(False)
    for m in stage1.modules():
        if isinstance(m, HashGrid):
            m.inference = "torch"
    return stage1


def stage2_step(field: ShellField, scene: ShellScene, data: Dataset, pixels: torch.Tensor,
                fc: FinetuneConfig, rc: RenderConfig, background: torch.Tensor,
                gen: torch.Generator, stage1: ShellField | None = None,
                ) -> tuple[torch.Tensor, dict[str, float]]:
    """Colour loss (`finetune.color_loss`) of one shard of a step (``batch_rays / shards``
    random rays drawn with ``gen``) rendered in the band, plus ``anchor_weight`` times the
    anchor (`anchor_term`, ``anchor_points / shards`` points) when the frozen stage-1 field
    ``stage1`` is given, and its logs."""
    idx, o, d = data.sample_pixel_rays(fc.batch_rays // fc.shards, fc.pixel_samples, gen)
    anchored = stage1 is not None and fc.anchor_weight > 0
    x, g1 = (anchor_targets(field, stage1, scene, max(1, fc.anchor_points // fc.shards), gen)
             if anchored else (None, None))
    out = render_band_rays(field, scene, o, d, rc, background, extra=x)
    pred = out["color"].reshape(len(idx), fc.pixel_samples, 3).mean(1)  # box filter
    target = pixels[idx]
    loss = color_loss(pred, target, fc.color_loss)
    mse = ((pred.detach().clamp(0, 1) - target) ** 2).mean().item()
    logs = {"psnr": psnr_of(mse),
            "spp": out["spp"].float().mean().item() * fc.pixel_samples}  # per pixel
    if x is not None:
        anchor = anchor_term(out["extra_sdf"], out["extra_s"], g1["sdf"], g1["s"],
                             box_side(field))
        loss = loss + fc.anchor_weight * anchor
        logs["anchor"] = anchor.item()
    return loss, {"loss": loss.item(), **logs}


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
    if not resume and run.checkpoint("stage2").exists():
        raise InputError(f"{run.checkpoint('stage2')}: stage 2 already ran; pass --resume "
                         f"to continue it, or delete the file to start over")
    stage1, cfg = field_from_checkpoint(read_checkpoint(run, "stage1"),
                                        str(run.checkpoint("stage1")), dev)
    if resume:
        ckpt = read_checkpoint(run, "stage2")
        field, cfg = field_from_checkpoint(ckpt, str(run.checkpoint("stage2")), dev)
    else:
        field = copy.deepcopy(stage1)
    override_config(cfg, config, ("finetune", "render"), "shells-finetune")
    if iters is not None:
        cfg.update({"finetune": {"iters": iters}}, "--iters")
    w = join(cfg, "finetune", ckpt is None, dev)
    fc, rc = cfg.finetune, cfg.render
    stage1 = frozen(stage1) if fc.anchor_weight > 0 else None
    scene = load_shells(run, mitsuba_variant(rc.variant, dev), shells)
    data = load_dataset(meta["data"], "train", downscale=int(meta["downscale"]),
                        background=cfg.data.background)
    use_hashgrid(field, fc.hashgrid)
    opt = make_optimizer(field, fc.lr, fc.lr_mlp)
    pixels = data.images.reshape(-1, 3).to(dev)
    background = torch.tensor(cfg.data.background, dtype=torch.float32, device=dev)
    summary = optimise(field, opt, cfg, Schedule.of("stage 2", fc),
                       lambda gen: stage2_step(field, scene, data, pixels, fc, rc, background,
                                               gen, stage1),
                       run.checkpoint("stage2"), run.log("stage2"), dev, resume=ckpt,
                       stop_at=stop_at, progress=progress)
    summary["shells"] = shells
    if summary["finished"] and w.main:  # the summary marks a finished stage 2
        field.eval()
        check = band_check(field, scene, data, pixels, rc, background)
        summary["band_check"] = check
        if check["warning"] and progress:
            tqdm.write(f"warning: {check['warning']}", file=sys.stderr)
        write_json(run.summary("stage2"), summary)
    return summary

