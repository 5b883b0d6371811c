"""Stage-1 throughput: N data-parallel processes x T threads each against 1 process x N*T threads.

    python -m bench.ddp_throughput DATA [--iters 100] [--procs 2] [--out DIR] [--json FILE]

Trains the toy preset on DATA twice with the same global batch and the same ray shards (so the
same computation): once as one process with ``OMP_NUM_THREADS = procs`` and once under
``torchrun --nproc-per-node procs`` with one thread per process; reports rays/s of each from
the runs' summaries (steady state: the rate over all steps, as shells-train reports it), the
wall time of each command and the largest relative difference of the final parameters. On a
machine with as many cores as processes this measures the cost of data parallelism (gradient
all-reduce, per-process overhead), not a speed-up. Run it alone on the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import torch

from bench.report import emit_json
from shells.presets import toy_config


def run(argv: list[str], threads: int) -> float:
    env = dict(os.environ, OMP_NUM_THREADS=str(threads))
    for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK"):
        env.pop(k, None)
    t0 = time.perf_counter()
    subprocess.run(argv, env=env, check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("data")
    p.add_argument("--iters", type=int, default=100)
    p.add_argument("--procs", type=int, default=2)
    p.add_argument("--out", default="/tmp/ddp_throughput")
    p.add_argument("--json", default=None, help="also write the result here")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = toy_config().to_dict()
    cfg["train"].update(iters=args.iters, shards=args.procs)
    cfg_file = out / "config.json"
    cfg_file.write_text(json.dumps({"train": cfg["train"]}))
    plain = out / "config-1-shard.json"  # the default: the whole batch in one shard
    plain.write_text(json.dumps({"train": {**cfg["train"], "shards": 1}}))
    train = str(Path(sys.executable).parent / "shells-train")
    common = ["--data", args.data, "--preset", "toy", "--device", "cpu"]
    rows = {}
    for name, argv_, threads in (
            ("1 process, 1 shard", [train, "--config", str(plain), "--out", str(out / "plain")],
             args.procs),
            ("1 process", [train, "--config", str(cfg_file), "--out", str(out / "one")],
             args.procs),
            (f"{args.procs} processes", [sys.executable, "-m", "torch.distributed.run",
                                         "--standalone", f"--nproc-per-node={args.procs}",
                                         train, "--config", str(cfg_file),
                                         "--out", str(out / "ddp")], 1)):
        run_dir = Path(argv_[-1])
        if run_dir.exists():
            raise SystemExit(f"{run_dir} exists; pass another --out")
        wall = run(argv_ + common, threads)
        summary = json.loads((run_dir / "train_summary.json").read_text())
        rows[name] = {"threads_per_process": threads, "rays_per_s": summary["rays_per_s"],
                      "train_seconds": summary["seconds"], "command_seconds": wall,
                      "test_psnr": summary.get("test", {}).get("psnr")}
    a = torch.load(out / "one" / "checkpoint.pt", weights_only=False)["field"]
    b = torch.load(out / "ddp" / "checkpoint.pt", weights_only=False)["field"]
    diff = max(float((a[k].double() - b[k].double()).norm() / a[k].double().norm().clamp_min(1e-30))
               for k in a if a[k].numel())
    one, ddp = rows["1 process"], rows[f"{args.procs} processes"]
    emit_json({"data": args.data, "iters": args.iters, "batch_rays": cfg["train"]["batch_rays"],
               "shards": args.procs, "rows": rows,
               "ratio_ddp_over_one": ddp["rays_per_s"] / one["rays_per_s"],
               "max_relative_parameter_difference": diff}, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
