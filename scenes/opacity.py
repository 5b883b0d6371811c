"""Exact per-pixel opacity (alpha) of a toy scene, computed deterministically.

alpha = 1 - T, with T the transmittance along the ray averaged over an n x n stratified grid of
points in the pixel: T = 0 when the ray hits an opaque sphere or box, else
exp(-∫ sigma_t ds) through the medium, integrated with the midpoint rule. sigma_t is evaluated
by Mitsuba's own ``gridvolume`` plugin, so the medium is exactly the one the colour pass
renders. This replaces a noisy Mitsuba pass (absorbing medium lit by a unit environment), which
the tests keep as the reference (`reference_opacity`).
"""

from __future__ import annotations

import math

import numpy as np

from scenes.cameras import gl_to_mitsuba, pixel_rays_gl
from scenes.content import SceneSpec, density_volume


def _sphere_hits(o: np.ndarray,  # [R, 3]
                 d: np.ndarray,  # [R, 3] unit
                 center, radius: float) -> tuple[np.ndarray, np.ndarray]:  # t0 [R], t1 [R]
    """Entry and exit distances of rays through a sphere (nan where they miss)."""
    oc = o - np.asarray(center, np.float64)
    b = np.einsum("ij,ij->i", oc, d)
    disc = b * b - (np.einsum("ij,ij->i", oc, oc) - radius * radius)
    h = np.sqrt(np.where(disc > 0, disc, np.nan))
    return -b - h, -b + h


