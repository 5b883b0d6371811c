"""Stage 2: fine-tuning inside the fixed shells (kill/resume determinism, shells untouched,
the renderer's sampling, colour loss only)."""

from __future__ import annotations

import hashlib
import json

import pytest
import torch

from shells.cli import finetune_main
from shells.config import toy_config
from shells.errors import InputError
from shells.finetune import finetune
from shells.pipeline import extract_run
from shells.run import load_field
from shells.training import train


def _tiny_config():
    cfg = toy_config()
    cfg.field.n_levels, cfg.field.log2_hashmap_size, cfg.field.max_resolution = 4, 12, 64
    cfg.train.iters, cfg.train.batch_rays = 4, 64
    cfg.train.n_samples, cfg.train.n_importance = 16, 8
    cfg.shell.resolution = 32
    cfg.finetune.iters, cfg.finetune.batch_rays = 6, 256
    cfg.finetune.checkpoint_every, cfg.finetune.log_every = 3, 1
    return cfg


@pytest.fixture(scope="module")
def stage1_run(tmp_path_factory):
    from tests.conftest import write_tiny_blender

    root = tmp_path_factory.mktemp("ft")
    data = write_tiny_blender(root / "data")
    run = root / "run"
    train(data, run, _tiny_config(), torch.device("cpu"), progress=False, evaluate_test=False)
    extract_run(run)
    return run


def _copy_run(src, dst):
    import shutil

    shutil.copytree(src, dst)
    return dst


def _digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_finetune_kill_resume_matches_and_keeps_shells(stage1_run, tmp_path):
    a = _copy_run(stage1_run, tmp_path / "a")
    shells_before = {p.name: _digest(p) for p in (a / "shells").glob("*.ply")}
    summary = finetune(a, progress=False)
    assert summary["step"] == 6 and (a / "finetune_summary.json").is_file()
    assert {p.name: _digest(p) for p in (a / "shells").glob("*.ply")} == shells_before
    # the field did change, and only through the colour loss inside the band
    f1, _ = load_field(a, stage="stage1")
    f2, _ = load_field(a, stage="stage2")
    changed = [n for (n, p1), (_, p2) in zip(f1.state_dict().items(), f2.state_dict().items())
               if not torch.equal(p1, p2)]
    assert changed
    log = [json.loads(ln) for ln in (a / "finetune_log.jsonl").open()]
    assert [r["step"] for r in log] == [1, 2, 3, 4, 5, 6]
    assert all(r["spp"] > 0 for r in log)  # the batches do hit the band
    # killed after the step-3 checkpoint (and before step 5's), then resumed
    b = _copy_run(stage1_run, tmp_path / "b")
    finetune(b, progress=False, stop_at=4)
    assert not (b / "finetune_summary.json").exists()  # unfinished
    ck = torch.load(b / "finetune.pt", weights_only=False)
    assert ck["step"] == 4
    c = _copy_run(stage1_run, tmp_path / "c")
    finetune(c, progress=False, stop_at=3)
    finetune(c, progress=False, resume=True)
    fa, _ = load_field(a, stage="stage2")
    fc, _ = load_field(c, stage="stage2")
    for (name, pa), (_, pc) in zip(fa.state_dict().items(), fc.state_dict().items()):
        torch.testing.assert_close(pa, pc, rtol=0, atol=0, msg=name)
    assert [json.loads(ln)["step"] for ln in (c / "finetune_log.jsonl").open()] == [1, 2, 3, 4, 5, 6]
    with pytest.raises(InputError, match="already"):
        finetune(a, progress=False)  # stage 2 exists: --resume or delete it


