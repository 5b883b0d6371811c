"""Ray-cast time of the fine shells against their LOD (shells-lod): the depth-peeled interval
cast (`ShellScene.intervals`, the band renderer's and stage 2's) of every pixel of the test
views at the data's resolution, median of 5 warm repeats, and the parity check's rays.

    python bench/lod_cast.py RUN [--width W]
"""

from __future__ import annotations

import argparse
import json
import time

import drjit as dr
import numpy as np

from shells.datasets import load_dataset
from shells.run import RunDir, load_field, load_shells, read_run


def cast_ms(scene, o, d, dp_max: int, repeats: int = 5) -> float:
    times = []
    for _ in range(repeats + 1):
        t0 = time.perf_counter()
        iv = scene.intervals(o, d, dp_max)
        dr.eval(iv.enter, iv.exit, iv.count, iv.t_inner)
        dr.sync_thread()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times[1:]))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("run")
    ap.add_argument("--width", type=int, default=None)
    args = ap.parse_args()
    run = RunDir(args.run)
    _, cfg = load_field(run.root)
    meta = read_run(run)
    data = load_dataset(meta["data"], "test", downscale=int(meta["downscale"]))
    cams = data.cameras.resized(args.width, args.width)
    o, d = [], []
    for i in range(len(cams)):
        oi, di = cams.pixel_rays(i)[:2]
        o.append(oi.reshape(-1, 3))
        d.append(di.reshape(-1, 3))
    import torch
    o, d = torch.cat(o), torch.cat(d)
    out = {"rays": int(len(o)), "width": cams.width, "height": cams.height}
    for which in ("fine", "lod"):
        scene = load_shells(run, None, which)
        out[f"{which}_ms"] = cast_ms(scene, o, d, cfg.render.dp_max)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
