"""The old run of `bench/stage1_curve.py --old-commit REV`, trained by the code of REV.

    PYTHONPATH=TREE python bench/stage1_curve_old.py --data D --downscale 8 --out RUN \
        --iters 3000 --segments 6

TREE is the source tree of REV (`git archive`; `stage1_curve.py` makes it). This script uses
only what `shells` offered before issue 13 (`train(..., stop_at=, resume=)`, `evaluate`,
`read_checkpoint`, `field_from_checkpoint`), checks that `shells` was imported from TREE and
not from the installed checkout, and trains what `shells-train --data D --downscale N` trained
on the CPU there: the toy preset (every ray sampled over its whole chord through the box,
32 + 16 samples, 1024 rays per step). Like `stage1_curve.curve`, the run is cut into
``--segments`` pieces (resume retraces the uninterrupted run) and each checkpoint is scored
on the test views off the clock. Prints one JSON object: the run in `curve.json`'s form.
``--segment K`` (0-based) trains and scores piece K alone (piece 0 replaces RUN, the others
resume it) and prints that piece: what `stage1_curve.py --interleave` alternates with the new
run's pieces.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from pathlib import Path

import torch


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True)
    p.add_argument("--downscale", type=int, default=8)
    p.add_argument("--out", required=True,
                   help="the run directory (replaced; resumed by --segment K > 0)")
    p.add_argument("--iters", type=int, default=None, help="default: the toy preset's")
    p.add_argument("--segments", type=int, default=6)
    p.add_argument("--segment", type=int, default=None, help="train piece K only (0-based)")
    a = p.parse_args()
    import shells

    tree = Path(os.environ.get("PYTHONPATH", "").split(os.pathsep)[0] or ".").resolve()
    if tree not in Path(shells.__file__).resolve().parents:
        raise SystemExit(f"shells was imported from {shells.__file__}, not from the old tree "
                         f"{tree}; set PYTHONPATH=TREE")
    from shells.config import toy_config
    from shells.datasets import load_dataset
    from shells.run import RunDir, field_from_checkpoint, read_checkpoint
    from shells.training import evaluate, train

    device = torch.device("cpu")
    cfg = toy_config()
    if a.iters is not None:
        cfg.update({"train": {"iters": a.iters}}, "bench")
    iters = cfg.train.iters
    test = load_dataset(a.data, "test", downscale=a.downscale)
    run = Path(a.out)
    cuts = sorted({max(1, round(iters * (k + 1) / a.segments)) for k in range(a.segments)})
    pieces = list(enumerate(cuts)) if a.segment is None else [(a.segment, cuts[a.segment])]
    if pieces[0][0] == 0:
        shutil.rmtree(run, ignore_errors=True)
    points, seconds, rays = [], 0.0, 0.0
    for i, k in pieces:
        s = train(a.data, run, cfg, device, downscale=a.downscale, resume=i > 0,
                  progress=False, stop_at=k, evaluate_test=False)
        seconds += s["seconds"]
        rays += s["rays_per_s"] * s["seconds"]
        t = time.perf_counter()
        field, rcfg = field_from_checkpoint(read_checkpoint(RunDir(run)), str(run), device)
        with torch.no_grad():
            psnr = evaluate(field, test, rcfg.train, 0, device)["psnr"]
        points.append({"step": k, "seconds": seconds, "psnr": psnr})
        print(f"old code: step {k}, {s['seconds']:.0f} s trained, test PSNR {psnr:.2f} dB "
              f"(scored in {time.perf_counter() - t:.0f} s)", flush=True)
    per_ray = cfg.train.n_samples + cfg.train.n_importance  # every ray gets all of them
    out = {"iters": iters, "points": points, "seconds": seconds, "rays_per_s": rays / seconds,
           "samples_per_s": rays / seconds * per_ray, "psnr": points[-1]["psnr"],
           "config": cfg.to_dict(), "code": str(tree)}
    print("RESULT " + json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
