"""Sampling a field's SDF f and kernel size s on a regular grid over the scene box."""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
import torch

from shells.errors import InputError


def check_aabb(aabb) -> np.ndarray:  # [2, 3] (min corner, max corner), float64
    """Validate a scene box given as [[xmin, ymin, zmin], [xmax, ymax, zmax]]."""
    box = np.asarray(aabb, dtype=np.float64)
    if box.shape != (2, 3) or not np.all(np.isfinite(box)) or not np.all(box[1] > box[0]):
        raise InputError(f"aabb {np.asarray(aabb).tolist()}: expected [[xmin, ymin, zmin], "
                         "[xmax, ymax, zmax]] with max > min on every axis")
    return box


def grid_axes(aabb, resolution: int) -> list[np.ndarray]:  # 3 x [R] world coordinates
    """Per-axis coordinates of the resolution^3 grid spanning the aabb corners inclusive."""
    box = check_aabb(aabb)
    return [np.linspace(box[0, a], box[1, a], resolution) for a in range(3)]


def sample_grid(fn: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
                aabb, resolution: int, chunk: int = 262144,
                device: str | torch.device = "cpu") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Evaluate ``fn(x [N, 3] world points) -> (sdf [N], s [N])`` on the grid, in chunks.

    Returns f [R, R, R] float32, s [R, R, R] float32 indexed [i, j, k] = (x, y, z), and the
    grid spacing (3,) in world units. Points are built per chunk on ``device`` (CPU or CUDA)
    under ``torch.no_grad()``; results come back to host memory chunk by chunk.
    """
    if int(resolution) < 2:
        raise InputError(f"grid resolution {resolution}: must be at least 2 (e.g. 256)")
    res = int(resolution)
    box = check_aabb(aabb)
    spacing = (box[1] - box[0]) / (res - 1)
    n = res ** 3
    f = np.empty(n, dtype=np.float32)
    s = np.empty(n, dtype=np.float32)
    lo = torch.as_tensor(box[0], dtype=torch.float32, device=device)
    h = torch.as_tensor(spacing, dtype=torch.float32, device=device)
    with torch.no_grad():
        for start in range(0, n, int(chunk)):
            flat = torch.arange(start, min(start + int(chunk), n), device=device)
            ijk = torch.stack(torch.unravel_index(flat, (res, res, res)), dim=-1)
            x = lo + ijk.to(torch.float32) * h  # [N, 3]
            sdf, kernel = fn(x)
            f[start:start + len(flat)] = sdf.reshape(-1).float().cpu().numpy()
            s[start:start + len(flat)] = kernel.reshape(-1).float().cpu().numpy()
    return f.reshape(res, res, res), s.reshape(res, res, res), spacing


def sample_grid_banded(fn: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
                       aabb, resolution: int, band: float, chunk: int = 262144,
                       device: str | torch.device = "cpu", lipschitz: float = 2.0,
                       progress: bool = False,
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """``sample_grid`` exact where |f| < ``band``, cheap elsewhere (coarse-to-fine).

    The field is first sampled on a grid 4x coarser per axis and interpolated trilinearly to
    the full grid. An interpolated value is off by at most L * sqrt(3) * h_coarse if f is
    L-Lipschitz (``lipschitz``, 2 by default: the Eikonal loss keeps |grad f| near 1), so every
    point with |f_interp| < band + that margin is evaluated exactly; the others keep the
    interpolated f (its sign and |f| >= band are right) and s. Shell extraction reads f only
    where |f| < zeta (the level-set falloff) plus one grid step, so with band >= zeta + 2 h its
    result equals that of the full sampling. ``progress``: a bar over the exact points.
    Returns f, s, spacing and the exact fraction.
    """
    res = int(resolution)
    if res < 2:
        raise InputError(f"grid resolution {resolution}: must be at least 2 (e.g. 256)")
    rc = max(2, (res - 1) // 4 + 1)
    if rc * 2 >= res:  # too small to gain anything
        f, s, spacing = sample_grid(fn, aabb, res, chunk, device)
        return f, s, spacing, 1.0
    box = check_aabb(aabb)
    spacing = (box[1] - box[0]) / (res - 1)
    fc, sc, spacing_c = sample_grid(fn, aabb, rc, chunk, device)

    def upsample(x: np.ndarray) -> np.ndarray:  # one grid at a time: bounded memory at 512^3
        return torch.nn.functional.interpolate(
            torch.from_numpy(x)[None, None], size=(res, res, res), mode="trilinear",
            align_corners=True)[0, 0].numpy().reshape(-1)  # corner-inclusive grids line up

    f = upsample(fc)
    s = upsample(np.log(sc))
    np.exp(s, out=s)
    margin = lipschitz * math.sqrt(3.0) * float(np.max(spacing_c))
    todo = np.flatnonzero(np.abs(f) < band + margin)
    lo = torch.as_tensor(box[0], dtype=torch.float32, device=device)
    h = torch.as_tensor(spacing, dtype=torch.float32, device=device)
    from shells.progress import tqdm
    bar = tqdm(total=len(todo), desc="sample field", unit="pt", unit_scale=True, leave=False,
               disable=not progress)
    with torch.no_grad(), bar:
        for start in range(0, len(todo), int(chunk)):
            idx = todo[start:start + int(chunk)]
            bar.update(len(idx))
            flat = torch.as_tensor(idx, device=device)
            ijk = torch.stack(torch.unravel_index(flat, (res, res, res)), dim=-1)
            sdf, kernel = fn(lo + ijk.to(torch.float32) * h)
            f[idx] = sdf.reshape(-1).float().cpu().numpy()
            s[idx] = kernel.reshape(-1).float().cpu().numpy()
    shape = (res, res, res)
    return (f.reshape(shape).astype(np.float32, copy=False),
            s.reshape(shape).astype(np.float32, copy=False), spacing, len(todo) / res ** 3)
