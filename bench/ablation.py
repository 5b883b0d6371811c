"""The paper's ablation (Table 4) on a toy scene: test PSNR, SSIM, samples/pixel and ms/frame
by kernel, band and fine-tuning.

    python -m bench.ablation --scene core-fuzz --out bench/out/ablation-core-fuzz
        [--iters N] [--finetune-iters N] [--res 64] [--views 32] [--append BENCHMARKS.md]

Rows (all scored on the test split, same protocol as `shells-render`):
- full ray, stage 1: the volumetric baseline (dense samples along the whole ray);
- global kernel (one learned s for the scene) vs spatially varying kernel, each with its
  adaptive band, before and after stage-2 fine-tuning;
- the varying-kernel field inside fixed bands |f| <= 0.02 and |f| <= 0.05 instead of the
  adaptive band, before and after fine-tuning.

Every step is skipped when its output already exists, so an interrupted run continues where it
stopped. Variant runs share the stage-1 checkpoint by symbolic link. The table is printed and
written to OUT/ablation.md and OUT/ablation.json; `--append FILE` also appends it to FILE
(e.g. BENCHMARKS.md) with the command, machine and date.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
from pathlib import Path

import torch

from bench.report import command_line
from scenes import make_scene
from shells.presets import toy_config
from shells.train.stage2 import finetune
from shells.pipeline import extract_run, render_run
from shells.run import RunDir
from shells.train.stage1 import train


def trained(data: Path, run: Path, global_kernel: bool, iters: int | None) -> Path:
    if not RunDir(run).checkpoint().is_file() or not RunDir(run).summary().is_file():
        cfg = toy_config()
        cfg.field.global_kernel = global_kernel
        train(data, run, cfg, torch.device("cpu"), iters=iters,
              resume=RunDir(run).checkpoint().is_file())
    return run


def later_stage_configs(out: Path) -> dict[str, Path]:
    """The toy preset's shell / finetune+render / render settings as `--config` files, passed
    to every extraction, fine-tuning and render, so the table always reflects the current
    defaults whatever preset a reused stage-1 checkpoint was trained with (they do not
    influence it)."""
    toy = toy_config().to_dict()
    files = {"extract": {"shell": toy["shell"]},
             "finetune": {"finetune": toy["finetune"], "render": toy["render"]},
             "render": {"render": toy["render"]}}
    paths = {}
    for name, data in files.items():
        paths[name] = out / f"config-{name}.json"
        paths[name].write_text(json.dumps(data, indent=1) + "\n")
    return paths


def variant(base: Path, path: Path) -> Path:
    """A run directory sharing base's stage-1 checkpoint (its own shells and stage 2)."""
    path.mkdir(parents=True, exist_ok=True)
    b, p = RunDir(base), RunDir(path)
    for src, dst in ((b.checkpoint(), p.checkpoint()), (b.run_json, p.run_json),
                     (b.config, p.config), (b.summary(), p.summary())):
        if not dst.exists():
            os.symlink(src.resolve(), dst)
    return path


def shells(run: Path, fixed: float | None, config: Path) -> dict:
    stats = RunDir(run).shells / "stats.json"
    if not stats.is_file():
        extract_run(run, fixed_width=fixed, config=config)
    return json.loads(stats.read_text())


def rendered(run: Path, mode: str, stage: str, config: Path) -> dict:
    out = run / f"render-{mode}-{stage}"
    if not (out / "metrics.json").is_file():
        render_run(run, mode=mode, stage=stage, out=out, config=config)
    return json.loads((out / "metrics.json").read_text())


def finetuned(run: Path, iters: int | None, config: Path) -> Path:
    if not RunDir(run).summary("stage2").is_file():
        finetune(run, iters=iters, resume=RunDir(run).checkpoint("stage2").is_file(),
                 config=config, device="cpu")
    return run


def ablation(scene: str, out: Path, iters: int | None, ft_iters: int | None,
             res: int, views: int) -> list[dict]:
    data = out / "data"
    if not (data / "transforms_test.json").is_file():
        make_scene(scene, data, res=res, views=views)
    varying = trained(data, out / "varying", False, iters)
    glob = trained(data, out / "global", True, iters)
    cfgs = later_stage_configs(out)
    runs = {  # name -> (run dir, kernel, band)
        "global": (glob, "global", "adaptive", None),
        "varying": (varying, "varying", "adaptive", None),
        "fixed-0.02": (variant(varying, out / "fixed-0.02"), "varying", "fixed ±0.02", 0.02),
        "fixed-0.05": (variant(varying, out / "fixed-0.05"), "varying", "fixed ±0.05", 0.05),
    }
    rows = []
    for name in ("varying", "global"):
        m = rendered(runs[name][0], "full", "stage1", cfgs["render"])
        rows.append({"kernel": runs[name][1], "band": "full ray (volumetric)", "finetune": "no",
                     "band_width_mean": None, **_scores(m)})
    for name, (run, kernel, band, fixed) in runs.items():
        st = shells(run, fixed, cfgs["extract"])
        width = st.get("band_width", {}).get("mean")
        rows.append({"kernel": kernel, "band": band, "finetune": "no", "band_width_mean": width,
                     **_scores(rendered(run, "band", "stage1", cfgs["render"]))})
        finetuned(run, ft_iters, cfgs["finetune"])
        rows.append({"kernel": kernel, "band": band, "finetune": "yes", "band_width_mean": width,
                     **_scores(rendered(run, "band", "stage2", cfgs["render"]))})
    return rows


def _scores(m: dict) -> dict:
    return {k: m.get(k) for k in ("psnr", "ssim", "samples_per_pixel", "ms_per_frame",
                                  "samples_per_covered_pixel")}


def table(rows: list[dict]) -> str:
    lines = ["| kernel | band | fine-tuned | band width (mean) | PSNR | SSIM | samples/px "
             "| ms/frame |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        w = "—" if r["band_width_mean"] is None else f"{r['band_width_mean']:.4f}"
        lines.append(f"| {r['kernel']} | {r['band']} | {r['finetune']} | {w} | {r['psnr']:.2f} | "
                     f"{r['ssim']:.4f} | {r['samples_per_pixel']:.2f} | {r['ms_per_frame']:.1f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="Paper Table 4 ablation on a toy scene (CPU).")
    p.add_argument("--scene", default="core-fuzz", choices=["sphere", "fuzzy-sphere", "core-fuzz"])
    p.add_argument("--out", required=True,
                   help="work directory (reused: finished steps are skipped)")
    p.add_argument("--iters", type=int, default=None, help="stage-1 steps (default: toy preset)")
    p.add_argument("--finetune-iters", type=int, default=None,
                   help="stage-2 steps (default: toy preset)")
    p.add_argument("--res", type=int, default=64)
    p.add_argument("--views", type=int, default=32)
    p.add_argument("--append", default=None, help="append the table to this Markdown file")
    args = p.parse_args(argv)
    out = Path(args.out)
    rows = ablation(args.scene, out, args.iters, args.finetune_iters, args.res, args.views)
    md = table(rows)
    print(md)
    (out / "ablation.json").write_text(json.dumps(rows, indent=1) + "\n")
    (out / "ablation.md").write_text(md + "\n")
    if args.append:
        cmd = command_line("ablation", argv)
        head = (f"\n### Ablation (Table 4), `{args.scene}` — {datetime.date.today()}\n\n"
                f"Command: `{cmd}`  \nMachine: {platform.machine()}, {os.cpu_count()} CPU cores, "
                f"torch {torch.__version__} (CPU), no GPU.\n\n")
        with open(args.append, "a") as fh:
            fh.write(head + md + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
