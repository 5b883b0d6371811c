"""The SDF's slope |grad f| at a field's level set, and the kernel's world-space width there.

    python bench/sdf_slope.py RUN [--stage stage1|stage2] [--resolution 160]

The NeuS opacity of a sample is computed from f / s and the unit normal (`neus_alpha`), so
along a ray the density falls off over s / |grad f| world units, not over s: the kernel size
in world units is s / |grad f|, which equals s only for an exact SDF (|grad f| = 1, what the
Eikonal term asks for). Samples the field on a grid over its box, keeps the points with
|f| < half a cell (the level set), and prints JSON percentiles of |grad f| (autograd through
the field), of s and of s / |grad f| there.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from shells.levelset.grid import grid_axes  # noqa: E402
from shells.run import RunDir, field_from_checkpoint, read_checkpoint  # noqa: E402

from report import emit_json  # noqa: E402


def pct(x: np.ndarray) -> dict:
    p = np.percentile(x, [5, 25, 50, 75, 95])
    return {"p5": float(p[0]), "p25": float(p[1]), "p50": float(p[2]), "p75": float(p[3]),
            "p95": float(p[4]), "mean": float(x.mean())}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run")
    p.add_argument("--stage", default="stage1", choices=["stage1", "stage2"])
    p.add_argument("--resolution", type=int, default=160)
    p.add_argument("--max-points", type=int, default=200000)
    a = p.parse_args()
    run = RunDir(a.run)
    ckpt = read_checkpoint(run, a.stage)
    field, _ = field_from_checkpoint(ckpt, a.run)
    box = field.aabb.cpu().numpy()
    axes = grid_axes(box, a.resolution)
    h = float(np.max((box[1] - box[0]) / (a.resolution - 1)))
    pts = torch.stack(torch.meshgrid(*[torch.as_tensor(ax, dtype=torch.float32) for ax in axes],
                                     indexing="ij"), dim=-1).reshape(-1, 3)
    keep = []
    with torch.no_grad():
        for chunk in pts.split(262144):
            f = field.geometry_field(chunk)["sdf"]
            keep.append(chunk[f.abs() < 0.5 * h])
    near = torch.cat(keep)
    if len(near) > a.max_points:
        near = near[torch.randperm(len(near), generator=torch.Generator().manual_seed(0))
                    [:a.max_points]]
    g_all, s_all = [], []
    for chunk in near.split(65536):
        x = chunk.clone().requires_grad_(True)
        geo = field.geometry_field(x)
        (grad,) = torch.autograd.grad(geo["sdf"].sum(), x)
        g_all.append(grad.norm(dim=-1).detach())
        s_all.append(geo["s"].detach())
    g = torch.cat(g_all).numpy().astype(np.float64)
    s = torch.cat(s_all).numpy().astype(np.float64)
    emit_json({"run": a.run, "stage": a.stage, "resolution": a.resolution,
               "level_set_points": int(len(g)), "grad_norm": pct(g), "s": pct(s),
               "s_world": pct(s / np.maximum(g, 1e-6))})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
