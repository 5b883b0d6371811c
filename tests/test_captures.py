"""The default preset keeps every object of small captures (slow: stage 1 for 1300 steps each).

`white-tube` on a baked-in white backdrop (alpha 255 everywhere): a white open tube before the
white background beside glossy solids of very different sizes; `off-centre` with a transparent
background: a fuzzy ball and a small sphere far from the box centre. Both 64 x 64, 40 training
views, `--preset auto`. Each object's test pixels (`scenes.parts.part_scores`) must come out
with a mean |error| within KEPT_FACTOR of the mean over all objects' pixels in stage 1's own
full-ray render, and the run must be healthy (`shells.train.health`). The whole pipeline on these
and more captures, band render included, is `python -m bench.captures` (BENCHMARKS.md)."""

from __future__ import annotations

import pytest
import torch

from scenes import make_scene
from scenes.parts import objects_kept, part_scores
from shells.data.datasets import has_transparency
from shells.presets import preset_config
from shells.train.stage1 import stage1_renderer, train

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("scene,backdrop", [("white-tube", (1.0, 1.0, 1.0)),
                                            ("off-centre", None)])
def test_the_default_keeps_every_object(tmp_path, scene, backdrop):
    data = tmp_path / "data"
    make_scene(scene, data, res=64, views=40, test_views=8, backdrop=backdrop)
    cpu = torch.device("cpu")
    cfg, name = preset_config("auto", data, 1, cpu)
    assert name == "object" and cfg.train.iters == 1300
    summary = train(data, tmp_path / "run", cfg, cpu, progress=False, evaluate_test=False)
    assert summary["health"]["ok"], summary["health"]["warnings"]
    assert summary["background"]["random"] == (backdrop is None)
    test, render = stage1_renderer(tmp_path / "run", data)
    alpha = test.alpha.numpy() if has_transparency(test.alpha) else None
    parts = part_scores(data, test.images.numpy(), alpha, render)
    kept = objects_kept(parts)
    assert kept["all"], kept["ratios"]
    assert all(v["pixels"] >= 40 for k, v in parts.items()), parts  # every object in view
