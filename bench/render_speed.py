"""Rendering speed of one trained run: narrow band vs full ray vs occupancy grid vs the floor;
also image-space refinement against the band render, and the fine against the LOD shells' cast.

    python -m bench.render_speed RUN [--width 1920 --height 1080] [--views N] [--stage latest]
                                     [--append BENCHMARKS.md] [--out DIR] [--config FILE]
                                     [--modes band full occupancy floor] [--grid-stage stage1]
    python -m bench.render_speed RUN --refine [--levels 3] [--sizes 400 800]
                                     [--view-ids 0 4 8 12] [--distances 0.6 0.8 1.0 1.4 2.0]
                                     [--repeats 2] [--config FILE] [--json OUT]
    python -m bench.render_speed RUN --cast-only [--width W --height H] [--json OUT]
    python -m bench.render_speed RUN --baked [--sizes 400 800] [--frames 60]
                                     [--gl llvmpipe swiftshader] [--json OUT]

RUN is a run directory as `shells-train` + `shells-extract` leave it (checkpoint.pt, run.json,
shells/outer.ply, shells/inner.ply); ``--config`` is a JSON file whose `render` section
overrides the run's. By default the first N views of the split (default: all) are rendered
with the same Dr.Jit field in four ways:

    band       adaptive shells: M+/M- depth peeling + Procedure 3 samples (the method)
    full       cfg.full_samples samples per ray over the whole scene box (volumetric baseline)
    occupancy  occupancy grid + fixed-step marching, empty-space skipping, early termination
               (Instant-NGP / nerfacc baseline, shells/render/occupancy.py); the grid is built
               once before timing, its build time is reported separately
    floor      primary rays against M+ alone, no field evaluation: the time floor of `band`

(``--modes``: only those; ``--grid-stage stage1``: the grid built from the run's stage-1 field,
which knows the empty space a stage-2 field was never sampled in), and reported as one Markdown
table: samples/pixel (mean over all pixels), median warm ms/frame
(`shells.render.views.render_views`: the first frame compiles kernels and is not counted; with
one view a second render of it is timed), and PSNR/SSIM (`shells.metrics`) when rendering at the
data set's own resolution (only speed otherwise). The table is printed, written with the raw
numbers to OUT/render_speed.{md,json} (OUT default RUN/bench-speed-WxH), and with ``--append``
appended to FILE together with the command, the device (Mitsuba variant) and the date. A plot of
PSNR against ms/frame goes to OUT/render_speed.png (matplotlib when installed, else Pillow; it
is skipped, with a message, when there are no PSNRs or neither library is available).

``--refine``: for each square frame size and test view, the band render and the refined render
(``--levels`` L, thresholds from the run's render config) are made alternately, ``--repeats``
times after a warm-up, and compared: PSNR and SSIM of the refined frame against the band frame,
test PSNR of both against the ground truth at that size (when the size divides the native
one), the share of covered pixels evaluated, and the time ratio (medians). ``--distances``
then moves the camera of the first view along its axis to these multiples of its distance from
the scene centre, at the largest size, and reports the time ratio at each. Prints JSON.

``--cast-only``: the depth-peeled interval cast (`ShellScene.intervals`, the band renderer's
and stage 2's) of every pixel of the test views through the fine shells and through their LOD
(shells-lod), median of 5 warm repeats; prints JSON.

``--baked``: the baked asset (shells-bake) against the band render of the same run. Python:
band and baked renders of the test views at the data set's size (PSNR, SSIM, layers or samples
per pixel, median warm ms/frame) and at each square ``--sizes`` (speed only). Browser: the
asset exported (shells-export --web) and served on 127.0.0.1, headless Chromium with each
software GL of ``--gl`` (llvmpipe: Mesa through ANGLE's EGL backend; swiftshader), a
synchronous ``--frames``-frame orbit at each size, each frame finished by a one-pixel
gl.readPixels; median ms/frame. Prints JSON.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import drjit as dr
import torch

from bench.report import command_line, emit_json
from shells.config import read_config_file
from shells.errors import InputError
from shells.pipeline import check_run
from shells.render.views import render_view, render_views
from shells.run import RunDir, load_field, load_shells

LABELS = {
    "band": "band (adaptive shells)",
    "full": "full ray",
    "occupancy": "occupancy grid",
    "floor": "M+ ray cast only (floor)",
}
MODES = ("band", "full", "occupancy", "floor")
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
    """One row per method; speed-up relative to full ray, or to the occupancy grid when full
    ray was not rendered."""
    def num(v, fmt):
        return "–" if v is None else format(v, fmt)

    ref = "full" if "full" in rows else "occupancy" if "occupancy" in rows else None
    ref_ms = rows[ref]["ms_per_frame"] if ref else None
    lines = [f"| method | samples/pixel | ms/frame (median, warm) | speed-up vs {ref or '–'} "
             "| PSNR | SSIM |",
             "|---|---:|---:|---:|---:|---:|"]
    for mode, m in rows.items():
        up = "–" if ref_ms is None else f"{ref_ms / m['ms_per_frame']:.1f}x"
        lines.append(f"| {LABELS[mode]} | {num(m['samples_per_pixel'], '.2f')} | "
                     f"{num(m['ms_per_frame'], '.2f')} | {up} | "
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


def open_run(run_dir: Path, stage: str = "latest", overrides: dict[str, Any] | None = None,
             split: str = "test") -> SimpleNamespace:
    """RUN's field and config (render section updated by ``overrides``), its Mitsuba variant, its
    fine shells and the split at the run's resolution (every mode's starting point)."""
    from shells.data.datasets import load_dataset
    from shells.device import mitsuba_variant

    run = RunDir(run_dir)
    meta = check_run(run, "band")  # needs run.json, a checkpoint and the outer shell
    field, cfg = load_field(run.root, device="cpu", stage=stage)
    cfg.update({"render": overrides or {}}, "bench.render_speed options")
    rc, bg = cfg.render, tuple(cfg.data.background)
    variant = mitsuba_variant(rc.variant)
    data = load_dataset(meta["data"], split, downscale=int(meta["downscale"]), background=bg)
    return SimpleNamespace(run=run, meta=meta, field=field, rc=rc, bg=bg, variant=variant,
                           scene=load_shells(run, variant), data=data)


def run_bench(run_dir: Path, split: str = "test", width: int | None = None,
              height: int | None = None, views: int | None = None, stage: str = "latest",
              out: Path | None = None, overrides: dict[str, Any] | None = None,
              progress: bool = False, modes: tuple[str, ...] = MODES,
              grid_stage: str | None = None) -> dict[str, Any]:
    """Render the views in the ``modes`` (of MODES); returns rows {mode: metrics} plus run
    facts. ``grid_stage``: the occupancy grid is built from that stage's field of the run
    (default: the rendered field's own)."""
    from shells.fields.drjit_field import DrJitField
    from shells.levelset.mesh import load_ply
    from shells.render.occupancy import grid_summary, march_step, occupancy_grid
    from shells.render.raycast import ShellScene

    r = open_run(run_dir, stage, overrides, split)
    run, rc, bg, variant, data = r.run, r.rc, r.bg, r.variant, r.data
    outer_only = ShellScene(load_ply(run.outer), None, variant)
    n = len(data.cameras) if not views else min(int(views), len(data.cameras))
    cams = data.cameras[:n].resized(width, height)
    same_size = (cams.width, cams.height) == (data.cameras.width, data.cameras.height)
    images = data.images[:n] if same_size else None
    dj = DrJitField(r.field)
    out = Path(out) if out else run.root / f"bench-speed-{cams.width}x{cams.height}"

    grid, grid_s = None, None
    if "occupancy" in modes:
        source = (DrJitField(load_field(run.root, device="cpu", stage=grid_stage)[0])
                  if grid_stage else None)
        dr.sync_thread()
        t0 = time.perf_counter()
        grid = occupancy_grid(dj, data.aabb, rc, source)  # cached on dj: render_views uses it
        dr.sync_thread()
        grid_s = time.perf_counter() - t0

    rows: dict[str, dict[str, Any]] = {}
    for mode in modes:
        if mode == "floor":
            rows[mode] = time_floor(outer_only, cams)
            continue
        (out / mode).mkdir(parents=True, exist_ok=True)
        rows[mode] = render_views(dj, cams, images, rc, mode, r.scene if mode == "band" else None,
                                  data.aabb, out / mode, progress, bg)
    return {
        "rows": rows, "out": out, "run": str(run.root), "split": split, "stage": stage,
        "grid_stage": grid_stage or stage,
        "width": cams.width, "height": cams.height, "n_views": n, "variant": variant,
        "same_size": same_size, "grid_build_s": grid_s,
        "grid": grid_summary(grid) if grid is not None else None,
        "occ_step": march_step(data.aabb, rc), "render_config": dataclasses.asdict(rc),
    }


def report_bench(res: dict[str, Any], command: str, append: Path | None) -> None:
    """Print the table of the modes with its notes; write OUT/render_speed.{md,json,png}."""
    rows, out, rc = res["rows"], res["out"], res["render_config"]
    date = datetime.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
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
    ]
    if g is not None:
        notes.append(
            f"- occupancy: {g['resolution']}^3 grid of the {res['grid_stage']} field, k = "
            f"{rc['occ_k']}, {g['occupied_fraction']:.1%} cells occupied, built in "
            f"{res['grid_build_s']:.2f} s (not in ms/frame); dt = {res['occ_step']:.5f}, "
            f"{rc['occ_chunk']} samples/ray/round, ERT at T < {rc['ert_eps']:g}")
    if "floor" in rows:
        notes.append(f"- floor: primary rays against M+ only, covering "
                     f"{rows['floor']['covered_fraction']:.1%} of the pixels")
    notes.append("- samples/pixel = field evaluations, mean over all pixels")
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
    if append:
        with open(append, "a") as fh:
            fh.write("\n" + section)
        print(f"appended to {append}")


