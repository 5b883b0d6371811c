"""Scene content (shapes, materials, media, lights) of the toy scenes as Mitsuba dicts.

Every scene lives inside radius 0.6 of the origin (scene box [-1, 1]^3). Lights are
directional (never visible to a camera), so a ray that misses the content sees black.
Each builder returns a `SceneSpec`: the Mitsuba scene-dict entries (no sensor, no integrator),
the JSON ``"scene"`` record, and the geometry the exact opacity is computed from (opaque
spheres and the density grid; see ``scenes/opacity.py``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import ndimage

SPHERE_RADIUS = 0.5  # `sphere`: opaque sphere radius
FUZZ_RADIUS = 0.6  # fuzzy scenes: radius of the bounding sphere of the medium
CORE_RADIUS = 0.3  # `core-fuzz`: opaque core radius
GRID_RES = 64  # voxels per axis of the density grid over [-FUZZ_RADIUS, FUZZ_RADIUS]^3
ROOM_RADIUS = 10.0  # `unbounded`: the textured room sphere around the content


@dataclass
class SceneSpec:
    """One toy scene: Mitsuba content plus the geometry its exact opacity is computed from."""

    content: dict[str, Any]  # Mitsuba scene-dict entries: shapes, media, lights
    meta: dict[str, Any]  # the JSON "scene" record
    spheres: list[tuple[tuple[float, float, float], float]] = field(default_factory=list)
    # ^ opaque spheres (centre, radius)
    boxes: list[tuple[tuple[float, float, float], tuple[float, float, float]]] = field(
        default_factory=list)  # opaque axis-aligned boxes (centre, half extents)
    density: Any = None  # [G, G, G] float32 grid (index [z, y, x]) of the medium, or None
    sigma_scale: float = 0.0  # extinction = sigma_scale * density (1 / world units)
    medium_radius: float = 0.0  # the medium lives inside this sphere at the origin
    room_radius: float = 0.0  # > 0: a self-lit room sphere of this radius closes every ray
    medium_centre: tuple[float, float, float] = (0.0, 0.0, 0.0)  # centre of the medium's sphere
    cylinders: list[tuple[tuple[float, float, float], float, float]] = field(
        default_factory=list)  # open tubes along z with a wall of zero thickness (centre,
    # radius, half height), opaque
    names: list[str] = field(default_factory=list)  # one name per object in `first_hit`'s
    # order (spheres, boxes, cylinders), then "fuzz" for the medium if there is one


def lights() -> dict[str, Any]:
    """Three directional lights of different colours/strengths (key, fill, rim from below)."""
    def light(direction, rgb):
        return {"type": "directional", "direction": list(direction),
                "irradiance": {"type": "rgb", "value": list(rgb)}}
    return {"key": light((-1.0, -0.6, -1.0), (2.4, 2.3, 2.1)),
            "fill": light((1.0, 0.8, -0.3), (0.9, 1.0, 1.2)),
            "rim": light((0.2, -0.4, 1.0), (0.6, 0.6, 0.6))}


def _checker_texture(rng: np.random.Generator, n_u: int = 12, n_v: int = 6,
                     px: int = 16) -> np.ndarray:  # [n_v * px, n_u * px, 3] linear RGB
    """A checker of ``n_u`` x ``n_v`` cells over the sphere's (phi, theta) UVs, each cell a
    random saturated colour, dark and light cells alternating (strong, learnable texture)."""
    hue = rng.uniform(0.0, 1.0, size=(n_v, n_u))
    # hue -> RGB on a smooth colour wheel, then alternate brightness like a checkerboard.
    rgb = 0.5 + 0.5 * np.cos(2 * np.pi * (hue[..., None] - np.array([0.0, 1 / 3, 2 / 3])))
    dark = (np.add.outer(np.arange(n_v), np.arange(n_u)) % 2 == 1)[..., None]
    rgb = np.where(dark, 0.15 * rgb + 0.02, 0.25 + 0.7 * rgb)
    return np.repeat(np.repeat(rgb, px, axis=0), px, axis=1).astype(np.float32)


def sphere(rng: np.random.Generator) -> SceneSpec:
    """`sphere`: opaque textured rough-plastic sphere (view-dependent highlight)."""
    content = {"ball": _textured_ball(rng, SPHERE_RADIUS), **lights()}
    return SceneSpec(content, {"name": "sphere", "center": [0.0, 0.0, 0.0],
                               "radius": SPHERE_RADIUS},
                     spheres=[((0.0, 0.0, 0.0), SPHERE_RADIUS)], names=["sphere"])


def _textured_ball(rng: np.random.Generator, radius: float) -> dict[str, Any]:
    import mitsuba as mi

    bsdf = {"type": "roughplastic", "distribution": "ggx", "alpha": 0.12,
            "diffuse_reflectance": {"type": "bitmap", "bitmap": mi.Bitmap(_checker_texture(rng)),
                                    "filter_type": "nearest", "raw": True}}
    return {"type": "sphere", "center": [0.0, 0.0, 0.0], "radius": radius, "bsdf": bsdf}


def fuzz_density(rng: np.random.Generator, res: int = GRID_RES, radius: float = FUZZ_RADIUS,
                 inner: float = 0.0) -> np.ndarray:  # [res, res, res] density, index [z, y, x]
    """Hair-like density on a voxel grid covering [-radius, radius]^3.

    Strands are radial: a random noise on the sphere of directions (trilinear lookup of a
    seeded 3D noise at x / |x|) sharpened into thin streaks, constant along each radius, times
    a smooth radial falloff from ``inner`` (full density) to ``radius`` (zero). Voxel centres
    are at (k + 0.5) / res of the box, matching Mitsuba's ``gridvolume``.
    """
    noise = rng.uniform(0.0, 1.0, size=(24, 24, 24))
    c = (np.arange(res) + 0.5) / res * 2 * radius - radius  # voxel centres
    z, y, x = np.meshgrid(c, c, c, indexing="ij")
    r = np.sqrt(x * x + y * y + z * z)
    unit = np.stack([x, y, z]) / np.maximum(r, 1e-6)  # [3, res, res, res]
    # Sample the noise on a sphere of radius 10 cells around the noise grid's centre.
    coords = 11.5 + 10.0 * unit
    strands = ndimage.map_coordinates(noise, coords.reshape(3, -1), order=1, mode="wrap")
    strands = np.clip((strands.reshape(r.shape) - 0.45) / 0.25, 0.0, 1.0) ** 2
    t = np.clip((r - inner) / (0.92 * radius - inner), 0.0, 1.0)
    falloff = 0.5 + 0.5 * np.cos(np.pi * t)  # 1 at `inner`, 0 at 0.92 radius and beyond
    return (strands * falloff).astype(np.float32)


def _fuzz_medium(density: np.ndarray,  # [G, G, G]
                 sigma_scale: float, radius: float, centre=(0.0, 0.0, 0.0)):
    """Heterogeneous medium of warm-coloured, forward-scattering fibres over the grid box."""
    import mitsuba as mi

    return mi.load_dict({
        "type": "heterogeneous",
        "sigma_t": density_volume(density, radius, centre),
        "scale": sigma_scale,
        "albedo": {"type": "rgb", "value": [0.85, 0.62, 0.38]},
        "phase": {"type": "hg", "g": 0.3}})


def density_volume(density: np.ndarray,  # [G, G, G]
                   radius: float, centre=(0.0, 0.0, 0.0)) -> dict[str, Any]:
    """``gridvolume`` dict mapping the grid onto centre + [-radius, radius]^3 (trilinear)."""
    import mitsuba as mi

    box = mi.ScalarTransform4f().translate([c - radius for c in centre]).scale(2 * radius)
    return {"type": "gridvolume", "grid": mi.VolumeGrid(density[..., None]),
            "to_world": box, "filter_type": "trilinear"}


THIN_SPHERE = ((-0.25, 0.0, 0.0), 0.3)  # `thin-parts`: the sphere (centre, radius)
THIN_ROD = ((0.35, 0.0, 0.0), (0.025, 0.025, 0.45))  # a rod 0.05 thick (centre, half extents)
THIN_PLATE = ((0.2, 0.0, -0.45), (0.35, 0.3, 0.015))  # a plate 0.03 thick below them


def _box(centre, half, rgb) -> dict[str, Any]:
    import mitsuba as mi

    return {"type": "cube",
            "to_world": mi.ScalarTransform4f().translate(list(centre)).scale(list(half)),
            "bsdf": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.2,
                     "diffuse_reflectance": {"type": "rgb", "value": list(rgb)}}}


def thin_parts(rng: np.random.Generator) -> SceneSpec:
    """`thin-parts`: a textured sphere beside a thin upright rod, over a thin plate: separate
    objects, thin parts and content far from a centred initial sphere."""
    (c, r), rod, plate = THIN_SPHERE, THIN_ROD, THIN_PLATE
    ball = dict(_textured_ball(rng, r), center=list(c))
    content = {"ball": ball, "rod": _box(*rod, (0.8, 0.15, 0.1)),
               "plate": _box(*plate, (0.15, 0.45, 0.8)), **lights()}
    return SceneSpec(content, {"name": "thin-parts", "sphere": [list(c), r],
                               "rod": [list(v) for v in rod], "plate": [list(v) for v in plate]},
                     spheres=[(c, r)], boxes=[rod, plate], names=["sphere", "rod", "plate"])


def unbounded(rng: np.random.Generator) -> SceneSpec:
    """`unbounded`: the `sphere` inside a textured, self-lit room sphere of radius
    ROOM_RADIUS (the toy unbounded scene). Every ray ends on something (alpha 1
    everywhere), and the room lies far outside the region the cameras look at: a bounded field
    cannot hold it, a contracted one can. The room's surface has a null BSDF, so the
    directional lights still reach the ball through it."""
    import mitsuba as mi

    ball = _textured_ball(rng, SPHERE_RADIUS)
    wall = (0.6 * _checker_texture(rng, n_u=24, n_v=12)).astype(np.float32)
    room = {"type": "sphere", "radius": ROOM_RADIUS, "flip_normals": True,
            "bsdf": {"type": "null"},
            "emitter": {"type": "area", "radiance": {"type": "bitmap", "bitmap": mi.Bitmap(wall),
                                                     "filter_type": "bilinear", "raw": True}}}
    return SceneSpec({"ball": ball, "room": room, **lights()},
                     {"name": "unbounded", "center": [0.0, 0.0, 0.0], "radius": SPHERE_RADIUS,
                      "room_radius": ROOM_RADIUS},
                     spheres=[((0.0, 0.0, 0.0), SPHERE_RADIUS)], room_radius=ROOM_RADIUS,
                     names=["sphere"])


def fuzzy_sphere(rng: np.random.Generator) -> SceneSpec:
    """`fuzzy-sphere`: a ball of hair-like heterogeneous medium, no hard surface."""
    density, sigma = fuzz_density(rng, inner=0.15), 30.0
    content = {"fuzz": {"type": "sphere", "radius": FUZZ_RADIUS, "bsdf": {"type": "null"},
                        "interior": _fuzz_medium(density, sigma, FUZZ_RADIUS)},
               **lights()}
    return SceneSpec(content, {"name": "fuzzy-sphere", "center": [0.0, 0.0, 0.0],
                               "radius": FUZZ_RADIUS},
                     density=density, sigma_scale=sigma, medium_radius=FUZZ_RADIUS,
                     names=["fuzz"])


def core_fuzz(rng: np.random.Generator) -> SceneSpec:
    """`core-fuzz`: an opaque sphere (radius 0.3) inside a fuzzy coat (outer radius 0.6)."""
    core = _textured_ball(rng, CORE_RADIUS)
    # sigma 6 (not 20 as for the ball): the coat stays translucent, so the core's sharp surface
    # is seen through it and the learned kernel has a reason to be small there
    density, sigma = fuzz_density(rng, inner=CORE_RADIUS), 6.0
    medium = _fuzz_medium(density, sigma, FUZZ_RADIUS)
    # The core sits inside the medium: rays leaving its surface must be attenuated by the coat.
    content = {"fuzz": {"type": "sphere", "radius": FUZZ_RADIUS, "bsdf": {"type": "null"},
                        "interior": medium},
               "core": dict(core, exterior=medium), **lights()}
    return SceneSpec(content, {"name": "core-fuzz", "center": [0.0, 0.0, 0.0],
                               "core_radius": CORE_RADIUS, "coat_radius": FUZZ_RADIUS},
                     spheres=[((0.0, 0.0, 0.0), CORE_RADIUS)], density=density,
                     sigma_scale=sigma, medium_radius=FUZZ_RADIUS, names=["core", "fuzz"])


def _glossy(rgb) -> dict[str, Any]:
    return {"type": "roughplastic", "distribution": "ggx", "alpha": 0.1,
            "diffuse_reflectance": {"type": "rgb", "value": list(rgb)}}


# `white-tube`: (centre, radius) of the spheres, (centre, half extents) of the cube, (centre,
# radius, half height) of the tube
TUBE_SPHERES = (((-0.3, -0.2, 0.1), 0.28), ((-0.3, 0.38, -0.3), 0.11))
TUBE_BOX = ((0.38, -0.32, -0.3), (0.09, 0.09, 0.09))
TUBE = ((0.18, 0.12, 0.0), 0.17, 0.4)


def white_tube(rng: np.random.Generator) -> SceneSpec:
    """`white-tube`: a white open tube with a wall of zero thickness (seen from both sides)
    beside glossy coloured solids of different sizes (a sphere of radius 0.28, a cube 0.18
    wide, a sphere of radius 0.11). The tube's lit side is as white as a white background:
    there only its shading tells it apart."""
    (c0, r0), (c1, r1) = TUBE_SPHERES
    (cb, hb), (ct, rt, ht) = TUBE_BOX, TUBE
    white = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.9, 0.9, 0.9]}}
    tube = {"type": "cylinder", "radius": rt,
            "p0": [ct[0], ct[1], ct[2] - ht], "p1": [ct[0], ct[1], ct[2] + ht],
            "bsdf": {"type": "twosided", "bsdf": white}}
    content = {"big": {"type": "sphere", "center": list(c0), "radius": r0,
                       "bsdf": _glossy((0.8, 0.12, 0.08))},
               "small": {"type": "sphere", "center": list(c1), "radius": r1,
                         "bsdf": _glossy((0.1, 0.7, 0.15))},
               "box": dict(_box(cb, hb, (0.1, 0.25, 0.85)), bsdf=_glossy((0.1, 0.25, 0.85))),
               "tube": tube, **lights()}
    return SceneSpec(content, {"name": "white-tube",
                               "spheres": [[list(c), r] for c, r in TUBE_SPHERES],
                               "box": [list(v) for v in TUBE_BOX], "tube": [list(ct), rt, ht]},
                     spheres=list(TUBE_SPHERES), boxes=[TUBE_BOX], cylinders=[TUBE],
                     names=["big sphere", "small sphere", "cube", "tube"])


OFF_FUZZ = ((0.3, -0.25, 0.2), 0.38)  # `off-centre`: the fuzzy ball (centre, radius)
OFF_SPHERE = ((-0.42, 0.38, -0.3), 0.12)  # ... and the small glossy sphere


def off_centre(rng: np.random.Generator) -> SceneSpec:
    """`off-centre`: a fuzzy ball (hair-like medium, no hard surface) far off the box centre
    and a small glossy sphere on the other side: nothing where the field's initial sphere is."""
    (cf, rf), (cs, rs) = OFF_FUZZ, OFF_SPHERE
    density, sigma = fuzz_density(rng, radius=rf, inner=0.1), 30.0
    content = {"fuzz": {"type": "sphere", "center": list(cf), "radius": rf,
                        "bsdf": {"type": "null"},
                        "interior": _fuzz_medium(density, sigma, rf, cf)},
               "ball": {"type": "sphere", "center": list(cs), "radius": rs,
                        "bsdf": _glossy((0.15, 0.3, 0.9))},
               **lights()}
    return SceneSpec(content, {"name": "off-centre", "fuzz": [list(cf), rf],
                               "sphere": [list(cs), rs]},
                     spheres=[OFF_SPHERE], density=density, sigma_scale=sigma,
                     medium_radius=rf, medium_centre=cf, names=["sphere", "fuzz"])
