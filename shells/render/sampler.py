"""Procedure 3: sample placement inside the shell intervals (§3.4).

For an interval [enter, exit] of width w:

    N     = min(ceil(max(w - w_s, 0) / delta_s) + 1, N_max)
    t_j   = linspace(enter, exit, N + 2)[1:-1],  j = 0..N-1   (equal spacing w / (N + 1))
    delta = w / N  for every sample of the interval

so an interval narrower than w_s gets one sample in its middle. The section length delta is our
choice (the paper leaves it open): the N sections of length w / N tile the interval exactly, so
the NeuS opacity of a fully crossed surface does not depend on how many samples the interval got.

Placement is written once (``_fill`` below, one symbolic Dr.Jit loop per ray) and writes either
layout from the same counts:

* packed (renderer): flat sample arrays t [M], delta [M], ray [M] with per-ray start [R] and
  count [R], samples of a ray contiguous and front to back;
* padded (stage-2 training, torch): t [R, S], delta [R, S], mask [R, S], S = the largest
  per-ray count of the batch (at least 1); unused slots are 0 and masked out.

Both layouts also say which rays end solid (`solid_end`, the one rule both renderers apply).

Unbounded scenes (``warp`` = the field's similarity and far radius, `shells.render.warp`):
interval ends are taken to the ray parameter s first, so counts, spacing and sections are
those above measured in s (evenly in contracted space), and each sample's distance and its
section [t(s_lo), t(s_hi)] are taken back to world distances: the sections still tile the
interval, and a far interval many world units wide gets the samples its contracted width asks
for instead of N_max.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import drjit as dr
import mitsuba as mi
import torch

from shells.config import RenderConfig
from shells.render.raycast import Intervals, ShellScene, tensor_xi, to_point3f
from shells.render.warp import ray_span, s_of_t, t_of_s


@dataclass
class PackedSamples:
    """Samples of all rays, flat (Dr.Jit arrays)."""

    t: Any  # mi.Float [M] distance along the ray
    delta: Any  # mi.Float [M] section length
    ray: Any  # mi.UInt32 [M] index of the sample's ray
    start: Any  # mi.UInt32 [R] first sample of each ray
    count: Any  # mi.UInt32 [R] samples per ray
    max_count: int  # largest count (loop bound for compositing)
    solid: Any = None  # mi.Bool [R] the ray ends on its last sample (`solid_end`); None: no ray

    @property
    def size(self) -> int:
        return dr.width(self.t) if self.max_count > 0 else 0


def solid_end(t_inner: Any,  # mi.Float [R] first M- hit of each ray, inf if none
              count: Any,  # mi.UInt32 [R] samples of each ray
              ) -> Any:  # mi.Bool [R]
    """The solid-end rule of band rendering, for the Dr.Jit renderer and the torch one alike.

    M- bounds the solid interior: a ray that reached it (and took samples before) is absorbed
    there, so its remaining transmittance takes the colour of its last sample (the surface it
    ended on) instead of the background. Rays that left every shell see the background.
    """
    return dr.isfinite(t_inner) & (count > 0)


def interval_counts(width: Any,  # mi.Float [...] interval widths (world units)
                    w_s: float, delta_s: float, n_max: int) -> Any:  # mi.UInt32 [...]
    """Procedure 3 sample count N = min(ceil(max(w - w_s, 0) / delta_s) + 1, N_max)."""
    n = dr.ceil(dr.maximum(width - w_s, 0.0) / delta_s) + 1.0
    return mi.UInt32(dr.minimum(n, float(n_max)))


def _per_interval_counts(iv: Intervals, enter: Any, exit_: Any,  # [R * K] (in s if warped)
                         cfg: RenderConfig, fixed: int | None) -> tuple[Any, Any]:
    """Counts per interval slot [R * K] (0 for unused slots) and per ray [R]."""
    R, K = iv.enter.shape
    slot = dr.arange(mi.UInt32, R * K)
    valid = (slot % K) < dr.repeat(mi.UInt32(iv.count.array), K)
    if fixed is None:
        n = interval_counts(dr.maximum(exit_ - enter, 0.0), cfg.w_s, cfg.delta_s, cfg.n_max)
    else:
        n = dr.full(mi.UInt32, fixed, R * K)
    n = dr.select(valid, n, 0)
    per_ray = dr.block_reduce(dr.ReduceOp.Add, n, K) if K > 1 else mi.UInt32(n)
    return n, per_ray


Warp = tuple  # (centre, radius, far_radius, near_radius) of an unbounded field: `field_warp`


def field_warp(field: Any) -> Warp | None:
    """The warp of a field (torch `ShellField` or its Dr.Jit twin): None when bounded."""
    sim = getattr(field, "similarity", None)
    if sim is None:
        return None
    return (tuple(sim.centre), float(sim.radius), float(field.far_radius),
            float(field.near_radius))


def shell_intervals(scene: ShellScene,
                    o: Any, d: Any,  # [R, 3] torch / numpy, or Dr.Jit Point3f / Vector3f
                    dp_max: int, warp: Warp | None = None) -> Intervals:
    """The shell intervals band sampling starts from (`ShellScene.intervals`). An unbounded
    field's rays (``warp``) are cast from their t_near (`ray_span`), where every sampler and
    stage 1 start them: the shells of whatever the field holds before t_near, which no ray of
    stage 1 sampled, neither end a ray there (an M- hit) nor use up its dp_max peels, so the
    band sees what the full-ray render sees."""
    return scene.intervals(o, d, dp_max, start=cast_start(o, d, warp))


def cast_start(o: Any, d: Any, warp: Warp | None) -> Any:
    """Where the shell cast of each ray starts (`shell_intervals`): t_near (`ray_span`,
    mi.Float [R]) for an unbounded field, None (the origin) for a bounded one."""
    if warp is None:
        return None
    return ray_span(to_point3f(o, mi.Point3f), to_point3f(d, mi.Vector3f), *warp)[0]


def _warped_ends(iv: Intervals, o: Any, d: Any, warp: Warp | None) -> tuple[Any, Any, Any]:
    """Interval ends [R * K] (in s when warped) and each ray's t_b [R] (None: not warped)."""
    enter, exit_ = iv.enter.array, iv.exit.array
    if warp is None:
        return enter, exit_, None
    near, tb, _ = ray_span(to_point3f(o, mi.Point3f), to_point3f(d, mi.Vector3f), *warp)
    K = iv.enter.shape[1]
    tbk = dr.repeat(tb, K) if K > 1 else tb
    nk = dr.repeat(near, K) if K > 1 else near
    # every sampler starts at t_near (`shells.render.warp.ray_span`): intervals are cut there
    enter = s_of_t(dr.maximum(enter, nk), tbk)
    exit_ = s_of_t(dr.maximum(exit_, nk), tbk)
    dr.eval(enter, exit_, tb)
    return enter, exit_, tb


