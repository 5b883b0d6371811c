"""A still of shells-animate outputs for the README: chosen frames of each animation in a row.

    python bench/animation_figure.py OUT.png DIR[:LABEL] [DIR[:LABEL] ...]
        [--frames 0 8 16 24] [--size 160]

Each DIR is a shells-animate output folder (r_###.png, metrics.json); frame indices past an
animation's end are clipped to its last frame. Every frame is scaled to --size pixels high.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import imageio.v3 as iio


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out")
    ap.add_argument("dirs", nargs="+")
    ap.add_argument("--frames", type=int, nargs="+", default=[0, 8, 16, 24])
    ap.add_argument("--size", type=int, default=160)
    args = ap.parse_args(argv)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = []
    for spec in args.dirs:
        folder, _, label = spec.partition(":")
        folder = Path(folder)
        m = json.loads((folder / "metrics.json").read_text())
        ks = [min(k, m["frames"] - 1) for k in args.frames]
        rows.append((label or folder.name, m, [iio.imread(folder / f"r_{k:03d}.png")[..., :3]
                                               for k in ks], ks))
    n = len(args.frames)
    fig, axes = plt.subplots(len(rows), n, figsize=(1.9 * n, 2.05 * len(rows)), squeeze=False)
    for r, (label, m, imgs, ks) in enumerate(rows):
        for c, (img, k) in enumerate(zip(imgs, ks)):
            ax = axes[r][c]
            ax.imshow(img, interpolation="lanczos")
            ax.set_xticks([]), ax.set_yticks([])
            ax.set_title(f"frame {k}", fontsize=8)
            if c == 0:
                ax.set_ylabel(f"{label}\n{m['ms_per_frame']:.0f} ms/frame", fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out, dpi=args.size / 1.6)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
