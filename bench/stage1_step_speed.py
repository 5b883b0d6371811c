"""Stage-1 step time of one trained field under several sampler settings (no optimiser step).

    OMP_NUM_THREADS=1 python bench/stage1_step_speed.py --run RUN --data DATA --downscale 8

RUN is a stage-1 run of the "occupancy" sampler (its checkpoint holds the occupancy grid).
Each setting runs 12 steps (forward + backward of `shells.training.stage1_step`) and times the
last 10; prints ms/step, rays/s and rays per step.
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

SETTINGS = [("box, 32 + 16, 4096 regulariser points", "box", 32, 16, 4096),
            ("occupancy, 32 + 16, 2048", "occupancy", 32, 16, 2048),
            ("occupancy, 16 + 16, 2048", "occupancy", 16, 16, 2048),
            ("occupancy, 24 + 8, 2048", "occupancy", 24, 8, 2048),
            ("occupancy, 16 + 16, 1024", "occupancy", 16, 16, 1024)]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--run", required=True)
    p.add_argument("--data", required=True)
    p.add_argument("--downscale", type=int, default=8)
    args = p.parse_args()
    ckpt = read_checkpoint(RunDir(args.run))
    field, cfg = field_from_checkpoint(ckpt, args.run)
    field.train()
    grid = stage1_grid(ckpt, field, cfg)
    if grid is None:
        p.error(f"{args.run}: not a run of the 'occupancy' sampler")
    data = load_dataset(args.data, "train", downscale=args.downscale)
    pixels, bg = data.images.reshape(-1, 3), torch.ones(3)
    print("| configuration | ms/step | rays/s | rays/step |\n|---|---|---|---|")
    for name, sampler, ns, ni, reg in SETTINGS:
        tc = dataclasses.replace(cfg.train, sampler=sampler, n_samples=ns, n_importance=ni,
                                 reg_points=reg)
        times, rays = [], 0.0
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
        dt = sum(times)
        print(f"| {name} | {dt / len(times) * 1000:.0f} | {rays / dt:.0f} | "
              f"{rays / len(times):.0f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
