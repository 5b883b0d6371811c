"""Shell extraction: gridded (f, s) -> outer shell M+ and inner shell M- (§3.3).

M+ = {SDF+ = 0} with SDF+ = min(f0, dilated f0) bounds everything visible; M- = {SDF- = 0}
with SDF- = max(f0, eroded f0) is where rays may stop (solid interior). Where the band
swallows a thin part, M- is simply absent there; if it is absent everywhere, ``inner`` is an
empty mesh, written as a valid PLY with 0 vertices and 0 faces, and ``stats['inner_empty']``
is true: the renderer then never terminates rays early ("no inner shell").
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy import ndimage

from shells.config import ShellConfig
from shells.errors import InputError
from shells.files import commit_files
from shells.levelset.evolve import (dilation_velocity, erosion_velocity, shell_sdfs,
                                    substeps)
from shells.levelset.grid import check_aabb
from shells.levelset.mesh import clean_mesh, marching_cubes, write_ply


@dataclass
class Shells:
    outer: trimesh.Trimesh  # M+, world units, outward faces
    inner: trimesh.Trimesh  # M-, may be empty (no interior termination)
    sdf_plus: np.ndarray  # [X, Y, Z] float32, min(f0, dilated)
    sdf_minus: np.ndarray  # [X, Y, Z] float32, max(f0, eroded)
    stats: dict  # JSON-ready: counts, band widths, volumes, parameters, timings
    aabb: np.ndarray  # [2, 3]
    f: np.ndarray | None = None  # [X, Y, Z] the input SDF (kept for the slice figure)
    s: np.ndarray | None = None  # [X, Y, Z] the input kernel size


def check_field(f: np.ndarray, s: np.ndarray, aabb) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate the gridded field once, at the boundary; returns float32 f, s and the box."""
    box = check_aabb(aabb)
    f = np.asarray(f, dtype=np.float32)
    s = np.asarray(s, dtype=np.float32)
    if f.ndim != 3 or min(f.shape) < 2 or s.shape != f.shape:
        raise InputError(f"field grids f {f.shape} and s {s.shape}: expected two equal "
                         "[X, Y, Z] grids with at least 2 points per axis")
    if not np.all(np.isfinite(f)) or not np.all(np.isfinite(s)):
        raise InputError("the SDF or kernel grid contains NaN/inf: the checkpoint is corrupt "
                         "or training diverged; retrain or resume from an earlier checkpoint")
    if np.any(s <= 0):
        raise InputError(f"kernel size s has non-positive values (min {float(s.min()):.3g}); "
                         "s must be > 0 world units: check the field's kernel output")
    if not np.any(f < 0):
        raise InputError("the SDF has no zero crossing in the scene box (f > 0 everywhere, "
                         "nothing inside): training diverged or the aabb is wrong")
    if not np.any(f > 0):
        raise InputError("the SDF has no zero crossing in the scene box (f < 0 everywhere, "
                         "all inside): training diverged or the aabb is too small")
    return f, s, box


