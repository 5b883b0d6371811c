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
from shells.training import load_field, train


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
