"""Run-level glue: shell extraction of a trained run, and the whole toy pipeline (shells-demo).

The library functions stay independent of the run directory; this module reads and writes RUN.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import torch

from shells.errors import InputError
from shells.run import RunDir


def extract_run(run_dir: str | Path, resolution: int | None = None,
                fixed_width: float | None = None,
                config: str | Path | None = None) -> dict[str, Any]:
    """Sample the stage-1 field on a grid, extract M+ and M-, write RUN/shells/; returns stats.

    ``fixed_width`` w gives the fixed band {|f| <= w} instead of the adaptive one (ablation);
    ``config``: a JSON file with a ``shell`` section overriding the run's shell settings.
    """
    from shells.config import override_config
    from shells.levelset.extract import extract_shells, write_shells
    from shells.levelset.grid import sample_grid_banded
    from shells.training import load_field

    run = RunDir(run_dir)
    field, cfg = load_field(run.root, stage="stage1")
    sc = override_config(cfg, config, ("shell",), "shells-extract").shell
    if resolution is not None:
        if resolution < 8:
            raise InputError(f"--resolution {resolution}: use at least 8 (e.g. 256)")
        sc.resolution = resolution

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
    shells.stats.setdefault("timings", {})["sample_grid"] = t_grid
    shells.stats["grid_exact_fraction"] = exact
    shells.stats["timings"]["total"] = time.perf_counter() - t0
    write_shells(shells, run.shells)
    return shells.stats


def demo(out: str | Path, scene: str = "core-fuzz", res: int = 64, views: int = 32,
         iters: int | None = None, finetune_iters: int | None = None) -> list[dict[str, Any]]:
    """Toy scene -> stage 1 -> shells -> stage 2 -> renders; returns the rows of the table."""
    from scenes import make_scene
    from shells.config import toy_config
    from shells.finetune import finetune
    from shells.render.run import render_run
    from shells.training import train

    out = Path(out)
    data, run = out / "data", out / "run"
    if RunDir(run).checkpoint.exists():
        raise InputError(f"{run}: a previous demo run is there; choose another --out or delete it")
    print(f"[1/5] rendering the toy scene '{scene}' -> {data}")
    make_scene(scene, data, res=res, views=views)
    cfg = toy_config()
    print("[2/5] stage 1: training the field (full-ray NeuS)")
    train(data, run, cfg, torch.device("cpu"), iters=iters)
    print("[3/5] extracting the shells")
    stats = extract_run(run)
    print("[4/5] stage 2: fine-tuning inside the band")
    finetune(run, iters=finetune_iters)
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
