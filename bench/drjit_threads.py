"""Dr.Jit's thread pool next to torch's OpenMP threads on the CPU: one run, ratios only.

    python bench/drjit_threads.py --run RUN [--steps 40 --rounds 3]

RUN is a stage-1 run of the "occupancy" sampler (e.g. the `object` preset on lego 1/8).

1. The geometry MLP of RUN's field on 65 536 points (no gradient), timed right after nothing,
   after the torch hash-grid lookup, after Dr.Jit's lookup with its pool of 2 threads, after
   Dr.Jit's lookup on the calling thread alone (`drjit_on_calling_thread`), and after Dr.Jit's
   lookup then a 50 ms sleep. Medians of 15 (the first 3 dropped).
2. Whole stage-1 steps of the run's own config (`stage1_step`, backward, Adam; 3 warm-up steps,
   then the median of ``--steps``), each in a fresh child process, alternating the pool of 2
   threads and the calling thread alone for ``--rounds`` rounds.

Prints a Markdown table of each part.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import drjit as dr
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from shells.fields.hashgrid import HashGrid, drjit_on_calling_thread  # noqa: E402
from shells.run import RunDir, field_from_checkpoint, read_checkpoint, read_run  # noqa: E402


def mlp_after(run: str) -> None:
    field, _ = field_from_checkpoint(read_checkpoint(RunDir(run), "stage1"), run)
    gen = torch.Generator().manual_seed(0)
    x01 = torch.rand(65536, 3, generator=gen) * 0.5 + 0.25
    h = torch.randn(65536, field.geo_in, generator=gen)
    dr.set_thread_count(2)

    def drjit_pool() -> None:
        field.grid(x01)

    def drjit_alone() -> None:
        with drjit_on_calling_thread():
            field.grid(x01)

    def torch_lookup() -> None:
        HashGrid.inference = "torch"
        field.grid(x01)
        HashGrid.inference = "auto"

    def then_sleep() -> None:
        field.grid(x01)
        time.sleep(0.05)

    cases = [("nothing", lambda: None), ("the torch lookup", torch_lookup),
             ("Dr.Jit's lookup, pool of 2 threads", drjit_pool),
             ("Dr.Jit's lookup, the calling thread alone", drjit_alone),
             ("Dr.Jit's lookup (pool of 2), then 50 ms asleep", then_sleep)]
    times: dict[str, list[float]] = {name: [] for name, _ in cases}
    with torch.no_grad():
        for _ in range(15):
            for name, before in cases:  # interleaved: the machine's drift falls on all alike
                before()
                t = time.perf_counter()
                field.geo_mlp(h)
                times[name].append(time.perf_counter() - t)
    print("| geometry MLP (65 536 points) right after | ms, median |\n|---|---|")
    for name, ts in times.items():
        print(f"| {name} | {1000 * statistics.median(ts[3:]):.1f} |")


def child(run: str, steps: int, alone: bool) -> None:
    """Stage-1 steps of RUN's config; prints {"ms": median ms/step}."""
    from shells.datasets import load_dataset
    from shells.loop import make_optimizer
    from shells.training import stage1_grid, stage1_step

    rd = RunDir(run)
    meta, ckpt = read_run(rd), read_checkpoint(rd, "stage1")
    field, cfg = field_from_checkpoint(ckpt, run)
    field.train()
    tc = cfg.train
    grid = stage1_grid(ckpt, field, cfg)
    data = load_dataset(meta["data"], "train", downscale=int(meta["downscale"]),
                        background=cfg.data.background)
    pixels, bg = data.images.reshape(-1, 3), torch.tensor(cfg.data.background)
    alpha = data.alpha.reshape(-1) if tc.random_background and data.alpha is not None else None
    opt = make_optimizer(field, tc.lr, tc.lr_mlp)
    dr.set_thread_count(2)
    ts = []
    with drjit_on_calling_thread() if alone else contextlib.nullcontext():
        for k in range(steps + 3):
            t = time.perf_counter()
            loss, _ = stage1_step(field, data, pixels, tc, bg, torch.Generator().manual_seed(k),
                                  grid, tc.iters // 2, alpha)
            opt.zero_grad()
            loss.backward()
            opt.step()
            ts.append(time.perf_counter() - t)
    print(json.dumps({"ms": 1000 * statistics.median(ts[3:])}))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--run", required=True)
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--child", choices=["pool", "alone"], help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        child(args.run, args.steps, args.child == "alone")
        return 0
    mlp_after(args.run)
    rows = []
    for _ in range(args.rounds):
        row = {}
        for mode in ("pool", "alone"):
            out = subprocess.run([sys.executable, __file__, "--run", args.run, "--steps",
                                  str(args.steps), "--child", mode], check=True,
                                 capture_output=True, text=True).stdout
            row[mode] = json.loads(out.strip().splitlines()[-1])["ms"]
        rows.append(row)
    print("\n| round | stage-1 step, pool of 2 threads: ms | on the calling thread alone: ms "
          "| ratio |\n|---|---|---|---|")
    for i, r in enumerate(rows, 1):
        print(f"| {i} | {r['pool']:.1f} | {r['alone']:.1f} | {r['pool'] / r['alone']:.2f}× |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
