"""Where the samples of a ray go in an unbounded scene: a per-ray parameter s that advances
evenly in contracted space (paper §4.7, after Mip-NeRF 360's disparity spacing).

A ray o + t d (world, unit d) leaves the ball of interest (`shells.fields.contraction`,
centre c, radius R) at t_b = R max(ball exit, 1) (a ray that never enters the ball, or
leaves it within one radius, gets t_b = R). Then

    s(t) = t                        t <= t_b     (contraction is the identity there)
    s(t) = 2 t_b - t_b^2 / t        t >  t_b     (even in disparity 1 / t; s -> 2 t_b at t -> inf)
    t(s) = s  or  t_b^2 / (2 t_b - s)

is continuous with slope 1 at t_b, so s is a world length inside the ball and, for rays from
the centre, exactly radius x the contracted radius beyond it. Every sampler of an unbounded
field works in s: counts and spacings of samples are those of the bounded renderer measured
in s (stage-1 stratified + importance samples, band intervals under Procedure 3, the
occupancy-grid march, the full-ray baseline), and a sample's section [s - a, s + b] becomes
the world section [t(s - a), t(s + b)] (so sections that tile an interval in s tile it in t).

Rays start at t_near (`ray_span`: where they enter the start sphere, by default the ball of
interest) and end at t_far = R (|o_unit| + 1 / (2 - rho_end)), rho_end = (far_radius + 2) / 2:
the point there is past the contracted radius rho_end, beyond the solid far sphere of the field
(`ShellField`, cfg.far_radius), so every ray's samples reach the far background.

The functions take torch tensors (stage 1) or Dr.Jit arrays (the renderers) and use the
matching math; shapes broadcast as the caller arranges them.
"""

from __future__ import annotations

from typing import Any

import torch


def _torch(x: Any) -> bool:
    return isinstance(x, torch.Tensor)


def s_of_t(t: Any, tb: Any) -> Any:
    """s(t) for distances t and the ray's t_b (same shape or broadcastable)."""
    if _torch(t):
        far = 2.0 * tb - tb * tb / t.clamp_min(1e-30)
        return torch.where(t > tb, far, t)
    import drjit as dr
    far = 2.0 * tb - tb * tb * dr.rcp(dr.maximum(t, 1e-30))
    return dr.select(t > tb, far, t)


def t_of_s(s: Any, tb: Any) -> Any:
    """t(s), the inverse; s >= 2 t_b (infinitely far) is clamped just below it."""
    if _torch(s):
        gap = (2.0 * tb - s).clamp_min(1e-7 * tb)
        return torch.where(s > tb, tb * tb / gap, s)
    import drjit as dr
    gap = dr.maximum(2.0 * tb - s, 1e-7 * tb)
    return dr.select(s > tb, tb * tb * dr.rcp(gap), s)


def _rho_end(far_radius: float) -> float:
    return 0.5 * (far_radius + 2.0)


def start_radius(near_radius: float) -> float:
    """World radius, in radius units, of the sphere where rays start (``near_radius``, the
    contracted radius of `ray_span`): the inverse contraction 1 / (2 - rho)."""
    return 1.0 / (2.0 - near_radius)


def ray_span(o: Any, d: Any,  # [R, 3] torch, or Dr.Jit Point3f / Vector3f [R]
             centre: tuple[float, float, float], radius: float, far_radius: float,
             near_radius: float = 1.0,
             ) -> tuple[Any, Any, Any]:  # t_near [R], t_b [R], t_far [R], world distances
    """Each ray's first distance t_near, its t_b (where s stops being t) and its last
    distance t_far.

    t_near is where the ray enters the start sphere, of contracted radius ``near_radius``
    (`FieldConfig.near_radius`; world radius `start_radius`), 0 from a camera inside it; a
    ray that misses the sphere starts at its point nearest to the centre. With the default
    1 the start sphere is the ball of interest: as a bounded scene's rays start at its box,
    nothing is sampled between an inward-looking camera and the region it looks at (no room
    for floaters in front of the cameras), but content outside the ball that lies before a
    ray's nearest point to the centre (a wall beside the object, seen obliquely) is then
    never sampled by that ray. A larger sphere samples it. Every sampler starts at t_near,
    and t_near <= t_b (s = t there)."""
    reach = 1.0 / (2.0 - _rho_end(far_radius))
    r_start = start_radius(near_radius)
    if _torch(o):
        ou = (o - o.new_tensor(centre)) / radius
        b = (ou * d).sum(-1)
        c2 = (ou * ou).sum(-1)
        disc = b * b - (c2 - 1.0)  # the ball of interest: its exit is t_b
        tb = (-b + disc.clamp_min(0.0).sqrt()).clamp_min(1.0)
        disc_s = disc if r_start == 1.0 else b * b - (c2 - r_start * r_start)  # start sphere
        near = torch.where(disc_s > 0, -b - disc_s.clamp_min(0.0).sqrt(), -b).clamp_min(0.0)
        return radius * near, radius * tb, radius * (c2.sqrt() + reach)
    import drjit as dr
    import mitsuba as mi
    ou = (o - mi.Point3f(*centre)) / radius
    b = dr.dot(ou, d)
    c2 = dr.squared_norm(ou)
    disc = b * b - (c2 - 1.0)  # the ball of interest: its exit is t_b
    tb = dr.maximum(-b + dr.sqrt(dr.maximum(disc, 0.0)), 1.0)
    disc_s = disc if r_start == 1.0 else b * b - (c2 - r_start * r_start)  # start sphere
    near = dr.maximum(dr.select(disc_s > 0, -b - dr.sqrt(dr.maximum(disc_s, 0.0)), -b), 0.0)
    return radius * near, radius * tb, radius * (dr.sqrt(c2) + reach)


def section_to_world(s: Any, lo: Any, hi: Any, tb: Any) -> tuple[Any, Any]:
    """A sample at s owning [s - lo, s + hi] in s: its world distance and section length."""
    return t_of_s(s, tb), t_of_s(s + hi, tb) - t_of_s(s - lo, tb)
