"""Rendering speed of one trained run: narrow band vs full ray vs occupancy grid vs the floor.

    python bench/render_speed.py RUN [--width 1920 --height 1080] [--views N]
                                     [--append BENCHMARKS.md] [--out DIR]

RUN is a run directory as `shells-train` + `shells-extract` leave it (checkpoint.pt, run.json,
shells/outer.ply, shells/inner.ply). The first N views of the split (default: all) are rendered
with the same Dr.Jit field in four ways:

    band       adaptive shells: M+/M- depth peeling + Procedure 3 samples (the method)
    full       cfg.full_samples samples per ray over the whole scene box (volumetric baseline)
    occupancy  occupancy grid + fixed-step marching, empty-space skipping, early termination
               (Instant-NGP / nerfacc baseline, shells/render/occupancy.py); the grid is built
               once before timing, its build time is reported separately
    floor      primary rays against M+ alone, no field evaluation: the time floor of `band`

and reported as one Markdown table: samples/pixel (mean over all pixels), median warm ms/frame
(`shells.render.views.render_views`: the first frame compiles kernels and is not counted; with one
view a second render of it is timed), and PSNR/SSIM (`shells.metrics`) when rendering at the
data set's own resolution (only speed otherwise). The table is printed, written with the raw
numbers to OUT/render_speed.{md,json} (OUT default RUN/bench-speed-WxH), and with ``--append``
appended to FILE together with the command, the device (Mitsuba variant) and the date. A plot of
PSNR against ms/frame goes to OUT/render_speed.png (matplotlib when installed, else Pillow; it
is skipped, with a message, when there are no PSNRs or neither library is available).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import platform
import shlex
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import drjit as dr

from shells.errors import InputError
from shells.pipeline import check_run
from shells.render.views import render_views
from shells.run import RunDir, load_field, load_shells

LABELS = {
    "band": "band (adaptive shells)",
    "full": "full ray",
    "occupancy": "occupancy grid",
    "floor": "M+ ray cast only (floor)",
}
COLOURS = {"band": (214, 39, 40), "full": (31, 119, 180), "occupancy": (44, 160, 44),
           "floor": (127, 127, 127)}


def time_floor(scene: Any, cameras: Any) -> dict[str, Any]:
    """Median warm ms/frame of the M+ primary ray cast over the views, and pixel coverage."""
    from shells.render.occupancy import floor_image

    H, W = cameras.height, cameras.width
    views = list(range(len(cameras)))
    if len(views) == 1:
        views = views * 2  # one view: a second, warm cast of it is timed
    times, covered = [], []
    for i in views:
        o, d = cameras.pixel_rays(i)
        dr.sync_thread()
        t0 = time.perf_counter()
        hit = floor_image(scene, o, d, H, W)
        dr.sync_thread()
        times.append(time.perf_counter() - t0)
        covered.append(float(hit.float().mean()))
    return {"samples_per_pixel": 0.0, "ms_per_frame": 1e3 * statistics.median(times[1:]),
            "ms_first_frame": 1e3 * times[0], "psnr": None, "ssim": None,
            "covered_fraction": float(sum(covered) / len(covered)), "width": W, "height": H,
            "mode": "floor"}


def markdown_table(rows: dict[str, dict[str, Any]]) -> str:
    """One row per method; speed-up relative to full ray."""
    def num(v, fmt):
        return "–" if v is None else format(v, fmt)

    full_ms = rows["full"]["ms_per_frame"]
    lines = ["| method | samples/pixel | ms/frame (median, warm) | speed-up vs full | PSNR "
             "| SSIM |",
             "|---|---:|---:|---:|---:|---:|"]
    for mode, m in rows.items():
        lines.append(f"| {LABELS[mode]} | {num(m['samples_per_pixel'], '.2f')} | "
                     f"{num(m['ms_per_frame'], '.2f')} | {full_ms / m['ms_per_frame']:.1f}x | "
                     f"{num(m['psnr'], '.2f')} | {num(m['ssim'], '.4f')} |")
    return "\n".join(lines)


def plot(rows: dict[str, dict[str, Any]], path: Path, title: str) -> str:
    """PSNR vs ms/frame (log x) as a PNG; returns a one-line message of what was done."""
    pts = {m: r for m, r in rows.items() if r["psnr"] is not None and math.isfinite(r["psnr"])}
    if not pts:
        return "plot skipped: no PSNR (resolution differs from the data set)"
    floor_ms = rows["floor"]["ms_per_frame"] if "floor" in rows else None
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        plt = None
    if plt is not None:
        fig, ax = plt.subplots(figsize=(5, 3.5), dpi=150)
        for m, r in pts.items():
            ax.scatter(r["ms_per_frame"], r["psnr"], color=[c / 255 for c in COLOURS[m]],
                       label=f"{LABELS[m]} ({r['samples_per_pixel']:.1f} spp)")
        if floor_ms:
            ax.axvline(floor_ms, color="grey", ls="--", label=LABELS["floor"])
        ax.set_xscale("log")
        ax.set_xlabel("ms / frame")
        ax.set_ylabel("PSNR (dB)")
        ax.set_title(title, fontsize=8)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(path)
        plt.close(fig)
        return f"plot: {path} (matplotlib)"
    try:
        from PIL import Image, ImageDraw
    except ImportError:
        return "plot skipped: neither matplotlib nor Pillow is installed"
    _plot_pillow(pts, floor_ms, path, title, Image, ImageDraw)
    return f"plot: {path} (Pillow raster; matplotlib is not installed)"


def _plot_pillow(pts: dict[str, dict[str, Any]], floor_ms: float | None, path: Path,
                 title: str, Image: Any, ImageDraw: Any) -> None:
    """A small scatter plot drawn by hand: log10 ms on x, PSNR on y, legend below."""
    Wp, Hp, left, right, top, bottom = 640, 420, 60, 20, 30, 130
    img = Image.new("RGB", (Wp, Hp), "white")
    g = ImageDraw.Draw(img)
    xs = [math.log10(r["ms_per_frame"]) for r in pts.values()]
    if floor_ms:
        xs.append(math.log10(floor_ms))
    ys = [r["psnr"] for r in pts.values()]
    x0, x1 = math.floor(min(xs)), math.ceil(max(xs) + 1e-9)
    x1 = max(x1, x0 + 1)
    y0, y1 = math.floor(min(ys) - 1), math.ceil(max(ys) + 1)

    def px(lx, y):  # log10 ms, PSNR -> pixel
        u = left + (lx - x0) / (x1 - x0) * (Wp - left - right)
        v = Hp - bottom - (y - y0) / (y1 - y0) * (Hp - top - bottom)
        return u, v

    g.rectangle([left, top, Wp - right, Hp - bottom], outline="black")
    for e in range(x0, x1 + 1):  # decades
        u, _ = px(e, y0)
        g.line([u, Hp - bottom, u, Hp - bottom + 5], fill="black")
        g.text((u - 12, Hp - bottom + 8), f"{10.0 ** e:g}", fill="black")
    step = max(1, round((y1 - y0) / 6))
    for y in range(y0, y1 + 1, step):
        _, v = px(x0, y)
        g.line([left - 5, v, left, v], fill="black")
        g.text((left - 30, v - 6), f"{y}", fill="black")
    g.text((Wp // 2 - 40, Hp - bottom + 22), "ms / frame (log)", fill="black")
    g.text((5, top - 20), "PSNR (dB)   " + title, fill="black")
    if floor_ms:
        u, _ = px(math.log10(floor_ms), y0)
        for v in range(top, Hp - bottom, 8):
            g.line([u, v, u, v + 4], fill=COLOURS["floor"])
    legend = Hp - bottom + 42
    for k, (m, r) in enumerate(pts.items()):
        u, v = px(math.log10(r["ms_per_frame"]), r["psnr"])
        g.ellipse([u - 5, v - 5, u + 5, v + 5], fill=COLOURS[m], outline="black")
        g.rectangle([left, legend + 16 * k, left + 10, legend + 16 * k + 10], fill=COLOURS[m])
        g.text((left + 16, legend + 16 * k), f"{LABELS[m]}: {r['ms_per_frame']:.1f} ms, "
               f"{r['psnr']:.2f} dB, {r['samples_per_pixel']:.1f} spp", fill="black")
    if floor_ms:
        k = len(pts)
        g.line([left, legend + 16 * k + 5, left + 10, legend + 16 * k + 5], fill=COLOURS["floor"])
        g.text((left + 16, legend + 16 * k), f"{LABELS['floor']}: {floor_ms:.2f} ms",
               fill="black")
    img.save(path)


def run_bench(run_dir: Path, split: str = "test", width: int | None = None,
              height: int | None = None, views: int | None = None, stage: str = "latest",
              out: Path | None = None, overrides: dict[str, Any] | None = None,
              progress: bool = False) -> dict[str, Any]:
    """Render the views in all four ways; returns rows {mode: metrics} plus run facts."""
    from shells.datasets import load_dataset
    from shells.device import mitsuba_variant
    from shells.fields.drjit_field import DrJitField
    from shells.levelset.mesh import load_ply
    from shells.render.occupancy import grid_summary, march_step, occupancy_grid
    from shells.render.raycast import ShellScene

    run = RunDir(run_dir)
    meta = check_run(run, "band")  # needs run.json, a checkpoint and the outer shell
    field, cfg = load_field(run.root, device="cpu", stage=stage)
    cfg.update({"render": overrides or {}}, "bench/render_speed.py options")
    rc, bg = cfg.render, tuple(cfg.data.background)
    variant = mitsuba_variant(rc.variant)
    scene = load_shells(run, variant)
    outer_only = ShellScene(load_ply(run.outer), None, variant)
    data = load_dataset(meta["data"], split, downscale=int(meta["downscale"]), background=bg)
    n = len(data.cameras) if not views else min(int(views), len(data.cameras))
    cams = data.cameras[:n].resized(width, height)
    same_size = (cams.width, cams.height) == (data.cameras.width, data.cameras.height)
    images = data.images[:n] if same_size else None
    dj = DrJitField(field)
    out = Path(out) if out else run.root / f"bench-speed-{cams.width}x{cams.height}"

    dr.sync_thread()
    t0 = time.perf_counter()
    grid = occupancy_grid(dj, data.aabb, rc)  # cached on dj: render_views reuses it
    dr.sync_thread()
    grid_s = time.perf_counter() - t0

    rows: dict[str, dict[str, Any]] = {}
    for mode in ("band", "full", "occupancy"):
        (out / mode).mkdir(parents=True, exist_ok=True)
        rows[mode] = render_views(dj, cams, images, rc, mode, scene if mode == "band" else None,
                                  data.aabb, out / mode, progress, bg)
    rows["floor"] = time_floor(outer_only, cams)
    return {
        "rows": rows, "out": out, "run": str(run.root), "split": split, "stage": stage,
        "width": cams.width, "height": cams.height, "n_views": n, "variant": variant,
        "same_size": same_size, "grid_build_s": grid_s, "grid": grid_summary(grid),
        "occ_step": march_step(data.aabb, rc), "render_config": dataclasses.asdict(rc),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=Path)
    p.add_argument("--width", type=int, default=None, help="default: the data set's")
    p.add_argument("--height", type=int, default=None, help="default: the data set's")
    p.add_argument("--views", type=int, default=None, help="first N views (default: all)")
    p.add_argument("--split", default="test")
    p.add_argument("--stage", default="latest", choices=["latest", "stage1", "stage2"])
    p.add_argument("--out", type=Path, default=None, help="default: RUN/bench-speed-WxH")
    p.add_argument("--append", type=Path, default=None, help="append the table to this file")
    p.add_argument("--full-samples", type=int, default=None, help="override render.full_samples")
    p.add_argument("--occ-resolution", type=int, default=None, help="override occ_resolution")
    p.add_argument("--occ-k", type=float, default=None, help="override occ_k")
    p.add_argument("--occ-chunk", type=int, default=None, help="override occ_chunk")
    p.add_argument("--progress", action="store_true")
    args = p.parse_args(argv)
    overrides = {k: v for k, v in (("full_samples", args.full_samples),
                                   ("occ_resolution", args.occ_resolution),
                                   ("occ_k", args.occ_k), ("occ_chunk", args.occ_chunk))
                 if v is not None}

    try:
        res = run_bench(args.run, args.split, args.width, args.height, args.views, args.stage,
                        args.out, overrides, args.progress)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    rows, out, rc = res["rows"], res["out"], res["render_config"]
    date = datetime.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    argv = argv if argv is not None else sys.argv[1:]
    command = "python bench/render_speed.py " + " ".join(shlex.quote(a) for a in argv)
    g = res["grid"]
    notes = [
        f"- command: `{command}`",
        f"- device: Mitsuba `{res['variant']}` ({platform.processor() or platform.machine()}); "
        f"date: {date}",
        f"- run: `{res['run']}` ({res['stage']} checkpoint), split `{res['split']}`, "
        f"{res['n_views']} view(s) at {res['width']}x{res['height']}"
        + ("" if res["same_size"] else " (not the data set's resolution: speed only)"),
        f"- full: {rc['full_samples']} samples/ray over the box; band: dp_max {rc['dp_max']}, "
        f"w_s {rc['w_s']}, delta_s {rc['delta_s']}, N_max {rc['n_max']}",
        f"- occupancy: {g['resolution']}^3 grid, k = {rc['occ_k']}, {g['occupied_fraction']:.1%} "
        f"cells occupied, built in {res['grid_build_s']:.2f} s (not in ms/frame); "
        f"dt = {res['occ_step']:.5f}, {rc['occ_chunk']} samples/ray/round, "
        f"ERT at T < {rc['ert_eps']:g}",
        f"- floor: primary rays against M+ only, covering {rows['floor']['covered_fraction']:.1%} "
        "of the pixels; samples/pixel = field evaluations, mean over all pixels",
    ]
    table = markdown_table(rows)
    section = (f"### Render speed: {Path(res['run']).name}, {res['width']}x{res['height']}, "
               f"{res['variant']}\n\n" + "\n".join(notes) + "\n\n" + table + "\n")
    print(section)
    out.mkdir(parents=True, exist_ok=True)
    (out / "render_speed.md").write_text(section)
    dump = {k: (str(v) if isinstance(v, Path) else v) for k, v in res.items()}
    dump.update(command=command, date=date)
    (out / "render_speed.json").write_text(json.dumps(dump, indent=1, default=str) + "\n")
    print(plot(rows, out / "render_speed.png",
               f"{Path(res['run']).name} {res['width']}x{res['height']} {res['variant']}"))
    if args.append:
        with open(args.append, "a") as fh:
            fh.write("\n" + section)
        print(f"appended to {args.append}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
