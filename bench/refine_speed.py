"""Image-space adaptive refinement against the band render of the same field (issue 18).

    python bench/refine_speed.py RUN [--sizes 400 800] [--levels 3] [--views 0 4 8 12]
        [--distances 0.6 0.8 1.0 1.4 2.0] [--config FILE] [--repeats 2] [--json OUT]

For each frame size and test view the band render and the refined render (``--levels`` L,
thresholds from the run's render config, overridden by ``--config`` {"render": {...}}) are
made alternately, ``--repeats`` times after a warm-up, and compared: PSNR and SSIM of the
refined frame against the band frame, test PSNR of both against the ground truth at that
size (the data set's images downscaled to it, when the size divides the native one), the
share of covered pixels evaluated, and the time ratio (medians). ``--distances`` then moves
the camera of the first view along its axis to these multiples of its distance from the
scene centre, at the largest size, and reports the time ratio at each.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from report import emit_json  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run")
    ap.add_argument("--sizes", type=int, nargs="+", default=[400, 800])
    ap.add_argument("--levels", type=int, default=3)
    ap.add_argument("--views", type=int, nargs="+", default=[0, 4, 8, 12])
    ap.add_argument("--distances", type=float, nargs="*", default=[0.6, 0.8, 1.0, 1.4, 2.0])
    ap.add_argument("--config", default=None)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)

    from shells.camera_paths import scene_frame
    from shells.datasets import load_dataset, read_frames
    from shells.device import mitsuba_variant
    from shells.fields.drjit_field import DrJitField
    from shells.metrics import psnr, ssim
    from shells.render.views import render_view
    from shells.run import RunDir, load_field, load_shells, read_run

    run = RunDir(args.run)
    meta = read_run(run)
    field, cfg = load_field(run.root)
    if args.config:
        cfg.update({"render": json.loads(Path(args.config).read_text())["render"]}, args.config)
    band_cfg = dataclasses.replace(cfg.render, refine_levels=0)
    ref_cfg = dataclasses.replace(cfg.render, refine_levels=args.levels)
    bg = tuple(cfg.data.background)
    variant = mitsuba_variant(band_cfg.variant)
    dj = DrJitField(field)
    scene = load_shells(run, variant)
    native = read_frames(meta["data"], "test").cameras.width
    small = load_dataset(meta["data"], "test", downscale=int(meta["downscale"]), background=bg)

    def pair(cams, i):
        times = {"band": [], "refine": []}
        for k in range(args.repeats + 1):
            b, _, tb, _ = render_view(dj, cams, i, band_cfg, "band", scene, small.aabb, bg)
            r, _, tr, counts = render_view(dj, cams, i, ref_cfg, "band", scene, small.aabb, bg)
            if k:
                times["band"].append(tb)
                times["refine"].append(tr)
        tb, tr = statistics.median(times["band"]), statistics.median(times["refine"])
        return b, r, tb, tr, counts

    rows = []
    for size in args.sizes:
        gt = None
        if native % size == 0:
            gt = load_dataset(meta["data"], "test", downscale=native // size, background=bg)
        cams = small.cameras.resized(size, size)
        for i in args.views:
            b, r, tb, tr, counts = pair(cams, i)
            row = {"size": size, "view": i, "band_ms": 1e3 * tb, "refine_ms": 1e3 * tr,
                   "ratio": tr / tb, "psnr_vs_band": psnr(r, b), "ssim_vs_band": ssim(r, b),
                   "evaluated_share": counts["evaluated"] / max(counts["covered"], 1),
                   "test_psnr_band": psnr(b, gt.images[i]) if gt is not None else None,
                   "test_psnr_refine": psnr(r, gt.images[i]) if gt is not None else None}
            rows.append(row)
            print(json.dumps({k: round(v, 4) if isinstance(v, float) else v
                              for k, v in row.items()}), flush=True)
    distances = []
    if args.distances:
        size = max(args.sizes)
        cams = small.cameras.resized(size, size)[args.views[0]:args.views[0] + 1]
        centre = torch.as_tensor(scene_frame(cams, small.aabb)[0], dtype=torch.float32)
        base = cams.c2w.clone()
        for f in args.distances:
            cams.c2w = base.clone()
            cams.c2w[0, :3, 3] = centre + f * (base[0, :3, 3] - centre)
            _, _, tb, tr, counts = pair(cams, 0)
            d = {"distance_factor": f, "band_ms": 1e3 * tb, "refine_ms": 1e3 * tr,
                 "ratio": tr / tb,
                 "evaluated_share": counts["evaluated"] / max(counts["covered"], 1),
                 "covered": counts["covered"]}
            distances.append(d)
            print(json.dumps({k: round(v, 4) if isinstance(v, float) else v
                              for k, v in d.items()}), flush=True)
    summary = {}
    for size in args.sizes:
        rs = [r for r in rows if r["size"] == size]
        summary[str(size)] = {
            k: statistics.mean(r[k] for r in rs)
            for k in ("band_ms", "refine_ms", "ratio", "psnr_vs_band", "ssim_vs_band",
                      "evaluated_share")}
        if rs[0]["test_psnr_band"] is not None:
            summary[str(size)]["test_psnr_band"] = statistics.mean(r["test_psnr_band"] for r in rs)
            summary[str(size)]["test_psnr_refine"] = statistics.mean(r["test_psnr_refine"]
                                                                     for r in rs)
    emit_json({"run": str(run.root), "levels": args.levels,
               "render_config": dataclasses.asdict(ref_cfg), "views": args.views,
               "summary": summary, "rows": rows, "distances": distances,
               "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores, {variant}, "
                          f"torch threads {torch.get_num_threads()}"}, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
