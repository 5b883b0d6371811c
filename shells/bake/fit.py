"""Baking: the layers of `shells.bake.layers`, their atlas textures fitted to the photos.

1. Start values distilled from the field at every texel's point: base colour = the radiance
   seen along -normal, opacity = the NeuS opacity of the layer's slab of u (the innermost slab
   is solid, as M- is), no view dependence; texels outside the charts take the nearest chart
   texel's values.
2. Fit (`fit_textures`): every pixel of the given views (the photos, and the caller's band
   renders of the field from other cameras) is cast once against each layer with ``spp`` rays
   (Mitsuba) and each hit's atlas coordinate cached; the texels are then fitted with Adam to
   the pixels, a pixel being the mean of its rays through `shells.bake.render.shade` (bilinear
   look-ups as the viewer samples the textures, its compositing rule), with a smoothness term
   between neighbouring texels of a chart.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from shells.bake.format import BakedAsset, Layer, Textures, quantise
from shells.bake.layers import (Grid, TexelMap, dilate, level_sets, sample_field, simplify,
                                subset, texel_map, unwrap)
from shells.bake.render import LayerHits, LayerScene, shade
from shells.errors import InputError
from shells.levelset.cage import is_watertight
from shells.progress import tqdm

CHANNELS = 13  # RGBA, SH 3 x 3


@dataclass
class BakeConfig:
    # u = f / s of the layers (0: the surface), more outside, where fuzz spreads
    levels: tuple[float, ...] = (-2.0, -1.0, 0.0, 1.0, 2.0, 3.0, 4.0)
    cells_per_pixel: float = 1.25  # marching-cubes cells across a training pixel's footprint
    # at the scene centre (at most the shells' grid), before decimation
    tolerance_px: float = 0.5  # how far a decimated layer may stray from its level set, in
    # training-pixel footprints (99th percentile)
    texel_px: float = 1.0  # atlas texel size in training-pixel footprints
    max_atlas: int = 4096  # the atlas's largest side (WebGL guarantees at least 4096)
    size_mb: float = 60.0  # texels x 13 bytes (the textures before PNG) at most this
    steps: int = 600  # Adam steps
    rays: int = 1 << 17  # training rays per step (pixels x spp)
    smooth: float = 0.1  # weight of squared differences between neighbouring chart texels
    smooth_pairs: int = 1 << 18  # texel pairs drawn per step for that term
    spp: int = 4  # rays per pixel, averaged as `shells-render --spp` and 4x MSAA draw a pixel
    max_pixels: int | None = 6_000_000  # a random share of the pixels beyond this many
    lr: float = 0.02  # start learning rate (texel values), decayed 10x over the schedule
    teacher_views: int | None = None  # band renders of the field from turned training cameras
    # added to the photos (None: teacher_per_view per training view; 0: none): they hold the
    # texels that the photos alone leave free
    teacher_per_view: int = 4
    prune_alpha: float = 1.5 / 255  # a triangle whose texels all stay below this opacity goes
    seed: int = 0


def slab_opacity(level: float, levels: tuple[float, ...]) -> float:
    """The NeuS opacity of the slab of u that layer ``level`` stands for (between the midpoints
    to its neighbours; the innermost is solid)."""
    ls = sorted(levels)
    k = ls.index(level)
    lo = -math.inf if k == 0 else 0.5 * (ls[k - 1] + level)
    hi = math.inf if k == len(ls) - 1 else 0.5 * (level + ls[k + 1])
    t_hi = 1.0 if hi == math.inf else 1.0 / (1.0 + math.exp(-hi))
    t_lo = 0.0 if lo == -math.inf else 1.0 / (1.0 + math.exp(-lo))
    return 1.0 - t_lo / t_hi


def distilled_start(field: Any, tmap: TexelMap, grid: Grid, levels: tuple[float, ...],
                    chunk: int = 1 << 16) -> Textures:
    """The textures' start values (module docstring, item 1)."""
    H, W = tmap.layer.shape
    ls = sorted(levels)
    flat = np.nonzero(tmap.inside.ravel())[0]
    pts = tmap.point.reshape(-1, 3)[flat]
    rgba = torch.zeros(H * W, 4)
    with torch.no_grad():
        for a in range(0, len(flat), chunk):
            x = torch.from_numpy(pts[a:a + chunk]).float()
            geo = field.geometry(x)
            rgba[flat[a:a + chunk], :3] = field.radiance(-geo["normal"], geo)
    layer = tmap.layer.ravel()[flat]
    alpha = np.array([slab_opacity(c, levels) for c in ls])[layer]
    # where the side layers are not kept the surface layer is the whole slab
    smallest = min((abs(c) for c in ls if c != 0), default=1.0)
    sharp = (np.array(ls)[layer] == 0) & (grid.at(grid.s, pts) * smallest < grid.h)
    alpha[sharp] = 1.0
    rgba[flat, 3] = torch.from_numpy(alpha).float()
    rgba = dilate(rgba.reshape(H, W, 4), tmap.inside)
    return Textures(rgba=rgba.contiguous(), sh=torch.zeros(H, W, 3, 3))


