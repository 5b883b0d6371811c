"""Render a toy scene with Mitsuba 3 and write it as a Blender/NeRF-synthetic data set.

Output layout (``out``)::

    transforms_train.json, transforms_test.json   camera_angle_x, aabb, scene, frames
    train/r_{k}.png, test/r_{k}.png               RGBA, 8-bit, sRGB colour, straight alpha

Each view has
- a colour pass rendered by Mitsuba (``volpath``, stratified sampler, box filter): the real
  materials and invisible directional lights, no environment -> premultiplied colour;
- an exact opacity alpha = 1 - transmittance (``scenes/opacity.py``): pixel coverage of the
  opaque spheres and the real opacity of fuzzy media (not "the ray hit the bounding sphere").
The stored straight colour is premultiplied / alpha.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Callable

import numpy as np

from scenes import content
from scenes.cameras import gl_to_mitsuba, sample_poses
from scenes.content import SceneSpec
from scenes.opacity import opacity
from shells.errors import InputError
from shells.files import atomic_write, write_image, write_json

Builder = Callable[[np.random.Generator], SceneSpec]
SCENES: dict[str, Builder] = {
    "sphere": content.sphere,
    "fuzzy-sphere": content.fuzzy_sphere,
    "core-fuzz": content.core_fuzz,
    "thin-parts": content.thin_parts,
    "unbounded": content.unbounded,
    "white-tube": content.white_tube,
    "off-centre": content.off_centre,
}
CAMERA_ANGLE_X = math.radians(40.0)  # horizontal field of view of every view
AABB = [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]  # scene box written to the JSON
MAX_DEPTH = 3  # path length of the colour pass (direct light + one extra bounce)


def _check_options(name: str, res: int, views: int, test_views: int, spp: int,
                   seed: int, backdrop: Any = None, distance: float | None = None) -> None:
    if name not in SCENES:
        raise InputError(f"unknown scene '{name}'; choose one of {sorted(SCENES)}")
    for flag, value, low in (("--res", res, 8), ("--views", views, 1),
                             ("--test-views", test_views, 1), ("--spp", spp, 1),
                             ("--seed", seed, 0)):
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < low:
            raise InputError(f"{flag} {value!r}: must be an integer >= {low}")
    if backdrop is not None and not (len(backdrop) == 3 and all(0 <= c <= 1 for c in backdrop)):
        raise InputError(f"--backdrop {backdrop!r}: expected three values (R, G, B) in [0, 1]")
    if distance is not None and not (1.8 <= distance <= 20):
        raise InputError(f"--distance {distance!r}: must be in [1.8, 20] (the content reaches "
                         "0.6 from the origin and must stay in view of a 40-degree camera)")


def ensure_variant() -> None:
    """Pick the default Mitsuba variant unless the caller has already chosen one."""
    import mitsuba as mi

    if mi.variant() is None:
        from shells.device import mitsuba_variant

        mitsuba_variant()


def build(name: str, seed: int) -> SceneSpec:
    """The content of scene ``name`` for ``seed`` (texture and density draw from it)."""
    ensure_variant()
    return SCENES[name](np.random.default_rng([seed, 1]))


def _sampler_type(spp: int) -> str:
    """Stratified sub-pixel positions (rim coverage then agrees with the exact alpha) when
    Mitsuba accepts ``spp`` as is (4**k); otherwise independent samples, so spp stays exact."""
    return "stratified" if spp >= 4 and 4 ** round(math.log(spp, 4)) == spp else "independent"


def load_colour_scene(spec: SceneSpec, res: int, spp: int):
    """Mitsuba scene of the colour pass; the sensor pose is set per view by `_render`."""
    import mitsuba as mi

    ensure_variant()
    sensor = {"type": "perspective", "fov": math.degrees(CAMERA_ANGLE_X), "fov_axis": "x",
              "near_clip": 0.01, "far_clip": 100.0,
              "film": {"type": "hdrfilm", "width": res, "height": res, "pixel_format": "rgba",
                       # box filter: each sample lands in its own pixel (no cross-talk)
                       "rfilter": {"type": "box"}},
              "sampler": {"type": _sampler_type(spp), "sample_count": spp}}
    integrator = {"type": "volpath", "max_depth": MAX_DEPTH}
    return mi.load_dict({"type": "scene", "integrator": integrator, "sensor": sensor,
                         **spec.content})


def _render(scene, c2w_gl: np.ndarray, seed: int) -> np.ndarray:  # [H, W, 4] linear RGBA
    import mitsuba as mi

    params = mi.traverse(scene.sensors()[0])
    # Updating the transform keeps one compiled kernel for all views.
    params["to_world"] = mi.ScalarTransform4f(gl_to_mitsuba(c2w_gl).tolist())
    params.update()
    return np.array(mi.render(scene, seed=seed), dtype=np.float64)


def _render_finite(scene, c2w_gl: np.ndarray, seed: int, tries: int = 4) -> np.ndarray:
    """Linear RGB [H, W, 3] of one view. The medium integrator now and then returns a NaN
    sample, which poisons its pixel: such pixels are re-rendered with the next seeds."""
    colour = _render(scene, c2w_gl, seed)[..., :3]
    for retry in range(1, tries):
        bad = ~np.isfinite(colour).all(-1)
        if not bad.any():
            break
        colour[bad] = _render(scene, c2w_gl, seed + retry)[..., :3][bad]
    if not np.isfinite(colour).all():
        raise RuntimeError(f"Mitsuba kept returning NaN pixels for seed {seed}; "
                           "try another --seed or --spp")
    return colour


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB encoding of linear values in [0, 1]."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def to_rgba8(premultiplied: np.ndarray,  # [H, W, 3] linear premultiplied colour
             alpha: np.ndarray,  # [H, W] opacity in [0, 1]
             ) -> np.ndarray:  # [H, W, 4] uint8, sRGB colour, straight alpha
    """Un-premultiply, sRGB-encode and quantise; colour is 0 where alpha rounds to 0."""
    alpha = np.clip(alpha, 0.0, 1.0)
    a8 = np.round(alpha * 255.0)
    straight = np.where(a8[..., None] > 0, premultiplied / np.maximum(alpha, 1e-6)[..., None],
                        0.0)
    rgb8 = np.round(linear_to_srgb(straight) * 255.0)
    return np.concatenate([rgb8, a8[..., None]], -1).astype(np.uint8)


def on_backdrop(rgba8: np.ndarray,  # [H, W, 4] uint8, straight alpha
                backdrop) -> np.ndarray:  # [H, W, 4] uint8, alpha 255 everywhere
    """The view composited on a backdrop colour (sRGB values in [0, 1]) as stored values,
    with an opaque alpha channel: a capture of an object in front of a backdrop."""
    a = rgba8[..., 3:].astype(np.float64) / 255.0
    bg = np.asarray(backdrop, np.float64) * 255.0
    rgb = np.round(rgba8[..., :3] * a + bg * (1.0 - a))
    return np.concatenate([rgb, np.full_like(a, 255.0)], -1).astype(np.uint8)


def _write_png(path: Path, rgba8: np.ndarray) -> None:
    atomic_write(path, lambda p: write_image(p, rgba8, extension=".png"))


def make_scene(name: str, out: str | Path, res: int = 64, views: int = 32, test_views: int = 8,
               spp: int = 64, seed: int = 0, variant: str | None = None,
               backdrop: Any = None, distance: float | None = None) -> dict[str, Any]:
    """Render toy scene ``name`` into ``out`` in the Blender/NeRF-synthetic format.

    ``res``: image width = height; ``views``/``test_views``: number of train/test views;
    ``spp``: samples per pixel of each pass; ``seed``: cameras, scene content and sampler seeds
    all derive from it (same seed -> byte-identical files). ``backdrop``: RGB in [0, 1]; the
    views are stored composited on it with an opaque alpha (`on_backdrop`), as photos of an
    object before a backdrop, instead of with their transparency. ``distance``: the cameras sit
    within +- 5 % of this distance from the origin (default 2.6 to 3.0). Returns the train
    JSON record.
    """
    _check_options(name, res, views, test_views, spp, seed, backdrop, distance)
    from shells.device import mitsuba_variant

    mitsuba_variant(variant)
    out = Path(out)
    rng = np.random.default_rng([seed, 0])
    radius = (2.6, 3.0) if distance is None else (0.95 * distance, 1.05 * distance)
    poses = {"train": sample_poses(rng, views, radius, even=True),
             "test": sample_poses(rng, test_views, radius)}
    render_seeds = {split: rng.integers(0, 2**31, size=len(p)) for split, p in poses.items()}
    spec = build(name, seed)
    scene = load_colour_scene(spec, res, spp)

    records = {}
    for split, c2ws in poses.items():
        frames = []
        for k, c2w in enumerate(c2ws):
            alpha = opacity(spec, c2w, CAMERA_ANGLE_X, res)
            colour = _render_finite(scene, c2w, int(render_seeds[split][k]))
            rgba8 = to_rgba8(colour, alpha)
            _write_png(out / split / f"r_{k}.png",
                       rgba8 if backdrop is None else on_backdrop(rgba8, backdrop))
            frames.append({"file_path": f"{split}/r_{k}", "transform_matrix": c2w.tolist()})
        records[split] = {"camera_angle_x": CAMERA_ANGLE_X, "aabb": AABB, "scene": spec.meta,
                          **({"unbounded": True} if spec.room_radius > 0 else {}),
                          "frames": frames}
        write_json(out / f"transforms_{split}.json", records[split])
    return records["train"]