def far_intervals(o: Any, d: Any,  # mi.Point3f / mi.Vector3f [R]
                  warp: Warp) -> Intervals:
    """The whole ray of an unbounded scene as one interval, [t_near, t_far] (`ray_span`):
    the `full` baseline there (the scene box's chord in a bounded one)."""
    near, _, t_far = ray_span(o, d, *warp)
    n = dr.width(d)
    dr.eval(t_far, near)
    return Intervals(enter=mi.TensorXf(near, (n, 1)), exit=mi.TensorXf(t_far, (n, 1)),
                     count=tensor_xi()(dr.full(mi.Int, 1, n), (n,)),
                     t_inner=mi.TensorXf(dr.full(mi.Float, dr.inf, n), (n,)))


@dr.syntax
def _fill(enter: Any, exit_: Any, n_int: Any, per_ray: Any, base: Any, K: int,
          t_out: Any, delta_out: Any, ray_out: Any, tb: Any = None) -> None:
    """Write each ray's samples to t_out/delta_out/ray_out[base[r] + i], i < per_ray[r].
    With ``tb`` (each ray's t_b) the ends are in s and the outputs are taken back to t."""
    R = dr.width(per_ray)
    r = dr.arange(mi.UInt32, R)
    row = r * K
    i = mi.UInt32(0)  # sample index within the ray
    k = mi.UInt32(0)  # current interval slot
    j = mi.UInt32(0)  # sample index within the interval
    while dr.hint(i < per_ray, max_iterations=-1, label="band_fill"):
        nk = dr.gather(mi.UInt32, n_int, row + k)
        e = dr.gather(mi.Float, enter, row + k)
        w = dr.maximum(dr.gather(mi.Float, exit_, row + k) - e, 0.0)
        nf = mi.Float(nk)
        dst = base + i
        if tb is None:
            dr.scatter(t_out, dr.fma(w, mi.Float(j + 1) / (nf + 1.0), e), dst)
            dr.scatter(delta_out, w / nf, dst)
        else:  # the sample and its section [e + j w / n, e + (j + 1) w / n], back to t
            dr.scatter(t_out, t_of_s(dr.fma(w, mi.Float(j + 1) / (nf + 1.0), e), tb), dst)
            hi = t_of_s(dr.fma(w, mi.Float(j + 1) / nf, e), tb)
            dr.scatter(delta_out, hi - t_of_s(dr.fma(w, mi.Float(j) / nf, e), tb), dst)
        if ray_out is not None:
            dr.scatter(ray_out, r, dst)
        i += 1
        j += 1
        if j >= nk:
            k += 1
            j = mi.UInt32(0)


