"""Occupancy-grid ray marching (the Instant-NGP / nerfacc approach) for the same trained field.

A baseline for the narrow band (render mode ``occupancy``): instead of shells, a binary grid
over the scene box says where the field may have density, and rays are marched with a fixed step
through it, skipping empty cells and stopping once they are (nearly) opaque.

Occupancy grid (`build_occupancy_grid`, cached per field by `occupancy_grid`)
    ``cfg.occ_resolution``^3 cells over the scene box. f and s are evaluated (Dr.Jit, no grad)
    at every cell centre and at ``cfg.occ_jitter`` uniformly jittered points per cell; a cell is
    occupied when at any of them

        |f| < h + k s,    h = half the cell diagonal, k = cfg.occ_k,

    and the result is dilated by one cell (3x3x3 max pool) for safety. Why this is enough: for
    an SDF (|grad f| <= 1) the centre test bounds |f| >= k s over the whole cell. Along a ray
    the NeuS transmittance across the layer f in [-k s, k s] falls by
    Phi_s(-k s) / Phi_s(k s) ~ e^-k, so a ray that enters an opaque surface has residual
    transmittance <= e^-k (k = 5: 0.7 %) when it reaches the skipped interior, and the skipped
    outside (f > k s) holds an opacity <= e^-k as well. The margins h and the dilation push the
    occupied layer further out (on the toy runs to about |f| < k s + 2 cells), so in practice
    the residual is far smaller. The interior of solids is deliberately empty: rays stop there.

Ray marching (`render_occupancy`)
    Box entry t0 and exit t1 as in ``full`` mode; step dt = cfg.occ_step (0: box diagonal /
    1024); sample j sits at t_j = t0 + (j + 1/2) dt with section length dt, j < ceil((t1 - t0) /
    dt). A sample whose point lies in an empty cell is not emitted, and the march jumps to the
    first step past that cell's exit face (one loop iteration per empty cell crossed, a DDA
    without the per-axis bookkeeping). Rays advance in rounds: each round marches every live ray
    until it has collected K samples (or left the box), evaluates the field at all collected
    samples at once, computes the NeuS alpha with the shared formula
    (``shells.fields.neus.neus_alpha`` through ``shading.shade_samples``, cos = d . n, section
    dt) and composites them front to back with ``shading.composite_packed``. Partial results
    chain exactly:

        C += T * C_round,  T *= 1 - O_round        (C_round, O_round over a black background)

    Rays whose transmittance fell below ``cfg.ert_eps`` (early ray termination) or that left the
    box are dropped (stream compaction) before the next round. As in Instant-NGP, K grows as
    rays die, keeping the samples per round near R0 * cfg.occ_chunk (R0 rays in the batch):
    K = cfg.occ_chunk * 2^floor(log2(R0 / R_live)), at most 8 x cfg.occ_chunk (powers of two,
    so only a few kernel variants are compiled). Few rounds matter: each one re-traces the field
    (milliseconds of Python) and synchronises for the compaction. Termination is checked between
    rounds, so a ray evaluates at most K - 1 samples past the point where T < eps; those samples
    are still composited (they only make the result more exact) and are counted.

Samples per ray = field evaluations actually made for that ray.

Unbounded fields (`field.similarity`, paper §4.7): the grid covers the field-space box (the
contracted ball of radius 2 around the centre, `ShellField`) and is built from f and s there;
rays march in the ray parameter s of `shells.render.warp` from t_near to t_far with a
fixed step ds (cfg.occ_step, or that box's diagonal / 1024), each step's world point taken to
field space for the lookup and its section [t(s - ds/2), t(s + ds/2)]: evenly in contracted
space, as Instant-NGP's exponential stepping through its cascaded grids. The cell jump of the
bounded march is left out there (a straight world ray is curved in field space), so every
step is visited, but only the occupied ones are evaluated and counted.

`raycast_floor` is the time floor of band rendering: the primary ray cast against M+ alone,
no field evaluation.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass
from typing import Any

import drjit as dr
import mitsuba as mi
import torch

from shells.config import RenderConfig
from shells.errors import InputError
from shells.fields.drjit_field import contract_point
from shells.fields.neus import half_cell_diagonal, may_have_density
from shells.levelset.grid import check_aabb
from shells.render.raycast import ShellScene, box_intervals, to_point3f
from shells.render.sampler import PackedSamples, field_warp
from shells.render.warp import ray_span, t_of_s
from shells.render.shading import WHITE, composite_packed, shade_samples

GRID_EVAL_CHUNK = 1 << 21  # points per field evaluation while building the grid
MAX_ROUND_GROWTH = 8  # samples per ray and round grow up to 8 x cfg.occ_chunk as rays die


@dataclass
class OccupancyGrid:
    """Binary occupancy over a box; cell (ix, iy, iz) is flat index (ix * N + iy) * N + iz."""

    occ: Any  # mi.Bool [N^3] occupied cells, flat index as above
    lo: tuple[float, float, float]  # box minimum corner (world units)
    cell: tuple[float, float, float]  # cell size per axis (world units)
    resolution: int  # N cells per axis

    def dense(self) -> torch.Tensor:  # -> [N, N, N] bool, indexed [ix, iy, iz]
        """The grid as a torch tensor (a copy), for tests and inspection."""
        N = self.resolution
        return torch.from_numpy(self.occ.numpy().copy()).reshape(N, N, N)

    @property
    def fraction(self) -> float:
        """Share of occupied cells."""
        return float(dr.count(self.occ)[0]) / dr.width(self.occ)


def _box(aabb: Any) -> torch.Tensor:  # -> [2, 3] float64 (min, max)
    """The scene box, validated once by the project's own check (shells.levelset.grid)."""
    return torch.from_numpy(check_aabb(torch.as_tensor(aabb).detach().cpu().numpy()))


