"""Level-set dilation and erosion of a gridded SDF (§3.3, Procedures 1-2 of the appendix).

The PDE, with f > 0 outside (NeuS convention) and n = grad f / |grad f|::

    df/dt = -|grad f| (v - lambda_w * kappa) * w(f),   kappa = div(n),
    w(f)  = 1/2 (1 + cos(pi * clamp(f / zeta, -1, 1))).

Units and choices (the paper leaves them open; these make the result independent of the grid
resolution as far as possible):

- Space and f are in world units (the scene box, typically [-1, 1]^3); derivatives are central
  differences with the world grid spacing, so |grad f| = 1 for an exact SDF.
- Time: the paper's T = 50 steps of dt = 0.1 give a total time T * dt = 5. The normal speed v
  is in world units per unit time, so a front not slowed by w(f) moves v * T * dt = 5 v world
  units. The falloff w(f) freezes every level set |f| >= zeta: the zero level set can never
  pass the original f = +zeta (dilation) or f = -zeta (erosion) level set, so for an exact SDF
  the total motion is at most zeta world units (the paper's "soft dilation near the surface").
- Stability: forward Euler with central differences is only conditionally usable, so each of
  the T steps is split into the fewest equal sub-steps that keep max|v| * dt_sub <= cfl * h
  (Courant number ``cfl``, default 0.5). The total time stays T * dt; only the accuracy of
  the integration depends on the grid.
- Curvature: lambda_curv is in grid units (the paper's value 0.01 with dt = 0.1 would be an
  explicit diffusion far beyond its stability limit in world units at 256^3). In world units
  lambda_w = lambda_curv * h^2, so lambda_w * dt / h^2 = 0.001 at every resolution: the term
  smooths the front at the voxel scale only. Its sign is the smoothing one (convex bumps
  recede, like mean-curvature flow); the opposite sign would be an ill-posed backward heat
  equation.
- Narrow band: w(f0) = 0 outside |f0| < zeta and f only moves where w > 0, so values there
  never change; only the band voxels are updated (flat index gathers), which makes a 256^3
  grid cheap.

Velocities (world units per unit time; s is the kernel size in world units, larger = fuzzier;
the surface density is sigma = 1 / (2 s)):

- dilation  v_d(x) = min(beta_d * s(x), v_max) where s(x) > sigma_min, else 0
  (sigma_min is an optional threshold on the kernel size s below which nothing grows
  outward; the default 0 dilates every surface by about 5 * beta_d * s = 3 s, which keeps the
  outer part of a sharp kernel - silhouettes and the colour weighting in front of the
  surface - inside the band: without dilation the band render of a sharp surface falls
  well short of full-ray rendering; see BENCHMARKS.md),
- erosion   v_e(x) = min(beta_e * s(x), v_max), moving inward.

With the defaults (beta_d = 0.6, sigma_min = 0, beta_e = 0.3, v_max = 0.035) an opaque surface
with s = 0.005 gets a band of about 3 s + 1.5 s = 0.023 (4.5 % of a radius-0.5 sphere), while
a fuzzy region (s = 0.05) is dilated and eroded up to the zeta limits (paper: 0.1 outward, 0.05
inward; the toy preset allows 0.25 / 0.1 for the thick core-fuzz coat, see shells/presets.py).
"""

from __future__ import annotations

import math
from typing import Any

import drjit as dr
import numpy as np
import torch

from shells.config import ShellConfig
from shells.device import drjit_llvm


def falloff(f, zeta: float):
    """w(f) = 1/2 (1 + cos(pi clamp(f / zeta, -1, 1))): 1 at f = 0, 0 for |f| >= zeta.

    Works on numpy arrays and torch tensors of any shape.
    """
    if isinstance(f, torch.Tensor):
        return 0.5 * (1.0 + torch.cos(math.pi * torch.clamp(f / zeta, -1.0, 1.0)))
    return 0.5 * (1.0 + np.cos(np.pi * np.clip(np.asarray(f) / zeta, -1.0, 1.0)))


def dilation_velocity(s: np.ndarray,  # [...] kernel size, world units
                      cfg: ShellConfig) -> np.ndarray:  # [...] outward speed >= 0
    """v_d = min(beta_d * s, v_max) where s > sigma_min, else 0 (world units per unit time)."""
    s = np.asarray(s, dtype=np.float32)
    v = np.minimum(cfg.beta_d * s, cfg.v_max)
    return np.where(s > cfg.sigma_min, v, 0.0).astype(np.float32)


