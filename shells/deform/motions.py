"""Cage motions: new positions of the cage's vertices per frame (paper §5, Fig. 12).

A motion maps rest positions X [n, 3] and a time t in [0, 1] (the animation's phase) to new
positions [n, 3]. The analytic ones are defined in an *asset frame* (`AssetFrame`: centre,
unit up vector, height range along up, a horizontal direction), so they act the same on any
asset whatever its size:

* ``still``: the identity (a check: the frame equals the undeformed band render);
* ``rigid``: a quarter turn about the up axis through the centre and a lift of 25 % of the
  height at mid-animation;
* ``bend``: Barr's bend in the (side, up) plane, the top turning by up to 60 degrees and back,
  the base fixed;
* ``twist``: rotation about the up axis by an angle growing linearly with height, up to
  +-90 degrees at the top;
* ``wind``: a sway along the side direction growing with the square of the height (a fifth of the height at the top), with a
  phase that travels across the asset (the paper's plant example), two gusts per animation.

The physically simulated ones (``drop``, ``hang``) are in `shells.deform.fem`; a file of
poses (.npz, ``positions`` [frames, n, 3]) is read by `read_motion_file`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from shells.errors import InputError


@dataclass(frozen=True)
class AssetFrame:
    centre: np.ndarray  # [3] world
    up: np.ndarray  # [3] unit
    side: np.ndarray  # [3] unit, normal to up: the direction of bend and sway
    base: float  # lowest height along up (the part that stays put)
    height: float  # extent along up

    @classmethod
    def of(cls, X: np.ndarray, up=(0.0, 0.0, 1.0)) -> "AssetFrame":
        up = np.asarray(up, np.float64)
        up = up / np.linalg.norm(up)
        ref = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        side = ref - (ref @ up) * up
        side /= np.linalg.norm(side)
        h = X @ up
        lo, hi = X.min(0), X.max(0)
        return cls(centre=0.5 * (lo + hi), up=up, side=side, base=float(h.min()),
                   height=float(max(h.max() - h.min(), 1e-9)))


def _rotate(P: np.ndarray, axis: np.ndarray, angle) -> np.ndarray:
    """Rodrigues rotation of rows of P about the unit axis; angle scalar or [n]."""
    c, s = np.cos(angle), np.sin(angle)
    c, s = np.broadcast_to(c, len(P))[:, None], np.broadcast_to(s, len(P))[:, None]
    k = axis[None, :]
    return P * c + np.cross(k, P) * s + k * (P @ axis)[:, None] * (1 - c)


def still(X: np.ndarray, t: float, a: AssetFrame) -> np.ndarray:
    return X.copy()


def rigid(X: np.ndarray, t: float, a: AssetFrame) -> np.ndarray:
    R, lift = rigid_motion(t, a)
    return (X - a.centre) @ R.T + a.centre + lift


def rigid_motion(t: float, a: AssetFrame) -> tuple[np.ndarray, np.ndarray]:
    """The ``rigid`` motion at time t as x -> R (x - centre) + centre + lift: (R [3, 3],
    lift [3])."""
    R = _rotate(np.eye(3), a.up, 0.5 * math.pi * t).T  # columns: images of the axes
    return R, a.up * 0.25 * a.height * math.sin(math.pi * t)


def bend(X: np.ndarray, t: float, a: AssetFrame) -> np.ndarray:
    theta = math.radians(60.0) * math.sin(math.pi * t)  # top's turn
    h = X @ a.up - a.base  # height above the base
    u = (X - a.centre) @ a.side  # offset along the bend direction
    if abs(theta) < 1e-9:
        return X.copy()
    k = theta / a.height  # curvature of the bent centre line
    R = 1.0 / k
    phi = k * h
    # Barr: the fibre at offset u follows a circle of radius R - u about the bend centre
    du = (R - (R - u) * np.cos(phi)) - u
    dh = (R - u) * np.sin(phi) - h
    return X + du[:, None] * a.side + dh[:, None] * a.up


def twist(X: np.ndarray, t: float, a: AssetFrame) -> np.ndarray:
    amount = 0.5 * math.pi * math.sin(2 * math.pi * t)
    h = (X @ a.up - a.base) / a.height
    P = X - a.centre
    return _rotate(P, a.up, amount * h) + a.centre


def wind(X: np.ndarray, t: float, a: AssetFrame) -> np.ndarray:
    h = np.clip((X @ a.up - a.base) / a.height, 0.0, None)
    across = (X - a.centre) @ np.cross(a.up, a.side) / a.height
    sway = 0.2 * a.height * h ** 2 * np.sin(2 * math.pi * (2 * t - 0.5 * across))
    return X + sway[:, None] * a.side


ANALYTIC: dict[str, Callable[[np.ndarray, float, AssetFrame], np.ndarray]] = {
    "still": still, "rigid": rigid, "bend": bend, "twist": twist, "wind": wind,
}


def analytic_poses(name: str, X: np.ndarray, frames: int, frame: AssetFrame) -> np.ndarray:
    """[frames, n, 3] positions of an analytic motion, t = k / (frames - 1)."""
    fn = ANALYTIC[name]
    ts = [k / max(frames - 1, 1) for k in range(frames)]
    return np.stack([fn(X, t, frame) for t in ts])


def read_motion_file(path: Path, n_vertices: int) -> tuple[np.ndarray, float | None]:
    """A file of cage poses: .npz with ``positions`` [frames, n, 3] (and optionally ``fps``)
    -> (positions float64, fps or None)."""
    if not path.is_file():
        raise InputError(f"{path}: no such motion file; give one of the motion names or an .npz "
                         "with positions [frames, vertices, 3]")
    try:
        with np.load(path) as z:
            if "positions" not in z.files:
                raise InputError(f"{path}: no 'positions' array; save the cage poses as "
                                 "np.savez(FILE, positions=[frames, vertices, 3])")
            P = np.asarray(z["positions"], np.float64)
            fps = float(z["fps"]) if "fps" in z.files else None
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"{path}: not a readable .npz motion ({type(exc).__name__}); save it "
                         "with np.savez(FILE, positions=...)")
    if P.ndim != 3 or P.shape[1:] != (n_vertices, 3) or len(P) == 0:
        raise InputError(f"{path}: positions of shape {P.shape}; this cage needs "
                         f"[frames, {n_vertices}, 3] (one position per cage vertex and frame)")
    if not np.all(np.isfinite(P)):
        raise InputError(f"{path}: positions contain NaN/inf")
    return P, fps
