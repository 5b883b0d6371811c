"""Stage 2: fine-tuning inside the fixed shells (kill/resume determinism, shells untouched,
the renderer's sampling, the anchor outside M+)."""

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
    # the field did change
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


def _sphere_scene(r_outer=0.5, r_inner=0.3):
    import trimesh

    from shells.render.raycast import ShellScene

    o = trimesh.creation.icosphere(subdivisions=4, radius=r_outer)
    i = trimesh.creation.icosphere(subdivisions=4, radius=r_inner)
    return ShellScene((o.vertices, o.faces), (i.vertices, i.faces))


def test_outside_outer_is_the_complement_of_m_plus():
    """Points of a sphere pair's box: outside M+ (radius 0.5) exactly where |x| > 0.5; the
    band (0.3 < |x| < 0.5) and M- (|x| < 0.3) are inside. Points within 0.02 of a sphere are
    left out (the icosphere's chords lie up to 0.002 inside the sphere)."""
    from shells.train.stage2 import outside_outer

    g = torch.Generator().manual_seed(0)
    x = torch.rand(20000, 3, generator=g) * 1.6 - 0.8
    r = x.norm(dim=-1)
    x = x[((r - 0.5).abs() > 0.02) & ((r - 0.3).abs() > 0.02)]
    r = x.norm(dim=-1)
    out = outside_outer(_sphere_scene(), x)
    assert torch.equal(out, r > 0.5)
    assert (r < 0.3).sum() > 100 and ((r > 0.3) & (r < 0.5)).sum() > 100  # all three drawn


