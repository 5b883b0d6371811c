"""Where the error of an unbounded run's renders is: pixels whose ray enters the ball of
interest (the object) against those whose ray misses it (the contracted background).

    python bench/ball_split.py RUN --data DATA --downscale 8 RUN/render-full RUN/render-band

RENDER_DIRs are `shells-render` outputs of RUN's test split (r_###.png). For each class it
prints the share of pixels, each render's pooled MSE and PSNR over the class, and each
render's squared error summed over the class (the class's part of the pooled error; the
per-frame PSNR averages of metrics.json differ from these pooled figures).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from shells.datasets import load_dataset  # noqa: E402


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run")
    p.add_argument("renders", nargs="+", metavar="RENDER_DIR")
    p.add_argument("--data", required=True)
    p.add_argument("--downscale", type=int, default=8)
    args = p.parse_args()
    config = Path(args.run) / "config.json"
    if not config.is_file():
        p.error(f"{config}: missing; RUN must be a shells-train run directory")
    field = json.loads(config.read_text())["field"]
    if not field.get("unbounded"):
        p.error(f"{args.run}: not an unbounded run (config.json field.unbounded is false)")
    centre, radius = torch.tensor(field["centre"], dtype=torch.float32), float(field["radius"])
    test = load_dataset(args.data, "test", downscale=args.downscale)
    H, W = test.images.shape[1:3]
    sse = {(r, c): 0.0 for r in args.renders for c in ("ball", "outside")}
    count = {"ball": 0, "outside": 0}
    for i in range(test.images.shape[0]):
        o, d = test.cameras.pixel_rays(i, 1)
        ou = (o - centre) / radius
        b = (ou * d).sum(-1)
        ball = (b * b - ((ou * ou).sum(-1) - 1.0) > 0).reshape(H, W).numpy()
        count["ball"] += int(ball.sum())
        count["outside"] += int((~ball).sum())
        gt = test.images[i].numpy()
        for r in args.renders:
            path = Path(r) / f"r_{i:03d}.png"
            if not path.is_file():
                p.error(f"{path}: missing; render RUN's test split into {r} first")
            img = iio.imread(path).astype(np.float32)[..., :3] / 255.0
            err = ((img - gt) ** 2).mean(-1)
            sse[(r, "ball")] += float(err[ball].sum())
            sse[(r, "outside")] += float(err[~ball].sum())
    total = sum(count.values())
    print("| pixels | share | " + " | ".join(f"{Path(r).name}: PSNR (summed sq. error)"
                                         for r in args.renders) + " |")
    print("|---|---|" + "---|" * len(args.renders))
    for c in ("ball", "outside"):
        cells = [f"{-10 * math.log10(sse[(r, c)] / count[c]):.2f} dB ({sse[(r, c)]:.0f})"
                 for r in args.renders]
        print(f"| ray {'enters' if c == 'ball' else 'misses'} the ball | "
              f"{count[c] / total:.1%} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
