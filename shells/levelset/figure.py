"""A slice figure like the paper's Fig. 5, drawn with numpy and written with imageio.

Left panel: f on a diverging blue-white-red map (blue inside, red outside, clipped at the
95th percentile of |f|). Right panel: log10 s on a dark-blue-to-yellow map. Both panels carry
the contours f0 = 0 (black), SDF+ = 0 (orange, outer shell) and SDF- = 0 (cyan, inner shell),
drawn as the pixels whose sign differs from a 4-neighbour. x runs right, y up.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import ndimage

from shells.files import atomic_write, write_image
from shells.levelset.grid import check_aabb

_DIVERGING = np.array([[0.23, 0.30, 0.75], [1.0, 1.0, 1.0], [0.71, 0.02, 0.15]])
_SEQUENTIAL = np.array([[0.27, 0.00, 0.33], [0.23, 0.32, 0.55], [0.13, 0.57, 0.55],
                        [0.37, 0.79, 0.38], [0.99, 0.91, 0.14]])  # viridis anchors
_CONTOURS = ((0, (0.0, 0.0, 0.0)), (1, (1.0, 0.55, 0.0)), (2, (0.0, 0.85, 0.95)))


def colormap(t: np.ndarray,  # [...] values in [0, 1]
             anchors: np.ndarray) -> np.ndarray:  # [..., 3] RGB in [0, 1]
    """Piecewise-linear colour map through equally spaced anchor colours."""
    t = np.clip(t, 0.0, 1.0) * (len(anchors) - 1)
    i = np.minimum(t.astype(int), len(anchors) - 2)
    w = (t - i)[..., None]
    return anchors[i] * (1 - w) + anchors[i + 1] * w


def sign_change(g: np.ndarray) -> np.ndarray:  # [H, W] bool: pixels on the zero contour
    neg = g <= 0
    edge = np.zeros_like(neg)
    edge[1:, :] |= neg[1:, :] != neg[:-1, :]
    edge[:-1, :] |= neg[1:, :] != neg[:-1, :]
    edge[:, 1:] |= neg[:, 1:] != neg[:, :-1]
    edge[:, :-1] |= neg[:, 1:] != neg[:, :-1]
    return edge & neg  # one pixel thick, on the inside


def slice_figure(f: np.ndarray, s: np.ndarray,  # [X, Y, Z] input SDF and kernel size
                 sdf_plus: np.ndarray, sdf_minus: np.ndarray,  # [X, Y, Z] shell SDFs
                 aabb, path: str | Path, min_size: int = 512) -> np.ndarray:
    """Write the z-slice nearest to z = 0 (the middle slice if 0 is outside the box) as a PNG
    and return the image [H, W, 3] uint8."""
    box = check_aabb(aabb)
    nz = f.shape[2]
    z = np.linspace(box[0, 2], box[1, 2], nz)
    k = int(np.argmin(np.abs(z))) if box[0, 2] <= 0 <= box[1, 2] else nz // 2
    # [X, Y] -> image rows = y (top = max y), columns = x
    to_img = lambda a: np.asarray(a[:, :, k], dtype=np.float64).T[::-1]  # noqa: E731
    fs, ss = to_img(f), to_img(s)
    lim = max(float(np.percentile(np.abs(fs), 95)), 1e-6)
    left = colormap(0.5 + 0.5 * fs / lim, _DIVERGING)
    logs = np.log10(np.maximum(ss, 1e-12))
    lo, hi = float(logs.min()), float(logs.max())
    right = colormap((logs - lo) / max(hi - lo, 1e-6), _SEQUENTIAL)
    scale = max(1, int(np.ceil(min_size / max(fs.shape))))
    panels = []
    for panel in (left, right):
        panel = np.repeat(np.repeat(panel, scale, 0), scale, 1)
        for which, colour in _CONTOURS:
            g = to_img((f, sdf_plus, sdf_minus)[which])
            g = ndimage.zoom(g, scale, order=1, grid_mode=True, mode="nearest")  # smooth lines
            panel[sign_change(g)] = colour
        panels.append(panel)
    gap = np.ones((panels[0].shape[0], max(4, scale), 3))
    img = (np.concatenate([panels[0], gap, panels[1]], axis=1) * 255).round().astype(np.uint8)
    atomic_write(path, lambda p: write_image(p, img, extension=".png"))
    return img
