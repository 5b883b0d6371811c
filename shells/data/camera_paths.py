"""Camera paths for videos: an orbit or a spiral around the scene, an interpolation through the
training cameras, or a nerfstudio ``camera_path.json``.

All paths are built from the training cameras (`shells.data.cameras.Cameras`, OpenCV axes) and the
scene box:

* up: the mean of the training cameras' up vectors (-y column of c2w), normalised, as
  nerfstudio orients captures;
* centre: the centre of the scene box; radius: the median distance of the training cameras
  from it; elevation: their median elevation angle above the plane normal to up;
* ``orbit``: N frames at equal azimuth steps (the first at the first training camera's
  azimuth, the last one step short of a full turn), at that radius and elevation, looking at
  the centre;
* ``spiral``: the orbit with the elevation swinging by +-15 degrees (one period) and the
  radius by +-10 % (two periods) over the turn;
* ``interpolate``: through the training cameras in file order, N frames evenly in path
  parameter, positions linear and rotations spherical-linear between neighbours;
* a file: nerfstudio's camera path (``camera_path`` list of ``camera_to_world`` 4x4, row major,
  OpenGL axes, in this data set's world units; ``fov`` vertical degrees; ``render_width``,
  ``render_height``, ``fps``).

The intrinsics of orbit / spiral / interpolate are the first training camera's (without lens
distortion), scaled to the requested size.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.spatial.transform import Rotation, Slerp

from shells.data.cameras import Cameras, look_at, opengl_to_opencv, pinhole_cameras
from shells.errors import InputError

NAMES = ("orbit", "spiral", "interpolate")


def scene_frame(cams: Cameras, aabb: Any) -> tuple[np.ndarray, np.ndarray, float, float]:
    """centre [3], unit up [3], radius and elevation (radians) of the training cameras."""
    box = np.asarray(torch.as_tensor(aabb, dtype=torch.float64).cpu())
    centre = 0.5 * (box[0] + box[1])
    c2w = cams.c2w.double().cpu().numpy()
    up = -c2w[:, :3, 1].mean(0)
    if np.linalg.norm(up) < 1e-9:
        up = np.array([0.0, 0.0, 1.0])
    up = up / np.linalg.norm(up)
    rel = c2w[:, :3, 3] - centre
    dist = np.linalg.norm(rel, axis=1)
    elev = np.arcsin(np.clip((rel @ up) / np.maximum(dist, 1e-12), -1.0, 1.0))
    return centre, up, float(np.median(dist)), float(np.median(elev))


def _basis(up: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane normal to ``up``; the first along ``ref``'s
    projection (the first camera's azimuth)."""
    a = ref - (ref @ up) * up
    if np.linalg.norm(a) < 1e-9:
        a = np.cross(up, [1.0, 0.0, 0.0])
        if np.linalg.norm(a) < 1e-9:
            a = np.cross(up, [0.0, 1.0, 0.0])
    a = a / np.linalg.norm(a)
    return a, np.cross(up, a)


def _intrinsics(cams: Cameras, width: int | None, height: int | None) -> tuple[float, float,
                                                                                int, int]:
    first = cams[:1].resized(width, height)
    return float(first.fx[0]), float(first.fy[0]), first.width, first.height


def around(cams: Cameras, aabb: Any, frames: int, spiral: bool = False,
           width: int | None = None, height: int | None = None) -> Cameras:
    """The orbit (or spiral) of the module docstring, ``frames`` cameras."""
    if frames < 1:
        raise InputError(f"--frames {frames}: must be at least 1")
    centre, up, radius, elev = scene_frame(cams, aabb)
    a, b = _basis(up, cams.c2w[0, :3, 3].double().cpu().numpy() - centre)
    c2w = []
    for k in range(frames):
        t = k / frames
        phi = 2.0 * math.pi * t
        e, r = elev, radius
        if spiral:
            e = elev + math.radians(15.0) * math.sin(2.0 * math.pi * t)
            r = radius * (1.0 + 0.1 * math.sin(4.0 * math.pi * t))
        eye = centre + r * (math.cos(e) * (math.cos(phi) * a + math.sin(phi) * b)
                            + math.sin(e) * up)
        c2w.append(look_at(eye, centre, up))
    fx, fy, w, h = _intrinsics(cams, width, height)
    return pinhole_cameras(torch.stack(c2w), fx=fx, fy=fy, width=w, height=h)