def _rounded(row: dict[str, Any]) -> str:
    return json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()})


def refine_bench(args: argparse.Namespace, overrides: dict[str, Any]) -> dict[str, Any]:
    """``--refine`` of the module docstring: refined against band frames, rows and summary."""
    from shells.data.camera_paths import scene_frame
    from shells.data.datasets import load_dataset, read_frames
    from shells.fields.drjit_field import DrJitField
    from shells.metrics import psnr, ssim

    r = open_run(args.run, args.stage, overrides)
    band_cfg = dataclasses.replace(r.rc, refine_levels=0)
    ref_cfg = dataclasses.replace(r.rc, refine_levels=args.levels)
    dj, small, data_dir = DrJitField(r.field), r.data, r.meta["data"]
    native = read_frames(data_dir, "test").cameras.width

    def pair(cams, i):
        times = {"band": [], "refine": []}
        for k in range(args.repeats + 1):
            b, _, tb, _ = render_view(dj, cams, i, band_cfg, "band", r.scene, small.aabb, r.bg)
            f, _, tf, counts = render_view(dj, cams, i, ref_cfg, "band", r.scene, small.aabb,
                                           r.bg)
            if k:
                times["band"].append(tb)
                times["refine"].append(tf)
        tb, tf = statistics.median(times["band"]), statistics.median(times["refine"])
        return b, f, tb, tf, counts

    rows = []
    for size in args.sizes:
        gt = None
        if native % size == 0:
            gt = load_dataset(data_dir, "test", downscale=native // size, background=r.bg)
        cams = small.cameras.resized(size, size)
        for i in args.view_ids:
            b, f, tb, tf, counts = pair(cams, i)
            rows.append({"size": size, "view": i, "band_ms": 1e3 * tb, "refine_ms": 1e3 * tf,
                         "ratio": tf / tb, "psnr_vs_band": psnr(f, b), "ssim_vs_band": ssim(f, b),
                         "evaluated_share": counts["evaluated"] / max(counts["covered"], 1),
                         "test_psnr_band": psnr(b, gt.images[i]) if gt is not None else None,
                         "test_psnr_refine": psnr(f, gt.images[i]) if gt is not None else None})
            print(_rounded(rows[-1]), flush=True)
    distances = []
    if args.distances:
        size = max(args.sizes)
        cams = small.cameras.resized(size, size)[args.view_ids[0]:args.view_ids[0] + 1]
        centre = torch.as_tensor(scene_frame(cams, small.aabb)[0], dtype=torch.float32)
        base = cams.c2w.clone()
        for f in args.distances:
            cams.c2w = base.clone()
            cams.c2w[0, :3, 3] = centre + f * (base[0, :3, 3] - centre)
            _, _, tb, tf, counts = pair(cams, 0)
            distances.append({"distance_factor": f, "band_ms": 1e3 * tb, "refine_ms": 1e3 * tf,
                              "ratio": tf / tb, "evaluated_share":
                                  counts["evaluated"] / max(counts["covered"], 1),
                              "covered": counts["covered"]})
            print(_rounded(distances[-1]), flush=True)
    summary = {}
    for size in args.sizes:
        rs = [x for x in rows if x["size"] == size]
        keys = ["band_ms", "refine_ms", "ratio", "psnr_vs_band", "ssim_vs_band",
                "evaluated_share"]
        if rs[0]["test_psnr_band"] is not None:
            keys += ["test_psnr_band", "test_psnr_refine"]
        summary[str(size)] = {k: statistics.mean(x[k] for x in rs) for k in keys}
    return {"run": str(r.run.root), "levels": args.levels,
            "render_config": dataclasses.asdict(ref_cfg), "views": args.view_ids,
            "summary": summary, "rows": rows, "distances": distances,
            "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores, {r.variant}, "
                       f"torch threads {torch.get_num_threads()}"}


def cast_ms(scene: Any, o: torch.Tensor, d: torch.Tensor, dp_max: int, repeats: int = 5
            ) -> float:
    """Median warm ms of the depth-peeled interval cast of rays (o, d) through ``scene``."""
    times = []
    for _ in range(repeats + 1):
        t0 = time.perf_counter()
        iv = scene.intervals(o, d, dp_max)
        dr.eval(iv.enter, iv.exit, iv.count, iv.t_inner)
        dr.sync_thread()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times[1:])