class Counts(NamedTuple):
    """Procedure 3's sample counts of a batch of rays, and the interval ends they came from."""

    enter: Any  # mi.Float [R * K] interval entries (in s when warped)
    exit: Any  # mi.Float [R * K] interval exits
    tb: Any  # mi.Float [R] each ray's t_b when warped, else None
    per_interval: Any  # mi.UInt32 [R * K] samples of each interval slot
    per_ray: Any  # mi.UInt32 [R] samples of each ray


def sample_counts(iv: Intervals, cfg: RenderConfig,
                  fixed: int | None = None,  # samples per interval instead of Procedure 3
                  warp: Warp | None = None, o: Any = None, d: Any = None,  # unbounded: the
                  # field's warp (`field_warp`) and the rays
                  ) -> Counts:
    """How many samples each interval and ray gets (the renderer sizes its groups of rays by
    them before `place_packed` places them)."""
    enter, exit_, tb = _warped_ends(iv, o, d, warp)
    n_int, per_ray = _per_interval_counts(iv, enter, exit_, cfg, fixed)
    dr.eval(n_int, per_ray)
    return Counts(enter, exit_, tb, n_int, per_ray)


def place_packed(iv: Intervals, cfg: RenderConfig,
                 fixed: int | None = None,  # samples per interval instead of Procedure 3
                 warp: Warp | None = None, o: Any = None, d: Any = None,  # unbounded: the
                 # field's warp (`field_warp`) and the rays
                 counts: Counts | None = None,  # `sample_counts` of the same arguments
                 ) -> PackedSamples:
    """Packed layout for the Dr.Jit renderer."""
    R, K = iv.enter.shape
    if counts is None:
        counts = sample_counts(iv, cfg, fixed, warp, o, d)
    enter, exit_, tb, n_int, per_ray = counts
    start = dr.prefix_sum(per_ray)
    dr.eval(start)
    M = int(dr.sum(per_ray)[0]) if R else 0
    max_count = int(dr.max(per_ray)[0]) if R else 0
    size = max(M, 1)  # keep arrays non-empty; PackedSamples.size reports 0
    t = dr.zeros(mi.Float, size)
    delta = dr.zeros(mi.Float, size)
    ray = dr.zeros(mi.UInt32, size)
    if M > 0:
        _fill(enter, exit_, n_int, per_ray, start, K, t, delta, ray, tb)
    dr.eval(t, delta, ray)
    return PackedSamples(t=t, delta=delta, ray=ray, start=start, count=per_ray,
                         max_count=max_count, solid=solid_end(iv.t_inner.array, per_ray))


def place_padded(iv: Intervals, cfg: RenderConfig, warp: Warp | None = None, o: Any = None,
                 d: Any = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Padded torch layout: t [R, S], delta [R, S], mask [R, S] bool, solid [R] bool
    (`solid_end`), on the device of the Mitsuba variant."""
    R, K = iv.enter.shape
    enter, exit_, tb, n_int, per_ray = sample_counts(iv, cfg, None, warp, o, d)
    solid = solid_end(iv.t_inner.array, per_ray)
    dr.eval(solid)
    S = max(int(dr.max(per_ray)[0]) if R else 0, 1)
    t = dr.zeros(mi.Float, R * S)
    delta = dr.zeros(mi.Float, R * S)
    if R:
        # S changes from batch to batch: opaque, so it is not baked into (and recompiling) kernels
        base = dr.arange(mi.UInt32, R) * dr.opaque(mi.UInt32, S)
        _fill(enter, exit_, n_int, per_ray, base, K, t, delta, None, tb)
    dr.eval(t, delta)
    t_torch = mi.TensorXf(t, (R, S)).torch()
    delta_torch = mi.TensorXf(delta, (R, S)).torch()
    count = mi.TensorXf(mi.Float(per_ray), (R,)).torch()
    mask = torch.arange(S, device=t_torch.device)[None, :] < count[:, None]
    solid_torch = mi.TensorXf(mi.Float(solid), (R,)).torch() > 0.5
    return t_torch, delta_torch, mask, solid_torch


def band_samples(scene: ShellScene,
                 origins: Any,  # [R, 3] torch (or Dr.Jit Point3f)
                 dirs: Any,  # [R, 3] unit directions
                 cfg: RenderConfig,
                 warp: Warp | None = None,  # `field_warp` of an unbounded field
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Stage-2 training samples of rays cast against the shells: t [R, S], delta [R, S],
    mask [R, S] bool and solid [R] bool (`solid_end`), torch, no grad, on the device of the
    Mitsuba variant (the torch rays' device when the variant matches it)."""
    iv = shell_intervals(scene, origins, dirs, cfg.dp_max, warp)
    return place_padded(iv, cfg, warp, origins, dirs)