@dataclass
class RayCache:
    """The training pixels whose rays hit a layer: target colours [P, 3]; their ``spp`` rays
    each (a pixel's contiguous): directions [P * spp, 3] and hits."""

    d: torch.Tensor
    target: torch.Tensor
    hits: list[LayerHits]
    spp: int

    def batch(self, pixels: torch.Tensor) -> tuple[torch.Tensor, list[LayerHits]]:
        """Ray indices [B * spp] of ``pixels`` [B], and their hits."""
        rays = (pixels[:, None] * self.spp + torch.arange(self.spp)).reshape(-1)
        return self.d[rays], [h.take(rays) for h in self.hits]


def cache_rays(scene: LayerScene, views: list[tuple[Any, torch.Tensor]], spp: int = 1,
               max_pixels: int | None = None, seed: int = 0,
               progress: bool = False) -> RayCache:
    """The pixels of ``views`` ((cameras, images [N, H, W, 3]) sets) one of whose ``spp`` rays
    (the sub-pixel grid of `Cameras.pixel_rays`, as ``shells-render --spp``) hits a layer; a
    random share of them when there are more than ``max_pixels`` pixels in all."""
    total = sum(len(c) * c.height * c.width for c, _ in views)
    keep = 1.0 if not max_pixels or total <= max_pixels else max_pixels / total
    gen = torch.Generator().manual_seed(seed)
    ds, targets, hits = [], [], [[] for _ in scene.scenes]
    pairs = [(cameras, images, i) for cameras, images in views for i in range(len(cameras))]
    for cameras, images, i in tqdm(pairs, desc="cast training rays", disable=not progress):
        o, d = cameras.pixel_rays(i, spp)
        hs = scene.cast(o, d)
        any_hit = torch.zeros(len(d) // spp, dtype=torch.bool)
        for h in hs:
            any_hit |= torch.isfinite(h.t).reshape(-1, spp).any(1)
        if keep < 1.0:
            any_hit &= torch.rand(len(any_hit), generator=gen) < keep
        px = torch.nonzero(any_hit).squeeze(1)
        rays = (px[:, None] * spp + torch.arange(spp)).reshape(-1)
        ds.append(d[rays].float())
        targets.append(images[i].reshape(-1, 3)[px])
        for k, h in enumerate(hs):
            hits[k].append(h.take(rays))
    cat = [LayerHits(torch.cat([x.t for x in hk]), torch.cat([x.tc for x in hk]))
           for hk in hits]
    return RayCache(torch.cat(ds), torch.cat(targets), cat, spp)


def neighbour_pairs(inside: np.ndarray, layer: np.ndarray | None = None) -> torch.Tensor:
    """Flat index pairs [P, 2] of horizontally and vertically adjacent texels that are both
    inside a chart (of the same layer)."""
    H, W = inside.shape
    idx = np.arange(H * W).reshape(H, W)
    lay = layer if layer is not None else np.zeros((H, W), np.int64)
    out = []
    for a, b in ((idx[:, :-1], idx[:, 1:]), (idx[:-1, :], idx[1:, :])):
        ok = inside.ravel()[a] & inside.ravel()[b] & (lay.ravel()[a] == lay.ravel()[b])
        out.append(np.stack([a[ok], b[ok]], 1))
    return torch.from_numpy(np.concatenate(out).astype(np.int64))


def fit_textures(meshes: list[tuple[np.ndarray, np.ndarray, np.ndarray]], start: Textures,
                 inside: np.ndarray, views: list[tuple[Any, torch.Tensor]],
                 background: tuple[float, float, float], cfg: BakeConfig,
                 variant: str | None = None, progress: bool = False,
                 layer: np.ndarray | None = None) -> tuple[Textures, dict[str, Any]]:
    """Fit the atlas textures of fixed layer meshes (V, F, uv) to the images of ``views``
    ((cameras, images) sets: the photos, the teacher's views); ``inside`` [H, W]: the chart
    texels (the smoothness term's domain), ``layer`` [H, W] their layers. Returns the textures
    and a record (steps, pixels, seconds, final PSNR of the batches on the rays that hit a
    layer)."""
    t0 = time.perf_counter()
    scene = LayerScene(meshes, variant)
    cache = cache_rays(scene, views, cfg.spp, cfg.max_pixels, cfg.seed, progress)
    R = len(cache.target)
    if R == 0:
        raise InputError("no training ray hits the layers: nothing to bake (is the field empty?)")
    H, W = inside.shape
    tex = start.stacked().permute(2, 0, 1).contiguous().requires_grad_()  # [13, H, W]
    pairs = neighbour_pairs(inside, layer)
    opt = torch.optim.Adam([tex], lr=cfg.lr)
    steps = cfg.steps
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda i: 0.1 ** (i / max(steps, 1)))
    gen = torch.Generator().manual_seed(cfg.seed)
    bg = torch.tensor(background, dtype=torch.float32)
    psnrs = []
    bar = tqdm(range(steps), desc="fit textures", disable=not progress)
    for _ in bar:
        idx = torch.randint(0, R, (max(1, min(cfg.rays // cfg.spp, R)),), generator=gen)
        d, hits = cache.batch(idx)
        colour, _ = shade(tex, hits, d, bg)
        colour = colour.reshape(-1, cfg.spp, 3).mean(1)  # the pixel: mean of its rays
        loss = torch.mean((colour - cache.target[idx]) ** 2)
        data_loss = loss.detach()
        if cfg.smooth > 0 and len(pairs):  # neighbouring texels alike: those seen by few rays
            p = pairs[torch.randint(0, len(pairs), (min(cfg.smooth_pairs, len(pairs)),),
                                    generator=gen)]
            flat = tex.reshape(CHANNELS, -1)
            loss = loss + cfg.smooth * ((flat[:, p[:, 0]] - flat[:, p[:, 1]]) ** 2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        with torch.no_grad():  # the textures hold values in [0, 1] for base and opacity
            tex[:4].clamp_(0.0, 1.0)
        psnrs.append(-10.0 * math.log10(max(data_loss.item(), 1e-12)))
        bar.set_postfix(psnr=f"{psnrs[-1]:.2f}", refresh=False)
    out = tex.detach().permute(1, 2, 0)
    return Textures(rgba=out[..., :4].contiguous(), sh=out[..., 4:].reshape(H, W, 3, 3)), {
        "steps": steps, "pixels": R, "seconds": time.perf_counter() - t0,
        "train_psnr_last": float(np.mean(psnrs[-10:])) if psnrs else None}


def visible_triangles(meshes: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
                      tex: Textures, tmap: TexelMap, threshold: float) -> list[np.ndarray]:
    """Per layer, the triangles [m] bool with an opacity of at least ``threshold`` somewhere:
    at a texel of theirs in the atlas, or at their corners or centroid (bilinear look-ups, for
    triangles smaller than a texel)."""
    from shells.bake.render import sample

    alpha = tex.rgba[..., 3]
    out = []
    for k, (V, F, uv) in enumerate(meshes):
        most = np.zeros(len(F), np.float32)
        sel = tmap.layer == k
        np.maximum.at(most, tmap.prim[sel], alpha.numpy()[sel])
        T = torch.from_numpy(uv[F])  # [m, 3, 2]
        for tc in (T[:, 0], T[:, 1], T[:, 2], T.mean(1)):
            most = np.maximum(most, sample(alpha[None], tc)[:, 0].numpy())
        out.append(most >= threshold)
    return out


def bake(field: Any, aabb: np.ndarray, outer: tuple[np.ndarray, np.ndarray],
         inner: tuple[np.ndarray, np.ndarray] | None, views: list[tuple[Any, torch.Tensor]],
         background: tuple[float, float, float], up: tuple[float, float, float],
         resolution: int, band: float, footprint: float, cfg: BakeConfig,
         variant: str | None = None, progress: bool = False) -> BakedAsset:
    """The whole bake -> a quantised `BakedAsset`. ``footprint``: a training pixel's size at
    the scene centre (world units), the unit of the decimation tolerance and the texel size."""
    t0 = time.perf_counter()
    grid = sample_field(field, aabb, resolution, band, progress)
    levels = sorted(cfg.levels)
    full = level_sets(grid, aabb, levels, outer, inner, band)
    simplified = []
    for (V, F), c in zip(full, levels):
        def distance(x: np.ndarray, c: float = c) -> np.ndarray:
            return grid.at(grid.f, x) - c * grid.at(grid.s, x)

        V2, F2, _ = simplify(V, F, distance, cfg.tolerance_px * footprint)
        simplified.append((V2, F2))
    t_layers = time.perf_counter() - t0
    meshes, (W, H), texel = unwrap(simplified, cfg.texel_px * footprint, cfg.max_atlas,
                                   cfg.size_mb * 1e6 / CHANNELS)
    tmap = texel_map(meshes, (W, H), variant)
    t_atlas = time.perf_counter() - t0 - t_layers
    start = distilled_start(field, tmap, grid, cfg.levels)
    tex, rec = fit_textures(meshes, start, tmap.inside, views, background, cfg, variant,
                            progress, tmap.layer)
    # triangles left transparent are dropped (the atlas keeps its charts: the coordinates of the
    # others do not move); closed: of the meshes before the unwrap, which splits their vertices
    # along seams but keeps the order of their triangles
    keep = visible_triangles(meshes, tex, tmap, cfg.prune_alpha)
    kept = [subset(V, F[m], uv) + (F0[m],) for (V, F, uv), (_, F0), m in
            zip(meshes, simplified, keep)]
    asset = BakedAsset(
        layers=[Layer(c, V, F.astype(np.uint32), uv, is_watertight(F0))
                for (V, F, uv, F0), c in zip(kept, levels)],
        atlas=quantise(tex), background=tuple(float(x) for x in background),
        up=tuple(float(x) for x in up))
    asset.meta = {"fit": {
        "levels": levels, "resolution": int(resolution),
        "triangles_marching_cubes": [int(len(F)) for _, F in full],
        "triangles_decimated": [int(len(F)) for _, F, _ in meshes],
        "triangles": sum(int(m.sum()) for m in keep),
        "tolerance": cfg.tolerance_px * footprint, "texel": texel, "footprint": footprint,
        "atlas_texels_in_charts": int(tmap.inside.sum()), "training_pixels": rec["pixels"],
        "spp": cfg.spp, "steps": rec["steps"], "rays_per_step": cfg.rays,
        "train_psnr_last": rec["train_psnr_last"], "seconds_layers": t_layers,
        "seconds_atlas": t_atlas, "seconds_fit": rec["seconds"],
        "seconds": time.perf_counter() - t0}}
    return asset