def cast_bench(args: argparse.Namespace, overrides: dict[str, Any]) -> dict[str, Any]:
    """``--cast-only`` of the module docstring: the fine and the LOD shells' cast."""
    r = open_run(args.run, args.stage, overrides)
    cams = r.data.cameras.resized(args.width, args.height)
    rays = [cams.pixel_rays(i)[:2] for i in range(len(cams))]
    o = torch.cat([x[0].reshape(-1, 3) for x in rays])
    d = torch.cat([x[1].reshape(-1, 3) for x in rays])
    out = {"run": str(r.run.root), "rays": int(len(o)), "width": cams.width,
           "height": cams.height, "dp_max": r.rc.dp_max}
    for which in ("fine", "lod"):
        scene = r.scene if which == "fine" else load_shells(r.run, r.variant, which)
        out[f"{which}_ms"] = cast_ms(scene, o, d, r.rc.dp_max)
    return out


def baked_bench(args: argparse.Namespace) -> dict[str, Any]:
    """``--baked`` (module docstring)."""
    import tempfile
    import threading

    from shells.bake.run import export_web, static_server
    from shells.browser import Browser
    from shells.pipeline import render_run

    run = RunDir(args.run)
    check_run(run, "baked")
    out: dict[str, Any] = {"run": str(run.root), "python": {}, "browser": {}}
    with tempfile.TemporaryDirectory(prefix="bench-baked-") as tmp:
        # band at the run's spp; baked at the asset's (as fitted, as the browser's MSAA) and at 1
        for mode, spp in (("band", None), ("baked", None), ("baked", 1)):
            for size in [None, *args.sizes]:
                m = render_run(run.root, mode=mode, width=size, height=size, out=Path(tmp) / "r",
                               progress=args.progress, spp=spp)
                key = f"{mode} spp {m['render_config']['spp']} {m['width']}x{m['height']}"
                out["python"][key] = {k: m.get(k) for k in (
                    "psnr", "ssim", "samples_per_pixel", "ms_per_frame", "views")}
        rows = out["python"]
        for key in [k for k in rows if k.startswith("baked ")]:
            size = key.split()[-1]
            band = next(v for k, v in rows.items() if k.startswith("band ") and k.endswith(size))
            rows[key]["band_ms_over_baked_ms"] = band["ms_per_frame"] / max(
                rows[key]["ms_per_frame"], 1e-9)
        web = Path(tmp) / "web"
        export_web(run.root, web)
        out["asset_bytes"] = (web / "layers.glb").stat().st_size
        srv = static_server(web, "127.0.0.1", 0)
        threading.Thread(target=srv.serve_forever, daemon=True).start()
        url = f"http://127.0.0.1:{srv.server_address[1]}/?paused=1"
        try:
            for gl in args.gl:
                with Browser(gl=gl, offline=True, timeout=600) as b:
                    for variant in args.variants:  # the viewer's URL options
                        b.open(url + (f"&{variant}" if variant else ""),
                               ready="window.shells && window.shells.ready", timeout=600)
                        for size in args.sizes:
                            r = b.evaluate(f"window.shells.benchmark({args.frames}, {size}, "
                                           f"{size})", timeout=1800)
                            key = " ".join(x for x in (gl, f"{size}x{size}", variant) if x)
                            out["browser"][key] = {
                                "median_ms": r["median_ms"], "fps": 1000.0 / r["median_ms"],
                                "frames": r["frames"], "renderer": r["renderer"]}
                    out["browser"]["triangles"] = b.evaluate("window.shells.triangles")
        finally:
            srv.shutdown()
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=Path)
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--refine", action="store_true",
                      help="image-space refinement against the band render")
    mode.add_argument("--cast-only", action="store_true",
                      help="the interval cast alone, fine against LOD shells")
    mode.add_argument("--baked", action="store_true",
                      help="the baked asset: Python against band, and in headless Chromium")
    p.add_argument("--width", type=int, default=None, help="default: the data set's")
    p.add_argument("--height", type=int, default=None, help="default: the data set's")
    p.add_argument("--views", type=int, default=None, help="first N views (default: all)")
    p.add_argument("--split", default="test")
    p.add_argument("--stage", default="latest", choices=["latest", "stage1", "stage2"])
    p.add_argument("--out", type=Path, default=None, help="default: RUN/bench-speed-WxH")
    p.add_argument("--append", type=Path, default=None, help="append the table to this file")
    p.add_argument("--config", default=None,
                   help="JSON file whose render section overrides the run's")
    p.add_argument("--full-samples", type=int, default=None, help="override render.full_samples")
    p.add_argument("--occ-resolution", type=int, default=None, help="override occ_resolution")
    p.add_argument("--occ-k", type=float, default=None, help="override occ_k")
    p.add_argument("--occ-chunk", type=int, default=None, help="override occ_chunk")
    p.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES,
                   help="which renders (default: all four)")
    p.add_argument("--grid-stage", default=None, choices=["stage1", "stage2"],
                   help="build the occupancy grid from this stage's field of the run (default: "
                        "the rendered field's own; a stage-2 field outside the band is untrained)")
    p.add_argument("--progress", action="store_true")
    g = p.add_argument_group("--refine")
    g.add_argument("--levels", type=int, default=3, help="render.refine_levels of the refined")
    g.add_argument("--sizes", type=int, nargs="+", default=[400, 800],
                   help="square sizes (--refine, --baked)")
    g.add_argument("--view-ids", type=int, nargs="+", default=[0, 4, 8, 12])
    g.add_argument("--distances", type=float, nargs="*", default=[0.6, 0.8, 1.0, 1.4, 2.0])
    g.add_argument("--repeats", type=int, default=2)
    g = p.add_argument_group("--baked")
    g.add_argument("--frames", type=int, default=60, help="frames of the browser's orbit")
    g.add_argument("--gl", nargs="+", default=["llvmpipe", "swiftshader"],
                   choices=["llvmpipe", "swiftshader"], help="Chromium's software GL")
    g.add_argument("--variants", nargs="+", default=[""], metavar="QUERY",
                   help="viewer URL options to time, each a variant (e.g. '' 'cull=1' "
                        "'msaa=0'; default: the viewer as it opens)")
    p.add_argument("--json", default=None,
                   help="--refine, --cast-only, --baked: also write JSON here")
    args = p.parse_args(argv)
    overrides = read_config_file(args.config).get("render", {}) if args.config else {}
    overrides.update({k: v for k, v in (("full_samples", args.full_samples),
                                        ("occ_resolution", args.occ_resolution),
                                        ("occ_k", args.occ_k), ("occ_chunk", args.occ_chunk))
                      if v is not None})
    try:
        if args.refine:
            emit_json(refine_bench(args, overrides), args.json)
        elif args.cast_only:
            emit_json(cast_bench(args, overrides), args.json)
        elif args.baked:
            emit_json(baked_bench(args), args.json)
        else:
            report_bench(run_bench(args.run, args.split, args.width, args.height, args.views,
                                   args.stage, args.out, overrides, args.progress,
                                   tuple(args.modes), args.grid_stage),
                         command_line("render_speed", argv), args.append)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
