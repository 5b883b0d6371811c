"""Per-part scores of a render of the `thin-parts` scene: the sphere, the rod and the plate.

A test pixel belongs to a part when its centre ray (the data set's own camera, OpenGL axes)
hits that part first (`scenes.opacity.first_hit`) and the ground truth is opaque there
(alpha > 0.99). For each part: its pixel count, the mean |error| (mean over RGB) of the render
against the ground truth and the mean rendered opacity. The renderer is a callable, so this
module needs nothing from `shells`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np

from scenes.cameras import pixel_rays_gl
from scenes.content import thin_parts
from scenes.dataset import CAMERA_ANGLE_X, ensure_variant
from scenes.opacity import first_hit

PARTS = ("sphere", "rod", "plate")  # the object ids of `thin_parts`, in order


def part_scores(data: str | Path,  # the thin-parts data set (make_scene)
                images: np.ndarray,  # [N, H, W, 3] its test images, composited
                alpha: np.ndarray,  # [N, H, W] their alpha
                render: Callable[[int], tuple[np.ndarray, np.ndarray]],
                # view i -> (rgb [H, W, 3], opacity [H * W]) of the test camera i
                ) -> dict[str, dict[str, float]]:
    """{part: {"pixels", "error", "opacity"}} over all test views."""
    frames = json.loads((Path(data) / "transforms_test.json").read_text())["frames"]
    ensure_variant()  # the scene description builds Mitsuba transforms (the data set may
    # have been rendered by an earlier process)
    spec = thin_parts(np.random.default_rng(0))
    H, W = images.shape[1:3]
    err = {k: [] for k in range(len(PARTS))}
    opac = {k: [] for k in range(len(PARTS))}
    for i in range(len(images)):
        c2w = np.asarray(frames[i]["transform_matrix"], np.float64)
        o, d = pixel_rays_gl(c2w, CAMERA_ANGLE_X, W, H)
        _, ids = first_hit(spec, o.reshape(-1, 3), d.reshape(-1, 3))
        rgb, opacity = render(i)
        e = np.abs(rgb - images[i]).mean(-1).reshape(-1)
        a, opacity = alpha[i].reshape(-1), np.asarray(opacity).reshape(-1)
        for k in err:
            m = (ids == k) & (a > 0.99)
            err[k].append(e[m])
            opac[k].append(opacity[m])
    out = {}
    for k, name in enumerate(PARTS):
        e, o_ = np.concatenate(err[k]), np.concatenate(opac[k])
        out[name] = {"pixels": int(e.size), "error": float(e.mean()) if e.size else float("nan"),
                     "opacity": float(o_.mean()) if o_.size else float("nan")}
    return out
