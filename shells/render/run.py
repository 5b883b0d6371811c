"""Render a split of a trained run and score it: `shells-render RUN` (§4.2).

Reads RUN/run.json (data set path, downscale), the latest checkpoint (stage 2 when present),
RUN/shells/{outer,inner}.ply (band mode), renders every view of the split with the Dr.Jit field,
and writes into OUT (default RUN/render-MODE):

    r_000.png ...      8-bit images (sRGB-encoded values as computed, no gamma change)
    spp_000.png ...    samples per pixel as a heatmap (black 0 -> yellow = max over the split)
    metrics.json       psnr, ssim, samples/pixel, ms/frame, resolution, mode, device, protocol

Everything is rendered into a hidden temporary folder beside OUT and moved in at the end, so a
failure leaves no partial output. ms_per_frame is the median over warm frames (the first frame
compiles the kernels) of ray batch -> image, measured after ``dr.sync_thread()``; camera ray
generation (torch) is not included.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import drjit as dr
import imageio.v3 as iio
import numpy as np
import torch
from tqdm import tqdm

from shells.config import RenderConfig
from shells.errors import InputError, read_json, write_json
from shells.metrics import PROTOCOL, psnr, ssim
from shells.render.frame import MODES, render_image
from shells.render.raycast import ShellScene
from shells.run import RunDir

_HEAT = np.array([[0, 0, 0], [80, 20, 120], [220, 50, 60], [250, 160, 20], [255, 255, 160]],
                 np.float64)  # black -> purple -> red -> orange -> pale yellow


def heatmap(spp: torch.Tensor, vmax: float) -> np.ndarray:  # [H, W] -> [H, W, 3] uint8
    """Samples per pixel as colours; 0 is black, vmax the brightest."""
    x = np.clip(spp.float().numpy() / max(vmax, 1.0), 0.0, 1.0) * (len(_HEAT) - 1)
    lo = np.floor(x).astype(int).clip(0, len(_HEAT) - 2)
    w = (x - lo)[..., None]
    return np.round(_HEAT[lo] * (1 - w) + _HEAT[lo + 1] * w).astype(np.uint8)


def to_png(img: torch.Tensor) -> np.ndarray:  # [H, W, 3] float in [0, 1] -> uint8
    return np.round(img.clamp(0, 1).numpy() * 255.0).astype(np.uint8)


def resized_cameras(cams: Any, width: int | None, height: int | None) -> Any:
    """Cameras at another resolution: intrinsics scaled per axis (aspect kept if one is None)."""
    if width is None and height is None:
        return cams
    if width is None:
        width = max(1, round(cams.width * height / cams.height))
    if height is None:
        height = max(1, round(cams.height * width / cams.width))
    if width < 1 or height < 1:
        raise InputError(f"--width {width} --height {height}: must be positive")
    sx, sy = width / cams.width, height / cams.height
    return dataclasses.replace(cams, fx=cams.fx * sx, cx=cams.cx * sx, fy=cams.fy * sy,
                               cy=cams.cy * sy, width=int(width), height=int(height))


def render_views(field: Any,  # Dr.Jit field: eval(x, d) -> FieldSample
                 cameras: Any,  # shells.cameras.Cameras of the split (possibly resized)
                 images: torch.Tensor | None,  # [N, H, W, 3] references, None = no metrics
                 cfg: RenderConfig,
                 mode: str,
                 scene: ShellScene | None,
                 aabb: Any,  # [2, 3]
                 out: Path,  # existing folder for the PNGs
                 progress: bool = True) -> dict[str, Any]:
    """Render all views into ``out``; returns the metrics (without the run's protocol fields)."""
    n, H, W = len(cameras), cameras.height, cameras.width
    times, psnrs, ssims, spps = [], [], [], []
    for i in tqdm(range(n), desc=f"render {mode}", disable=not progress):
        o, d = cameras.pixel_rays(i, cfg.spp)
        dr.sync_thread()
        t0 = time.perf_counter()
        img, spp = render_image(field, o, d, H, W, cfg, mode, scene, aabb)
        dr.sync_thread()
        times.append(time.perf_counter() - t0)
        iio.imwrite(out / f"r_{i:03d}.png", to_png(img))
        spps.append(spp)
        if images is not None:
            psnrs.append(psnr(img, images[i]))
            ssims.append(ssim(img, images[i]))
    if n == 1:  # one view: time a second, warm render of it
        o, d = cameras.pixel_rays(0, cfg.spp)
        dr.sync_thread()
        t0 = time.perf_counter()
        render_image(field, o, d, H, W, cfg, mode, scene, aabb)
        dr.sync_thread()
        times.append(time.perf_counter() - t0)
    vmax = max(float(s.max()) for s in spps)
    for i, s in enumerate(spps):
        iio.imwrite(out / f"spp_{i:03d}.png", heatmap(s, vmax))
    all_spp = torch.stack(spps).float()
    covered = all_spp > 0
    return {
        "psnr": float(np.mean(psnrs)) if psnrs else None,
        "ssim": float(np.mean(ssims)) if ssims else None,
        "psnr_per_view": psnrs or None,
        "samples_per_pixel": float(all_spp.mean()),
        "samples_per_covered_pixel": float(all_spp[covered].mean()) if covered.any() else 0.0,
        "covered_fraction": float(covered.float().mean()),
        "ms_per_frame": 1e3 * statistics.median(times[1:]),
        "ms_first_frame": 1e3 * times[0],
        "width": W, "height": H, "n_views": n, "mode": mode,
    }


def check_run(run: RunDir, mode: str) -> dict[str, Any]:
    """Fail early, before anything is loaded or written."""
    if mode not in MODES:
        raise InputError(f"--mode {mode}: expected one of {MODES}")
    meta = read_json(run.run_json, "run description (run.json); run shells-train first")
    if not isinstance(meta, dict) or "data" not in meta:
        raise InputError(f"{run.run_json}: missing key 'data'; re-run shells-train")
    if not run.checkpoint.is_file() and not run.finetune_checkpoint.is_file():
        raise InputError(f"{run.checkpoint}: no checkpoint; run shells-train first")
    if mode == "band" and not run.outer.is_file():
        raise InputError(f"{run.outer}: no outer shell; run shells-extract first")
    return meta


def load_shells(run: RunDir, variant: str | None) -> ShellScene:
    """ShellScene from RUN/shells; a missing or empty inner.ply means no interior termination."""
    from shells.levelset.mesh import load_ply

    outer = load_ply(run.outer)
    if len(outer[1]) == 0:
        raise InputError(f"{run.outer}: the outer shell is empty; re-run shells-extract")
    inner = load_ply(run.inner) if run.inner.is_file() else None
    return ShellScene(outer, inner, variant)


def render_run(run_dir: str | Path, split: str = "test", mode: str = "band",
               width: int | None = None, height: int | None = None,
               out: str | Path | None = None, progress: bool = True,
               stage: str = "latest", config: str | Path | None = None,
               spp: int | None = None) -> dict[str, Any]:
    """Render every view of ``split`` and write images + metrics.json; returns the metrics.

    ``stage`` picks the checkpoint: 'latest' (stage 2 when present), 'stage1' or 'stage2';
    ``config``: a JSON file with a ``render`` section overriding the run's render settings;
    ``spp``: rays per pixel (overrides both).
    """
    run = RunDir(run_dir)
    meta = check_run(run, mode)

    from shells.cameras import subpixel_offsets
    from shells.config import override_config
    from shells.datasets import load_dataset
    from shells.device import mitsuba_variant
    from shells.fields.drjit_field import DrJitField
    from shells.training import load_field

    field, cfg = load_field(run.root, device="cpu", stage=stage)
    rc = override_config(cfg, config, ("render",), "shells-render").render
    if spp is not None:
        rc.spp = spp
    subpixel_offsets(rc.spp)  # a non-square count fails here, before anything is written
    variant = mitsuba_variant(rc.variant)
    scene = load_shells(run, variant) if mode == "band" else None
    data = load_dataset(meta["data"], split, downscale=int(meta.get("downscale", 1)),
                        background=tuple(rc.background))
    cams = resized_cameras(data.cameras, width, height)
    same_size = (cams.width, cams.height) == (data.cameras.width, data.cameras.height)
    dj = DrJitField(field)

    out = Path(out) if out is not None else run.render_dir(mode)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}."))
    try:
        metrics = render_views(dj, cams, data.images if same_size else None, rc, mode, scene,
                               data.aabb, tmp, progress)
        metrics.update({
            "split": split, "variant": variant, "stage": stage, "out": str(out),
            "device": "cuda" if variant.startswith("cuda") else "cpu",
            "background": list(rc.background), "data": str(meta["data"]),
            "downscale": int(meta.get("downscale", 1)),
            "protocol": PROTOCOL + ("" if same_size else
                                    "; resolution differs from the data set: no metrics"),
            "render_config": dataclasses.asdict(rc),
        })
        write_json(tmp / "metrics.json", metrics)
        out.mkdir(parents=True, exist_ok=True)
        names = sorted(p.name for p in tmp.iterdir())
        for name in [n for n in names if n != "metrics.json"] + ["metrics.json"]:
            os.replace(tmp / name, out / name)  # metrics.json last: it marks a complete render
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return metrics
