"""Cost of a deformed frame against the undeformed band frame of the same view.

    python -m bench.deform_speed RUN [--motion wind] [--sizes 128 256 512] [--zoom 1]
        [--view 0] [--shells fine|lod] [--repeats 5] [--json OUT]

RUN needs a cage (shells-cage). For each frame size, camera ``--view`` of the test split is
rendered (a) undeformed in band mode and (b) with the cage posed by ``--motion`` at mid-
animation (t = 0.5), alternating, ``--repeats`` times after one warm-up each; reported are
the medians of (a) the band render, (b) the deformed frame's pose (locator grid, affine maps,
moved shells) and its render, and the ratio (b) / (a) with and without the pose.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time

from bench.report import emit_json


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run")
    ap.add_argument("--motion", default="wind")
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512])
    ap.add_argument("--zoom", type=float, default=1.0)
    ap.add_argument("--view", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--shells", choices=["fine", "lod"], default="fine")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)

    from shells.data.datasets import load_dataset
    from shells.deform.motions import ANALYTIC, AssetFrame
    from shells.device import mitsuba_variant
    from shells.fields.drjit_field import DrJitField
    from shells.render.deformed import CageAsset
    from shells.render.views import render_view
    from shells.pipeline import capture_up
    from shells.run import RunDir, load_cage, load_field, load_shells, read_run

    run = RunDir(args.run)
    meta = read_run(run)
    field, cfg = load_field(run.root)
    rc, bg = cfg.render, tuple(cfg.data.background)
    variant = mitsuba_variant(rc.variant)
    dj = DrJitField(field)
    scene = load_shells(run, variant, args.shells)
    cage, emb, outer, inner = load_cage(run, args.shells)
    data = load_dataset(meta["data"], "test", downscale=int(meta["downscale"]), background=bg)
    up = capture_up(meta["data"], data)
    pose = ANALYTIC[args.motion](cage.vertices, 0.5, AssetFrame.of(cage.vertices, up))
    asset = CageAsset(dj, cage.vertices, cage.tets, emb, outer[1], inner[1], variant)
    rows = []
    for size in args.sizes:
        cams = data.cameras[args.view:args.view + 1].resized(size, size)
        cams.fx, cams.fy = cams.fx * args.zoom, cams.fy * args.zoom
        band, setup, render, spp_b, spp_d = [], [], [], 0.0, 0.0
        for k in range(args.repeats + 1):
            _, spp, s, _ = render_view(dj, cams, 0, rc, "band", scene, data.aabb, bg)
            t0 = time.perf_counter()
            dfield, dscene = asset.pose(pose)
            t1 = time.perf_counter()
            _, dspp, ds, _ = render_view(dfield, cams, 0, rc, "band", dscene, data.aabb, bg)
            if k == 0:
                continue  # warm-up: kernels compile
            band.append(s)
            setup.append(t1 - t0)
            render.append(ds)
            spp_b, spp_d = float(spp.double().mean()), float(dspp.double().mean())
        b, p, r = (statistics.median(x) for x in (band, setup, render))
        rows.append({"size": size, "band_ms": 1e3 * b, "pose_ms": 1e3 * p,
                     "deformed_render_ms": 1e3 * r, "ratio_render": r / b,
                     "ratio_with_pose": (p + r) / b, "band_spp": spp_b,
                     "deformed_spp": spp_d})
        print(f"{size}x{size}: band {1e3 * b:7.1f} ms | deformed: pose {1e3 * p:6.1f} ms + "
              f"render {1e3 * r:7.1f} ms | ratio {r / b:4.2f} (render) {(p + r) / b:4.2f} "
              f"(with pose) | spp {spp_b:.2f} / {spp_d:.2f}", flush=True)
    doc = {"run": str(run.root), "shells": args.shells, "motion": args.motion,
           "view": args.view, "zoom": args.zoom,
           "cage_vertices": int(len(cage.vertices)), "cage_tetrahedra": int(len(cage.tets)),
           "rows": rows,
           "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores, {variant}"}
    emit_json(doc, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
