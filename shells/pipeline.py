"""Run-level steps: shell extraction and rendering of a trained run, and the whole toy pipeline
(shells-demo). The library functions below them stay independent of the run directory; these
read and write RUN through `shells.run`.

`render_run` (shells-render RUN) reads RUN/run.json (data set path, downscale), the chosen
checkpoint (stage 2 when present), RUN/shells/{outer,inner}.ply (band mode), renders every view
of the split with the Dr.Jit field (`shells.render.views.render_views`) and writes into OUT
(default RUN/render-MODE) the PNGs and metrics.json (psnr, ssim, samples/pixel, ms/frame,
resolution, mode, device, the stage loaded, protocol). Everything is rendered into a hidden
temporary folder beside OUT and moved in at the end, metrics.json last, so a failure leaves no
partial output.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from shells.config import override_config
from shells.errors import InputError, write_json
from shells.metrics import PROTOCOL
from shells.run import RunDir, load_field, load_shells, read_run, resolve_stage


def extract_run(run_dir: str | Path, resolution: int | None = None,
                fixed_width: float | None = None,
                config: str | Path | None = None) -> dict[str, Any]:
    """Sample the stage-1 field on a grid, extract M+ and M-, write RUN/shells/; returns stats.

    ``fixed_width`` w gives the fixed band {|f| <= w} instead of the adaptive one (ablation);
    ``config``: a JSON file with a ``shell`` section overriding the run's shell settings.
    """
    from shells.levelset.extract import extract_shells, write_shells
    from shells.levelset.grid import sample_grid_banded

    run = RunDir(run_dir)
    field, cfg = load_field(run.root, stage="stage1")
    override_config(cfg, config, ("shell",), "shells-extract")
    if resolution is not None:
        cfg.update({"shell": {"resolution": resolution}}, "--resolution")
    sc = cfg.shell

    def fn(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        g = field.geometry(x)
        return g["sdf"], g["s"]

    t0 = time.perf_counter()
    # exact where the evolution and the meshes look (|f| < zeta or the fixed width, + 2 h),
    # coarse elsewhere
    h = float((field.aabb[1] - field.aabb[0]).max()) / (sc.resolution - 1)
    band = max(sc.dilate_zeta, sc.erode_zeta, fixed_width or 0.0) + 2.0 * h
    f, s, _, exact = sample_grid_banded(fn, field.aabb.cpu().numpy(), sc.resolution, band,
                                        sc.chunk)
    t_grid = time.perf_counter() - t0
    shells = extract_shells(f, s, field.aabb.cpu().numpy(), sc, fixed_width=fixed_width)
    shells.stats["timings_s"]["sample_grid"] = t_grid
    shells.stats["grid_exact_fraction"] = exact
    shells.stats["timings_s"]["total"] = time.perf_counter() - t0
    write_shells(shells, run.shells)
    return shells.stats


def check_run(run: RunDir, mode: str) -> dict[str, Any]:
    """Fail early, before anything is loaded or written; returns run.json."""
    from shells.render.frame import MODES

    if mode not in MODES:
        raise InputError(f"--mode {mode}: expected one of {MODES}")
    meta = read_run(run)
    if not run.checkpoint("stage1").is_file() and not run.checkpoint("stage2").is_file():
        raise InputError(f"{run.checkpoint()}: no checkpoint; run shells-train first")
    if mode == "band" and not run.outer.is_file():
        raise InputError(f"{run.outer}: no outer shell; run shells-extract first")
    return meta


def render_run(run_dir: str | Path, split: str = "test", mode: str = "band",
               width: int | None = None, height: int | None = None,
               out: str | Path | None = None, progress: bool = True,
               stage: str = "latest", config: str | Path | None = None,
               spp: int | None = None) -> dict[str, Any]:
    """Render every view of ``split`` and write images + metrics.json; returns the metrics.

    ``stage`` picks the checkpoint: 'latest' (stage 2 when present), 'stage1' or 'stage2';
    ``config``: a JSON file with a ``render`` section overriding the run's render settings;
    ``spp``: rays per pixel (overrides both).
    """
    from shells.datasets import load_dataset
    from shells.device import mitsuba_variant
    from shells.fields.drjit_field import DrJitField
    from shells.render.views import render_views, resized_cameras

    run = RunDir(run_dir)
    meta = check_run(run, mode)
    loaded = resolve_stage(run, stage)
    field, cfg = load_field(run.root, device="cpu", stage=loaded)
    override_config(cfg, config, ("render",), "shells-render")
    if spp is not None:
        cfg.update({"render": {"spp": spp}}, "--spp")
    rc, bg = cfg.render, tuple(cfg.data.background)
    variant = mitsuba_variant(rc.variant)
    scene = load_shells(run, variant) if mode == "band" else None
    data = load_dataset(meta["data"], split, downscale=int(meta["downscale"]), background=bg)
    cams = resized_cameras(data.cameras, width, height)
    same_size = (cams.width, cams.height) == (data.cameras.width, data.cameras.height)
    dj = DrJitField(field)

    out = Path(out) if out is not None else run.render_dir(mode)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}."))
    try:
        metrics = render_views(dj, cams, data.images if same_size else None, rc, mode, scene,
                               data.aabb, tmp, progress, bg)
        metrics.update({
            "split": split, "variant": variant, "stage": loaded, "out": str(out),
            "device": "cuda" if variant.startswith("cuda") else "cpu",
            "background": list(bg), "data": str(meta["data"]),
            "downscale": int(meta["downscale"]),
            "protocol": PROTOCOL + ("" if same_size else
                                    "; resolution differs from the data set: no metrics"),
            "render_config": dataclasses.asdict(rc),
        })
        write_json(tmp / "metrics.json", metrics)
        out.mkdir(parents=True, exist_ok=True)
        names = sorted(p.name for p in tmp.iterdir())
        for name in [n for n in names if n != "metrics.json"] + ["metrics.json"]:
            os.replace(tmp / name, out / name)  # metrics.json last: it marks a complete render
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return metrics


def demo(out: str | Path, scene: str = "core-fuzz", res: int = 64, views: int = 32,
         iters: int | None = None, finetune_iters: int | None = None) -> list[dict[str, Any]]:
    """Toy scene -> stage 1 -> shells -> stage 2 -> renders; returns the rows of the table."""
    from scenes import make_scene
    from shells.config import toy_config
    from shells.finetune import finetune
    from shells.training import train

    out = Path(out)
    data, run = out / "data", out / "run"
    if RunDir(run).checkpoint().exists():
        raise InputError(f"{run}: a previous demo run is there; choose another --out or delete it")
    print(f"[1/5] rendering the toy scene '{scene}' -> {data}")
    make_scene(scene, data, res=res, views=views)
    cfg = toy_config()
    print("[2/5] stage 1: training the field (full-ray NeuS)")
    train(data, run, cfg, torch.device("cpu"), iters=iters)
    print("[3/5] extracting the shells")
    stats = extract_run(run)
    print("[4/5] stage 2: fine-tuning inside the band")
    finetune(run, iters=finetune_iters, device="cpu")
    print("[5/5] rendering the test views")
    rows = [render_run(run, mode="full", stage="stage1", out=run / "render-full-stage1"),
            render_run(run, mode="band", stage="stage1", out=run / "render-band-stage1"),
            render_run(run, mode="band", stage="stage2", out=run / "render-band")]
    names = ["full ray, stage 1", "band, stage 1", "band, stage 2 (fine-tuned)"]
    print()
    print(f"{'renderer':<28} {'PSNR':>7} {'SSIM':>7} {'samples/px':>11} {'ms/frame':>9}")
    for name, m in zip(names, rows):
        print(f"{name:<28} {m['psnr']:7.2f} {m['ssim']:7.4f} {m['samples_per_pixel']:11.2f} "
              f"{m['ms_per_frame']:9.1f}")
    print(f"\nshells: {RunDir(run).outer}, {RunDir(run).inner} "
          f"({stats['outer_triangles']} / {stats['inner_triangles']} triangles)")
    print(f"images: {run / 'render-band'} (band), {run / 'render-full-stage1'} (full)")
    return [{"renderer": n, **m} for n, m in zip(names, rows)]