def test_finetune_cli_errors(stage1_run, tmp_path, capsys):
    bare = tmp_path / "bare"
    bare.mkdir()
    assert finetune_main([str(bare)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bare" in err[0]
    noshell = _copy_run(stage1_run, tmp_path / "noshell")
    import shutil

    shutil.rmtree(noshell / "shells")
    assert finetune_main([str(noshell)]) == 2
    err = capsys.readouterr().err.strip()
    assert "shells-extract" in err and not (noshell / "finetune.pt").exists()


def test_config_override_of_a_trained_run(stage1_run, tmp_path, capsys):
    """--config on extract / finetune / render changes only the allowed sections, is recorded,
    and a wrong section or value type is a one-line exit-2 error that writes nothing."""
    from shells.cli import extract_main, render_main

    run = _copy_run(stage1_run, tmp_path / "run")
    shell_cfg = tmp_path / "shell.json"
    shell_cfg.write_text(json.dumps({"shell": {"dilate_zeta": 0.2, "resolution": 24}}))
    assert extract_main([str(run), "--config", str(shell_cfg)]) == 0
    params = json.loads((run / "shells" / "stats.json").read_text())["params"]
    assert params["dilate_zeta"] == 0.2 and params["resolution"] == 24
    # the checkpoint's own config is untouched: a plain extract goes back to the run's zeta
    _, cfg = load_field(run, stage="stage1")
    assert cfg.shell.dilate_zeta == _tiny_config().shell.dilate_zeta != 0.2
    before = {p.name: _digest(p) for p in (run / "shells").iterdir()}

    bad_section = tmp_path / "field.json"
    bad_section.write_text(json.dumps({"field": {"n_levels": 2}}))
    assert extract_main([str(run), "--config", str(bad_section)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "field.json" in err[0] and "'shell'" in err[0]
    bad_type = tmp_path / "type.json"
    bad_type.write_text(json.dumps({"shell": {"dilate_zeta": "wide"}}))
    assert extract_main([str(run), "--config", str(bad_type)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "shell.dilate_zeta" in err[0] and "float" in err[0]
    assert {p.name: _digest(p) for p in (run / "shells").iterdir()} == before

    ft_cfg = tmp_path / "ft.json"
    ft_cfg.write_text(json.dumps({"finetune": {"iters": 2, "pixel_samples": 4},
                                  "render": {"delta_s": 0.05}}))
    assert finetune_main([str(run), "--config", str(shell_cfg)]) == 2
    assert not (run / "finetune.pt").exists()
    assert finetune_main([str(run), "--config", str(ft_cfg)]) == 0
    _, cfg2 = load_field(run, stage="stage2")
    assert cfg2.finetune.iters == 2 and cfg2.render.delta_s == 0.05
    log = [json.loads(ln) for ln in (run / "finetune_log.jsonl").open()]
    assert len(log) == 2 and log[-1]["spp"] > 0  # samples per pixel over its 4 rays
    capsys.readouterr()

    r_cfg = tmp_path / "render.json"
    r_cfg.write_text(json.dumps({"render": {"full_samples": 16}}))
    out = tmp_path / "full"
    assert render_main([str(run), "--mode", "full", "--config", str(r_cfg),
                        "--out", str(out)]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["render_config"]["full_samples"] == 16 and m["samples_per_pixel"] <= 16
    # spp = 4: four rays per pixel, their samples counted together
    r4_cfg = tmp_path / "render4.json"
    r4_cfg.write_text(json.dumps({"render": {"full_samples": 16, "spp": 4}}))
    out4 = tmp_path / "full4"
    assert render_main([str(run), "--mode", "full", "--config", str(r4_cfg),
                        "--out", str(out4)]) == 0
    m4 = json.loads((out4 / "metrics.json").read_text())
    assert m4["samples_per_pixel"] == pytest.approx(4 * m["samples_per_pixel"], rel=0.05)
    assert abs(m4["psnr"] - m["psnr"]) < 1.0  # the same field, box-filtered
    assert render_main([str(run), "--config", str(ft_cfg), "--out", str(tmp_path / "x")]) == 2
    assert not (tmp_path / "x").exists()
