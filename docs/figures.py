"""The README's pictures from `shells-render` and `shells-animate` outputs.

    python docs/figures.py demo --data DATA --full RENDER_DIR --band RENDER_DIR --out docs/demo.png
        [--view 0 [--view 3 ...]] [--downscale 1] [--scale 3]
    python docs/figures.py animation OUT.png DIR[:LABEL] [DIR[:LABEL] ...]
        [--frames 0 8 16 24] [--size 160]
    python docs/figures.py curve OUT.png RUN[:LABEL] [RUN[:LABEL] ...] [--title TEXT]
    python docs/figures.py baked OUT.png RUN [--size 480] [--gl llvmpipe]
    python docs/figures.py phases OUT.png PATHS.json[:LABEL] [PATHS.json[:LABEL] ...]

demo: ground truth | full-ray render | band render | band samples per pixel, one row per view.
animation: chosen frames of each animation in a row, with its ms/frame.
curve: stage 1's running test curve (RUN/train_curve.jsonl) against wall time, one line a run.
baked: screenshots of RUN's baked asset in the exported browser viewer (headless Chromium):
colour with the HUD, and layers per pixel.
phases: a stage-1 step split into its phases, torch path against compiled, from the JSON of
`python -m bench.step_speed paths`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np


def demo(args: argparse.Namespace) -> int:
    """Ground truth | full-ray render | band render | band samples per pixel, one row per
    ``--view``. RENDER_DIRs are `shells-render` outputs (r_###.png, spp_###.png); DATA is the
    data set whose test split was rendered (at ``--downscale``). Images are upscaled by
    ``--scale`` (nearest) so 64x64 toys stay legible."""
    from shells.data.datasets import load_dataset

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


def animation(args: argparse.Namespace) -> int:
    """Chosen frames of each animation in a row. Each DIR is a `shells-animate` output folder
    (r_###.png, metrics.json); frame indices past an animation's end are clipped to its last
    frame. Every frame is scaled to ``--size`` pixels high."""
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


def curve(args: argparse.Namespace) -> int:
    """Stage 1's running test curves: PSNR of each RUN's fixed held-out pixels
    (RUN/train_curve.jsonl, shells-train with train.curve_every > 0) against the wall time of
    its stage 1 in hours, summed over its sittings."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    for spec in args.runs:
        run, _, label = spec.partition(":")
        lines = (Path(run) / "train_curve.jsonl").read_text().splitlines()
        points = [json.loads(ln) for ln in lines if ln.strip()]
        if not points:
            raise SystemExit(f"{run}/train_curve.jsonl: no points yet")
        ax.plot([p["wall_s"] / 3600 for p in points], [p["psnr"] for p in points], marker=".",
                label=f"{label or Path(run).name} (step {points[-1]['step']}: "
                      f"{points[-1]['psnr']:.2f} dB)")
    ax.set_xlabel("stage-1 wall time (h)")
    ax.set_ylabel("test PSNR (dB), held-out pixels")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    if args.title:
        ax.set_title(args.title, fontsize=9)
    fig.tight_layout()
    fig.savefig(args.out, dpi=120)
    print(f"wrote {args.out}")
    return 0


def phases(args: argparse.Namespace) -> int:
    """A stage-1 step's phases (ms, the mean of the two seeds' profiled steps) of the torch and
    the compiled hash-grid path, one pair of stacked bars for each ``bench.step_speed paths``
    JSON."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bars, labels = [], []
    for spec in args.files:
        path, _, label = spec.partition(":")
        v = json.loads(Path(path).read_text())["variants"]
        for name in ("torch", "compiled"):
            a, b = v[name]["phases_ms"], v[f"{name}, seed + 1"]["phases_ms"]
            bars.append({k: (a[k] + b[k]) / 2 for k in a if k != "step (profiled)"})
            labels.append(f"{label or Path(path).stem}, {name}")
    keys = list(bars[0])
    fig, ax = plt.subplots(figsize=(7.2, 0.55 * len(bars) + 1.6))
    cmap = plt.get_cmap("tab10")
    for i, bar in enumerate(bars):
        left = 0.0
        for j, k in enumerate(keys):
            ax.barh(i, bar[k], left=left, color=cmap(j % 10),
                    label=k.split(": ")[-1] if i == 0 else None)
            left += bar[k]
        ax.text(left + 2, i, f"{left:.0f} ms", va="center", fontsize=8)
    ax.set_yticks(range(len(bars)), labels, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("ms per stage-1 step (profiled)")
    ax.legend(fontsize=7, ncol=3, loc="upper center", bbox_to_anchor=(0.5, -0.22))
    fig.savefig(args.out, dpi=120, bbox_inches="tight")
    print(f"wrote {args.out}")
    return 0


def baked(args: argparse.Namespace) -> int:
    """Screenshots of RUN/baked in the exported three.js viewer, in headless Chromium with a
    software GL: the colour view with its HUD (the fps of one warm frame, layers, triangles,
    size) beside the layers per pixel view, from the viewer's start camera (test view 0's
    position)."""
    import base64
    import tempfile
    import threading

    from shells.bake.run import export_web, static_server
    from shells.browser import Browser

    with tempfile.TemporaryDirectory() as tmp:
        export_web(args.run, Path(tmp) / "web")
        srv = static_server(Path(tmp) / "web", "127.0.0.1", 0)
        threading.Thread(target=srv.serve_forever, daemon=True).start()
        url = (f"http://127.0.0.1:{srv.server_address[1]}/?paused=1&width={args.size}"
               f"&height={args.size}")
        shots = []
        try:
            with Browser(gl=args.gl, size=(args.size, args.size)) as b:
                b.call("Emulation.setDeviceMetricsOverride", width=args.size, height=args.size,
                       deviceScaleFactor=1, mobile=False)
                for show in ("colour", "layers"):
                    b.open(f"{url}&show={show}", ready="window.shells && window.shells.ready",
                           timeout=300)
                    b.evaluate("window.shells.frame(), window.shells.frame()", timeout=120)
                    shot = b.call("Page.captureScreenshot", timeout=120)
                    shots.append(iio.imread(base64.b64decode(shot["data"]))[..., :3])
        finally:
            srv.shutdown()
    h = min(x.shape[0] for x in shots)
    gap = np.full((h, 4, 3), 255, np.uint8)
    iio.imwrite(args.out, np.concatenate([shots[0][:h], gap, shots[1][:h]], 1))
    print(f"wrote {args.out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python docs/figures.py",
                                description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    for fn in (demo, animation, curve, baked, phases):
        doc = " ".join(fn.__doc__.split())
        sub.add_parser(fn.__name__, help=doc.split(". ")[0], description=doc).set_defaults(fn=fn)
    sp = sub.choices["demo"]
    sp.add_argument("--data", required=True)
    sp.add_argument("--full", required=True, help="full-mode render directory")
    sp.add_argument("--band", required=True, help="band-mode render directory")
    sp.add_argument("--view", type=int, action="append", default=None,
                    help="a test view (repeatable: one row each; default 0)")
    sp.add_argument("--downscale", type=int, default=1)
    sp.add_argument("--scale", type=int, default=3)
    sp.add_argument("--out", required=True)
    sp = sub.choices["animation"]
    sp.add_argument("out")
    sp.add_argument("dirs", nargs="+", metavar="DIR[:LABEL]")
    sp.add_argument("--frames", type=int, nargs="+", default=[0, 8, 16, 24])
    sp.add_argument("--size", type=int, default=160)
    sp = sub.choices["curve"]
    sp.add_argument("out")
    sp.add_argument("runs", nargs="+", metavar="RUN[:LABEL]")
    sp.add_argument("--title", default=None)
    sp = sub.choices["baked"]
    sp.add_argument("out")
    sp.add_argument("run")
    sp.add_argument("--size", type=int, default=480, help="canvas size in pixels")
    sp.add_argument("--gl", default="llvmpipe", choices=["llvmpipe", "swiftshader"])
    sp = sub.choices["phases"]
    sp.add_argument("out")
    sp.add_argument("files", nargs="+", metavar="PATHS.json[:LABEL]")
    args = p.parse_args(argv)
    return args.fn(args)


if __name__ == "__main__":
    sys.exit(main())
