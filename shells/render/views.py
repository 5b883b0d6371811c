"""Render the views of a camera set with the Dr.Jit renderer, write PNGs, and score them (§4.2).

`render_views` writes into a folder:

    r_000.png ...      8-bit images (sRGB-encoded values as computed, no gamma change)
    spp_000.png ...    samples per pixel as a heatmap (black 0 -> yellow = max over the views)

and returns the metrics (PSNR, SSIM, samples/pixel, ms/frame, resolution, mode). ms_per_frame
is the median over warm frames (the first frame compiles the kernels) of ray batch -> image,
measured after ``dr.sync_thread()``; camera ray generation (torch) is not included.
The run-level command around it (`shells-render RUN`) is `shells.pipeline.render_run`.
"""

from __future__ import annotations

import dataclasses
import statistics
import time
from pathlib import Path
from typing import Any

import drjit as dr
import imageio.v3 as iio
import numpy as np
import torch
from tqdm import tqdm

from shells.config import RenderConfig
from shells.errors import InputError
from shells.metrics import psnr, ssim
from shells.render.frame import render_image
from shells.render.shading import WHITE
from shells.render.raycast import ShellScene

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
                 progress: bool = True,
                 background: tuple[float, float, float] = WHITE,  # the data set's
                 ) -> dict[str, Any]:
    """Render all views into ``out``; returns the metrics (without the run's protocol fields)."""
    n, H, W = len(cameras), cameras.height, cameras.width
    times, psnrs, ssims, spps = [], [], [], []
    for i in tqdm(range(n), desc=f"render {mode}", disable=not progress):
        o, d = cameras.pixel_rays(i, cfg.spp)
        dr.sync_thread()
        t0 = time.perf_counter()
        img, spp = render_image(field, o, d, H, W, cfg, mode, scene, aabb, background)
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
        render_image(field, o, d, H, W, cfg, mode, scene, aabb, background)
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
