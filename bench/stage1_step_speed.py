"""Stage-1 step time of one trained field under several sampler settings (no optimiser step).

    OMP_NUM_THREADS=1 python bench/stage1_step_speed.py --run RUN --data DATA --downscale 8

RUN is a stage-1 run of the "occupancy" sampler (its checkpoint holds the occupancy grid).
Each setting runs 12 steps (forward + backward of `shells.training.stage1_step`) and times the
last 10; prints ms/step, rays/s and rays per step.

    python bench/stage1_step_speed.py --run RUN --data DATA --downscale 4 --sizes [--profile]

``--sizes``: instead, the run's sampler settings on fresh fields of other hash-grid sizes
(the same rays and grid; 10 steps, medians of the last 8), forward + backward and the Adam
step timed apart; ``--profile`` adds a torch.profiler table of 3 steps of the trained field.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from shells.datasets import load_dataset  # noqa: E402
from shells.run import RunDir, field_from_checkpoint, read_checkpoint  # noqa: E402
from shells.training import stage1_grid, stage1_step  # noqa: E402

SIZES = [("fresh, the run's sizes", {}),
         ("fresh, 8 levels, 2^18, finest 256 (lego 1/8)",
          dict(n_levels=8, log2_hashmap_size=18, max_resolution=256)),
         ("fresh, 16 levels, 2^19, finest 512",
          dict(n_levels=16, log2_hashmap_size=19, max_resolution=512)),
         ("fresh, 9 levels, 2^17, finest 512",
          dict(n_levels=9, log2_hashmap_size=17, max_resolution=512))]

SETTINGS = [("box, 32 + 16, 4096 regulariser points", "box", 32, 16, 4096, 0.0),
            ("occupancy, 32 + 16, 2048", "occupancy", 32, 16, 2048, 0.0),
            ("occupancy, 32 + 16, 2048, culled below 1e-4", "occupancy", 32, 16, 2048, 1e-4),
            ("occupancy, 32 + 16, 2048, culled below 1e-3", "occupancy", 32, 16, 2048, 1e-3),
            ("occupancy, 16 + 16, 2048", "occupancy", 16, 16, 2048, 0.0),
            ("occupancy, 16 + 16, 2048, culled below 1e-4", "occupancy", 16, 16, 2048, 1e-4),
            ("occupancy, 24 + 8, 2048", "occupancy", 24, 8, 2048, 0.0),
            ("occupancy, 16 + 16, 1024", "occupancy", 16, 16, 1024, 0.0)]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--run", required=True)
    p.add_argument("--data", required=True)
    p.add_argument("--downscale", type=int, default=8)
    p.add_argument("--sizes", action="store_true", help="fresh fields of other grid sizes")
    p.add_argument("--profile", action="store_true", help="with --sizes: a profiler table")
    args = p.parse_args()
    ckpt = read_checkpoint(RunDir(args.run))
    field, cfg = field_from_checkpoint(ckpt, args.run)
    field.train()
    grid = stage1_grid(ckpt, field, cfg)
    if grid is None:
        p.error(f"{args.run}: not a run of the 'occupancy' sampler")
    data = load_dataset(args.data, "train", downscale=args.downscale)
    pixels, bg = data.images.reshape(-1, 3), torch.ones(3)
    if args.sizes:
        return sizes(field, cfg, data, pixels, bg, grid, args.profile)
    print("| configuration | ms/step | rays/s | rays/step | samples with gradient |\n"
          "|---|---|---|---|---|")
    for name, sampler, ns, ni, reg, cull in SETTINGS:
        tc = dataclasses.replace(cfg.train, sampler=sampler, n_samples=ns, n_importance=ni,
                                 reg_points=reg, cull_weight=cull)
        times, rays, grads, samples = [], 0.0, 0.0, 0.0
        for k in range(12):
            t = time.perf_counter()
            loss, logs = stage1_step(field, data, pixels, tc, bg,
                                     torch.Generator().manual_seed(k),
                                     grid if sampler == "occupancy" else None)
            loss.backward()
            field.zero_grad()
            if k >= 2:
                times.append(time.perf_counter() - t)
                rays += logs["rays"]
                grads += logs["grad_samples"]
                samples += logs["samples"]
        dt = sum(times)
        print(f"| {name} | {dt / len(times) * 1000:.0f} | {rays / dt:.0f} | "
              f"{rays / len(times):.0f} | {grads / max(samples, 1):.1%} |", flush=True)
    return 0


def sizes(trained, cfg, data, pixels, bg, grid, profile: bool) -> int:
    from shells.loop import make_optimizer
    from shells.training import build_field

    print("| field | parameters | forward + backward ms | Adam ms |\n|---|---|---|---|")
    for name, change in [("the trained field", None)] + SIZES:
        if change is None:
            field = trained
        else:
            c = dataclasses.replace(cfg, field=dataclasses.replace(cfg.field, **change))
            field = build_field(c, data.aabb, torch.device("cpu"))
        field.train()
        opt = make_optimizer(field, cfg.train.lr, cfg.train.lr_mlp)
        fb, ad = [], []
        for k in range(10):
            t0 = time.perf_counter()
            loss, _ = stage1_step(field, data, pixels, cfg.train, bg,
                                  torch.Generator().manual_seed(k), grid)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            t1 = time.perf_counter()
            opt.step()
            if k >= 2:
                fb.append(t1 - t0)
                ad.append(time.perf_counter() - t1)
        n = sum(q.numel() for q in field.parameters())
        print(f"| {name} | {n / 1e6:.2f} M | {1000 * sorted(fb)[len(fb) // 2]:.0f} | "
              f"{1000 * sorted(ad)[len(ad) // 2]:.0f} |", flush=True)
    if profile:
        from torch.profiler import ProfilerActivity
        from torch.profiler import profile as torch_profile

        with torch_profile(activities=[ProfilerActivity.CPU]) as prof:
            for k in range(3):
                loss, _ = stage1_step(trained, data, pixels, cfg.train, bg,
                                      torch.Generator().manual_seed(k), grid)
                loss.backward()
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
