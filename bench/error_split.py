"""Where the error of a render is: silhouette pixels, object interior or background.

    python bench/error_split.py RUN RUN/render-band [RUN/render-full ...]

For every test view of RUN's data set (Blender format, RGBA PNGs), pixels are split by the
reference alpha: "object" (alpha > 0.5), "edge" (object pixels on its one-pixel boundary and
background pixels touching it) and "background" (the rest, which on the toy scenes includes
thin translucent fuzz). Prints, per render directory, the summed squared error, pixel count and
MSE of each class over all views (RGB composited on the run's white background).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
from scipy import ndimage

from shells.run import RunDir, read_run


def split_errors(data: Path, render: Path) -> dict[str, dict[str, float]]:
    frames = json.loads((data / "transforms_test.json").read_text())["frames"]
    acc = {"edge": [], "object": [], "background": []}
    for i, fr in enumerate(frames):
        ref = iio.imread(data / (fr["file_path"] + ".png")).astype(np.float32) / 255.0
        alpha = ref[..., 3:]
        rgb = ref[..., :3] * alpha + (1.0 - alpha)  # white background, as the renderer
        img = iio.imread(render / f"r_{i:03d}.png").astype(np.float32)[..., :3] / 255.0
        err = ((img - rgb) ** 2).mean(-1)  # [H, W]
        inside = alpha[..., 0] > 0.5
        edge = ((inside & ~ndimage.binary_erosion(inside))
                | (~inside & ndimage.binary_dilation(inside)))
        acc["edge"].append(err[edge])
        acc["object"].append(err[inside & ~edge])
        acc["background"].append(err[~inside & ~edge])
    out = {}
    for k, v in acc.items():
        e = np.concatenate(v)
        out[k] = {"sse": float(e.sum()), "pixels": int(e.size),
                  "mse": float(e.mean()) if e.size else 0.0}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="run directory (its run.json names the data set)")
    p.add_argument("renders", nargs="+", help="render directories (r_###.png of the test split)")
    args = p.parse_args(argv)
    data = Path(read_run(RunDir(args.run))["data"])
    print(f"{'render':<48} {'class':<11} {'SSE':>8} {'pixels':>7} {'MSE':>8}")
    for r in args.renders:
        for k, v in split_errors(data, Path(r)).items():
            print(f"{r:<48} {k:<11} {v['sse']:8.2f} {v['pixels']:7d} {v['mse']:8.5f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