def _eval_f_s(field: Any, x: torch.Tensor  # [P, 3] float32 world points
              ) -> tuple[torch.Tensor, torch.Tensor]:  # f [P], s [P]
    """SDF and kernel size at points (geometry only when the field offers it)."""
    p = to_point3f(x, mi.Point3f)
    if getattr(field, "similarity", None) is not None:  # an unbounded field's grid: field space
        r = field.eval_geometry_field(p)
    elif hasattr(field, "eval_geometry"):
        r = field.eval_geometry(p)
    else:  # fields without a geometry-only path: any direction will do for f and s
        r = field.eval(p, mi.Vector3f(0.0, 0.0, 1.0))
    sdf, s = mi.Float(r.sdf), mi.Float(r.s)
    if dr.width(s) != dr.width(sdf):
        s = dr.zeros(mi.Float, dr.width(sdf)) + s
    dr.eval(sdf, s)
    return sdf.torch().clone(), s.torch().clone()


def build_occupancy_grid(field: Any,  # Dr.Jit field: eval_geometry(x) or eval(x, d)
                         aabb: Any,  # [2, 3] scene box (min, max)
                         resolution: int = 128,
                         k: float = 5.0,
                         jitter: int = 2,
                         dilate: int = 1,  # cells of dilation (3x3x3 max pool per cell)
                         seed: int = 0,
                         ) -> OccupancyGrid:
    """Occupied where |f| < h + k s at the centre or a jittered point of the cell (see module)."""
    if resolution < 1 or k < 0 or jitter < 0 or dilate < 0:
        raise InputError(f"occupancy grid: resolution={resolution}, k={k}, jitter={jitter}, "
                         f"dilate={dilate}: need resolution >= 1 and the others >= 0")
    box = _box(aabb)
    N = int(resolution)
    cell = (box[1] - box[0]) / N  # [3]
    h = half_cell_diagonal(box, N)
    gen = torch.Generator().manual_seed(seed)
    occ = torch.zeros(N ** 3, dtype=torch.bool)  # flat (ix * N + iy) * N + iz
    for a in range(0, N ** 3, GRID_EVAL_CHUNK):
        flat = torch.arange(a, min(a + GRID_EVAL_CHUNK, N ** 3))  # [P]
        ijk = torch.stack([flat // (N * N), (flat // N) % N, flat % N], -1).double()  # [P, 3]
        for p in range(1 + jitter):
            u = (torch.full_like(ijk, 0.5) if p == 0 else
                 torch.rand(ijk.shape, generator=gen, dtype=torch.float64))  # [P, 3] in cell
            x = (box[0] + (ijk + u) * cell).float()  # [P, 3] world points
            f, s = _eval_f_s(field, x)
            occ[a:a + len(flat)] |= may_have_density(f, s, h, k)
    grid = occ.reshape(1, 1, N, N, N).float()
    if dilate > 0:
        grid = torch.nn.functional.max_pool3d(grid, 2 * dilate + 1, stride=1, padding=dilate)
    flat = grid.reshape(-1) > 0.5
    return OccupancyGrid(occ=mi.Bool(flat.numpy()), lo=tuple(float(v) for v in box[0]),
                         cell=tuple(float(v) for v in cell), resolution=N)


_GRIDS: "weakref.WeakKeyDictionary[Any, dict]" = weakref.WeakKeyDictionary()


def occupancy_grid(field: Any, aabb: Any, cfg: RenderConfig,
                   source: Any = None) -> OccupancyGrid:
    """The field's grid for this box and config, built on first use and cached with the field.

    The cache is keyed by the field object (a rebuilt DrJitField gets a new grid) and the
    box/resolution/k/jitter; it lives as long as the field does. ``source``: build the grid
    from another field's f and s instead (e.g. the same run's stage-1 field, whose geometry
    outside the band stage 2 never sampled); it then takes the place of the field's own grid
    in the cache, so later renders of ``field`` march through it.
    """
    key = (tuple(_box(aabb).reshape(-1).tolist()), int(cfg.occ_resolution), float(cfg.occ_k),
           int(cfg.occ_jitter))
    try:
        per_field = _GRIDS.setdefault(field, {})
    except TypeError:  # not weak-referenceable: no caching
        per_field = {}
    if key not in per_field or source is not None:
        per_field[key] = build_occupancy_grid(field if source is None else source, aabb,
                                              cfg.occ_resolution, cfg.occ_k, cfg.occ_jitter)
    return per_field[key]


def march_step(aabb: Any, cfg: RenderConfig) -> float:
    """dt: cfg.occ_step, or the box diagonal / 1024 when that is 0."""
    if cfg.occ_step > 0:
        return float(cfg.occ_step)
    box = _box(aabb)
    return float(torch.linalg.norm(box[1] - box[0])) / 1024.0


@dr.syntax
def _march(o: Any,  # mi.Point3f [Ra] live rays
           d: Any,  # mi.Vector3f [Ra] unit directions
           t0: Any,  # mi.Float [Ra] box entry
           n_steps: Any,  # mi.UInt32 [Ra] steps inside the box
           j: Any,  # mi.UInt32 [Ra] next step index
           occ: Any,  # mi.Bool [N^3] occupancy grid
           lo: Any, inv_cell: Any, cell: Any,  # mi.Vector3f (width 1) grid geometry
           N: int, dt: float, K: int,
           t_out: Any,  # mi.Float [Ra * K] written: sample distances, ray r at r * K + i
           ) -> tuple[Any, Any]:  # samples written [Ra], next step index [Ra]
    """Collect up to K occupied sample positions per ray, from step j on; skip empty cells."""
    base = dr.arange(mi.UInt32, dr.width(j)) * K
    n = mi.UInt32(0)  # samples collected this round
    last = float(N - 1)
    while dr.hint((n < K) & (j < n_steps), max_iterations=-1, label="occ_march"):
        t = dr.fma(mi.Float(j) + 0.5, dt, t0)
        x = dr.fma(d, t, o)
        c = dr.clip(dr.floor((x - lo) * inv_cell), 0.0, last)  # cell coordinates, float
        ci = mi.Vector3u(c)
        if dr.gather(mi.Bool, occ, (ci.x * N + ci.y) * N + ci.z):
            dr.scatter(t_out, t, base + n)
            n += 1
            j += 1
        else:
            # leave the empty cell: first step whose sample lies past the cell's exit face
            face = dr.fma(c + dr.select(d > 0, 1.0, 0.0), cell, lo)  # [3] exit planes
            tf = dr.select(dr.abs(d) > 1e-12, (face - o) / d, dr.inf)
            t_exit = dr.minimum(dr.minimum(tf.x, tf.y), tf.z)
            j_exit = dr.ceil((t_exit - t0) / dt - 0.5)
            j_exit = dr.clip(j_exit, 0.0, mi.Float(n_steps))  # t_exit may be behind / far
            j = dr.maximum(j + 1, mi.UInt32(j_exit))
    return n, j


@dr.syntax
def _march_warped(o: Any, d: Any,  # mi.Point3f / mi.Vector3f [Ra] live rays (world)
                  tb: Any,  # mi.Float [Ra] each ray's t_b (shells.render.warp)
                  n_steps: Any, j: Any,  # mi.UInt32 [Ra] steps in s, next step index
                  occ: Any, lo: Any, inv_cell: Any,  # grid over the field-space box
                  N: int, ds: float, K: int, centre: tuple[float, float, float],
                  radius: float,
                  s_out: Any,  # mi.Float [Ra * K] written: sample parameters s
                  ) -> tuple[Any, Any]:  # samples written [Ra], next step index [Ra]
    """Collect up to K occupied steps per ray from step j on, in s, looking up each step's
    field-space point (the contraction of its world point)."""
    base = dr.arange(mi.UInt32, dr.width(j)) * K
    n = mi.UInt32(0)
    last = float(N - 1)
    while dr.hint((n < K) & (j < n_steps), max_iterations=-1, label="occ_march_warped"):
        s = (mi.Float(j) + 0.5) * ds
        z = contract_point(dr.fma(d, t_of_s(s, tb), o), centre, radius)[0]
        ci = mi.Vector3u(dr.clip(dr.floor((z - lo) * inv_cell), 0.0, last))
        if dr.gather(mi.Bool, occ, (ci.x * N + ci.y) * N + ci.z):
            dr.scatter(s_out, s, base + n)
            n += 1
        j += 1
    return n, j


def render_occupancy(field: Any,  # Dr.Jit field: eval(x, d) -> FieldSample
                     origins: Any,  # [R, 3] torch/numpy or mi.Point3f
                     dirs: Any,  # [R, 3] unit directions
                     cfg: RenderConfig,
                     aabb: Any,  # [2, 3] scene box
                     background: tuple[float, float, float] = WHITE,  # the data set's
                     grid: OccupancyGrid | None = None,  # default: occupancy_grid(field, ...)
                     ) -> tuple[Any, Any, Any]:
    """Colour mi.Color3f [R] over the background, opacity mi.Float [R], samples mi.UInt32 [R]."""
    warp = field_warp(field)
    if warp is not None:  # unbounded: the grid over the field-space box, marched in s
        aabb = field.aabb
    if aabb is None:
        raise InputError("occupancy mode needs the scene box: pass aabb [2, 3]")
    grid = grid if grid is not None else occupancy_grid(field, aabb, cfg)
    o = to_point3f(origins, mi.Point3f)
    d = to_point3f(dirs, mi.Vector3f)
    R, N = dr.width(d), grid.resolution
    dt = march_step(aabb, cfg)
    lo, cell = mi.Vector3f(*grid.lo), mi.Vector3f(*grid.cell)
    inv_cell = mi.Vector3f(*[1.0 / c for c in grid.cell])
    bg = mi.Color3f(*[float(c) for c in background])

    if warp is None:
        iv = box_intervals(o, d, aabb)  # K = 1 interval: [near, far], count 0 on a miss
        near, far = iv.enter.array, iv.exit.array  # [R]
        hit = mi.Int(iv.count.array) > 0
        steps = dr.select(hit, mi.UInt32(dr.ceil((far - near) / dt)), 0)  # [R]
    else:  # steps j from s(t_near) = t_near to s(t_far); t_b is kept in `near` for the march
        t_near, near, t_far = ray_span(o, d, *warp)
        far = 2.0 * near - near * near / t_far  # s(t_far)
        steps = mi.UInt32(dr.ceil(far / dt))
        first = mi.UInt32(dr.floor(t_near / dt))

    trans = dr.ones(mi.Float, R)  # outputs, written back for every live ray each round
    acc = dr.zeros(mi.Color3f, R)
    count = dr.zeros(mi.UInt32, R)
    dr.eval(steps, trans, acc, count)

    rid = dr.compress(steps > 0)  # [Ra] live rays (indices into the batch)
    # live-ray state, compacted together with rid
    ro, rd = dr.gather(mi.Point3f, o, rid), dr.gather(mi.Vector3f, d, rid)
    t0, ns = dr.gather(mi.Float, near, rid), dr.gather(mi.UInt32, steps, rid)
    j = (dr.zeros(mi.UInt32, dr.width(rid)) if warp is None
         else dr.gather(mi.UInt32, first, rid))
    T = dr.ones(mi.Float, dr.width(rid))
    C = dr.zeros(mi.Color3f, dr.width(rid))
    n_total = dr.zeros(mi.UInt32, dr.width(rid))
    dr.eval(ro, rd, t0, ns, j, T, C, n_total)
    black = mi.Color3f(0.0)
    R0 = max(dr.width(rid), 1)
    while dr.width(rid) > 0:
        Ra = dr.width(rid)
        growth = min(MAX_ROUND_GROWTH, 2 ** int(math.floor(math.log2(R0 / Ra))))
        K = int(cfg.occ_chunk) * growth  # samples per live ray this round
        t_pad = dr.zeros(mi.Float, Ra * K)  # [Ra, K] padded sample distances (s if warped)
        if warp is None:
            n, j = _march(ro, rd, t0, ns, j, grid.occ, lo, inv_cell, cell, N, dt, K, t_pad)
        else:
            n, j = _march_warped(ro, rd, t0, ns, j, grid.occ, lo, inv_cell, N, dt, K,
                                 warp[0], warp[1], t_pad)
        dr.eval(t_pad, n, j)
        slot = dr.arange(mi.UInt32, Ra * K)
        idx = dr.compress((slot % K) < dr.repeat(n, K))  # [M] valid slots, ray-major
        M = dr.width(idx)
        if M > 0:
            t, delta = dr.gather(mi.Float, t_pad, idx), dr.full(mi.Float, dt, M)
            if warp is not None:  # s -> t, the section [s - ds/2, s + ds/2] -> world
                tb = dr.gather(mi.Float, t0, idx // K)
                t, delta = (t_of_s(t, tb),
                            t_of_s(t + 0.5 * dt, tb) - t_of_s(t - 0.5 * dt, tb))
            samples = PackedSamples(t=t, delta=delta, ray=idx // K,
                                    start=dr.prefix_sum(n), count=n, max_count=K)
            alpha, rgb = shade_samples(field, samples, ro, rd)  # [M] each
            c_round, o_round = composite_packed(alpha, rgb, samples.start, n, black)  # [Ra]
            C = dr.fma(c_round, T, C)
            T = T * (1.0 - o_round)
            n_total = n_total + n
        dr.scatter(trans, T, rid)
        dr.scatter(acc, C, rid)
        dr.scatter(count, n_total, rid)
        live = (T >= cfg.ert_eps) & (j < ns)
        dr.eval(trans, acc, count, C, T, n_total, j, live)
        keep = dr.compress(live)  # [Ra'] positions among the current live rays
        rid, ro, rd = (dr.gather(type(v), v, keep) for v in (rid, ro, rd))
        t0, ns, j, T, C, n_total = (dr.gather(type(v), v, keep) for v in (t0, ns, j, T, C, n_total))
        dr.eval(rid, ro, rd, t0, ns, j, T, C, n_total)
    colour = dr.fma(bg, trans, acc)
    opacity = 1.0 - trans
    dr.eval(colour, opacity, count)
    return colour, opacity, count


def raycast_floor(scene: ShellScene,
                  origins: Any,  # [R, 3] torch/numpy or mi.Point3f
                  dirs: Any,  # [R, 3] unit directions
                  ) -> tuple[Any, Any]:  # hit mi.Bool [R], distance mi.Float [R] (inf on a miss)
    """Primary rays against the scene's shells, nothing else: the time floor of band rendering.

    Give it a ShellScene holding M+ only (``ShellScene(outer)``) to time "M+ ray cast alone";
    the call is the one the band sampler's first depth peel makes.
    """
    o = to_point3f(origins, mi.Point3f)
    d = to_point3f(dirs, mi.Vector3f)
    si = scene.scene.ray_intersect(mi.Ray3f(o, d), mi.RayFlags.Minimal, False)
    hit = si.is_valid()
    t = dr.select(hit, si.t, dr.inf)
    dr.eval(hit, t)
    return hit, t


def floor_image(scene: ShellScene,
                origins: torch.Tensor,  # [H * W, 3] row-major pixel rays
                dirs: torch.Tensor,  # [H * W, 3]
                height: int, width: int) -> torch.Tensor:  # [H, W] bool: pixel hits M+
    """`raycast_floor` for a frame, returned as a torch mask (what the timing covers)."""
    if origins.shape[0] != height * width or dirs.shape[0] != height * width:
        raise InputError(f"{origins.shape[0]} rays for a {width}x{height} image")
    hit, _ = raycast_floor(scene, origins, dirs)
    return mi.TensorXf(mi.Float(hit), (height, width)).torch() > 0.5


def grid_summary(grid: OccupancyGrid) -> dict[str, Any]:
    """Resolution, occupied share and cell size, for reports."""
    half_diagonal = 0.5 * math.sqrt(sum(c * c for c in grid.cell))
    return {"resolution": grid.resolution, "occupied_fraction": grid.fraction,
            "cell": list(grid.cell), "half_diagonal": half_diagonal}