def test_anchor_holds_the_field_outside_m_plus_only():
    """The anchor is 0 for the stage-1 field itself; a field whose kernel and SDF moved gives
    |log ratio of s| + |shift of f| / the box's side, hand-worked; its gradient reaches the
    field and not the frozen stage-1 copy; with M+ filling the box nothing is anchored."""
    import copy

    from shells.config import FieldConfig
    from shells.fields.network import ShellField
    from shells.train.stage2 import anchor_loss

    torch.manual_seed(0)
    field = ShellField(FieldConfig(n_levels=4, log2_hashmap_size=12, max_resolution=64),
                       torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    stage1 = copy.deepcopy(field).requires_grad_(False)
    scene = _sphere_scene()
    gen = lambda: torch.Generator().manual_seed(3)  # noqa: E731
    assert anchor_loss(field, stage1, scene, 4096, gen()).item() == 0.0

    class Moved(torch.nn.Module):  # f + 0.2, s x 2 (log 2), everything else the same
        def __init__(self, base):
            super().__init__()
            self.base, self.aabb, self.similarity = base, base.aabb, None
            self.shift = torch.nn.Parameter(torch.tensor(0.2))

        def geometry(self, x):
            g = dict(self.base.geometry(x))
            g["sdf"], g["s"] = g["sdf"] + self.shift, g["s"] * 2.0
            return g

    moved = Moved(field)
    loss = anchor_loss(moved, stage1, scene, 4096, gen())
    assert loss.item() == pytest.approx(torch.log(torch.tensor(2.0)).item() + 0.2 / 2.0,
                                        rel=1e-5)
    loss.backward()
    assert moved.shift.grad.item() == pytest.approx(1.0 / 2.0)  # d|f - f1| / side
    assert all(p.grad is None for p in stage1.parameters())
    big = _sphere_scene(r_outer=5.0, r_inner=0.1)  # M+ holds the whole box
    assert anchor_loss(moved, stage1, big, 4096, gen()).item() == 0.0


def test_anchor_points_of_an_unbounded_field_map_back_to_field_space():
    """An unbounded field's anchor points: the world points map to the drawn field-space
    points (W(x) = z), and none lies at contracted radius 1.99 or beyond."""
    from shells.config import FieldConfig
    from shells.fields.network import ShellField
    from shells.train.stage2 import MAX_CONTRACTED, anchor_points

    cfg = FieldConfig(n_levels=4, log2_hashmap_size=12, max_resolution=64, unbounded=True,
                      centre=(0.5, 0.0, -0.5), radius=2.0)
    c, r = torch.tensor(cfg.centre), cfg.radius
    field = ShellField(cfg, torch.stack([c - 2 * r, c + 2 * r]))
    z, x = anchor_points(field, 5000, torch.Generator().manual_seed(0))
    assert 2400 < len(z) < 2800  # kept: the ball of 1.99 in the cube of 2, 51.6 %
    assert ((z - c).norm(dim=-1) / r).max() < MAX_CONTRACTED
    assert torch.allclose(field.to_field(x), z, atol=1e-4)
    assert ((x - c).norm(dim=-1) / r).max() > 5.0  # far points are far in the world


def test_anchor_keeps_the_kernel_outside_m_plus(stage1_run, tmp_path):
    """Stage 2 with and without the anchor from the same stage-1 field: with it, the field
    outside M+ stays nearer its stage-1 values."""
    from shells.run import RunDir, load_shells
    from shells.train.stage2 import anchor_loss

    dev = {}
    for w in (0.0, 10.0):
        run = _copy_run(stage1_run, tmp_path / f"w{w}")
        (run / "w.json").write_text(json.dumps({"finetune": {"anchor_weight": w, "iters": 30,
                                                             "lr": 3e-2}}))
        finetune(run, progress=False, config=run / "w.json")
        f1, _ = load_field(run, stage="stage1")
        f2, _ = load_field(run, stage="stage2")
        scene = load_shells(RunDir(run), None)
        with torch.no_grad():
            dev[w] = anchor_loss(f2, f1, scene, 20000, torch.Generator().manual_seed(9)).item()
    assert dev[0.0] > 0 and dev[10.0] < 0.5 * dev[0.0]


def test_step_bench_times_the_anchor(stage1_run, capsys):
    """`python -m bench.step_speed stage2 RUN --anchor`: each shard count without and with the
    anchor, in that order."""
    from bench.step_speed import main

    assert main(["stage2", str(stage1_run), "--shards", "1", "--steps", "1", "--anchor"]) == 0
    rows = json.loads(capsys.readouterr().out)["rows"]
    assert [(r["shards"], r["anchor"]) for r in rows] == [(1, False), (1, True)]
    assert all(r["s_per_step"] > 0 for r in rows)


def test_drift_diagnostic_of_a_stage_2_that_did_not_move(stage1_run, tmp_path, capsys):
    """`python -m bench.diagnostics drift RUN` on a stage 2 whose learning rates are 1e-12:
    both fields pass the occupancy test at the same points, none newly, and s2 / s1 = 1,
    f2 - f1 = 0 where stage 1 is empty."""
    from bench.diagnostics import main

    run = _copy_run(stage1_run, tmp_path / "still")
    (run / "still.json").write_text(json.dumps({"finetune": {"lr": 1e-12, "lr_mlp": 1e-12}}))
    finetune(run, progress=False, config=run / "still.json")
    assert main(["drift", str(run), "--points", "20000"]) == 0
    out = json.loads(capsys.readouterr().out)
    occ = out["occupied_share"]
    assert 0 < occ["stage1"] < 1 and occ["stage2"] == occ["stage1"]
    assert out["newly_occupied_share"] == 0
    ratio, shift = out["empty_in_stage1"]["s2_over_s1"], out["empty_in_stage1"]["f2_minus_f1"]
    assert all(abs(ratio[k] - 1) < 1e-5 and abs(shift[k]) < 1e-5 for k in ("p5", "p50", "p95"))


def test_band_check_in_the_stage_2_summary(stage1_run, tmp_path, capsys):
    """A finished stage 2 scores the band against full ray on the same training pixels: its
    summary holds both PSNRs and their difference, and shells-finetune prints them; with the
    shells moved off the object (the band then sees empty space) the band falls far under full
    ray and the check says so."""
    import shutil

    import numpy as np
    import trimesh

    from shells.train.health import BAND_CHECK_DB

    a = _copy_run(stage1_run, tmp_path / "a")
    assert finetune_main([str(a)]) == 0
    out = capsys.readouterr().out
    check = json.loads((a / "finetune_summary.json").read_text())["band_check"]
    assert check["pixels"] == 4096 and check["band_spp"] > 0
    assert check["gap_db"] == pytest.approx(check["band_psnr"] - check["full_psnr"])
    assert f"full ray {check['full_psnr']:.2f} dB" in out
    b = _copy_run(stage1_run, tmp_path / "b")
    for name in ("outer.ply", "inner.ply"):  # both shells shifted far along x
        mesh = trimesh.load(b / "shells" / name, process=False)
        mesh.apply_translation(np.array([50.0, 0.0, 0.0]))
        mesh.export(b / "shells" / name)
    shutil.rmtree(b / "shells" / "lod", ignore_errors=True)
    summary = finetune(b, progress=False)
    moved = summary["band_check"]
    assert moved["gap_db"] < -BAND_CHECK_DB and "under full ray" in moved["warning"]
