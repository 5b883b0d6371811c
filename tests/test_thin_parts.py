"""Stage 1 keeps separate objects and thin parts (issue 13): the `thin-parts` toy scene, a
textured sphere off the centre beside a rod 0.05 thick (1.6 px) over a plate 0.03 thick.

The field starts as a sphere at the box centre. Stage 1 is the real-object preset
(`--preset object`, sized from the data: a 128-cell finest level here, the occupancy sampler,
the weak Eikonal term 0.005, random backgrounds) for 1500 of its 3000 steps. The test views'
pixels that see the rod and the plate (their centre ray hits it first and the ground truth is
opaque there) are compared with the sphere's: both must come out opaque, with an error no
larger than the sphere's (on this data set 0.59x and 0.77x; BENCHMARKS.md, "Issue 13"). The
toy preset (Eikonal 0.1, which its sphere's SDF accuracy rests on) keeps the plate but not
reliably the rod, at 6x the sphere's error."""

from __future__ import annotations

import pytest
import torch

from scenes import make_scene
from scenes.parts import PARTS, part_scores
from shells.presets import preset_config
from shells.train.stage1 import stage1_renderer, train

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("thin")
    data = root / "data"
    make_scene("thin-parts", data, res=64, views=32, test_views=6)
    cfg, preset = preset_config("object", data, 1, torch.device("cpu"))
    assert cfg.train.sampler == "occupancy" and cfg.train.eikonal_weight == 0.005
    cfg.update({"train": {"iters": 1500}}, "test")
    train(data, root / "run", cfg, torch.device("cpu"), progress=False, evaluate_test=False)
    return data, root / "run"


def test_the_thin_rod_and_plate_are_kept(trained) -> None:
    data, run = trained
    test, render = stage1_renderer(run, data)
    parts = part_scores(data, test.images.numpy(), test.alpha.numpy(), render)
    sphere, rod, plate = (parts[k] for k in PARTS)
    assert rod["pixels"] >= 20 and plate["pixels"] >= 20, "too few rod / plate pixels"
    for name, part in (("rod", rod), ("plate", plate)):
        assert part["opacity"] >= 0.9, f"{name}: mean opacity {part['opacity']:.3f}"
        assert part["error"] <= sphere["error"], (
            f"{name}: mean |error| {part['error']:.4f} > sphere's {sphere['error']:.4f}")
