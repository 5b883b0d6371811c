"""Render the views of a camera set with the Dr.Jit renderer, write PNGs, and score them (§4.2).

`render_views` writes into a folder:

    r_000.png ...      8-bit images (sRGB-encoded values as computed, no gamma change)
    spp_000.png ...    samples per pixel as a heatmap (black 0 -> yellow = max over the views)

and returns the metrics (PSNR, SSIM, samples/pixel, ms/frame, resolution, mode). ms_per_frame
is the median over warm frames (the first frame of each process compiles the kernels) of ray
batch -> image, measured after ``dr.sync_thread()``; camera ray generation (torch) is not
included. Several processes (`shells.distributed`) share the views: view i on rank i mod N.
`write_video` turns the frames into an MP4.
The run-level command around it (`shells-render RUN`) is `shells.pipeline.render_run`.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path
from typing import Any

import drjit as dr
import imageio.v3 as iio
import numpy as np
import torch

from shells import distributed
from shells.config import RenderConfig
from shells.files import write_image
from shells.metrics import psnr, ssim
from shells.progress import tqdm
from shells.render.frame import rays_per_batch, render_image
from shells.render.refine import render_refined, tile_rows
from shells.render.shading import WHITE
from shells.render.raycast import ShellScene

_HEAT = np.array([[0, 0, 0], [80, 20, 120], [220, 50, 60], [250, 160, 20], [255, 255, 160]],
                 np.float64)  # black -> purple -> red -> orange -> pale yellow


_BLOCK = 1 << 20  # pixels converted at a time (bounded temporaries for large frames)


def _row_blocks(height: int, width: int) -> list[tuple[int, int]]:
    rows = max(1, _BLOCK // max(width, 1))
    return [(a, min(height, a + rows)) for a in range(0, height, rows)]


def heatmap(spp: torch.Tensor, vmax: float) -> np.ndarray:  # [H, W] -> [H, W, 3] uint8
    """Samples per pixel as colours; 0 is black, vmax the brightest."""
    out = np.empty((*spp.shape, 3), np.uint8)
    for a, b in _row_blocks(*spp.shape):
        x = np.clip(spp[a:b].float().numpy() / max(vmax, 1.0), 0.0, 1.0) * (len(_HEAT) - 1)
        lo = np.floor(x).astype(int).clip(0, len(_HEAT) - 2)
        w = (x - lo)[..., None]
        out[a:b] = np.round(_HEAT[lo] * (1 - w) + _HEAT[lo + 1] * w)
    return out


def to_png(img: torch.Tensor) -> np.ndarray:  # [H, W, 3] float in [0, 1] -> uint8
    out = np.empty(img.shape, np.uint8)
    for a, b in _row_blocks(*img.shape[:2]):
        out[a:b] = np.round(img[a:b].clamp(0, 1).numpy() * 255.0)
    return out


def render_views(field: Any,  # Dr.Jit field: eval(x, d) -> FieldSample
                 cameras: Any,  # shells.data.cameras.Cameras of the split (possibly resized)
                 images: torch.Tensor | None,  # [N, H, W, 3] references, None = no metrics
                 cfg: RenderConfig,
                 mode: str,
                 scene: ShellScene | None,
                 aabb: Any,  # [2, 3]
                 out: Path,  # existing folder for the PNGs (shared by all ranks)
                 progress: bool = True,
                 background: tuple[float, float, float] = WHITE,  # the data set's
                 world: distributed.World | None = None,  # rank r of N renders views r, r+N, ..
                 ) -> dict[str, Any]:
    """Render the views into ``out``; returns the metrics of all views (on every rank; without
    the run's protocol fields). With several ranks each renders its share and the heatmaps
    share one scale; the images are those of a single process, bit for bit."""
    w = world or distributed.World()
    views, warm, spps = render_frames(field, cameras, images, cfg, mode, scene, aabb, out,
                                      progress, background, w)
    parts = distributed.gather_objects((views, warm))
    views = [v for p in parts for v in p[0]]
    warm = [t for p in parts for t in p[1]]
    return summarise(views, warm, spps, out, cameras, mode, w.size,
                     cameras.height * cameras.width * cfg.spp)


def render_frames(field: Any, cameras: Any, images: torch.Tensor | None, cfg: RenderConfig,
                  mode: str, scene: ShellScene | None, aabb: Any, out: Path, progress: bool,
                  background: tuple[float, float, float], w: distributed.World,
                  ) -> tuple[list[dict[str, Any]], list[float], dict[int, torch.Tensor]]:
    """Views r, r + N, ... of rank r of N into out/r_###.png: per-view records, warm frame
    times, samples-per-pixel maps {view: [H, W]}."""
    mine = list(range(w.rank, len(cameras), w.size))
    views, warm, spps = [], [], {}
    for j, i in enumerate(tqdm(mine, desc=f"render {mode}", disable=not (progress and w.main))):
        img, spp, seconds, counts = render_view(field, cameras, i, cfg, mode, scene, aabb,
                                                background)
        if j > 0:  # the first frame of a process compiles the kernels
            warm.append(seconds)
        write_image(out / f"r_{i:03d}.png", to_png(img))
        spps[i] = spp.to(torch.int16) if int(spp.max()) < 2 ** 15 else spp  # kept for the heatmaps
        views.append({"view": i, "spp_sum": float(spp.double().sum()),
                      "covered": counts["covered"], "evaluated": counts["evaluated"],
                      "spp_max": float(spp.max()),
                      "psnr": psnr(img, images[i]) if images is not None else None,
                      "ssim": ssim(img, images[i]) if images is not None else None,
                      "first_s": seconds if j == 0 else None})
    if len(mine) == 1:  # one view: time a second, warm render of it
        warm.append(render_view(field, cameras, mine[0], cfg, mode, scene, aabb, background)[2])
    return views, warm, spps


def summarise(views: list[dict[str, Any]], warm: list[float], spps: dict[int, torch.Tensor],
              out: Path, cameras: Any, mode: str, processes: int,
              rays_per_frame: int) -> dict[str, Any]:
    """Heatmaps out/spp_###.png of the maps in ``spps`` on the scale of all ``views``, and the
    metrics of all views (with nerfstudio's ns-eval names, `ns_eval`)."""
    n, H, W = len(cameras), cameras.height, cameras.width
    views = sorted(views, key=lambda v: v["view"])
    vmax = max(v["spp_max"] for v in views)
    for i, s in spps.items():
        write_image(out / f"spp_{i:03d}.png", heatmap(s, vmax))
    psnrs = [v["psnr"] for v in views if v["psnr"] is not None]
    ssims = [v["ssim"] for v in views if v["ssim"] is not None]
    covered = sum(v["covered"] for v in views)
    firsts = [v["first_s"] for v in views if v["first_s"] is not None]
    return {**ns_eval(psnrs, ssims, warm, rays_per_frame),
        "psnr_per_view": psnrs or None,
        "samples_per_pixel": sum(v["spp_sum"] for v in views) / (n * H * W),
        "samples_per_covered_pixel": (sum(v["spp_sum"] for v in views) / covered
                                      if covered else 0.0),
        "covered_fraction": covered / (n * H * W),
        "evaluated_fraction_of_covered": (sum(v.get("evaluated", v["covered"]) for v in views)
                                          / covered if covered else 0.0),
        "ms_per_frame": 1e3 * statistics.median(warm),
        "ms_first_frame": 1e3 * max(firsts),
        "width": W, "height": H, "n_views": n, "mode": mode, "processes": processes,
    }


def ns_eval(psnrs: list[float], ssims: list[float], warm: list[float],
            rays_per_frame: int) -> dict[str, Any]:
    """The fields of nerfstudio's ns-eval output: mean and standard deviation over the views of
    PSNR and SSIM, and over the warm frames of fps and rays per second (LPIPS is left out: its
    network weights are not available offline). Also nested under "results", as ns-eval
    writes them."""
    def stats(name: str, xs: list[float]) -> dict[str, float | None]:
        if not xs:
            return {name: None, f"{name}_std": None}
        return {name: float(np.mean(xs)), f"{name}_std": float(np.std(xs))}

    out = {**stats("psnr", psnrs), **stats("ssim", ssims),
           **stats("fps", [1.0 / t for t in warm]),
           **stats("num_rays_per_sec", [rays_per_frame / t for t in warm])}
    return {**out, "results": dict(out)}


def render_view(field: Any, cameras: Any, i: int, cfg: RenderConfig, mode: str,
                scene: ShellScene | None, aabb: Any, background: tuple[float, float, float],
                ) -> tuple[torch.Tensor, torch.Tensor, float, dict[str, int]]:
    """View i: image [H, W, 3], samples per pixel [H, W], seconds (ray batches -> image), and
    pixel counts {"covered": rays with shell intervals (band) or samples, "evaluated": pixels
    whose field was evaluated (fewer than covered with cfg.refine_levels > 0)}.

    A frame larger than one ray batch (`rays_per_batch`, from the memory budget
    cfg.memory_mb) is rendered in tiles of whole rows, each with its own rays, so memory is
    bounded by the frame itself (16 bytes a pixel) plus one batch. In band mode with
    cfg.refine_levels > 0 the tiles are those of `shells.render.refine.tile_rows`."""
    H, W, K = cameras.height, cameras.width, cfg.spp
    refine = mode == "band" and cfg.refine_levels > 0
    rows = tile_rows(cfg, W) if refine else max(1, rays_per_batch(cfg, mode) // (W * K))
    img = torch.empty(H, W, 3, dtype=torch.float32)
    spp = torch.empty(H, W, dtype=torch.int32)
    seconds, counts = 0.0, {"covered": 0, "evaluated": 0}
    for y0 in range(0, H, rows):
        y1 = min(H, y0 + rows)
        o, d = cameras.pixel_rays(i, K, (y0, y1))
        dr.sync_thread()
        t0 = time.perf_counter()
        if refine:
            img[y0:y1], spp[y0:y1], evaluated, covered = render_refined(
                field, o, d, y1 - y0, W, cfg, scene, background)
        else:
            img[y0:y1], spp[y0:y1] = render_image(field, o, d, y1 - y0, W, cfg, mode, scene,
                                                  aabb, background)
            evaluated = covered = spp[y0:y1] > 0
        dr.sync_thread()
        seconds += time.perf_counter() - t0
        counts["covered"] += int(covered.sum())
        counts["evaluated"] += int(evaluated.sum())
        del o, d
    return img, spp, seconds, counts


def write_video(frames: list[Path], path: Path, fps: float) -> None:
    """An H.264 MP4 of the PNG ``frames`` (read one at a time: bounded memory); odd sizes are
    padded by one edge pixel (H.264 wants even sizes)."""
    import imageio.v2 as iio2

    writer = iio2.get_writer(path, format="FFMPEG", mode="I", fps=fps, codec="libx264",
                             quality=8, macro_block_size=1, ffmpeg_log_level="error")
    try:
        for f in frames:
            img = iio.imread(f)[..., :3]
            pad = ((0, img.shape[0] % 2), (0, img.shape[1] % 2), (0, 0))
            writer.append_data(np.pad(img, pad, mode="edge"))
    finally:
        writer.close()
