"""shells-process-data: pose normalisation by hand, bad input, and COLMAP on lego (slow, data)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from shells.data.cameras import look_at
from shells.data.colmap import _rotation_to_z, focus_point, normalise_poses

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def test_focus_point_rotation_and_normalisation_by_hand():
    target = np.array([0.3, -0.2, 0.5])
    up = np.array([0.0, 1.0, 0.0])  # a capture whose "up" is world +y
    eyes = [target + 3.0 * np.array([math.cos(a), 0.4, math.sin(a)]) for a in
            np.linspace(0, 2 * math.pi, 7, endpoint=False)]
    c2w = np.stack([look_at(e, target, up).double().numpy() for e in eyes])
    np.testing.assert_allclose(focus_point(c2w), target, atol=1e-6)  # look_at is float32
    rot = _rotation_to_z(up)
    np.testing.assert_allclose(rot @ up, [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-12)
    out, pts, tf = normalise_poses(c2w, target[None])
    np.testing.assert_allclose(pts, 0.0, atol=1e-6)  # the focus point is the new origin
    assert np.abs(out[:, :3, 3]).max() == pytest.approx(1.0)  # cameras in the unit cube
    np.testing.assert_allclose(-out[:, :3, 1].mean(0) / np.linalg.norm(out[:, :3, 1].mean(0)),
                               [0, 0, 1], atol=1e-6)  # mean camera up is +z now
    fwd = out[:, :3, 2]  # still looking at the (new) origin
    np.testing.assert_allclose(np.einsum("ni,ni->n", fwd, -out[:, :3, 3])
                               / np.linalg.norm(out[:, :3, 3], axis=1), 1.0, atol=1e-6)
    assert tf["scale"] > 0 and len(tf["centre"]) == 3


def test_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys):
    from shells.cli import process_data_main

    out = tmp_path / "data"
    assert process_data_main([str(tmp_path / "nope"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope" in err[0]
    few = tmp_path / "few"
    few.mkdir()
    (few / "a.png").write_bytes(b"")
    assert process_data_main([str(few), "--out", str(out)]) == 2
    assert "at least 3" in capsys.readouterr().err
    for i in range(3):
        (few / f"{i}.png").write_bytes(b"")
    assert process_data_main([str(few), "--out", str(out), "--max-error", "0"]) == 2
    assert "--max-error 0" in capsys.readouterr().err
    out.mkdir()
    assert process_data_main([str(few), "--out", str(out)]) == 2
    assert "already exists" in capsys.readouterr().err
    assert {p.name for p in tmp_path.iterdir()} == {"few", "data"}  # no staging folder left
    assert not list(out.iterdir())


@pytest.mark.slow
@pytest.mark.data
@pytest.mark.skipif(not (DATA / "lego").is_dir(), reason="../shared/data/lego not present")
def test_colmap_recovers_the_lego_poses(tmp_path):
    """The 87 lego training views at 400x400 on white, poses withheld (about 100 s on 2 cores;
    COLMAP runs on one thread with a fixed seed, so a run repeats exactly): issue 16's criterion,
    >= 95 % of the 87 within 1 degree and 1 % of the camera-sphere radius after a similarity
    alignment (87 of 87 with the default guided matching and 2 px thresholds; 82 with COLMAP's
    defaults, BENCHMARKS.md), median errors well under that, the focal length within 3 %."""
    import imageio.v3 as iio

    from shells.data.datasets import load_dataset
    from shells.data.colmap import process_data

    src = tmp_path / "photos"
    src.mkdir()
    data = load_dataset(DATA / "lego", "train", downscale=2)  # composited on white
    for name, img in zip(data.names, data.images):
        iio.imwrite(src / f"{Path(name).stem}.png", (img.numpy() * 255).round().astype(np.uint8))
    summary = process_data(src, tmp_path / "colmap")
    assert summary["registered"] >= 83  # of 87
    from bench.colmap_accuracy import accuracy

    acc = accuracy(tmp_path / "colmap", DATA / "lego" / "transforms_train.json")
    assert acc["registered_fraction"] >= 0.95, acc
    assert acc["rotation_error_deg"]["median"] < 0.5, acc
    assert acc["position_error_of_radius"]["median"] < 0.01, acc
    assert acc["within_fraction_of_all"] >= 0.95, acc  # issue 16: >= 95 % within 1 deg / 1 %
    print(f"lego: {acc['within_1deg_1pct']} of {acc['true_images']} within 1 deg / 1 %")
    f_true = 0.5 * 400 / math.tan(0.5 * json.loads(
        (DATA / "lego" / "transforms_train.json").read_text())["camera_angle_x"])
    assert acc["fl_x"] == pytest.approx(f_true, rel=0.03)
    loaded = load_dataset(tmp_path / "colmap", "train")  # the loader reads what it wrote
    assert loaded.images.shape[1:3] == (400, 400) and torch.isfinite(loaded.aabb).all()
