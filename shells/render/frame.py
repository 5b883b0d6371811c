"""Render rays and frames in Dr.Jit: narrow band (`band`) or dense whole-ray baseline (`full`).

Per batch of rays (§3.4, §4.2):

    band: rays -> M+/M- intervals (raycast) -> Procedure 3 samples (sampler, packed); a ray
          that reaches M- (the solid interior) ends there, its remaining transmittance taking
          the colour of its last sample instead of the background (`sampler.solid_end`, the
          rule the torch band renderer `shells.render.band` applies too)
    full: rays -> scene-box interval          -> cfg.full_samples samples per ray (same placement
          with a fixed count: linspace(near, far, N + 2)[1:-1], sections of (far - near) / N)
    then: one batched field evaluation at all samples -> NeuS alpha (shells.fields.neus, the
          formula shared with training) with cos = d . n and the sample's section length ->
          front-to-back compositing per ray over the background (`shells.render.shading`).
          Band mode with render.band_ert_eps > 0 (the sharp preset's) shades the samples in
          rounds instead and stops a ray once its transmittance is below it
          (`_composite_rounds`); with render.band_peel_step it peels that many M+ hits of
          every ray, shades them, and peels on only the rays still letting light through
          (`_render_band_on_demand`).
    baked: the baked layer meshes (`shells.bake.render`): each layer's nearest hit, its
          interpolated colour and opacity blended in the layers' fixed order; ``scene`` is then
          a `shells.bake.render.LayerScene` and the field is not used.
    occupancy: occupancy-grid ray marching with empty-space skipping and early termination
          (the Instant-NGP / nerfacc baseline, shells.render.occupancy): same NeuS alpha and
          compositing, in rounds of cfg.occ_chunk samples per ray.

The field is anything with ``eval(x, d) -> FieldSample`` (``shells.fields.drjit_field``:
.sdf, .s Float [M]; .normal, .rgb 3-vectors [M]) on Dr.Jit arrays x, d (3-vectors of width M),
e.g. ``shells.fields.drjit_field.DrJitField``. Nothing goes through torch in between; the inputs may
be torch rays (converted without a copy) and the outputs convert to torch without a copy.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import drjit as dr
import mitsuba as mi
import numpy as np
import torch

from shells.config import RenderConfig
from shells.errors import InputError
from shells.render.occupancy import render_occupancy
from shells.render.raycast import ShellScene, box_intervals, to_point3f
from shells.render.sampler import (PackedSamples, cast_start, far_intervals, field_warp,
                                  place_packed, sample_counts, shell_intervals, solid_end)
from shells.render.shading import WHITE, composite_packed, end_colour, shade_samples

MODES = ("band", "full", "occupancy", "baked")
BYTES_PER_RAY = 512  # Dr.Jit and torch memory of a ray in a batch (origin, direction, shell
# hits, colour, counts), besides its samples; an upper estimate
BYTES_PER_SLOT = 16  # memory of one interval slot of a band ray (entry, exit, its sample count)
BYTES_PER_SAMPLE = 96  # memory of one field sample (position, direction, t, section, ray
# index, SDF, kernel, normal, colour, alpha); an upper estimate


def rays_per_batch(cfg: RenderConfig, mode: str) -> int:
    """Rays rendered at once: whole pixels (a multiple of cfg.spp) in the budgets
    cfg.chunk_samples and cfg.memory_mb.

    Full, occupancy and baked batches hold each ray with its worst-case samples. A band batch
    holds its rays and their interval slots in half the memory budget; its samples are counted
    after the cast and shaded in groups of rays that fit the other half (`sample_budget`):
    Procedure 3's worst case (n_max samples in each of dp_max / 2 intervals) is far more than
    a frame's rays take, and small batches cost a band frame its speed (each field evaluation
    has a fixed cost)."""
    K = cfg.spp
    if mode == "band":
        per_ray = BYTES_PER_RAY + ((cfg.dp_max + 1) // 2) * BYTES_PER_SLOT
        return max(1, ((cfg.memory_mb << 20) // 2) // (K * per_ray)) * K
    per_ray = {"full": cfg.full_samples,  # occupancy: samples held per live ray and round
               "occupancy": cfg.occ_chunk,  # baked: no samples; a layer's hit and attributes
               "baked": 4}[mode]
    by_samples = cfg.chunk_samples // max(per_ray * K, 1)
    by_memory = (cfg.memory_mb << 20) // (K * (BYTES_PER_RAY + per_ray * BYTES_PER_SAMPLE))
    return max(1, min(by_samples, by_memory)) * K


def sample_budget(cfg: RenderConfig) -> int:
    """Samples a band batch places and shades at once: cfg.chunk_samples, and at most half of
    cfg.memory_mb (the rays have the other half, `rays_per_batch`)."""
    return max(1, min(cfg.chunk_samples, ((cfg.memory_mb << 20) // 2) // BYTES_PER_SAMPLE))


def ray_groups(counts: Any,  # mi.UInt32 [R] samples of each ray
               budget: int) -> list[tuple[int, int]]:
    """Consecutive ray ranges [a, b) whose samples add up to at most ``budget`` each (a ray
    with more samples than that is a group of its own)."""
    total = np.cumsum(np.asarray(counts, dtype=np.int64))
    groups, a, base = [], 0, 0
    while a < len(total):
        b = max(int(np.searchsorted(total, base + budget, side="right")), a + 1)
        groups.append((a, b))
        a, base = b, int(total[b - 1])
    return groups


def render_rays(field: Any,  # Dr.Jit field: eval(x, d) -> FieldSample
                origins: Any,  # [R, 3] torch/numpy or mi.Point3f
                dirs: Any,  # [R, 3] unit directions
                cfg: RenderConfig,
                mode: str = "band",
                scene: ShellScene | None = None,  # needed in band mode
                aabb: Any = None,  # [2, 3] scene box, needed in full and occupancy modes
                background: tuple[float, float, float] = WHITE,  # data.background
                ) -> tuple[Any, Any]:  # colour mi.Color3f [R], samples per ray mi.UInt32 [R]
    """Colour of each ray over the background, and how many field samples it took."""
    o = to_point3f(origins, mi.Point3f)
    d = to_point3f(dirs, mi.Vector3f)
    if mode == "band":
        if scene is None:
            raise InputError("band mode needs the shells: pass a ShellScene")
        if cfg.band_ert_eps > 0 and 0 < cfg.band_peel_step < cfg.dp_max:
            return _render_band_on_demand(field, o, d, scene, cfg, background)
        iv = shell_intervals(scene, o, d, cfg.dp_max, field_warp(field))
        return render_intervals(field, o, d, iv, cfg, background)[:2]
    if mode == "full":
        warp = field_warp(field)
        if warp is not None:  # an unbounded field: the whole ray, evenly in contracted space
            return render_intervals(field, o, d, far_intervals(o, d, warp), cfg, background,
                                    fixed=cfg.full_samples)[:2]
        if aabb is None:
            raise InputError("full mode needs the scene box: pass aabb [2, 3]")
        return render_intervals(field, o, d, box_intervals(o, d, aabb), cfg, background,
                                fixed=cfg.full_samples)[:2]
    if mode == "baked":  # scene: a shells.bake.render.LayerScene, which renders itself
        return scene.render(o, d, background)
    if mode == "occupancy":
        colour, _, count = render_occupancy(field, o, d, cfg, aabb, background)
        return colour, count
    raise InputError(f"mode '{mode}': expected one of {MODES}")


def render_intervals(field: Any, o: Any, d: Any,  # mi.Point3f / mi.Vector3f [R]
                     iv: Any,  # shells.render.raycast.Intervals of these rays
                     cfg: RenderConfig,
                     background: tuple[float, float, float] = WHITE,
                     fixed: int | None = None,  # samples per interval instead of Procedure 3
                     extras: bool = False,  # also opacity and the mean field normal
                     ) -> tuple[Any, ...]:
    """Samples in the intervals, one field evaluation, compositing: colour mi.Color3f [R] and
    samples per ray mi.UInt32 [R]; with ``extras`` also the opacity mi.Float [R] (1 on rays
    that end solid) and the weight-averaged field normal mi.Vector3f [R] (not normalised; 0
    without samples), which the adaptive refinement (`shells.render.refine`) compares."""
    warp, n = field_warp(field), dr.width(d)
    bg = mi.Color3f(*[float(c) for c in background])
    if fixed is None and not extras and cfg.band_ert_eps > 0:  # band early termination
        light = _shade_band(field, o, d, iv, cfg, Light.dark(n))
        return light.colour(solid_end(iv.t_inner.array, light.taken), bg), light.taken
    counts = sample_counts(iv, cfg, fixed, warp, o, d)
    # a band batch's samples are known only now (full batches were sized by theirs)
    if fixed is None and n > 1 and int(dr.sum(counts.per_ray)[0]) > sample_budget(cfg):
        return _render_groups(field, o, d, iv, cfg, background, extras,
                              ray_groups(counts.per_ray, sample_budget(cfg)))
    samples = place_packed(iv, cfg, counts=counts)
    if samples.size == 0:
        out = (dr.zeros(mi.Color3f, n) + bg, samples.count)
        return out + ((dr.zeros(mi.Float, n), dr.zeros(mi.Vector3f, n)) if extras else ())
    shaded = shade_samples(field, samples, o, d, normals=extras)
    alpha, rgb = shaded[:2]
    end = end_colour(rgb, samples, bg)  # the solid-end rule (background in full mode)
    colour, opacity = composite_packed(alpha, rgb, samples.start, samples.count, end)
    if not extras:
        dr.eval(colour, samples.count)
        return colour, samples.count
    normal, _ = composite_packed(alpha, shaded[2], samples.start, samples.count,
                                 mi.Color3f(0.0))
    if samples.solid is not None:
        opacity = dr.select(samples.solid, 1.0, opacity)
    dr.eval(colour, samples.count, opacity, normal)
    return colour, samples.count, opacity, mi.Vector3f(normal)


def _render_groups(field: Any, o: Any, d: Any, iv: Any, cfg: RenderConfig,
                   background: tuple[float, float, float], extras: bool,
                   groups: list[tuple[int, int]]) -> tuple[Any, ...]:
    """`render_intervals` of each group of rays [a, b), its outputs put back in ray order."""
    n = dr.width(d)
    outs = None
    for a, b in groups:
        idx = dr.arange(mi.UInt32, a, b)
        part = render_intervals(field, dr.gather(mi.Point3f, o, idx),
                                dr.gather(mi.Vector3f, d, idx), iv.rows(a, b), cfg, background,
                                extras=extras)
        if outs is None:
            outs = tuple(dr.zeros(type(x), n) for x in part)
        for out, x in zip(outs, part):
            dr.scatter(out, x, idx)
        dr.eval(outs)
    return outs


class Light(NamedTuple):
    """What the band samples shaded so far left on each ray (Dr.Jit arrays [R])."""

    trans: Any  # mi.Float transmittance after the samples taken
    acc: Any  # mi.Color3f colour accumulated
    taken: Any  # mi.UInt32 samples taken
    last: Any  # mi.Color3f colour of the last sample taken

    @classmethod
    def dark(cls, n: int) -> "Light":
        """n rays before their first sample."""
        return cls(dr.ones(mi.Float, n), dr.zeros(mi.Color3f, n), dr.zeros(mi.UInt32, n),
                   dr.zeros(mi.Color3f, n))

    def take(self, idx: Any) -> "Light":
        """The rays ``idx`` (mi.UInt32)."""
        return Light(*(dr.gather(type(v), v, idx) for v in self))

    def put(self, part: "Light", idx: Any) -> None:
        """Write ``part`` (the rays ``idx``) back in place."""
        for v, w in zip(self, part):
            dr.scatter(v, w, idx)
        dr.eval(*self)

    def colour(self, solid: Any, bg: Any) -> Any:
        """The rays' colours: the remaining transmittance ends on the last sample's colour
        where ``solid`` (`shells.render.sampler.solid_end`; None: nowhere), else on ``bg``."""
        end = bg if solid is None else dr.select(solid, self.last, bg)
        colour = dr.fma(end, self.trans, self.acc)
        dr.eval(colour, self.taken)
        return colour


def _composite_rounds(field: Any, samples: PackedSamples, o: Any, d: Any,
                      cfg: RenderConfig, light: Light) -> Light:
    """Band samples shaded front to back in rounds, with early ray termination: each round
    evaluates the next ``cfg.band_chunk`` samples (more as rays drop out) of every live ray,
    and a ray whose transmittance fell below ``cfg.band_ert_eps`` takes no more. The colour
    differs from shading every sample by less than that transmittance (the light of the
    samples not taken); the solid-end rule applies to the remaining transmittance as before,
    with the last sample taken. ``light``: what earlier samples left on the rays (`Light.dark`
    for none); returns it after these samples."""
    trans, acc, taken, last = (dr.copy(v) for v in light)
    rid = dr.compress((samples.count > 0) & (trans >= cfg.band_ert_eps))  # live rays
    first, total = (dr.gather(mi.UInt32, v, rid) for v in (samples.start, samples.count))
    ro, rd = dr.gather(mi.Point3f, o, rid), dr.gather(mi.Vector3f, d, rid)
    pos = dr.zeros(mi.UInt32, dr.width(rid))  # samples taken so far by each live ray
    T, C = dr.gather(mi.Float, trans, rid), dr.gather(mi.Color3f, acc, rid)
    before = dr.gather(mi.UInt32, taken, rid)
    dr.eval(first, total, ro, rd, pos, T, C, before)
    black = mi.Color3f(0.0)
    R0 = max(dr.width(rid), 1)
    while dr.width(rid) > 0:
        Ra = dr.width(rid)
        K = int(cfg.band_chunk) * min(64, 2 ** int(math.floor(math.log2(R0 / Ra))))
        m = dr.minimum(total - pos, K)  # samples of each live ray this round
        slot = dr.arange(mi.UInt32, Ra * K)
        idx = dr.compress((slot % K) < dr.repeat(m, K))  # [M] valid slots, ray-major
        live = idx // K
        src = dr.gather(mi.UInt32, first + pos, live) + idx % K  # packed sample index
        sub = PackedSamples(t=dr.gather(mi.Float, samples.t, src),
                            delta=dr.gather(mi.Float, samples.delta, src), ray=live,
                            start=dr.prefix_sum(m), count=m, max_count=K)
        alpha, rgb = shade_samples(field, sub, ro, rd)
        c_round, o_round = composite_packed(alpha, rgb, sub.start, m, black)
        C = dr.fma(c_round, T, C)
        T = T * (1.0 - o_round)
        pos = pos + m
        dr.scatter(trans, T, rid)
        dr.scatter(acc, C, rid)
        dr.scatter(taken, before + pos, rid)
        dr.scatter(last, dr.gather(mi.Color3f, rgb, sub.start + m - 1), rid)
        go = (T >= cfg.band_ert_eps) & (pos < total)
        dr.eval(trans, acc, taken, last, T, C, pos, go)
        keep = dr.compress(go)
        rid, first, total, pos, before = (dr.gather(mi.UInt32, v, keep)
                                          for v in (rid, first, total, pos, before))
        ro, rd = dr.gather(mi.Point3f, ro, keep), dr.gather(mi.Vector3f, rd, keep)
        T, C = dr.gather(mi.Float, T, keep), dr.gather(mi.Color3f, C, keep)
        dr.eval(rid, first, total, pos, before, ro, rd, T, C)
    return Light(trans, acc, taken, last)


def _shade_band(field: Any, o: Any, d: Any, iv: Any, cfg: RenderConfig, light: Light) -> Light:
    """`_composite_rounds` of the band samples of intervals ``iv`` (after ``light``), placed
    and shaded in groups of rays within `sample_budget` (`ray_groups`)."""
    n, warp = dr.width(d), field_warp(field)
    counts = sample_counts(iv, cfg, None, warp, o, d)
    if n > 1 and int(dr.sum(counts.per_ray)[0]) > sample_budget(cfg):
        light = Light(*(dr.copy(v) for v in light))
        for a, b in ray_groups(counts.per_ray, sample_budget(cfg)):
            idx = dr.arange(mi.UInt32, a, b)
            light.put(_shade_band(field, dr.gather(mi.Point3f, o, idx),
                                  dr.gather(mi.Vector3f, d, idx), iv.rows(a, b), cfg,
                                  light.take(idx)), idx)
        return light
    samples = place_packed(iv, cfg, counts=counts)
    if samples.size == 0:
        return light
    return _composite_rounds(field, samples, o, d, cfg, light)


def _render_band_on_demand(field: Any, o: Any, d: Any,  # mi.Point3f / mi.Vector3f [R]
                           scene: ShellScene, cfg: RenderConfig,
                           background: tuple[float, float, float]) -> tuple[Any, Any]:
    """Band mode with early termination, peeling on demand: every ray peels
    ``cfg.band_peel_step`` M+ hits and their samples are shaded; then the rays whose peel goes
    on and whose transmittance is still at least ``cfg.band_ert_eps`` peel that many more
    (`ShellScene.resume`: the same intervals as one peel) and shade them, and so on up to
    ``cfg.dp_max``. The others never cast against the layers behind: most of a sharp field's
    covered rays are opaque after their first intervals. A ray that stopped before its peel
    ended may not know it reaches M-: its end colour takes the background, a difference of
    less than its transmittance (below ``cfg.band_ert_eps``). Returns colour mi.Color3f [R]
    and the samples taken per ray mi.UInt32 [R]."""
    n, warp, step = dr.width(d), field_warp(field), cfg.band_peel_step
    bg = mi.Color3f(*[float(c) for c in background])
    iv, peel = scene.peel(o, d, cfg.dp_max, step, start=cast_start(o, d, warp))
    light = _shade_band(field, o, d, iv, cfg, Light.dark(n))
    t_inner = dr.copy(iv.t_inner.array)
    rays, ro, rd, hits = dr.arange(mi.UInt32, n), o, d, step  # the rays peeling on
    while hits < cfg.dp_max:
        keep = dr.compress(peel.going & (dr.gather(mi.Float, light.trans, rays) >=
                                         cfg.band_ert_eps))
        if dr.width(keep) == 0:
            break
        rays, peel = dr.gather(mi.UInt32, rays, keep), peel.take(keep)
        ro, rd = dr.gather(mi.Point3f, ro, keep), dr.gather(mi.Vector3f, rd, keep)
        hits = min(cfg.dp_max, hits + step)
        iv, peel = scene.resume(ro, rd, peel, cfg.dp_max, hits)
        light.put(_shade_band(field, ro, rd, iv, cfg, light.take(rays)), rays)
        dr.scatter(t_inner, iv.t_inner.array, rays)
    return light.colour(solid_end(t_inner, light.taken), bg), light.taken


def render_image(field: Any,
                 origins: torch.Tensor,  # [H * W * cfg.spp, 3] row-major pixel rays
                 dirs: torch.Tensor,  # [H * W * cfg.spp, 3]
                 height: int, width: int,
                 cfg: RenderConfig,
                 mode: str = "band",
                 scene: ShellScene | None = None,
                 aabb: Any = None,
                 background: tuple[float, float, float] = WHITE,
                 ) -> tuple[torch.Tensor, torch.Tensor]:  # rgb [H, W, 3] float32, spp [H, W] int
    """A frame in ray chunks of `rays_per_batch` rays (cfg.chunk_samples samples at most, in
    the memory budget cfg.memory_mb).

    A pixel's cfg.spp rays (contiguous, `Cameras.pixel_rays(i, spp)`) are averaged (box
    filter); its sample count is the sum over them."""
    K = cfg.spp
    R = height * width * K
    if origins.shape[0] != R or dirs.shape[0] != R:
        raise InputError(f"{origins.shape[0]} rays for a {width}x{height} image at {K} spp")
    chunk = rays_per_batch(cfg, mode)  # whole pixels per chunk
    rgbs, spps = [], []
    for a in range(0, R, chunk):
        colour, count = render_rays(field, origins[a:a + chunk], dirs[a:a + chunk], cfg, mode,
                                    scene, aabb, background)
        n = dr.width(count)
        rgbs.append(mi.TensorXf(dr.ravel(colour), (n, 3)).torch())
        spps.append(mi.TensorXf(mi.Float(count), (n,)).torch())
    rgb = torch.cat(rgbs).reshape(height, width, K, 3).mean(2)
    spp = torch.cat(spps).reshape(height, width, K).sum(2).to(torch.int32)
    return rgb, spp
