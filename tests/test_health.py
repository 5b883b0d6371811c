"""A run that learnt nothing says so: the health checks of stage 1 and of shell extraction, and
the data-driven background (random backgrounds only where the alpha holds transparency, a
baked-in backdrop trained on its own colour)."""

from __future__ import annotations

import json
import math

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from shells.cli import extract_main
from shells.data.datasets import backdrop_colour, has_transparency
from shells.train.health import (SOLID_SHARE, STALL_DB, Stage1Health, degenerate_grid, psnr_floor,
                                 solid_share)
from tests.conftest import tiny_config, write_tiny_blender


def test_transparency_is_decided_from_the_values_not_the_channel():
    assert not has_transparency(None)
    assert not has_transparency(torch.ones(2, 8, 8))  # alpha 255 everywhere
    stray = torch.ones(10, 10, 10)
    stray[0, 0, 0] = 0.0  # one pixel in 1000: below TRANSPARENT_SHARE (1e-3)? equal -> yes
    assert has_transparency(stray)
    stray[0, 0, 0] = 0.6  # half transparent is not transparent
    assert not has_transparency(stray)


def test_backdrop_colour_is_the_uniform_border():
    img = torch.full((3, 10, 10, 3), 0.5)
    img[:, 3:7, 3:7] = torch.tensor([1.0, 0.0, 0.0])  # content inside the border
    assert backdrop_colour(img) == (0.5, 0.5, 0.5)
    img[:, :, :5] = torch.rand(3, 10, 5, 3)  # half the border is a scene, not a backdrop
    assert backdrop_colour(img) is None


def test_psnr_floor_is_the_better_of_blank_and_mean_colour():
    px = torch.tensor([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0]])
    # blank (white): mse 1/4 -> 6.02 dB; mean colour 0.75: mse (3 * 0.0625 + 0.5625) / 4 =
    # 0.1875 -> 7.27 dB
    assert psnr_floor(px, torch.ones(3)) == pytest.approx(-10 * math.log10(0.1875))
    assert psnr_floor(px, torch.zeros(3)) == pytest.approx(-10 * math.log10(0.1875))
    assert psnr_floor(px[:3], torch.ones(3)) == pytest.approx(100.0)  # blank is exact


def test_stage1_health_warns_once_per_kind():
    h = Stage1Health(floor_db=12.0, iters=1000)  # stall checked from step 250
    assert h.update(50, 13.0, 0.05) == []  # early: a low PSNR is not yet a stall
    assert len(h.update(100, 13.0, SOLID_SHARE + 0.01)) == 1  # solid
    assert h.update(150, 13.0, 0.99) == []  # said once
    new = h.update(250, 12.0 + STALL_DB - 0.5, 0.99)
    assert len(new) == 1 and "has not learnt" in new[0]
    s = h.summary()
    assert not s["ok"] and s["kinds"] == ["solid", "stalled"] and s["solid_share"] == 0.99
    ok = Stage1Health(floor_db=12.0, iters=1000)
    for k in range(50, 1001, 50):
        assert ok.update(k, 25.0, 0.1) == []
    assert ok.summary()["ok"]
    empty = Stage1Health(floor_db=12.0, iters=100)
    assert "is empty" in empty.update(100, 12.5, 0.0)[0]
    assert empty.summary()["kinds"] == ["empty"]


def test_degenerate_grid():
    f = torch.linspace(-1, 1, 1000)
    assert solid_share(f) == pytest.approx(0.5)
    assert degenerate_grid(f) is None
    assert "solid in 95%" in degenerate_grid(f - 0.9)
    assert "empty" in degenerate_grid(f.abs() + 0.1)


