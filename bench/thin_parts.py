"""Does stage 1 keep thin parts? Mean test error of the `thin-parts` toy scene's rod and plate
against its sphere after stage 1.

    python -m bench.thin_parts --out OUT [--preset auto|toy|object] [--config CFG.json]
                               [--iters 1500] [--test-views 6] [--seed 0] [--picture PNG]

Renders the scene as `tests/test_thin_parts.py` does (64x64, 32 train views, ``--test-views``
test views) into OUT/data unless it is there, trains stage 1 with ``--preset`` (auto and
object: the real-object preset sized from the data, as the test trains; toy: the demo's
preset) with the "occupancy" sampler and ``--iters`` steps, plus
``--config`` on top, and prints JSON: per part (`scenes.parts.part_scores`) the test
pixels, mean |error| and mean opacity of the full-ray render (stage 1's own sampler), the
error ratios rod / sphere and plate / sphere (the test asks for <= 1), and the training
seconds; ``--picture PNG`` also writes the test views (ground truth above the render).
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from bench.report import emit_json
from scenes import make_scene
from scenes.parts import part_scores
from shells.config import read_config_file
from shells.presets import preset_config
from shells.train.stage1 import stage1_renderer, train


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", required=True)
    p.add_argument("--preset", default="auto", choices=("auto", "toy", "object"),
                   help="the base config as `shells-train --preset` (auto: the object preset)")
    p.add_argument("--config", default=None, help="JSON overrides on top of the test's config")
    p.add_argument("--iters", type=int, default=1500)
    p.add_argument("--test-views", type=int, default=6, help="6: the test's data set")
    p.add_argument("--seed", type=int, default=0,
                   help="the data set's seed (texture, Monte-Carlo noise); 0: the test's")
    p.add_argument("--picture", default=None, metavar="PNG",
                   help="also write the test views, ground truth above the render (3x)")
    a = p.parse_args(argv)
    out = Path(a.out)
    data = out / "data"
    if not (data / "transforms_test.json").is_file():
        make_scene("thin-parts", data, res=64, views=32, test_views=a.test_views,
                   seed=a.seed)
    cpu = torch.device("cpu")
    cfg, preset = preset_config(a.preset, data, 1, cpu)
    cfg.update({"train": {"sampler": "occupancy", "iters": a.iters}}, "bench.thin_parts")
    if a.config:
        cfg.update(read_config_file(a.config), a.config)
    run = out / "run"
    shutil.rmtree(run, ignore_errors=True)
    summary = train(data, run, cfg, cpu, progress=False, evaluate_test=False)
    test, render = stage1_renderer(run, data)

    parts = part_scores(data, test.images.numpy(), test.alpha.numpy(), render)
    if a.picture:
        cols = [np.concatenate([test.images[i].numpy(), render(i)[0]], 0)
                for i in range(len(test.images))]
        pic = np.kron(np.concatenate(cols, 1), np.ones((3, 3, 1)))
        iio.imwrite(a.picture, (pic.clip(0, 1) * 255).round().astype(np.uint8))
    emit_json({"preset": preset, "config": a.config, "iters": a.iters, "seed": a.seed,
               "train_s": summary["seconds"], "parts": parts,
               "rod_over_sphere": parts["rod"]["error"] / parts["sphere"]["error"],
               "plate_over_sphere": parts["plate"]["error"] / parts["sphere"]["error"]})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
