"""The README picture: ground truth | full-ray render | band render | band samples per pixel.

    python bench/demo_figure.py --data DATA --full RENDER_DIR --band RENDER_DIR --out docs/demo.png

RENDER_DIRs are `shells-render` outputs (r_###.png, spp_###.png); DATA is the data set whose
test split was rendered (at `--downscale`). Images are upscaled by `--scale` (nearest) so 64x64
toys stay legible. `--view` may be given several times: one row per view.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from shells.datasets import load_dataset


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True)
    p.add_argument("--full", required=True, help="full-mode render directory")
    p.add_argument("--band", required=True, help="band-mode render directory")
    p.add_argument("--view", type=int, action="append", default=None)
    p.add_argument("--downscale", type=int, default=1)
    p.add_argument("--scale", type=int, default=3)
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    test = load_dataset(args.data, "test", downscale=args.downscale)
    rows = []
    for view in args.view or [0]:
        gt = (np.clip(test.images[view].numpy(), 0, 1) * 255 + 0.5).astype(np.uint8)
        name = f"{view:03d}.png"
        tiles = [gt, iio.imread(Path(args.full) / f"r_{name}")[..., :3],
                 iio.imread(Path(args.band) / f"r_{name}")[..., :3],
                 iio.imread(Path(args.band) / f"spp_{name}")[..., :3]]
        gap = np.full((gt.shape[0], 2, 3), 255, np.uint8)
        rows += [np.concatenate(sum(([t, gap] for t in tiles), [])[:-1], axis=1),
                 np.full((2, len(tiles) * (gt.shape[1] + 2) - 2, 3), 255, np.uint8)]
    row = np.concatenate(rows[:-1], axis=0)
    row = np.repeat(np.repeat(row, args.scale, 0), args.scale, 1)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(args.out, row)
    print(f"wrote {args.out} ({row.shape[1]}x{row.shape[0]})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