def interpolate(cams: Cameras, frames: int, width: int | None = None,
                height: int | None = None) -> Cameras:
    """``frames`` cameras through the training cameras in order (see the module docstring)."""
    if frames < 1:
        raise InputError(f"--frames {frames}: must be at least 1")
    c2w = cams.c2w.double().cpu().numpy()
    n = len(c2w)
    if n < 2:
        raise InputError("--path interpolate needs at least two training cameras")
    keys = np.arange(n, dtype=np.float64)
    slerp = Slerp(keys, Rotation.from_matrix(c2w[:, :3, :3]))
    s = np.linspace(0.0, n - 1.0, frames) if frames > 1 else np.zeros(1)
    rot = slerp(s).as_matrix()
    lo = np.clip(np.floor(s).astype(int), 0, n - 2)
    f = (s - lo)[:, None]
    pos = (1.0 - f) * c2w[lo, :3, 3] + f * c2w[lo + 1, :3, 3]
    out = np.tile(np.eye(4), (frames, 1, 1))
    out[:, :3, :3], out[:, :3, 3] = rot, pos
    fx, fy, w, h = _intrinsics(cams, width, height)
    return pinhole_cameras(torch.from_numpy(out).float(), fx=fx, fy=fy, width=w, height=h)


def from_file(path: str | Path, width: int | None = None,
              height: int | None = None) -> tuple[Cameras, float | None]:
    """The cameras of a nerfstudio camera_path.json and its fps (None if it has none)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"--path {path}: no such file; pass orbit, spiral, interpolate or a "
                         "nerfstudio camera_path.json")
    try:
        data = json.loads(path.read_text())
        views = data["camera_path"]
        W = int(width or data.get("render_width") or 0)
        H = int(height or data.get("render_height") or 0)
        c2w, fy = [], []
        for v in views:
            m = np.asarray(v["camera_to_world"], dtype=np.float64).reshape(4, 4)
            if not np.isfinite(m).all():
                raise ValueError("camera_to_world is not finite")
            c2w.append(m)
            fov = float(v.get("fov", 50.0))
            if not 0.0 < fov < 180.0:
                raise ValueError(f"fov {fov} outside (0, 180) degrees")
            fy.append(fov)
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{path}: not a nerfstudio camera path ({type(exc).__name__}: {exc}); "
                         "expected {\"camera_path\": [{\"camera_to_world\": [16 numbers], "
                         "\"fov\": degrees}, ...], \"render_width\", \"render_height\"}")
    if not c2w:
        raise InputError(f"{path}: the camera path has no cameras")
    if W < 1 or H < 1:
        raise InputError(f"{path}: no render_width / render_height; pass --width and --height")
    gl = torch.from_numpy(np.stack(c2w)).float()
    f = [0.5 * H / math.tan(math.radians(v) / 2.0) for v in fy]
    cams = pinhole_cameras(opengl_to_opencv(gl), fx=f[0], width=W, height=H)
    cams.fx[:] = torch.tensor(f)
    cams.fy[:] = torch.tensor(f)
    fps = data.get("fps")
    return cams, (float(fps) if fps else None)


def camera_path(spec: str, cams: Cameras, aabb: Any, frames: int, width: int | None = None,
                height: int | None = None) -> tuple[Cameras, float | None]:
    """``spec`` = orbit | spiral | interpolate | a camera_path.json -> (cameras, file fps)."""
    if spec in ("orbit", "spiral"):
        return around(cams, aabb, frames, spec == "spiral", width, height), None
    if spec == "interpolate":
        return interpolate(cams, frames, width, height), None
    return from_file(spec, width, height)
