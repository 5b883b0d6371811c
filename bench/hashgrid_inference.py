"""Hash-grid lookups without gradient: the torch lookup against ``dr.nn.HashGridEncoding``.

    python bench/hashgrid_inference.py [--data ../shared/data/lego --downscale 8 --iters 600]

`shells.fields.hashgrid.HashGrid` with ``inference`` "torch" and "auto" (Dr.Jit's LLVM kernel
for lookups that need no gradient). Times one no-gradient lookup of 49 152 random points (the
sample-placement pass of a 1024-ray step: 32 + 16 samples per ray) on a fresh field of the
`object` preset's 1/8 sizes (median of 15 after 3 warm-up calls, alternating the two paths,
outputs compared bit for bit). With ``--data``, also trains stage 1 of the preset ``--preset
auto`` picks for ``--iters`` steps once per path, one run after the other, and prints both
runs' rays/s and their ratio. Prints JSON.

Reading the outputs back (``.torch()``) waits for Dr.Jit's kernel; timing a bare ``dr.eval``
does not (the LLVM backend launches kernels asynchronously), which makes Dr.Jit look 10-20x
faster than it is.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from unittest import mock
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import shells.training as training  # noqa: E402
from shells.config import toy_config  # noqa: E402
from shells.fields.hashgrid import HashGrid  # noqa: E402

from preset_speed import preset_rays_per_s  # noqa: E402
from report import emit_json  # noqa: E402

PATHS = ("torch", "auto")


def lookup_ms(n: int = 49152) -> tuple[dict[str, float], bool]:
    cfg = toy_config()
    cfg.field = dataclasses.replace(cfg.field, n_levels=8, log2_hashmap_size=18,
                                    max_resolution=256)
    field = training.build_field(cfg, torch.tensor([[-1.5] * 3, [1.5] * 3]),
                                 torch.device("cpu"))
    grid = field.grid
    with torch.no_grad():
        grid.params.uniform_(-1.0, 1.0)
    x = torch.rand(n, 3, generator=torch.Generator().manual_seed(0))
    times = {k: [] for k in PATHS}
    outs = {}
    with torch.no_grad():
        for _ in range(18):
            for k in PATHS:
                grid.inference = k
                t = time.perf_counter()
                outs[k] = grid(x)
                times[k].append(time.perf_counter() - t)
    same = bool(torch.equal(outs["torch"], outs["auto"]))
    return {k: 1e3 * statistics.median(v[3:]) for k, v in times.items()}, same


def train_rays_per_s(data: str, downscale: int, iters: int, path: str) -> float:
    with mock.patch.object(HashGrid, "inference", path):
        return preset_rays_per_s(data, downscale, iters, "bench/hashgrid_inference.py")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", default=None)
    p.add_argument("--downscale", type=int, default=8)
    p.add_argument("--iters", type=int, default=600)
    a = p.parse_args()
    ms, same = lookup_ms()
    out = {"torch": torch.__version__, "threads": torch.get_num_threads(),
           "lookup_ms_49152_points": ms, "bit_identical": same}
    if a.data:
        rays = {k: train_rays_per_s(a.data, a.downscale, a.iters, k) for k in PATHS}
        out["train"] = {"data": a.data, "downscale": a.downscale, "iters": a.iters,
                        "rays_per_s": rays, "auto_over_torch": rays["auto"] / rays["torch"]}
    emit_json(out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
