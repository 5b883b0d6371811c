"""Band vs full-ray rendering of one trained run, same field (issue 5's toy check).

    python bench/band_vs_full.py RUN [--stage stage1] [--width W --height H]

Renders the test split in `full` and `band` mode (RUN/bench-full-STAGE, RUN/bench-band-STAGE)
and prints PSNR of each, the PSNR gap, samples/pixel (all pixels and covered pixels only), the
sample-count ratio full / band and the median warm ms/frame of each, as one JSON object.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from shells.pipeline import render_run

from report import emit_json


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run")
    p.add_argument("--stage", default="stage1", choices=["stage1", "stage2", "latest"])
    p.add_argument("--width", type=int, default=None)
    p.add_argument("--height", type=int, default=None)
    p.add_argument("--json", default=None, help="also write the result here")
    args = p.parse_args(argv)
    run = Path(args.run)
    m = {mode: render_run(run, mode=mode, stage=args.stage, width=args.width, height=args.height,
                          out=run / f"bench-{mode}-{args.stage}", progress=False)
         for mode in ("full", "band")}
    res = {
        "run": str(run), "stage": args.stage, "width": m["band"]["width"],
        "height": m["band"]["height"], "variant": m["band"]["variant"],
        "psnr_full": m["full"].get("psnr"), "psnr_band": m["band"].get("psnr"),
        "ssim_full": m["full"].get("ssim"), "ssim_band": m["band"].get("ssim"),
        "spp_full": m["full"]["samples_per_pixel"], "spp_band": m["band"]["samples_per_pixel"],
        "spp_band_covered": m["band"]["samples_per_covered_pixel"],
        "covered_fraction": m["band"]["covered_fraction"],
        "ms_full": m["full"]["ms_per_frame"], "ms_band": m["band"]["ms_per_frame"],
    }
    if res["psnr_full"] is not None:
        res["psnr_gap_full_minus_band"] = res["psnr_full"] - res["psnr_band"]
    res["sample_ratio_full_over_band"] = res["spp_full"] / max(res["spp_band"], 1e-12)
    res["speedup_full_over_band"] = res["ms_full"] / res["ms_band"]
    emit_json(res, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
