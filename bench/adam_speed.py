"""Adam's step on the CPU: torch's per-tensor loop, foreach and fused kernels, one run.

    python bench/adam_speed.py [--data ../shared/data/lego --downscale 8 --iters 600]

Times `optimizer.step()` (median of 25 after 5 warm-up steps, random gradients) on a fresh
field of the `object` preset's 1/8 sizes (8 levels, 2^18 table, finest 256) with the groups
and hyper-parameters of `shells.loop.make_optimizer`, once per kernel. With ``--data``, also
trains stage 1 of the preset ``--preset auto`` picks for the data for ``--iters`` steps twice,
one run after the other: with the per-tensor Adam, then with `make_optimizer`'s (fused), and
prints both runs' rays/s and their ratio. Prints JSON.
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
from shells.loop import make_optimizer  # noqa: E402

from preset_speed import preset_rays_per_s  # noqa: E402
from report import emit_json  # noqa: E402

KERNELS = {"per-tensor": {"fused": False, "foreach": False},
           "foreach": {"fused": False, "foreach": True},
           "fused": {"fused": True, "foreach": False}}


def with_kernel(opt: torch.optim.Adam, kernel: str) -> torch.optim.Adam:
    """A new Adam over the same groups and hyper-parameters, with another kernel."""
    groups = [{**g, **KERNELS[kernel]} for g in opt.param_groups]
    return torch.optim.Adam(groups)


def step_ms(kernel: str) -> float:
    cfg = toy_config()
    cfg.field = dataclasses.replace(cfg.field, n_levels=8, log2_hashmap_size=18,
                                    max_resolution=256)
    field = training.build_field(cfg, torch.tensor([[-1.5] * 3, [1.5] * 3]),
                                 torch.device("cpu"))
    opt = with_kernel(make_optimizer(field, 1e-2, 1e-2), kernel)
    for p in field.parameters():
        p.grad = torch.randn_like(p)
    times = []
    for _ in range(30):
        t = time.perf_counter()
        opt.step()
        times.append(time.perf_counter() - t)
    return 1e3 * statistics.median(times[5:])


def train_rays_per_s(data: str, downscale: int, iters: int, kernel: str) -> float:
    original = training.make_optimizer
    with mock.patch.object(training, "make_optimizer",
                           lambda *a: with_kernel(original(*a), kernel)):
        return preset_rays_per_s(data, downscale, iters, "bench/adam_speed.py")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", default=None)
    p.add_argument("--downscale", type=int, default=8)
    p.add_argument("--iters", type=int, default=600)
    a = p.parse_args()
    out = {"torch": torch.__version__, "threads": torch.get_num_threads(),
           "step_ms": {k: step_ms(k) for k in KERNELS}}
    if a.data:
        rays = {k: train_rays_per_s(a.data, a.downscale, a.iters, k)
                for k in ("per-tensor", "fused")}
        out["train"] = {"data": a.data, "downscale": a.downscale, "iters": a.iters,
                        "rays_per_s": rays, "fused_over_per_tensor":
                        rays["fused"] / rays["per-tensor"]}
    emit_json(out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
