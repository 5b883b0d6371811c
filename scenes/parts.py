"""Per-object scores of a render of a toy scene: is every object there?

A test pixel belongs to an opaque object when its centre ray (the data set's own camera, OpenGL
axes) hits that object first (`scenes.opacity.first_hit`) and the ground truth is opaque there
(alpha > 0.99); it belongs to the fuzzy medium ("fuzz") when its ray hits no opaque object and
the ground truth's alpha is above 0.5. For each object: its pixel count, the mean |error| (mean
over RGB) of the render against the ground truth and the mean rendered opacity; "rest" holds
the same over all other pixels (the background included). The renderer is a callable, so this
module needs nothing from `shells`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np

from scenes.cameras import pixel_rays_gl
from scenes.dataset import CAMERA_ANGLE_X, SCENES, ensure_variant
from scenes.opacity import first_hit, opacity

PARTS = ("sphere", "rod", "plate")  # the objects of `thin-parts`, in order


def part_scores(data: str | Path,  # a toy data set (make_scene)
                images: np.ndarray,  # [N, H, W, 3] its test images, composited
                alpha: np.ndarray | None,  # [N, H, W] their alpha (None: the data set's own
                # files are opaque; the exact opacity of the scene is used)
                render: Callable[[int], tuple[np.ndarray, np.ndarray]],
                # view i -> (rgb [H, W, 3], opacity [H * W]) of the test camera i
                ) -> dict[str, dict[str, float]]:
    """{object name: {"pixels", "error", "opacity"}} over all test views, and "rest"."""
    record = json.loads((Path(data) / "transforms_test.json").read_text())
    frames = record["frames"]
    ensure_variant()  # the scene description builds Mitsuba objects (the data set may have
    # been rendered by an earlier process)
    spec = SCENES[record["scene"]["name"]](np.random.default_rng(0))  # geometry only
    names = spec.names
    H, W = images.shape[1:3]
    err = {k: [] for k in range(len(names) + 1)}  # the last: the rest
    opac = {k: [] for k in err}
    n_hard = len(spec.spheres) + len(spec.boxes) + len(spec.cylinders)
    for i in range(len(images)):
        c2w = np.asarray(frames[i]["transform_matrix"], np.float64)
        o, d = pixel_rays_gl(c2w, CAMERA_ANGLE_X, W, H)
        _, ids = first_hit(spec, o.reshape(-1, 3), d.reshape(-1, 3))
        a = (alpha[i] if alpha is not None else opacity(spec, c2w, CAMERA_ANGLE_X, W))
        a = np.asarray(a).reshape(-1)
        rgb, rendered = render(i)
        e = np.abs(rgb - images[i]).mean(-1).reshape(-1)
        rendered = np.asarray(rendered).reshape(-1)
        owner = np.where((ids >= 0) & (a > 0.99), ids, -1)
        if spec.density is not None:
            owner = np.where((ids < 0) & (a > 0.5), n_hard, owner)  # the medium
        owner = np.where(owner < 0, len(names), owner)
        for k in err:
            m = owner == k
            err[k].append(e[m])
            opac[k].append(rendered[m])
    out = {}
    for k, name in enumerate([*names, "rest"]):
        e, o_ = np.concatenate(err[k]), np.concatenate(opac[k])
        out[name] = {"pixels": int(e.size), "error": float(e.mean()) if e.size else float("nan"),
                     "opacity": float(o_.mean()) if o_.size else float("nan")}
    return out


KEPT_FACTOR = 2.0  # an object is kept when its error is at most this times the mean error over
# all objects' pixels


def objects_kept(scores: dict[str, dict[str, float]]) -> dict:
    """Whether every object of `part_scores` is there: {"all": bool, "ratios": {object: its
    mean |error| over the mean |error| of all objects' pixels}} (KEPT_FACTOR)."""
    objs = {k: v for k, v in scores.items() if k != "rest" and v["pixels"] > 0}
    total = sum(v["error"] * v["pixels"] for v in objs.values())
    mean = total / max(1, sum(v["pixels"] for v in objs.values()))
    ratios = {k: v["error"] / max(mean, 1e-9) for k, v in objs.items()}
    return {"all": all(r <= KEPT_FACTOR for r in ratios.values()), "ratios": ratios}
