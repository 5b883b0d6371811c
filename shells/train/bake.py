"""Baking: nested layer meshes inside the band, their appearance fitted to the training photos.

1. Layers (`layer_meshes`): level sets u = f / s = c of the stage-2 field, c in ``levels``
   (default -2, -1, ..., 4): the kernel-normalised SDF, so the layers spread where the kernel
   is wide (fuzz) and close up where it is sharp. The surface layer (c = 0) is kept whole; a side
   layer only inside the band (inside M+, outside M-) and only where its distance to the
   surface, |c| s, is at least one grid step (elsewhere it would repeat the surface layer).
2. Start values distilled from the field: base colour = the radiance seen along -normal,
   opacity = the NeuS opacity of the layer's slab of u (the innermost slab is solid, as M- is).
3. Fit (`fit_layers`): every pixel of the given views (the photos, and the caller's band
   renders of the field from other cameras) is cast once against each layer with ``spp``
   rays (Mitsuba) and the hits cached; the per-vertex attributes are then fitted with Adam to
   the pixels, a pixel being the mean of its rays through `shells.render.baked.shade` (the
   compositing rule the viewers apply), with a smoothness term along mesh edges. Triangles
   left fully transparent are dropped, the rays cast again and the fit continued on the rest.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from shells.errors import InputError
from shells.progress import tqdm
from shells.render.baked import BakedAsset, LayerAttributes, LayerHits, LayerScene, quantise, shade

BYTES_PER_VERTEX = 12 + 4 + 12  # position, RGBA, three SH axes (the GLB's layout)
BYTES_PER_TRIANGLE = 12


@dataclass
class BakeConfig:
    # u = f / s of the layers (0: the surface), more outside, where fuzz spreads; fewer lost
    # core-fuzz's coat, more were not kept (outside M+): BENCHMARKS.md, "Baked shells"
    levels: tuple[float, ...] = (-2.0, -1.0, 0.0, 1.0, 2.0, 3.0, 4.0)
    cells_per_pixel: float = 1.25  # layer-grid cells across a training pixel's footprint (at
    # most the shells' grid): a little finer than the pixels, the smoothness term holds them
    size_mb: float = 60.0  # budget of the GLB; the grid is made coarser until the layers fit
    steps: int = 600  # Adam steps in all (three quarters before the pruning, the rest after)
    rays: int = 1 << 17  # training rays per step (pixels x spp)
    smooth: float = 0.1  # weight of the squared attribute differences along mesh edges
    smooth_edges: int = 1 << 18  # edges drawn per step for that term
    spp: int = 4  # rays per pixel, averaged as `shells-render --spp` and 4x MSAA draw a pixel
    max_pixels: int | None = 6_000_000  # a random share of the pixels beyond this many
    lr: float = 0.05  # start learning rate (on logits and SH), decayed 10x over the schedule
    prune_alpha: float = 1.5 / 255  # a triangle whose three opacities are below this goes
    teacher_views: int | None = None  # band renders of the field from turned training cameras
    # added to the photos (None: teacher_per_view per training view; 0: none): they hold the
    # vertices that the photos alone leave free
    teacher_per_view: int = 4
    max_triangles: int | None = None  # simplify the layers to about this many (a browser's
    # software GL draws about a million triangles a second); None: as marching cubes made them
    seed: int = 0


def layer_meshes(field: Any, aabb: np.ndarray, resolution: int, levels: tuple[float, ...],
                 outer: tuple[np.ndarray, np.ndarray], inner: tuple[np.ndarray, np.ndarray] | None,
                 band: float, max_triangles: int | None = None, progress: bool = False,
                 ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per level (sorted, innermost first): V [n, 3], F [m, 3], s at the vertices [n]; with
    ``max_triangles``, the layers simplified together to about that many triangles."""

    from shells.levelset.containment import inside
    from shells.levelset.grid import sample_grid_banded
    from shells.levelset.mesh import clean_mesh, marching_cubes

    def fn(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        g = field.geometry_field(x)
        return g["sdf"], g["s"]

    f, s, spacing, _ = sample_grid_banded(fn, aabb, resolution, band, progress=progress)
    h = float(np.max(spacing))
    lo = np.asarray(aabb, np.float64)[0]
    out = []
    for c in sorted(levels):
        mesh = clean_mesh(marching_cubes(f - np.float32(c) * s, aabb))
        V, F = np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int64)
        sv = f_at(s, lo, spacing, V)
        if c != 0 and len(F):
            centre = V[F].mean(1)
            keep = (np.abs(c) * sv[F].min(1) >= h) & (np.abs(f_at(f, lo, spacing, centre))
                                                      < band)
            keep &= inside(*outer, centre)
            if inner is not None and len(inner[1]):
                keep &= ~inside(*inner, centre)
            V, F, sv = _subset(V, F[keep], sv)
        out.append((V, F, sv))
    total = sum(len(F) for _, F, _ in out)
    if max_triangles and total > max_triangles:  # quadric decimation, each layer its share
        import fast_simplification

        for k, (V, F, _) in enumerate(out):
            if len(F) >= 8:
                V, F = fast_simplification.simplify(V, F, 1.0 - max_triangles / total)
                V = np.asarray(V, np.float32)
                out[k] = (V, np.asarray(F, np.int64), f_at(s, lo, spacing, V))
    return out


