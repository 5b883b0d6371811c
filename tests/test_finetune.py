"""Stage 2: fine-tuning inside the fixed shells (kill/resume determinism, shells untouched,
the renderer's sampling, colour loss only)."""

from __future__ import annotations

import hashlib
import json

import pytest
import torch

from shells.cli import finetune_main
from shells.errors import InputError
from shells.train.stage2 import finetune
from shells.run import load_field
from tests.conftest import tiny_config, trained_run


def _tiny_config():
    return tiny_config()


@pytest.fixture(scope="module")
def stage1_run(tmp_path_factory):
    return trained_run(tmp_path_factory.mktemp("ft"), _tiny_config())


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
    capsys.readouterr()  # the successful extract's progress bars

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


def test_one_loop_for_both_stages(stage1_run, tmp_path):
    """Stage 1 and stage 2 log the same fields; stage 2's schedule comes from its config
    (warm-up, final factor); the summaries mark finished stages; stats.json has one timing key."""
    from shells.train.loop import lr_factor
    from shells.run import RunDir, read_log

    run = _copy_run(stage1_run, tmp_path / "run")
    cfg_file = tmp_path / "ft.json"
    cfg_file.write_text(json.dumps({"finetune": {"warmup_iters": 2, "lr_final_factor": 0.5}}))
    finetune(run, progress=False, config=cfg_file, device="cpu")
    r = RunDir(run)
    s1, s2 = read_log(r.log("stage1")), read_log(r.log("stage2"))
    common = {"step", "loss", "psnr", "rays_per_s", "elapsed_s"}
    assert common <= set(s1[-1]) and common <= set(s2[-1])
    ck = torch.load(r.checkpoint("stage2"), weights_only=False)
    fc = ck["config"]["finetune"]
    assert (fc["warmup_iters"], fc["lr_final_factor"]) == (2, 0.5)
    for g in ck["optimizer"]["param_groups"]:  # the lr of the last step (step 5 of 6)
        assert g["lr"] == pytest.approx(g["base_lr"] * lr_factor(5, 6, 2, 0.5))
    assert lr_factor(5, 6, 2, 0.5) != pytest.approx(lr_factor(5, 6, 0, 0.1))  # not the default
    summary = json.loads(r.summary("stage2").read_text())
    assert summary["finished"] and summary["step"] == 6 and summary["rays_per_s"] > 0
    stats = json.loads((r.shells / "stats.json").read_text())
    assert "timings" not in stats and {"sample_grid", "evolve", "total"} <= set(stats["timings_s"])


def test_run_layer_messages_and_loaded_stage(stage1_run, tmp_path, capsys):
    """load_field(stage2) without stage 2 names shells-finetune; metrics.json says which
    checkpoint was loaded, not 'latest'."""
    from shells.cli import render_main

    run = _copy_run(stage1_run, tmp_path / "run")
    with pytest.raises(InputError, match="shells-finetune"):
        load_field(run, stage="stage2")
    out = tmp_path / "band"
    assert render_main([str(run), "--out", str(out)]) == 0  # --stage latest (the default)
    assert json.loads((out / "metrics.json").read_text())["stage"] == "stage1"
    capsys.readouterr()  # the progress bars of that render
    assert render_main([str(run), "--stage", "stage2", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "shells-finetune" in err[-1] and not (tmp_path / "x").exists()


def test_stage2_device_and_variant_agree():
    """The Mitsuba variant follows the torch device; a variant for another device is an error."""
    from shells.device import mitsuba_variant

    assert mitsuba_variant(None, "cpu") == "llvm_ad_rgb"
    assert mitsuba_variant("llvm_ad_rgb", torch.device("cpu")) == "llvm_ad_rgb"
    with pytest.raises(InputError, match="render.variant"):
        mitsuba_variant("cuda_ad_rgb", "cpu")
    mitsuba_variant("llvm_ad_rgb")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_finetune_on_cuda_tracks_cpu(stage1_run, tmp_path):
    """Stage 2 on CUDA (cuda_ad_rgb ray casting, CUDA field and generators): it runs, and the
    losses follow the CPU run's (different random streams on another device: not bit-exact)."""
    from shells.device import mitsuba_variant
    from shells.run import RunDir, read_log

    try:
        cpu = _copy_run(stage1_run, tmp_path / "cpu")
        finetune(cpu, progress=False, device="cpu")
        gpu = _copy_run(stage1_run, tmp_path / "gpu")
        finetune(gpu, progress=False, device="cuda")
        a, b = read_log(RunDir(cpu).log("stage2")), read_log(RunDir(gpu).log("stage2"))
        assert [r["step"] for r in b] == [1, 2, 3, 4, 5, 6]
        assert abs(a[-1]["psnr"] - b[-1]["psnr"]) < 3.0 and b[-1]["spp"] > 0
        f, _ = load_field(gpu, stage="stage2")
        assert all(torch.isfinite(p).all() for p in f.parameters())
    finally:
        mitsuba_variant("llvm_ad_rgb")
