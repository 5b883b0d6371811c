"""The layer meshes of a bake and their shared texture atlas.

1. Level sets (`level_sets`): u = f / s = c of the stage-2 field, c in ``levels``: the
   kernel-normalised SDF, so the layers spread where the kernel is wide (fuzz) and close up
   where it is sharp. The surface layer (c = 0) is kept whole; a side layer only inside the band
   (inside M+, outside M-) and only where its distance to the surface, |c| s, is at least one
   grid step (elsewhere it would repeat the surface layer): where the band is thin one layer
   draws it, where it is wide several.
2. Decimation (`simplify`) by each layer's own geometric error, not a global triangle count:
   the most a layer can be simplified while its triangles stay within ``tol`` of its level
   set (the grid's f - c s at the triangles' centroids and edge midpoints, 99th percentile):
   flat parts lose most of their triangles, detailed ones keep them.
3. One UV atlas for all layers (`unwrap`, xatlas), charts padded so that bilinear filtering
   does not bleed between them, at a texel size tied to the training pixels' footprint.
4. The texels' places (`texel_map`): each atlas texel's layer, triangle and barycentrics (a
   ray cast of the flattened UV meshes), hence its 3D point; `dilate` gives the texels outside
   every chart the value of the nearest chart texel.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from shells.errors import InputError


@dataclass
class Grid:
    """The field sampled on the bake's grid: SDF f and kernel size s, origin lo, cell spacing."""

    f: np.ndarray
    s: np.ndarray
    lo: np.ndarray
    spacing: np.ndarray

    def at(self, values: np.ndarray, x: np.ndarray) -> np.ndarray:
        """The grid ``values`` trilinearly at points x [n, 3]."""
        from scipy.ndimage import map_coordinates

        return map_coordinates(values, ((x - self.lo) / self.spacing).T, order=1, mode="nearest")

    @property
    def h(self) -> float:
        return float(np.max(self.spacing))