def _box_hits(o: np.ndarray,  # [R, 3]
              d: np.ndarray,  # [R, 3] unit
              centre, half) -> tuple[np.ndarray, np.ndarray]:  # t0 [R], t1 [R]
    """Entry and exit distances of rays through an axis-aligned box (nan where they miss)."""
    lo = np.asarray(centre, np.float64) - np.asarray(half, np.float64)
    hi = np.asarray(centre, np.float64) + np.asarray(half, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        a, b = (lo - o) * inv, (hi - o) * inv
    t0 = np.nanmax(np.minimum(a, b), axis=1)
    t1 = np.nanmin(np.maximum(a, b), axis=1)
    miss = ~(t1 > t0)
    return np.where(miss, np.nan, t0), np.where(miss, np.nan, t1)


def _tube_hits(o: np.ndarray,  # [R, 3]
               d: np.ndarray,  # [R, 3] unit
               centre, radius: float, half: float) -> tuple[np.ndarray, np.ndarray]:
    """First and last distances where rays cross an open tube along z (a wall of zero
    thickness, centre +- half in z; nan where they miss it)."""
    oc = o - np.asarray(centre, np.float64)
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = oc[:, 0] * d[:, 0] + oc[:, 1] * d[:, 1]
    c = oc[:, 0] ** 2 + oc[:, 1] ** 2 - radius * radius
    with np.errstate(divide="ignore", invalid="ignore"):
        disc = b * b - a * c
        h = np.sqrt(np.where(disc > 0, disc, np.nan))
        roots = np.stack([(-b - h) / a, (-b + h) / a], 1)  # [R, 2]
    z = oc[:, 2, None] + roots * d[:, 2, None]
    ok = (np.abs(z) <= half) & (roots > 0)
    t = np.where(ok, roots, np.nan)
    return np.fmin(t[:, 0], t[:, 1]), np.fmax(t[:, 0], t[:, 1])


def first_hit(spec: SceneSpec,
              o: np.ndarray,  # [R, 3]
              d: np.ndarray,  # [R, 3] unit
              ) -> tuple[np.ndarray, np.ndarray]:  # t [R] (inf: none), object id [R] (-1: none)
    """The first opaque object each ray hits: ids 0.. for `spec.spheres`, then `spec.boxes`,
    then `spec.cylinders`."""
    t_stop, ids = np.full(len(o), np.inf), np.full(len(o), -1)
    hits = [_sphere_hits(o, d, c, r) for c, r in spec.spheres]
    hits += [_box_hits(o, d, c, h) for c, h in spec.boxes]
    hits += [_tube_hits(o, d, c, r, h) for c, r, h in spec.cylinders]
    for k, (t0, _) in enumerate(hits):
        closer = (t0 > 0) & (t0 < t_stop)
        t_stop, ids = np.where(closer, t0, t_stop), np.where(closer, k, ids)
    return t_stop, ids


def ray_transmittance(spec: SceneSpec,
                      o: np.ndarray,  # [R, 3]
                      d: np.ndarray,  # [R, 3] unit directions
                      n_steps: int = 128) -> np.ndarray:  # [R] transmittance in [0, 1]
    """Transmittance of each ray through the scene to infinity (cameras are outside it)."""
    t_stop, _ = first_hit(spec, o, d)
    trans = np.where(np.isfinite(t_stop), 0.0, 1.0)
    if spec.density is None:
        return trans

    import drjit as dr
    import mitsuba as mi

    t0, t1 = _sphere_hits(o, d, spec.medium_centre, spec.medium_radius)
    t0, t1 = np.maximum(t0, 0.0), np.fmin(t1, t_stop)
    live = np.flatnonzero(np.nan_to_num(t1 - t0, nan=0.0) > 0)
    if live.size == 0:
        return trans
    dt = (t1[live] - t0[live]) / n_steps  # [L]
    s = t0[live, None] + dt[:, None] * (np.arange(n_steps) + 0.5)  # [L, S] midpoints
    p = o[live, None] + s[..., None] * d[live, None]  # [L, S, 3]
    volume = mi.load_dict(density_volume(spec.density, spec.medium_radius,
                                         spec.medium_centre))
    it = dr.zeros(mi.Interaction3f, p.shape[0] * n_steps)
    it.p = mi.Point3f(*(p.reshape(-1, 3).T.astype(np.float32)))
    sigma = np.array(volume.eval_1(it), np.float64).reshape(-1, n_steps)  # [L, S]
    trans[live] *= np.exp(-spec.sigma_scale * sigma.sum(1) * dt)
    return trans


def opacity(spec: SceneSpec,
            c2w_gl: np.ndarray,  # [4, 4] OpenGL camera-to-world
            camera_angle_x: float, res: int, n_sub: int = 5,
            n_steps: int = 128) -> np.ndarray:  # [res, res] alpha in [0, 1]
    """Pixel alpha of the view: 1 - mean transmittance over n_sub x n_sub stratified rays.

    n_sub is odd by default so that a coverage of exactly one half cannot occur: alpha > 0.5
    then agrees with "the pixel-centre ray hits" along a straight-ish rim.
    """
    if spec.room_radius > 0:  # the room closes every ray
        return np.ones((res, res))
    grid = (np.arange(n_sub) + 0.5) / n_sub
    offsets = np.stack(np.meshgrid(grid, grid, indexing="ij"), -1).reshape(-1, 2)  # [K, 2]
    o, d = pixel_rays_gl(c2w_gl, camera_angle_x, res, res, offsets)  # [H, W, K, 3]
    trans = ray_transmittance(spec, o.reshape(-1, 3), d.reshape(-1, 3), n_steps)
    return 1.0 - trans.reshape(res, res, -1).mean(-1)


def reference_opacity(spec: SceneSpec,
                      c2w_gl: np.ndarray,  # [4, 4] OpenGL camera-to-world
                      camera_angle_x: float, res: int, spp: int,
                      seed: int = 0) -> np.ndarray:  # [res, res] alpha (noisy estimate)
    """Monte-Carlo alpha rendered by Mitsuba: surfaces black, medium a pure absorber, no lights,
    a constant unit environment -> pixel value = transmittance (slow; for tests)."""
    import mitsuba as mi

    absorber = mi.load_dict({
        "type": "heterogeneous", "scale": spec.sigma_scale, "albedo": {"type": "rgb", "value": 0.0},
        "sigma_t": density_volume(spec.density, spec.medium_radius, spec.medium_centre),
    }) if spec.density is not None else None
    items = {}
    for key, entry in spec.content.items():
        if entry.get("type") in ("directional", "point", "constant", "envmap"):
            continue
        entry = dict(entry)
        if entry["bsdf"]["type"] != "null":
            entry["bsdf"] = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}}
        for side in ("interior", "exterior"):
            if side in entry:
                entry[side] = absorber
        items[key] = entry
    items["environment"] = {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}}
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "volpath", "max_depth": 64},
        "sensor": {"type": "perspective", "fov": math.degrees(camera_angle_x), "fov_axis": "x",
                   "to_world": mi.ScalarTransform4f(gl_to_mitsuba(c2w_gl).tolist()),
                   "film": {"type": "hdrfilm", "width": res, "height": res,
                            "pixel_format": "rgb", "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
        **items})
    return 1.0 - np.array(mi.render(scene, seed=seed), np.float64).mean(-1)