def f_at(f: np.ndarray, lo: np.ndarray, spacing: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The grid ``f`` (origin ``lo``, cell ``spacing``) trilinearly at points x [n, 3]."""
    from scipy.ndimage import map_coordinates

    return map_coordinates(f, ((x - lo) / spacing).T, order=1, mode="nearest")


def _subset(V: np.ndarray, F: np.ndarray, *per_vertex: np.ndarray) -> tuple[np.ndarray, ...]:
    """The vertices used by F, renumbered, with their per-vertex arrays."""
    used = np.unique(F)
    remap = np.full(len(V), -1, np.int64)
    remap[used] = np.arange(len(used))
    return (V[used], remap[F]) + tuple(a[used] for a in per_vertex)


def mesh_edges(F: np.ndarray) -> np.ndarray:
    """The unique edges [E, 2] (int64) of triangles F [m, 3]."""
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]).astype(np.int64)
    return np.unique(np.sort(e, 1), axis=0)


def mesh_bytes(meshes: list[tuple[np.ndarray, np.ndarray, Any]]) -> int:
    return sum(len(V) * BYTES_PER_VERTEX + len(F) * BYTES_PER_TRIANGLE for V, F, _ in meshes)


def distilled_start(field: Any, V: np.ndarray, s: np.ndarray, level: float,
                    levels: tuple[float, ...], h: float, chunk: int = 1 << 16,
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """rgba [n, 4] of a layer from the field (module docstring, item 2), sh zeros [n, 3, 3]."""
    ls = sorted(levels)
    k = ls.index(level)
    lo = -math.inf if k == 0 else 0.5 * (ls[k - 1] + level)
    hi = math.inf if k == len(ls) - 1 else 0.5 * (level + ls[k + 1])
    rgba = torch.empty(len(V), 4)
    with torch.no_grad():
        for a in range(0, len(V), chunk):
            x = torch.from_numpy(V[a:a + chunk]).float()
            geo = field.geometry(x)
            rgba[a:a + chunk, :3] = field.radiance(-geo["normal"], geo)
    t_hi = 1.0 if hi == math.inf else 1.0 / (1.0 + math.exp(-hi))
    t_lo = 0.0 if lo == -math.inf else 1.0 / (1.0 + math.exp(-lo))
    alpha = torch.full((len(V),), 1.0 - t_lo / t_hi)
    if level == 0:  # where the side layers are not kept the surface layer is the whole slab
        sharp = torch.from_numpy(s) * min((abs(c) for c in ls if c != 0), default=1.0) < h
        alpha[sharp] = 1.0
    rgba[:, 3] = alpha
    return rgba, torch.zeros(len(V), 3, 3)


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
            any_hit |= (h.prim >= 0).reshape(-1, spp).any(1)
        if keep < 1.0:
            any_hit &= torch.rand(len(any_hit), generator=gen) < keep
        px = torch.nonzero(any_hit).squeeze(1)
        rays = (px[:, None] * spp + torch.arange(spp)).reshape(-1)
        ds.append(d[rays].float())
        targets.append(images[i].reshape(-1, 3)[px])
        for k, h in enumerate(hs):
            hits[k].append(LayerHits(h.prim[rays].to(torch.int32), h.uv[rays], h.t[rays]))
    cat = [LayerHits(torch.cat([x.prim for x in hk]).long(), torch.cat([x.uv for x in hk]),
                     torch.cat([x.t for x in hk])) for hk in hits]
    return RayCache(torch.cat(ds), torch.cat(targets), cat, spp)


def _logit(x: torch.Tensor) -> torch.Tensor:
    x = x.clamp(0.02, 0.98)
    return torch.log(x / (1 - x))


def fit_layers(meshes: list[tuple[np.ndarray, np.ndarray]], start: list[LayerAttributes],
               views: list[tuple[Any, torch.Tensor]], background: tuple[float, float, float],
               steps: int, cfg: BakeConfig, variant: str | None = None,
               progress: bool = False, cache: RayCache | None = None,
               ) -> tuple[list[LayerAttributes], dict[str, Any]]:
    """Fit the attributes of fixed layer meshes to the images of ``views`` ((cameras, images)
    sets: the photos, the teacher's views); returns them and a record (steps, seconds, final
    PSNR of the batches, on the rays that hit a layer; the ray cache, which a later fit on the
    same meshes may pass back as ``cache``)."""
    t0 = time.perf_counter()
    scene = LayerScene(meshes, variant)
    if cache is None:
        cache = cache_rays(scene, views, cfg.spp, cfg.max_pixels, cfg.seed, progress)
    R = len(cache.target)
    if R == 0:
        raise InputError("no training ray hits the layers: nothing to bake (is the field empty?)")
    edges = [torch.from_numpy(mesh_edges(F)) for _, F in meshes]
    n_edges = sum(len(e) for e in edges)
    params = []
    for a in start:
        params += [_logit(a.rgba).requires_grad_(), a.sh.clone().requires_grad_()]
    opt = torch.optim.Adam(params, lr=cfg.lr)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda i: 0.1 ** (i / max(steps, 1)))
    gen = torch.Generator().manual_seed(cfg.seed)
    bg = torch.tensor(background, dtype=torch.float32)
    psnrs = []
    bar = tqdm(range(steps), desc="fit layers", disable=not progress)
    for _ in bar:
        idx = torch.randint(0, R, (max(1, min(cfg.rays // cfg.spp, R)),), generator=gen)
        d, hits = cache.batch(idx)
        attrs = [LayerAttributes(torch.sigmoid(params[2 * k]), params[2 * k + 1])
                 for k in range(len(start))]
        colour, _ = shade(scene.faces, attrs, hits, d, bg)
        colour = colour.reshape(-1, cfg.spp, 3).mean(1)  # the pixel: mean of its rays
        loss = torch.mean((colour - cache.target[idx]) ** 2)
        data_loss = loss.detach()
        if cfg.smooth > 0:  # neighbouring vertices alike: the noise of vertices seen by few rays
            share = min(1.0, cfg.smooth_edges / max(n_edges, 1))  # a random share per step
            for e, a in zip(edges, attrs):
                k = int(round(share * len(e)))
                if k:
                    e = e[torch.randint(0, len(e), (k,), generator=gen)] if share < 1 else e
                    dif = torch.cat([a.rgba[e[:, 0]] - a.rgba[e[:, 1]],
                                     (a.sh[e[:, 0]] - a.sh[e[:, 1]]).flatten(1)], 1)
                    loss = loss + cfg.smooth * (dif ** 2).sum() / (share * n_edges * dif.shape[1])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        psnrs.append(-10.0 * math.log10(max(data_loss.item(), 1e-12)))
        bar.set_postfix(psnr=f"{psnrs[-1]:.2f}", refresh=False)
    out = [LayerAttributes(torch.sigmoid(params[2 * k]).detach(), params[2 * k + 1].detach())
           for k in range(len(start))]
    return out, {"steps": steps, "pixels": R, "seconds": time.perf_counter() - t0,
                 "train_psnr_last": float(np.mean(psnrs[-10:])) if psnrs else None,
                 "cache": cache}


def prune(meshes: list[tuple[np.ndarray, np.ndarray]], attrs: list[LayerAttributes],
          threshold: float) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[LayerAttributes]]:
    """Drop triangles whose three opacities are below ``threshold`` (and unused vertices)."""
    out_m, out_a = [], []
    for (V, F), a in zip(meshes, attrs):
        alpha = a.rgba[:, 3].numpy()
        keep = (alpha[F] >= threshold).any(1)
        V2, F2, rgba, sh = _subset(V, F[keep], a.rgba.numpy(), a.sh.numpy())
        out_m.append((V2, F2))
        out_a.append(LayerAttributes(torch.from_numpy(rgba), torch.from_numpy(sh)))
    return out_m, out_a


def bake(field: Any, aabb: np.ndarray, outer: tuple[np.ndarray, np.ndarray],
         inner: tuple[np.ndarray, np.ndarray] | None, views: list[tuple[Any, torch.Tensor]],
         background: tuple[float, float, float], up: tuple[float, float, float],
         resolution: int, band: float, cfg: BakeConfig, variant: str | None = None,
         progress: bool = False) -> BakedAsset:
    """The whole bake (module docstring) -> a quantised `BakedAsset`."""
    t0 = time.perf_counter()
    budget = cfg.size_mb * 1e6
    res = int(resolution)
    for _ in range(4):  # coarser grids until the layers fit the budget (area ~ resolution^2)
        layers = layer_meshes(field, aabb, res, cfg.levels, outer, inner, band,
                              cfg.max_triangles, progress)
        size = mesh_bytes(layers)
        if size <= budget:
            break
        res = max(16, int(res * math.sqrt(budget / size) * 0.95))
    else:
        raise InputError(f"--size-mb {cfg.size_mb}: the layers take {size / 1e6:.1f} MB even "
                         f"on a {res}^3 grid; allow more or bake fewer --levels")
    t_layers = time.perf_counter() - t0
    h = float(np.max((aabb[1] - aabb[0]) / (res - 1)))
    levels = sorted(cfg.levels)
    start = [LayerAttributes(*distilled_start(field, V, s, c, cfg.levels, h))
             for (V, F, s), c in zip(layers, levels)]
    meshes = [(V, F) for V, F, _ in layers]
    first = max(1, (3 * cfg.steps) // 4)
    attrs, rec1 = fit_layers(meshes, start, views, background, first, cfg, variant, progress)
    tri_before = sum(len(F) for _, F in meshes)
    meshes, attrs = prune(meshes, attrs, cfg.prune_alpha)
    same = sum(len(F) for _, F in meshes) == tri_before  # nothing pruned: the same hits
    attrs, rec2 = fit_layers(meshes, attrs, views, background, max(1, cfg.steps - first), cfg,
                             variant, progress, cache=rec1["cache"] if same else None)
    asset = BakedAsset(
        layers=[quantise(c, V, F, a.rgba, a.sh) for (V, F), a, c in zip(meshes, attrs, levels)],
        background=tuple(float(x) for x in background), up=tuple(float(x) for x in up))
    asset.meta = {"fit": {
        "levels": levels, "resolution": res, "triangles_before_pruning": tri_before,
        "triangles": sum(len(F) for _, F in meshes), "training_pixels": rec1["pixels"],
        "spp": cfg.spp,
        "steps": rec1["steps"] + rec2["steps"], "rays_per_step": cfg.rays,
        "train_psnr_last": rec2["train_psnr_last"], "seconds_layers": t_layers,
        "seconds_fit": rec1["seconds"] + rec2["seconds"],
        "seconds": time.perf_counter() - t0}}
    return asset