def extract_shells(f: np.ndarray,  # [X, Y, Z] SDF at the grid points, f > 0 outside
                   s: np.ndarray,  # [X, Y, Z] kernel size, world units
                   aabb,  # [2, 3] box whose corners are the first / last grid points
                   cfg: ShellConfig | None = None,
                   device: str | torch.device = "cpu",
                   fixed_width: float | None = None,
                   roi: tuple[tuple[float, float, float], float] | None = None,
                   progress: bool = False) -> Shells:
    """Dilate / erode f by the kernel-dependent speeds and mesh both shells.

    ``fixed_width`` w replaces the adaptive band by the fixed one {|f| <= w} (SDF+ = f - w,
    SDF- = f + w): the baseline of the paper's ablation (Table 4, "fixed +-w"). ``roi``
    (centre, radius): the ball of interest of an unbounded scene, against whose faces small
    components are measured (`clean_mesh`). ``progress``: bars over the evolutions' steps.
    """
    cfg = cfg if cfg is not None else ShellConfig()
    f, s, box = check_field(f, s, aabb)
    spacing = (box[1] - box[0]) / (np.asarray(f.shape) - 1)
    timings = {}
    t0 = time.perf_counter()
    if fixed_width is None:
        sdf_plus, sdf_minus = shell_sdfs(f, s, spacing, cfg, device, progress)
    else:
        if not fixed_width > 0:
            raise InputError(f"fixed band width {fixed_width}: must be > 0 world units")
        sdf_plus, sdf_minus = f - np.float32(fixed_width), f + np.float32(fixed_width)
    timings["evolve"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    outer = clean_mesh(marching_cubes(sdf_plus, box), cfg.min_component_fraction, roi)
    inner = clean_mesh(marching_cubes(sdf_minus, box), cfg.min_component_fraction, roi)
    surface = marching_cubes(f, box)
    timings["mesh"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    widths = band_widths(surface, sdf_plus, sdf_minus, box, cfg)
    timings["stats"] = time.perf_counter() - t0

    stats = {
        "resolution": list(f.shape),
        "aabb": box.tolist(),
        "spacing": spacing.tolist(),
        "params": dataclasses.asdict(cfg),
        "band": "adaptive" if fixed_width is None else f"fixed +-{fixed_width:g}",
        "substeps": {  # per Euler step, from the fastest speed in the grid (an upper bound)
            "dilate": substeps(float(dilation_velocity(s, cfg).max()), cfg.dt, spacing, cfg.cfl),
            "erode": substeps(float(erosion_velocity(s, cfg).max()), cfg.dt, spacing, cfg.cfl)},
        "outer_triangles": int(len(outer.faces)),
        "outer_vertices": int(len(outer.vertices)),
        "inner_triangles": int(len(inner.faces)),
        "inner_vertices": int(len(inner.vertices)),
        "inner_empty": bool(len(inner.faces) == 0),
        "outer_watertight": bool(outer.is_watertight),
        "inner_watertight": bool(len(inner.faces) == 0 or inner.is_watertight),
        "volume_surface": float(surface.volume) if len(surface.faces) else 0.0,
        "volume_outer": float(outer.volume) if len(outer.faces) else 0.0,
        "volume_inner": float(inner.volume) if len(inner.faces) else 0.0,
        "kernel_size": _percentiles(s[np.abs(f) < 2 * spacing.max()]),
        **widths,
        "timings_s": timings,
    }
    stats["volume_between"] = stats["volume_outer"] - stats["volume_inner"]
    return Shells(outer, inner, sdf_plus, sdf_minus, stats, box, f, s)


def _percentiles(x: np.ndarray) -> dict:
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {"count": 0}
    p = np.percentile(x, [5, 50, 95])
    return {"count": int(x.size), "mean": float(x.mean()), "p5": float(p[0]),
            "p50": float(p[1]), "p95": float(p[2]), "max": float(x.max())}


def band_widths(surface: trimesh.Trimesh,  # M0: marching cubes of f0
                sdf_plus: np.ndarray, sdf_minus: np.ndarray,  # [X, Y, Z]
                box: np.ndarray,  # [2, 3]
                cfg: ShellConfig, max_points: int = 20000) -> dict:
    """Statistics of `normal_distances`: dilation d+, erosion d-, band width d+ + d-.

    Points with no M- within reach (the band swallowed the interior) are counted in
    ``no_inner_fraction`` and left out of the width statistics.
    """
    if len(surface.faces) == 0:
        return {"band_width": {"count": 0}, "dilation": {"count": 0}, "erosion": {"count": 0},
                "no_inner_fraction": 1.0}
    _, d_plus, d_minus = normal_distances(surface, sdf_plus, sdf_minus, box, cfg, max_points)
    return {"band_width": _percentiles(d_plus + d_minus), "dilation": _percentiles(d_plus),
            "erosion": _percentiles(d_minus),
            "no_inner_fraction": float(np.mean(np.isnan(d_minus)))}


def normal_distances(surface: trimesh.Trimesh, sdf_plus: np.ndarray, sdf_minus: np.ndarray,
                     box: np.ndarray, cfg: ShellConfig, max_points: int = 20000
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # [N, 3], [N], [N]
    """Distances from the surface f0 = 0 to M+ (outward) and to M- (inward) along the normal.

    At (a subsample of) the M0 vertices p with outward normal n, march t in steps of h/8 and
    find, by linear interpolation of the trilinearly interpolated grids, the first t with
    SDF+(p + t n) > 0 (d+) and with SDF-(p - t n) < 0 (d-); NaN where none is within reach
    (2 zeta + 2 h). Returns the points p and d+, d-.
    """
    spacing = (box[1] - box[0]) / (np.asarray(sdf_plus.shape) - 1)
    verts = np.asarray(surface.vertices)
    normals = np.asarray(surface.vertex_normals)
    if len(verts) > max_points:
        pick = np.random.default_rng(0).choice(len(verts), max_points, replace=False)
        verts, normals = verts[pick], normals[pick]
    step = spacing.min() / 8.0

    def first_crossing(grid, sign, reach):  # first t with sign * grid(p + sign t n) > 0
        ts = np.arange(0.0, reach + step, step)
        pts = verts[:, None, :] + sign * ts[None, :, None] * normals[:, None, :]  # [N, T, 3]
        idx = ((pts - box[0]) / spacing).reshape(-1, 3).T
        vals = sign * ndimage.map_coordinates(grid, idx, order=1, mode="nearest")
        vals = vals.reshape(pts.shape[:2])
        hit = vals > 0
        j = np.argmax(hit, axis=1)
        rows = np.arange(len(j))
        a, b = vals[rows, np.maximum(j - 1, 0)], vals[rows, j]
        frac = np.where((j > 0) & (b > a), -a / np.where(b > a, b - a, 1.0), 0.0)
        t = np.where(j > 0, ts[np.maximum(j - 1, 0)] + frac * step, 0.0)
        return np.where(hit[rows, j], t, np.nan)

    d_plus = first_crossing(sdf_plus, +1, 2 * cfg.dilate_zeta + 2 * spacing.max())
    d_minus = first_crossing(sdf_minus, -1, 2 * cfg.erode_zeta + 2 * spacing.max())
    return verts, d_plus, d_minus


def write_shells(shells: Shells, out_dir: str | Path, figure: bool = True) -> None:
    """Write out_dir/{outer.ply, inner.ply, stats.json[, slice.png]} all or nothing.

    Everything is written into a hidden staging folder next to ``out_dir`` first; only when
    all files exist are they renamed into place (signals held back meanwhile), so a failure or
    an interruption leaves ``out_dir`` as it was.
    """
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(dir=out_dir.parent, prefix=f".{out_dir.name}-staging-"))
    try:
        write_ply(stage / "outer.ply", shells.outer)
        write_ply(stage / "inner.ply", shells.inner)
        (stage / "stats.json").write_text(json.dumps(shells.stats, indent=2) + "\n")
        if figure and shells.f is not None and shells.s is not None:
            from shells.levelset.figure import slice_figure
            slice_figure(shells.f, shells.s, shells.sdf_plus, shells.sdf_minus, shells.aabb,
                         stage / "slice.png")
        commit_files(stage, out_dir, last="stats.json")
    finally:
        shutil.rmtree(stage, ignore_errors=True)