def _baked(root, grey: float = 0.5):
    """A tiny data set whose alpha is 255 everywhere over a uniform grey backdrop."""
    write_tiny_blender(root, res=16)
    for png in root.glob("*/r_*.png"):
        im = iio.imread(png).astype(np.float64)
        a = im[..., 3:] / 255.0
        rgb = np.round(im[..., :3] * a + 255.0 * grey * (1 - a))
        iio.imwrite(png, np.concatenate([rgb, np.full_like(a, 255)], -1).astype(np.uint8))
    return root


def test_a_baked_in_backdrop_is_trained_on_its_own_colour(tmp_path):
    from shells.train.stage1 import train
    from shells.presets import data_background, preset_config

    cpu = torch.device("cpu")
    clear = write_tiny_blender(tmp_path / "clear", res=16)
    assert data_background(clear, 1) is None  # transparent: composited on data.background
    baked = _baked(tmp_path / "baked")
    assert data_background(baked, 1) == (0.502, 0.502, 0.502)  # 128 / 255
    cfg, name = preset_config("auto", baked, 1, cpu)
    assert name == "object" and cfg.train.random_background
    assert cfg.data.background == (0.502, 0.502, 0.502)
    assert preset_config("toy", baked, 1, cpu)[0].data.background == (0.502, 0.502, 0.502)
    assert preset_config("auto", clear, 1, cpu)[0].data.background == (1.0, 1.0, 1.0)
    cfg.update({"train": {"iters": 2, "log_every": 1}, "field": {"n_levels": 4}}, "test")
    s = train(baked, tmp_path / "run", cfg, cpu, progress=False, evaluate_test=False)
    assert s["background"] == {"colour": [0.502, 0.502, 0.502], "random": False}
    cfg2, _ = preset_config("auto", clear, 1, cpu)
    cfg2.update({"train": {"iters": 2, "log_every": 1}, "field": {"n_levels": 4}}, "test")
    s2 = train(clear, tmp_path / "run2", cfg2, cpu, progress=False, evaluate_test=False)
    assert s2["background"]["random"]


def test_a_solid_field_is_reported_and_not_extracted(tmp_path, capsys):
    """The field starts solid in the whole box (an initial sphere of radius 10 around a box of
    half-width 1) and does not learn (learning rates 1e-12): stage 1 says so in one line and
    in its summary, and shells-extract refuses it with exit status 2, writing nothing."""
    from shells.train.stage1 import train

    data = write_tiny_blender(tmp_path / "data", res=16)
    cfg = tiny_config(train_iters=6)
    cfg.update({"field": {"init_radius": 10.0},
                "train": {"lr": 1e-12, "lr_mlp": 1e-12, "log_every": 3}}, "test")
    run = tmp_path / "run"
    summary = train(data, run, cfg, torch.device("cpu"), progress=False, evaluate_test=False)
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("warning: ")]
    assert len(lines) >= 1 and "solid in 100% of the scene box" in lines[0]
    assert len([ln for ln in lines if "solid" in ln]) == 1  # once, not at every probe
    health = json.loads((run / "train_summary.json").read_text())["health"]
    assert health == summary["health"] and not health["ok"] and "solid" in health["kinds"]
    logs = [json.loads(ln) for ln in (run / "train_log.jsonl").read_text().splitlines()]
    assert [r["solid"] for r in logs] == [1.0, 1.0]
    assert extract_main([str(run)]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if "error" in ln]  # not the bar
    assert len(err) == 1 and "degenerate field, not extracted" in err[0]
    assert "checkpoint.pt" in err[0] and '"background"' in err[0]
    assert not (run / "shells").exists()


def test_a_healthy_tiny_run_has_no_warning(tmp_path, capsys):
    from shells.train.stage1 import train

    data = write_tiny_blender(tmp_path / "data", res=16)
    cfg = tiny_config(train_iters=4)
    summary = train(data, tmp_path / "run", cfg, torch.device("cpu"), progress=False,
                    evaluate_test=False)
    assert "warning" not in capsys.readouterr().err
    assert summary["health"]["solid_share"] < 0.2 and "solid" not in summary["health"]["kinds"]