def sample_field(field: Any, aabb: np.ndarray, resolution: int, band: float,
                 progress: bool = False) -> Grid:
    from shells.levelset.grid import sample_grid_banded

    def fn(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        g = field.geometry_field(x)
        return g["sdf"], g["s"]

    f, s, spacing, _ = sample_grid_banded(fn, aabb, resolution, band, progress=progress)
    return Grid(f, s, np.asarray(aabb, np.float64)[0], np.asarray(spacing, np.float64))


def level_sets(grid: Grid, aabb: np.ndarray, levels: tuple[float, ...],
               outer: tuple[np.ndarray, np.ndarray], inner: tuple[np.ndarray, np.ndarray] | None,
               band: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per level (sorted, innermost first): V [n, 3] float32, F [m, 3] int64 (item 1)."""
    from shells.levelset.containment import inside
    from shells.levelset.mesh import clean_mesh, marching_cubes

    out = []
    for c in sorted(levels):
        mesh = clean_mesh(marching_cubes(grid.f - np.float32(c) * grid.s, aabb))
        V, F = np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int64)
        if c != 0 and len(F):
            sv = grid.at(grid.s, V)
            centre = V[F].mean(1)
            keep = (np.abs(c) * sv[F].min(1) >= grid.h) & (np.abs(grid.at(grid.f, centre))
                                                           < band)
            keep &= inside(*outer, centre)
            if inner is not None and len(inner[1]):
                keep &= ~inside(*inner, centre)
            V, F = subset(V, F[keep])
        out.append((V, F))
    return out


def subset(V: np.ndarray, F: np.ndarray, *per_vertex: np.ndarray) -> tuple[np.ndarray, ...]:
    """The vertices used by F, renumbered, with their per-vertex arrays."""
    used = np.unique(F)
    remap = np.full(len(V), -1, np.int64)
    remap[used] = np.arange(len(used))
    return (V[used], remap[F]) + tuple(a[used] for a in per_vertex)


def surface_error(V: np.ndarray, F: np.ndarray, distance: Any) -> float:
    """99th percentile of |distance| at the triangles' centroids and edge midpoints."""
    if len(F) == 0:
        return 0.0
    T = V[F].astype(np.float64)
    pts = np.concatenate([T.mean(1), 0.5 * (T[:, 0] + T[:, 1]), 0.5 * (T[:, 1] + T[:, 2]),
                          0.5 * (T[:, 2] + T[:, 0])])
    return float(np.quantile(np.abs(distance(pts)), 0.99))


def simplify(V: np.ndarray, F: np.ndarray, distance: Any, tol: float, steps: int = 7,
             most: float = 0.995) -> tuple[np.ndarray, np.ndarray, float]:
    """The most reduced quadric decimation of (V, F) whose `surface_error` under ``distance``
    (the signed distance to the level set, a function of points [n, 3]) is within ``tol`` of
    the full mesh's (a bisection over the share of triangles removed): V, F, the share."""
    import fast_simplification

    if len(F) < 64 or tol <= 0:
        return V, F, 0.0
    limit = surface_error(V, F, distance) + tol
    best = (V, F)
    ok, bad = 0.0, float(np.log(1.0 - most))  # log of the share of triangles kept
    for _ in range(steps):
        keep = float(np.exp(0.5 * (ok + bad)))
        V2, F2 = fast_simplification.simplify(V, F, 1.0 - keep)
        if len(F2) and surface_error(np.asarray(V2), np.asarray(F2), distance) <= limit:
            best, ok = (np.asarray(V2, np.float32), np.asarray(F2, np.int64)), np.log(keep)
        else:
            bad = np.log(keep)
    return best[0], best[1], 1.0 - len(best[1]) / len(F)


def unwrap(meshes: list[tuple[np.ndarray, np.ndarray]], texel: float, max_size: int,
           max_texels: float, padding: int = 2,
           ) -> tuple[list[tuple[np.ndarray, np.ndarray, np.ndarray]], tuple[int, int], float]:
    """One xatlas atlas of all ``meshes`` at about ``texel`` world units a texel, coarser if
    the atlas would exceed ``max_size`` a side or ``max_texels`` in all: per mesh (V, F, uv)
    with seams split (uv in [0, 1], (0, 0) the top-left corner), (width, height), the texel."""
    import xatlas

    for _ in range(8):
        atlas = xatlas.Atlas()
        for V, F in meshes:
            if len(F):
                atlas.add_mesh(np.ascontiguousarray(V, np.float32),
                               np.ascontiguousarray(F, np.uint32))
        pack = xatlas.PackOptions()
        pack.padding, pack.bilinear, pack.texels_per_unit = padding, True, 1.0 / texel
        pack.resolution = 0
        atlas.generate(pack_options=pack)
        W, H = int(atlas.width), int(atlas.height)
        over = max(max(W, H) / max_size, (W * H / max_texels) ** 0.5)
        if atlas.atlas_count == 1 and over <= 1.0:
            break
        texel *= max(over, 1.05) * 1.03
    else:
        raise InputError(f"the layers do not unwrap into one {max_size}^2 atlas; bake fewer "
                         "--levels or a smaller --size-mb")
    out, k = [], 0
    for V, F in meshes:
        if len(F) == 0:
            out.append((np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64),
                        np.zeros((0, 2), np.float32)))
            continue
        vmap, ind, uv = atlas.get_mesh(k)
        k += 1
        out.append((np.asarray(V, np.float32)[vmap], np.asarray(ind, np.int64).reshape(-1, 3),
                    np.asarray(uv, np.float32)))
    return out, (W, H), texel


@dataclass
class TexelMap:
    """Where each atlas texel lies: layer [H, W] int64 (-1: outside every chart), triangle of
    that layer [H, W], barycentrics of vertices 1 and 2 [H, W, 2], world point [H, W, 3]."""

    layer: np.ndarray
    prim: np.ndarray
    bary: np.ndarray
    point: np.ndarray

    @property
    def inside(self) -> np.ndarray:
        return self.layer >= 0


def texel_map(meshes: list[tuple[np.ndarray, np.ndarray, np.ndarray]], size: tuple[int, int],
              variant: str | None = None) -> TexelMap:
    """The `TexelMap` of an atlas: rays along -z through the texel centres against the UV
    triangles laid flat at z = 0."""
    import drjit as dr
    import mitsuba as mi

    from shells.device import mitsuba_variant
    from shells.render.raycast import make_mesh

    mitsuba_variant(variant)
    W, H = size
    counts = [len(F) for _, F, _ in meshes]
    offsets = np.concatenate([[0], np.cumsum(counts)])
    Vs, Fs, base = [], [], 0
    for V, F, uv in meshes:
        Vs.append(np.concatenate([uv, np.zeros((len(uv), 1), np.float32)], 1))
        Fs.append(F + base)
        base += len(uv)
    flat = mi.load_dict({"type": "scene", "uv": make_mesh(
        "atlas", np.concatenate(Vs), np.concatenate(Fs))})
    j, i = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    u, v = (i.ravel() + 0.5) / W, (j.ravel() + 0.5) / H
    o = mi.Point3f(mi.Float(u.astype(np.float32)), mi.Float(v.astype(np.float32)), 1.0)
    pi = flat.ray_intersect_preliminary(mi.Ray3f(o, mi.Vector3f(0, 0, -1)))
    valid = pi.is_valid()
    prim = dr.select(valid, mi.Int(pi.prim_index), -1)
    dr.eval(prim, pi.prim_uv)
    prim = np.asarray(prim).astype(np.int64)
    bary = np.stack([np.asarray(pi.prim_uv.x), np.asarray(pi.prim_uv.y)], 1)
    layer = np.where(prim >= 0, np.searchsorted(offsets, prim, side="right") - 1, -1)
    local = np.where(prim >= 0, prim - offsets[np.maximum(layer, 0)], -1)
    point = np.zeros((len(prim), 3), np.float32)
    for k, (V, F, _) in enumerate(meshes):
        sel = np.nonzero(layer == k)[0]
        if len(sel):
            T = V[F[local[sel]]]  # [n, 3, 3]
            b = bary[sel]
            point[sel] = (1 - b.sum(1))[:, None] * T[:, 0] + b[:, :1] * T[:, 1] + \
                b[:, 1:] * T[:, 2]
    return TexelMap(layer.reshape(H, W), local.reshape(H, W), bary.reshape(H, W, 2),
                    point.reshape(H, W, 3))


def dilate(values: torch.Tensor,  # [H, W, C]
           valid: np.ndarray,  # [H, W] bool
           ) -> torch.Tensor:
    """``values`` with every invalid texel replaced by the nearest valid one (chart padding:
    bilinear look-ups at a chart's edge read no foreign colour)."""
    from scipy.ndimage import distance_transform_edt

    if valid.all() or not valid.any():
        return values
    _, (jj, ii) = distance_transform_edt(~valid, return_indices=True)
    return values[torch.from_numpy(jj), torch.from_numpy(ii)]