def erosion_velocity(s: np.ndarray,  # [...] kernel size, world units
                     cfg: ShellConfig) -> np.ndarray:  # [...] inward speed >= 0
    """v_e = min(beta_e * s, v_max) (world units per unit time; the front moves inward)."""
    s = np.asarray(s, dtype=np.float32)
    return np.minimum(cfg.beta_e * s, cfg.v_max).astype(np.float32)


def substeps(v_max: float, dt: float, spacing, cfl: float = 0.5) -> int:
    """Sub-steps per Euler step so that v_max * dt / n <= cfl * min(spacing)."""
    h = float(np.min(spacing))
    return max(1, int(math.ceil(abs(v_max) * dt / (cfl * h) - 1e-9)))


BYTES_PER_BAND_VOXEL = 200  # memory of one band voxel in a step: 19 neighbour indices and
# ~25 float temporaries (4 bytes each); the band is split into chunks that fit the budget
LLVM_BYTES_PER_BAND_VOXEL = 16  # the same in the fused Dr.Jit kernel (`_integrate_llvm`): its
# index, speed and new value (4 bytes each); neighbours and temporaries stay in registers


def evolve(f0: np.ndarray,  # [X, Y, Z] SDF on the grid, f > 0 outside (world units)
           v: np.ndarray,  # [X, Y, Z] normal speed: > 0 moves the zero set outward, < 0 inward
           spacing,  # (3,) grid spacing in world units
           steps: int, dt: float, zeta: float, lambda_curv: float,
           cfl: float = 0.5, device: str | torch.device = "cpu",
           memory_mb: int = 2048,
           progress: str | None = None) -> np.ndarray:  # [X, Y, Z]
    """Integrate df/dt = -|grad f| (v - lambda_curv h^2 kappa) w(f) for total time steps * dt.

    Central differences (one-sided at the grid border), forward Euler with the sub-steps of
    `substeps`; only the band |f0| < zeta is updated (see the module docstring for units).
    A band larger than ``memory_mb`` allows (`BYTES_PER_BAND_VOXEL`, or on the CPU
    `LLVM_BYTES_PER_BAND_VOXEL`) is updated in chunks (in torch, their neighbour indices
    rebuilt every step); each step still reads the grid of the step before (the chunks' new
    values are written back together), so the result is the same, bit for bit. ``progress``:
    the label of a progress bar over the (sub-)steps (None: no bar). Returns the evolved grid
    as float32 numpy.

    On the CPU a step is one fused Dr.Jit LLVM kernel (`_integrate_llvm`, the same arithmetic
    as the torch `_step`, which CUDA tensors take): the ~26 tensor ops of `_step` each read and
    write the whole band, where the kernel reads a voxel's neighbours once and finds them from
    its flat index (on fox's wide shells at 256^3 the evolution runs well over an order of
    magnitude faster than in torch; BENCHMARKS.md).
    """
    f0 = np.asarray(f0, dtype=np.float32)
    assert f0.ndim == 3 and np.shape(v) == f0.shape, (f0.shape, np.shape(v))
    shape = f0.shape
    h = np.asarray(spacing, dtype=np.float64).reshape(3)
    band = np.flatnonzero(np.abs(f0) < zeta)
    if band.size == 0 or steps <= 0:
        return f0.copy()
    f = torch.from_numpy(f0.copy()).to(device).reshape(-1)
    active = torch.from_numpy(band).to(device)
    v_a = torch.from_numpy(np.asarray(v, dtype=np.float32).reshape(-1)[band]).to(device)
    # Small bands: one thread (intra-op threading of ~1e5-element ops costs more than it
    # saves, badly so on a loaded machine); the previous setting is restored on exit.
    threads = torch.get_num_threads()
    if band.size < (1 << 21) and f.device.type == "cpu":
        torch.set_num_threads(1)
    chunk = max(1024, (int(memory_mb) << 20) // BYTES_PER_BAND_VOXEL)
    try:
        if f.device.type == "cpu" and drjit_llvm() and f.numel() < 2 ** 31:
            chunk = max(1024, (int(memory_mb) << 20) // LLVM_BYTES_PER_BAND_VOXEL)
            return _integrate_llvm(f, active, v_a, shape, h, steps, dt, zeta, lambda_curv, cfl,
                                   chunk, progress)
        if band.size <= chunk:
            return _integrate(f, active, v_a, shape, h, steps, dt, zeta, lambda_curv, cfl,
                              progress)
        return _integrate_chunked(f, active, v_a, shape, h, steps, dt, zeta, lambda_curv, cfl,
                                  chunk, progress)
    finally:
        torch.set_num_threads(threads)


def _prepared(active: torch.Tensor, shape: tuple[int, int, int], h: np.ndarray,
              with_diagonals: bool) -> dict:
    """`_neighbours` with 'inv_d' as float32 1 / (world distance of the differences)."""
    idx = _neighbours(active, shape, with_diagonals)
    idx["inv_d"] = [(d / float(h[ax])).to(torch.float32) for ax, d in enumerate(idx["inv_d"])]
    return idx


def _steps(n: int, progress: str | None) -> Any:
    """range(n), under a progress bar labelled ``progress`` unless it is None."""
    if progress is None:
        return range(n)
    from shells.progress import tqdm
    return tqdm(range(n), desc=progress, unit="step", leave=False)


def _integrate(f, active, v_a, shape, h, steps, dt, zeta, lambda_curv, cfl,
               progress: str | None = None) -> np.ndarray:
    n_sub = substeps(float(v_a.abs().max()), dt, h, cfl)
    dt_sub = dt / n_sub
    lam_w = float(lambda_curv) * float(h.min()) ** 2  # grid units -> world units (docstring)
    idx = _prepared(active, shape, h, with_diagonals=lam_w > 0.0)
    for _ in _steps(steps * n_sub, progress):
        f.index_copy_(0, active, _step(f, idx, v_a, h, dt_sub, lam_w, zeta))
    return f.reshape(shape).cpu().numpy()


def _integrate_chunked(f, active, v_a, shape, h, steps, dt, zeta, lambda_curv, cfl,
                       chunk: int, progress: str | None = None) -> np.ndarray:
    """`_integrate` in chunks of the band: new values of all chunks into one buffer, written
    back once per step (the grid a step reads is the grid of the step before)."""
    n_sub = substeps(float(v_a.abs().max()), dt, h, cfl)
    dt_sub = dt / n_sub
    lam_w = float(lambda_curv) * float(h.min()) ** 2
    new = torch.empty_like(v_a)
    parts = [(a, min(a + chunk, active.numel())) for a in range(0, active.numel(), chunk)]
    for _ in _steps(steps * n_sub, progress):
        for a, b in parts:
            idx = _prepared(active[a:b], shape, h, with_diagonals=lam_w > 0.0)
            new[a:b] = _step(f, idx, v_a[a:b], h, dt_sub, lam_w, zeta)
            del idx
        f.index_copy_(0, active, new)
    return f.reshape(shape).cpu().numpy()


def _integrate_llvm(f, active, v_a, shape, h, steps, dt, zeta, lambda_curv, cfl,
                    chunk: int, progress: str | None = None) -> np.ndarray:
    """`_integrate` with each sub-step one Dr.Jit kernel per chunk of ``chunk`` band voxels
    (`_step_llvm`); all chunks' new values are computed from the grid of the step before,
    then scattered into it."""
    from drjit.llvm import Float, Int32

    n_sub = substeps(float(v_a.abs().max()), dt, h, cfl)
    dt_sub = dt / n_sub
    lam_w = float(lambda_curv) * float(h.min()) ** 2
    grid = Float(f.contiguous())
    parts = [(Int32(active[a:a + chunk].to(torch.int32)), Float(v_a[a:a + chunk].contiguous()))
             for a in range(0, active.numel(), chunk)]
    for _ in _steps(steps * n_sub, progress):
        new = [_step_llvm(grid, act, v, shape, h, dt_sub, lam_w, zeta) for act, v in parts]
        dr.eval(new)  # every chunk reads the grid of the step before ...
        for (act, _), values in zip(parts, new):
            dr.scatter(grid, values, act)  # ... then all are written back
        dr.eval(grid)
    return grid.numpy().reshape(shape)


def _step_llvm(grid, active, v_a, shape: tuple[int, int, int], h, dt_sub: float,
               lam_w: float, zeta: float):
    """`_step` for Dr.Jit (grid, v_a: Float; active: Int32 flat indices), traced into one
    kernel: the same operations in the same order (the same values to float32 rounding: the
    kernel may fuse multiply-adds), with the neighbours (clamped at the border, one-sided
    differences there) found from the flat index as `_neighbours` finds them."""
    from drjit.llvm import Float

    strides = (shape[1] * shape[2], shape[2], 1)
    i = active // strides[0]
    rest = active - i * strides[0]
    j = rest // strides[1]
    coords = (i, j, rest - j * strides[1])
    sp, sm, inv_d = [], [], []
    for ax in range(3):
        up, down = coords[ax] < shape[ax] - 1, coords[ax] > 0
        sp.append(dr.select(up, strides[ax], 0))
        sm.append(dr.select(down, -strides[ax], 0))
        # 1 / (distance of the two neighbours): 2 h inside, h at a border (as _neighbours)
        inv_d.append(dr.select(up & down, float(np.float32(0.5 / float(h[ax]))),
                               float(np.float32(1.0 / float(h[ax])))))
    k_phase = math.pi / zeta
    fc = dr.gather(Float, grid, active)
    fp = [dr.gather(Float, grid, active + sp[ax]) for ax in range(3)]
    fm = [dr.gather(Float, grid, active + sm[ax]) for ax in range(3)]
    g = [(fp[ax] - fm[ax]) * inv_d[ax] for ax in range(3)]
    gnorm2 = g[0] * g[0] + g[1] * g[1] + g[2] * g[2]
    gnorm = dr.sqrt(gnorm2)
    rate = gnorm * (v_a * (0.5 * dt_sub))
    if lam_w > 0.0:
        num = Float(0.0)
        for ax in range(3):
            f_ii = (fp[ax] + fm[ax] - 2.0 * fc) * (1.0 / float(h[ax]) ** 2)
            num = num + f_ii * (gnorm2 - g[ax] * g[ax])
        for a, b in ((0, 1), (0, 2), (1, 2)):
            corners = [dr.gather(Float, grid, active + da + db)
                       for da, db in ((sp[a], sp[b]), (sp[a], sm[b]), (sm[a], sp[b]),
                                      (sm[a], sm[b]))]
            f_ab = ((corners[0] - corners[1] - corners[2] + corners[3])
                    * (-0.5 / (float(h[a]) * float(h[b]))))
            num = num + g[a] * g[b] * f_ab
        kmax = 1.0 / float(h.min())
        kappa = dr.clip(num / (gnorm2 * gnorm + 1e-12), -kmax, kmax)
        rate = rate - (0.5 * dt_sub * lam_w) * (kappa * gnorm)
    one_plus_cos = dr.cos(dr.clip(fc * k_phase, -math.pi, math.pi)) + 1.0
    return fc - rate * one_plus_cos


def _step(f, idx: dict, v_a, h, dt_sub: float, lam_w: float, zeta: float) -> torch.Tensor:
    """New values of the voxels idx['centre'] after one Euler sub-step (f is not changed).
    The hot path: constants are folded so each step is ~26 tensor ops."""
    inv_d = idx["inv_d"]
    half_dt_v = 0.5 * dt_sub * v_a  # w = (1 + cos) / 2 folded into the speed
    half_dt_lam = 0.5 * dt_sub * lam_w
    k_phase = math.pi / zeta
    active32 = idx["centre"]
    fc = torch.index_select(f, 0, active32)
    fp = [torch.index_select(f, 0, idx["p"][ax]) for ax in range(3)]
    fm = [torch.index_select(f, 0, idx["m"][ax]) for ax in range(3)]
    g = [(fp[ax] - fm[ax]).mul_(inv_d[ax]) for ax in range(3)]
    gnorm2 = torch.addcmul(torch.addcmul(g[0] * g[0], g[1], g[1]), g[2], g[2])
    gnorm = torch.sqrt(gnorm2)
    rate = gnorm * half_dt_v  # dt |grad f| v / 2
    if lam_w > 0.0:
        curv = _curvature_times_grad(f, fc, fp, fm, g, gnorm2, gnorm, idx, h)
        rate = rate.sub_(half_dt_lam * curv)
    one_plus_cos = torch.cos(torch.clamp(fc * k_phase, -math.pi, math.pi)).add_(1.0)
    return fc.sub_(rate.mul_(one_plus_cos))


def _neighbours(active: torch.Tensor,  # [A] flat indices of the band voxels (int64)
                shape: tuple[int, int, int], with_diagonals: bool) -> dict:
    """Flat indices (int32) of the clamped axis neighbours (and the 12 in-plane diagonals).

    'p'[ax] / 'm'[ax]: +1 / -1 along axis ax; 'pp'/'pm'/'mp'/'mm'[(a, b)]: corners in the a-b
    plane; 'inv_d'[ax]: 1 / (index distance between the +1 and -1 neighbours), 2 inside and 1
    on the border (one-sided differences), to be scaled by 1/h.
    """
    strides = (shape[1] * shape[2], shape[2], 1)
    coords = torch.unravel_index(active, shape)
    step_p, step_m = [], []
    for ax in range(3):
        c = coords[ax]
        step_p.append((torch.clamp(c + 1, max=shape[ax] - 1) - c) * strides[ax])
        step_m.append((torch.clamp(c - 1, min=0) - c) * strides[ax])
    del coords
    n32 = torch.iinfo(torch.int32).max
    dtype = torch.int32 if int(np.prod(shape)) < n32 else torch.int64
    out = {"centre": active.to(dtype),
           "p": [(active + step_p[ax]).to(dtype) for ax in range(3)],
           "m": [(active + step_m[ax]).to(dtype) for ax in range(3)],
           "inv_d": [strides[ax] / (step_p[ax] - step_m[ax]).clamp(min=1).to(torch.float64)
                     for ax in range(3)]}
    if with_diagonals:
        for a, b in ((0, 1), (0, 2), (1, 2)):
            out[("pp", a, b)] = (active + step_p[a] + step_p[b]).to(dtype)
            out[("pm", a, b)] = (active + step_p[a] + step_m[b]).to(dtype)
            out[("mp", a, b)] = (active + step_m[a] + step_p[b]).to(dtype)
            out[("mm", a, b)] = (active + step_m[a] + step_m[b]).to(dtype)
    return out


def _curvature_times_grad(f, fc, fp, fm, g, gnorm2, gnorm, idx, h):
    """|grad f| * div(grad f / |grad f|) by central second differences, |kappa| <= 1/h.

    |grad f| kappa = (sum_i f_ii (|g|^2 - g_i^2) - 2 sum_{i<j} g_i g_j f_ij) / |g|^2.
    """
    num = torch.zeros_like(fc)
    for ax in range(3):
        f_ii = (fp[ax] + fm[ax] - 2.0 * fc) * (1.0 / float(h[ax]) ** 2)
        num.addcmul_(f_ii, gnorm2 - g[ax] * g[ax])
    for a, b in ((0, 1), (0, 2), (1, 2)):
        def at(key):
            return torch.index_select(f, 0, idx[(key, a, b)])
        f_ab = (at("pp") - at("pm") - at("mp") + at("mm")) * (-0.5 / (float(h[a]) * float(h[b])))
        num.addcmul_(g[a] * g[b], f_ab)  # -2 g_a g_b f_ab, f_ab = (...) / (4 h_a h_b)
    kmax = 1.0 / float(h.min())
    kappa = num.div_(gnorm2 * gnorm + 1e-12).clamp_(-kmax, kmax)
    return kappa.mul_(gnorm)


def shell_sdfs(f0: np.ndarray,  # [X, Y, Z] SDF, f > 0 outside
               s: np.ndarray,  # [X, Y, Z] kernel size (world units)
               spacing,  # (3,) world units
               cfg: ShellConfig,
               device: str | torch.device = "cpu",
               progress: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(SDF+, SDF-) = (min(f0, dilated f0), max(f0, eroded f0)), both [X, Y, Z] float32.

    The min / max make the containment exact on the grid: {f0 <= 0} is inside {SDF+ <= 0} and
    {SDF- <= 0} is inside {f0 <= 0}. ``progress``: a bar over each evolution's steps.

    With the density-support terms (`ShellConfig.support_k_outer` / ``support_k_inner``, k > 0)
    also SDF+ <= f0 - (h + k s) and SDF- >= f0 + h + k s, h half a cell's diagonal: the band then
    holds every grid point the occupancy rule marks (`shells.fields.neus.may_have_density`,
    |f| < h + k s). The level-set fronts move a distance, which a sharp field whose f is far
    from a distance (|grad f| well below 1 inside a solid, a thin part whose f never reaches 0
    on the grid) turns into too little change of f: a ray then ended on M- before the surface
    had absorbed it, and density lay outside M+.
    """
    f0 = np.asarray(f0, dtype=np.float32)
    dil = evolve(f0, dilation_velocity(s, cfg), spacing, cfg.steps, cfg.dt, cfg.dilate_zeta,
                 cfg.dilate_curvature, cfg.cfl, device, cfg.memory_mb,
                 "dilate (M+)" if progress else None)
    ero = evolve(f0, -erosion_velocity(s, cfg), spacing, cfg.steps, cfg.dt, cfg.erode_zeta,
                 cfg.erode_curvature, cfg.cfl, device, cfg.memory_mb,
                 "erode (M-)" if progress else None)
    plus, minus = np.minimum(f0, dil), np.maximum(f0, ero)
    h = np.float32(0.5 * float(np.linalg.norm(np.asarray(spacing, dtype=np.float64))))
    s = np.asarray(s, dtype=np.float32)
    if cfg.support_k_outer > 0:
        np.minimum(plus, f0 - (h + np.float32(cfg.support_k_outer) * s), out=plus)
    if cfg.support_k_inner > 0:
        np.maximum(minus, f0 + (h + np.float32(cfg.support_k_inner) * s), out=minus)
    return plus, minus
