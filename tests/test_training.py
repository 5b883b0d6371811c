"""Stage-1 training: schedule numbers, kill/resume determinism, CLI errors."""

from __future__ import annotations

import json
import math

import pytest
import torch

from shells.cli import train_main
from shells.presets import toy_config
from shells.errors import InputError
from shells.train.loop import lr_factor
from shells.run import load_field
from shells.train.stage1 import train


def test_fused_adam_matches_the_reference_adam():
    """make_optimizer's fused Adam makes the updates of torch's per-tensor Adam (float32
    rounding apart), hash-table rows without gradient (zeros) included."""
    from tests.conftest import tiny_config
    from shells.train.optim import make_optimizer
    from shells.train.stage1 import build_field

    cfg = tiny_config()
    aabb = torch.tensor([[-1.0] * 3, [1.0] * 3])
    fast, ref = build_field(cfg, aabb, torch.device("cpu")), build_field(cfg, aabb,
                                                                          torch.device("cpu"))
    opt = make_optimizer(fast, 1e-2, 1e-3, sink=False)
    assert all(g["fused"] for g in opt.param_groups)
    reference = make_optimizer(ref, 1e-2, 1e-3, sink=False)  # the same groups, on torch's per-tensor loop
    for g in reference.param_groups:
        g.update(fused=False, foreach=False)
    init = build_field(cfg, aabb, torch.device("cpu")).state_dict()
    gen = torch.Generator().manual_seed(0)
    for _ in range(5):
        for p, q in zip(fast.parameters(), ref.parameters()):
            grad = torch.randn(p.shape, generator=gen)
            grad[torch.rand(p.shape, generator=gen) < 0.5] = 0.0  # rows no ray touched
            p.grad, q.grad = grad.clone(), grad.clone()
        opt.step()
        reference.step()
    moved = 0.0
    for (name, p), q in zip(fast.named_parameters(), ref.parameters()):
        torch.testing.assert_close(p, q, rtol=1e-5, atol=1e-6, msg=name)
        moved = max(moved, float((p.detach() - init[name]).abs().max()))
    assert moved > 1e-3  # the test did move the parameters


def test_lr_schedule_hand_worked():
    # warm-up: (step + 1) / warmup; then cosine from 1 down to `final`
    assert lr_factor(0, 100, 10, 0.1) == pytest.approx(0.1)
    assert lr_factor(9, 100, 10, 0.1) == pytest.approx(1.0)
    assert lr_factor(10, 100, 10, 0.1) == pytest.approx(1.0)
    assert lr_factor(55, 100, 10, 0.1) == pytest.approx(0.55)  # half-way: (1 + 0.1) / 2
    assert lr_factor(100, 100, 10, 0.1) == pytest.approx(0.1)


def _tiny_config(sampler: str = "box"):
    cfg = toy_config()
    cfg.field.n_levels, cfg.field.log2_hashmap_size, cfg.field.max_resolution = 4, 12, 64
    cfg.train.iters, cfg.train.batch_rays = 6, 64
    cfg.train.n_samples, cfg.train.n_importance = 16, 8
    cfg.train.checkpoint_every, cfg.train.log_every, cfg.train.warmup_iters = 3, 1, 2
    if sampler == "occupancy":  # grid rebuilt at steps 2 and 4: the step-3 checkpoint holds
        # the grid of step 2, which the resume must restore; coarse-to-fine over the run too
        cfg.update({"train": {"sampler": "occupancy", "occ_warmup": 2, "occ_every": 2,
                              "occ_resolution": 16, "coarse_to_fine_iters": 5,
                              "coarse_to_fine_start": 2}})
    return cfg


def test_trainer_renders_at_eval_density(tiny_blender, tmp_path):
    """``eval_density`` k: the test PSNR and the running curve render k times the training's
    coarse and importance samples a ray, exactly as a run of that many samples would."""
    import dataclasses
    from shells.data.datasets import load_dataset
    from shells.train.stage1 import RunningCurve, build_field, eval_samples, evaluate

    cpu = torch.device("cpu")
    tc = _tiny_config().train
    test = load_dataset(tiny_blender, "test")
    field = build_field(_tiny_config(), test.aabb, cpu)
    dense = dataclasses.replace(tc, eval_density=2)
    doubled = dataclasses.replace(tc, n_samples=32, n_importance=16)
    assert eval_samples(dense) == (32, 16) and eval_samples(tc) == (16, 8)
    with torch.no_grad():
        at2, ref, at1 = (evaluate(field, test, c)["psnr_per_view"] for c in (dense, doubled, tc))
    assert at2 == ref and at2 != at1
    for c in (dense, doubled):  # the curve's pixels and samples: the same record both ways
        RunningCurve(test, dataclasses.replace(c, curve_pixels=64), tmp_path / "c.jsonl",
                     cpu).point(field, None, 1, 0.0)
    a, b = (json.loads(ln)["psnr"] for ln in (tmp_path / "c.jsonl").open())
    assert a == b


@pytest.mark.parametrize("sampler", ["box", "occupancy"])
def test_kill_and_resume_matches_uninterrupted(tiny_blender, tmp_path, sampler):
    cpu = torch.device("cpu")
    cfg = lambda: _tiny_config(sampler)  # noqa: E731
    train(tiny_blender, tmp_path / "a", cfg(), cpu, progress=False, evaluate_test=False)
    # "killed" after step 4: the last checkpoint is from step 3, so steps 4-6 are redone
    train(tiny_blender, tmp_path / "b", cfg(), cpu, progress=False, stop_at=4,
          evaluate_test=False)
    ckpt = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=False)
    assert ckpt["step"] == 4
    if sampler == "occupancy":
        assert ckpt["extra"]["occ"].shape == (16, 16, 16)
    # simulate the crash before the step-4 checkpoint: roll back to an earlier state
    train(tiny_blender, tmp_path / "c", cfg(), cpu, progress=False, stop_at=3,
          evaluate_test=False)
    train(tiny_blender, tmp_path / "c", cfg(), cpu, progress=False, resume=True,
          evaluate_test=False)
    fa, _ = load_field(tmp_path / "a")
    fc, _ = load_field(tmp_path / "c")
    for (name, pa), (_, pc) in zip(fa.state_dict().items(), fc.state_dict().items()):
        torch.testing.assert_close(pa, pc, rtol=0, atol=0, msg=name)
    steps = [json.loads(ln)["step"] for ln in (tmp_path / "c" / "train_log.jsonl").open()]
    assert steps == [1, 2, 3, 4, 5, 6]  # one record per step, none duplicated by the resume


def test_running_curve_scores_fixed_test_pixels_without_touching_training(tiny_blender,
                                                                            tmp_path):
    """RUN/train_curve.jsonl: every curve_every steps the PSNR of a fixed pixel subset of
    evenly spaced test views; with every pixel drawn it is the views' pooled PSNR as
    `evaluate` renders them. The curve leaves the training's random streams alone, survives a
    kill / resume without duplicate points, and wall_s adds up over the sittings."""
    from shells.train.stage1 import evaluate
    from shells.data.datasets import load_dataset

    cpu = torch.device("cpu")

    def cfg(curve: bool):
        c = _tiny_config()
        if curve:  # the tiny set's test views are 16 x 16: 256 pixels is all of them
            c.update({"train": {"curve_every": 2, "curve_views": 3, "curve_pixels": 256}})
        return c

    with_curve = train(tiny_blender, tmp_path / "a", cfg(True), cpu, progress=False,
                       evaluate_test=False)
    train(tiny_blender, tmp_path / "b", cfg(False), cpu, progress=False, evaluate_test=False)
    fa, _ = load_field(tmp_path / "a")
    fb, _ = load_field(tmp_path / "b")
    for (name, pa), (_, pb) in zip(fa.state_dict().items(), fb.state_dict().items()):
        torch.testing.assert_close(pa, pb, rtol=0, atol=0, msg=name)
    assert not (tmp_path / "b" / "train_curve.jsonl").exists()

    points = [json.loads(ln) for ln in (tmp_path / "a" / "train_curve.jsonl").open()]
    assert [p["step"] for p in points] == [2, 4, 6]
    assert all(p["views"] == [0, 1] and p["pixels"] == 512 for p in points)  # 2 test views
    walls = [p["wall_s"] for p in points]
    assert walls == sorted(walls) and 0 < walls[-1] <= with_curve["wall_s"]
    test = load_dataset(tiny_blender, "test")
    per_view = evaluate(fa, test, cfg(True).train)["psnr_per_view"]
    pooled = -10 * math.log10(sum(10 ** (-p / 10) for p in per_view) / len(per_view))
    assert points[-1]["psnr"] == pytest.approx(pooled, abs=1e-3)

    train(tiny_blender, tmp_path / "c", cfg(True), cpu, progress=False, stop_at=4,
          evaluate_test=False)
    first = torch.load(tmp_path / "c" / "checkpoint.pt", weights_only=False)["wall_s"]
    resumed = train(tiny_blender, tmp_path / "c", cfg(True), cpu, progress=False, resume=True,
                    evaluate_test=False)
    again = [json.loads(ln) for ln in (tmp_path / "c" / "train_curve.jsonl").open()]
    assert [p["step"] for p in again] == [2, 4, 6]
    assert resumed["wall_s"] == pytest.approx(first + resumed["seconds"])


def test_occupancy_steps_draw_until_the_batch_crosses_the_grid(tiny_blender):
    """The "occupancy" sampler: pixels are drawn until batch_rays of them cross an occupied
    cell; the rest cost no samples but enter the loss."""
    from shells.data.datasets import load_dataset
    from shells.render.volume import SpanGrid
    from shells.train.stage1 import build_field, draw_pixels, stage1_step

    cfg = _tiny_config("occupancy")
    data = load_dataset(tiny_blender, "train")
    field = build_field(cfg, data.aabb, torch.device("cpu"))
    grid = SpanGrid(field.aabb, 16, cfg.train.occ_k)
    grid.update(field)  # the initial sphere of radius 0.5: a shell of cells
    assert 0.0 < grid.fraction < 0.7
    gen = torch.Generator().manual_seed(0)
    idx, o, d, near, far, hit, crosses = draw_pixels(data, grid, 64, 1, gen)
    assert int(crosses.sum()) == 64 and bool(crosses[-1])  # cut after the 64th crossing pixel
    assert len(idx) > 64  # some drawn pixels crossed nothing
    assert torch.equal(crosses, hit)  # one ray per pixel
    pixels = data.images.reshape(-1, 3)
    loss, logs = stage1_step(field, data, pixels, cfg.train, torch.ones(3),
                             torch.Generator().manual_seed(0), grid)
    assert logs["rays"] == len(idx)
    assert logs["samples"] == 64 * (cfg.train.n_samples + cfg.train.n_importance)
    loss.backward()
    assert field.rad_mlp[0].weight.grad.abs().sum() > 0  # (hash weights start at zero)


def test_occupancy_rescue_renders_lost_content_on_the_whole_chord(tiny_blender):
    """``occ_rescue``: a drawn pixel that crosses no occupied cell but whose target is not its
    background is rendered on its whole box chord (content the grid lost); the others that
    cross nothing still cost no samples."""
    from shells.data.datasets import load_dataset
    from shells.render.volume import SpanGrid
    from shells.train.stage1 import build_field, draw_pixels, stage1_step

    cfg = _tiny_config("occupancy")
    data = load_dataset(tiny_blender, "train")
    field = build_field(cfg, data.aabb, torch.device("cpu"))
    grid = SpanGrid(field.aabb, 16, cfg.train.occ_k)
    grid.update(field)
    grid.occ[:, :, grid.N // 2:] = False  # the grid lost the upper half of the sphere
    pixels = data.images.reshape(-1, 3)
    idx, _, _, _, _, _, crosses = draw_pixels(data, grid, 64, 1, torch.Generator().manual_seed(0))
    lost = ~crosses & ((pixels[idx] - 1.0).abs().amax(-1) > 0.05)
    assert int(lost.sum()) > 0 and int((~crosses & ~lost).sum()) > 0
    per_ray = cfg.train.n_samples + cfg.train.n_importance
    cfg.train.occ_rescue = 0.05
    _, logs = stage1_step(field, data, pixels, cfg.train, torch.ones(3),
                          torch.Generator().manual_seed(0), grid)
    assert logs["rescued"] == int(lost.sum()) and logs["rays"] == len(idx)
    assert logs["samples"] == (64 + int(lost.sum())) * per_ray
    cfg.train.occ_rescue = 0.0
    _, logs = stage1_step(field, data, pixels, cfg.train, torch.ones(3),
                          torch.Generator().manual_seed(0), grid)
    assert logs["rescued"] == 0 and logs["samples"] == 64 * per_ray


def test_normal_term_delayed_and_ramped_in(tiny_blender):
    """normal_delay / normal_ramp: the normal term's weight is 0, then rises linearly; the
    step's loss holds exactly that share of it (same draw at every step number)."""
    from shells.data.datasets import load_dataset
    from shells.train.stage1 import build_field, normal_factor, stage1_step

    cfg = _tiny_config()
    cfg.update({"train": {"normal_delay": 3, "normal_ramp": 4, "normal_weight": 0.5}})
    tc = cfg.train
    assert [normal_factor(k, tc) for k in (0, 2, 3, 4, 6, 7, 100)] == [0, 0, 0.25, 0.5, 1, 1, 1]
    cfg.update({"train": {"normal_delay": 0, "normal_ramp": 0}})
    assert normal_factor(0, cfg.train) == 1.0  # the default: on from the start
    cfg.update({"train": {"normal_delay": 3, "normal_ramp": 4}})
    data = load_dataset(tiny_blender, "train")
    field = build_field(cfg, data.aabb, torch.device("cpu"))
    pixels = data.images.reshape(-1, 3)
    losses = {}
    for k in (0, 4, 9):
        loss, logs = stage1_step(field, data, pixels, tc, torch.ones(3),
                                 torch.Generator().manual_seed(0), None, k)
        losses[k] = (loss.item(), logs)
    base = losses[0][0]
    normal = losses[0][1]["normal"]
    assert normal > 0 and losses[0][1]["w_normal"] == 0.0
    assert losses[4][0] == pytest.approx(base + 0.5 * 0.5 * normal, rel=1e-6)
    assert losses[9][0] == pytest.approx(base + 0.5 * normal, rel=1e-6)
    with pytest.raises(InputError, match="normal_ramp"):
        cfg.update({"train": {"normal_ramp": -1}})


def test_coarse_to_fine_switches_levels_on():
    from shells.fields.network import ShellField
    from shells.train.stage1 import active_levels

    cfg = _tiny_config()
    cfg.update({"train": {"coarse_to_fine_iters": 10, "coarse_to_fine_start": 2}})
    assert [active_levels(k, cfg.train, 4) for k in (0, 4, 5, 9, 10)] == [2, 2, 3, 3, None]
    field = ShellField(cfg.field, torch.tensor([[-1.0] * 3, [1.0] * 3]))
    with torch.no_grad():  # hash features and the weights reading them (zero at init) random
        field.grid.params.uniform_(-1, 1)
        field.geo_mlp[0].weight[:, 3:].normal_()
    x = torch.rand(50, 3) * 2 - 1
    full = field.geometry(x)["sdf"]
    field.active_levels = 2
    part = field.geometry(x)["sdf"]
    F = cfg.field.n_features_per_level
    w = field.geo_mlp[0].weight.detach().clone()
    with torch.no_grad():  # the same as zeroing the weights that read levels 2 and 3
        field.geo_mlp[0].weight[:, 3 + 2 * F:] = 0
        field.active_levels = None
        torch.testing.assert_close(field.geometry(x)["sdf"], part)
        field.geo_mlp[0].weight.copy_(w)
    assert not torch.allclose(full, part)


def test_object_preset_schedule_follows_the_training_pixels():
    from shells.presets import object_finetune_iters, object_iters

    # 3000 steps per doubling at 870 000 pixels (lego 1/8: 87 views of 100 x 100) and above;
    # sqrt of the pixel share below, at least 1000
    assert object_iters(0, 87 * 100 * 100) == 3000 and object_iters(1, 87 * 200 * 200) == 6000
    assert object_iters(0, 4e6) == 3000
    assert object_iters(0, 40 * 64 * 64) == 1300  # sqrt(163 840 / 870 000) = 0.434
    assert object_iters(0, 48 * 128 * 128) == 2900  # sqrt(786 432 / 870 000) = 0.951
    assert object_iters(0, 10) == 1000
    # stage 2: 1500 steps (1000 more per doubling above 512) on the same share, at least 500
    assert object_finetune_iters(0, 87e4) == 1500 and object_finetune_iters(2, 87e4) == 2500
    assert object_finetune_iters(0, 40 * 64 * 64) == 700  # 1500 x 0.434 = 651
    assert object_finetune_iters(0, 10) == 500


def test_auto_preset_follows_the_image_size(tmp_path):
    from tests.conftest import write_tiny_blender
    from shells.presets import preset_config

    cpu = torch.device("cpu")
    small = write_tiny_blender(tmp_path / "small", res=64)
    big = write_tiny_blender(tmp_path / "big", res=128)
    small_cfg, small_name = preset_config("auto", small, 1, cpu)  # one recipe at every size
    assert small_name == "object" and small_cfg.train.sampler == "occupancy"
    assert small_cfg.train.iters == 1000  # 4 views of 64 x 64: the shortest schedule
    assert preset_config("object", small, 1, cpu) == (small_cfg, "object")  # the same on a CPU
    cfg, name = preset_config("auto", big, 1, cpu)
    assert name == "object" and cfg.train.sampler == "occupancy"
    # focal 128 / 2 / tan(0.3) = 206 px at distance 3.1 over a box of 2: 2 * 2 * 206 / 3.1 =
    # 266 cells -> 512; at downscale 2, 133 -> 256
    assert cfg.field.max_resolution == 512
    assert preset_config("auto", big, 2, cpu)[0].field.max_resolution == 256
    assert preset_config("auto", big, 2, cpu)[1] == "object"  # 64 px a side
    half = preset_config("object", big, 2, cpu)[0]
    assert half.field.max_resolution == 256
    # stage 2: steps of 4096 rays, 500 on these 4-view data sets (`object_finetune_iters`)
    assert (cfg.finetune.iters, cfg.finetune.batch_rays) == (500, 4096)
    assert (half.finetune.iters, half.finetune.batch_rays) == (500, 4096)
    # stage 1: 2048 crossing rays per step at the base size (256), 1024 above it
    assert (half.train.batch_rays, cfg.train.batch_rays) == (2048, 1024)
    assert preset_config("toy", big, 1, cpu)[0].finetune.iters == 500
    # a field as sharp as lego's at 800^2 (finest level 2048: 4 x 828 px / 3.1 = 1068 cells)
    # gets its shells at 512^3, every mesh piece kept, further out, M- past f = -(h + s), 32
    # peels and band early termination; below it the shells and the band keep the defaults
    sharp = preset_config("auto", write_tiny_blender(tmp_path / "sharp", res=512), 1, cpu)[0]
    assert sharp.field.max_resolution == 2048
    assert (sharp.shell.resolution, sharp.shell.min_component_fraction, sharp.shell.beta_d,
            sharp.shell.beta_e, sharp.shell.support_k_inner, sharp.shell.support_k_outer,
            sharp.render.dp_max, sharp.render.band_ert_eps,
            sharp.render.band_peel_step) == (512, 0.0, 1.2, 0.3, 3.0, 0.0, 32, 1e-4, 8)
    # ... and a stage 2 that draws 2.25 times the training pixels, within [base, 30 000] steps:
    # 4 views of 512^2 (1 M pixels) keep the base 3500
    assert sharp.finetune.iters == 3500
    # ... and a trainer that renders its curve and test views at twice its samples per ray
    assert (sharp.train.eval_density, cfg.train.eval_density) == (2, 1)
    from shells.presets import sharp_finetune_iters
    # 2.25 * 55.7 M / 4096 = 30 586: the cap
    assert sharp_finetune_iters(3500, 87 * 800 * 800, 4096) == 30_000
    assert sharp_finetune_iters(3500, 20e6, 4096) == 11_000  # 10 986 rounded to 100
    assert sharp_finetune_iters(3500, 32 * 512 * 512, 4096) == 4600  # 4608 rounded
    assert sharp_finetune_iters(3500, 16 * 512 * 512, 4096) == 3500  # 2304 < base
    assert (cfg.shell.resolution, cfg.shell.min_component_fraction, cfg.shell.beta_d,
            cfg.shell.beta_e, cfg.shell.support_k_inner, cfg.render.dp_max,
            cfg.render.band_ert_eps, cfg.render.band_peel_step) == (256, 0.01, 0.6, 0.8, 0.0,
                                                                    8, 0.0, 0)
    # the weak Eikonal term is for bounded objects; an unbounded capture keeps the toy's 0.1
    from shells.fields.contraction import Similarity
    assert cfg.train.eikonal_weight == 0.005
    sim = Similarity(centre=(0.0, 0.0, 0.0), radius=1.0)
    assert preset_config("object", big, 1, cpu, sim=sim)[0].train.eikonal_weight == 0.1
    assert preset_config("object", big, 1, cpu, sim=sim)[0].train.cull_weight == 0.0
    # and the ray slope with the free-space term (fox); a bounded object keeps the paper's
    unb = preset_config("object", big, 1, cpu, sim=sim)[0].train
    assert (unb.slope, unb.free_weight) == ("ray", 0.1)
    # the root mean squared colour error for bounded objects (small objects are kept), L1 on
    # fox and in stage 2
    assert (cfg.train.color_loss, unb.color_loss, cfg.finetune.color_loss) == ("rmse", "l1",
                                                                               "l1")
    assert (cfg.train.slope, cfg.train.free_weight) == ("normal", 0.0)
    # rays start 2 radii from the centre (contracted 1.5), or at 0.8 of the nearest camera's
    # distance (3.105 here) when that is less, never inside the ball (contracted 1)
    near = {r: preset_config("object", big, 1, cpu,
                             sim=Similarity(centre=(0.0, 0.0, 0.0), radius=r))[0].field.near_radius
            for r in (1.0, 2.0, 4.0)}
    assert near[1.0] == pytest.approx(1.5)
    assert near[2.0] == pytest.approx(2.0 - 1.0 / (0.8 * math.hypot(3.0, 0.8) / 2.0))
    assert near[4.0] == 1.0
    assert preset_config("toy", big, 1, cpu, sim=sim)[0].field.near_radius == 1.0
    # wide shells, 32 peels and up to 64 samples per interval for an unbounded capture; a
    # bounded object keeps the object preset's caps
    unb_cfg = preset_config("object", big, 1, cpu, sim=sim)[0]
    assert (unb_cfg.shell.dilate_zeta, unb_cfg.shell.erode_zeta, unb_cfg.render.dp_max) == \
        (1.0, 0.5, 32)
    assert (unb_cfg.render.w_s, unb_cfg.render.delta_s, unb_cfg.render.n_max) == (0.04, 0.03, 64)
    assert (unb_cfg.finetune.shards, cfg.finetune.shards) == (4, 1)  # stage 2 in 4 shards
    assert (cfg.shell.dilate_zeta, cfg.shell.erode_zeta, cfg.render.dp_max) == (0.25, 0.1, 8)
    assert (cfg.render.w_s, cfg.render.delta_s, cfg.render.n_max) == (0.03, 0.02, 16)
    assert preset_config("paper", big, 1, cpu)[1] == "paper"
    # RGBA objects train on random backgrounds; the toy and paper presets on the data's colour
    assert cfg.train.random_background and half.train.random_background
    assert not preset_config("toy", big, 1, cpu)[0].train.random_background
    assert not preset_config("paper", big, 1, cpu)[0].train.random_background
    assert cfg.train.cull_weight == 1e-4 and cfg.train.occ_rescue == 0.05  # the object preset's
    toy_train = preset_config("toy", big, 1, cpu)[0].train
    assert toy_train.cull_weight == 0.0 and toy_train.occ_rescue == 0.0


def test_train_cli_errors(tiny_blender, tmp_path, capsys):
    assert train_main(["--data", str(tmp_path / "nope"), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope" in err[0]
    assert not (tmp_path / "r").exists()  # nothing written for bad input
    assert train_main(["--data", str(tiny_blender), "--out", str(tmp_path / "r2"),
                       "--resume"]) == 2
    assert "run.json" in capsys.readouterr().err
    bad = tmp_path / "bad.json"
    bad.write_text('{"train": {"itres": 5}}')
    assert train_main(["--data", str(tiny_blender), "--out", str(tmp_path / "r3"),
                       "--config", str(bad)]) == 2
    assert "itres" in capsys.readouterr().err


def test_stage1_runs_drjit_lookups_on_the_calling_thread(tiny_blender, tmp_path, monkeypatch):
    """Stage 1's steps (and its occupancy-grid rebuilds) run with Dr.Jit's pool reduced to the
    calling thread (`drjit_on_calling_thread`), and the pool has its size again afterwards."""
    import drjit as dr

    import shells.train.stage1 as tr

    seen, real = [], tr.stage1_step
    monkeypatch.setattr(tr, "stage1_step", lambda *a, **k: seen.append(dr.thread_count())
                        or real(*a, **k))
    size = dr.thread_count()
    dr.set_thread_count(2)  # a pool with a worker, whatever this machine's default
    try:
        tr.train(tiny_blender, tmp_path / "t", _tiny_config("occupancy"), torch.device("cpu"),
                 progress=False, evaluate_test=False)
        assert seen == [1] * 6 and dr.thread_count() == 2
    finally:
        dr.set_thread_count(size)


def test_global_kernel_ablation_keeps_one_kernel_size(tiny_blender, tmp_path):
    # FieldConfig.global_kernel: s is one learned scalar (paper Table 4's "global kernel" row)
    cfg = _tiny_config()
    cfg.field.global_kernel = True
    train(tiny_blender, tmp_path / "g", cfg, torch.device("cpu"), progress=False,
          evaluate_test=False)
    field, saved = load_field(tmp_path / "g")
    assert saved.field.global_kernel
    x = torch.rand(500, 3) * 2 - 1
    with torch.no_grad():
        s = field.kernel(x)
    assert float(s.max() - s.min()) == 0.0
    assert float(s[0]) != pytest.approx(cfg.field.init_kernel, rel=1e-4)  # it did learn
    # and the default field's kernel does vary in space after the same training
    train(tiny_blender, tmp_path / "v", _tiny_config(), torch.device("cpu"), progress=False,
          evaluate_test=False)
    with torch.no_grad():
        sv = load_field(tmp_path / "v")[0].kernel(x)
    assert float(sv.max() - sv.min()) > 0.0


def test_config_values_are_type_checked():
    from shells.config import Config
    from shells.errors import InputError

    cfg = Config()
    cfg.update({"shell": {"dilate_zeta": 1}, "data": {"background": [0, 0, 0]},
                "render": {"variant": "llvm_ad_rgb"}})  # int for a float, list for a tuple
    assert cfg.shell.dilate_zeta == 1 and cfg.data.background == (0, 0, 0)
    for bad, where in (({"train": {"iters": 2.5}}, "train.iters"),
                       ({"train": {"iters": True}}, "train.iters"),
                       ({"field": {"global_kernel": 1}}, "field.global_kernel"),
                       ({"shell": {"beta_d": "0.6"}}, "shell.beta_d"),
                       ({"data": {"background": 1.0}}, "data.background"),
                       ({"render": {"variant": 1}}, "render.variant")):
        with pytest.raises(InputError, match=where):
            Config().update(bad, "x.json")


def test_supersampled_training_pixels(tiny_blender, tmp_path, capsys):
    # train.pixel_samples = 4: batch_rays // 4 pixels per step, each with one jittered ray in
    # each quarter of the pixel (projected back onto the image, the rays land there)
    from shells.data.datasets import load_dataset

    data = load_dataset(tiny_blender, "train")
    H, W = data.images.shape[1:3]
    gen = torch.Generator().manual_seed(1)
    idx, o, d = data.sample_pixel_rays(64, 4, gen)
    assert idx.shape == (16,) and o.shape == d.shape == (64, 3)
    cam = (idx // (H * W)).repeat_interleave(4)
    uv, _ = data.cameras.project(o + d, cam)
    pix = torch.stack([(idx % W), (idx // W) % H], -1).repeat_interleave(4, 0).float()
    sub = (uv - pix).reshape(16, 4, 2)  # position inside the pixel
    assert (sub > -1e-4).all() and (sub < 1 + 1e-4).all()
    quarter = torch.floor(sub * 2 + 1e-6).clamp(0, 1)
    assert torch.equal(quarter, torch.tensor([[0.0, 0], [1, 0], [0, 1], [1, 1]]).expand(16, 4, 2))
    # a short run trains and evaluates with box-filtered pixels; a non-square count is an error
    cfg = _tiny_config()
    cfg.train.pixel_samples = 4
    out = train(tiny_blender, tmp_path / "r", cfg, torch.device("cpu"), progress=False)
    assert out["test"]["psnr"] > 0
    assert json.loads((tmp_path / "r" / "config.json").read_text())["train"]["pixel_samples"] == 4
    bad = tmp_path / "bad.json"
    bad.write_text('{"train": {"pixel_samples": 3}}')
    assert train_main(["--data", str(tiny_blender), "--out", str(tmp_path / "r2"),
                       "--config", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "square" in err[0] and not (tmp_path / "r2").exists()


def test_config_ranges_are_checked_when_loaded(tmp_path, capsys):
    """Out-of-range values fail when the file (or flag) is read, in one line naming the key;
    the config is left as it was. Runs stored before data.background read their background."""
    from shells.config import Config, load_config
    from shells.errors import InputError

    cases = [({"render": {"spp": 3}}, "render.spp", "square"),
             ({"train": {"pixel_samples": 8}}, "train.pixel_samples", "square"),
             ({"render": {"dp_max": 0}}, "render.dp_max", ">= 1"),
             ({"train": {"batch_rays": 0}}, "train.batch_rays", ">= 1"),
             ({"shell": {"resolution": 4}}, "shell.resolution", ">= 8"),
             ({"data": {"background": [1, 1]}}, "data.background", "three values"),
             ({"field": {"min_kernel": 0.2}}, "field.init_kernel", "min_kernel"),
             ({"field": {"near_radius": 0.9}}, "field.near_radius", "far_radius"),
             ({"field": {"near_radius": 1.95}}, "field.near_radius", "far_radius"),
             ({"render": {"variant": 5}}, "render.variant", "str or null")]
    for data, key, why in cases:
        cfg = Config()
        with pytest.raises(InputError, match=why) as exc:
            cfg.update(data, "x.json")
        assert key in str(exc.value) and "\n" not in str(exc.value)
        assert cfg.to_dict() == Config().to_dict()  # unchanged
    f = tmp_path / "c.json"
    f.write_text('{"finetune": {"iters": 0}}')
    with pytest.raises(InputError, match="finetune.iters"):
        load_config(f)
    old = Config().to_dict()
    del old["data"]
    old["train"]["background"] = [0.0, 0.0, 0.0]
    old["render"]["background"] = [0.0, 0.0, 0.0]
    assert Config.from_dict(old).data.background == (0.0, 0.0, 0.0)
    assert train_main(["--data", str(tmp_path), "--out", str(tmp_path / "r"), "--iters", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--iters" in err[0] and "train.iters" in err[0]


def test_off_band_weight_hand_worked():
    """The off-band term is the mean over rays of the weight at f < -(h + k s): with a 2-unit
    box and 1 cell per axis (h = sqrt(3)) and k = 1, s = 0.1 everywhere, the band is
    |f| < 1.832; ray 0 holds 0.2 of its 0.9 there, ray 1 nothing of its 0.5."""
    from shells.config import TrainConfig
    from shells.train.stage1 import off_band

    class F:
        aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])

    tc = TrainConfig(occ_resolution=1, occ_k=1.0)
    w = torch.tensor([[0.5, 0.2, 0.2], [0.3, 0.2, 0.0]], requires_grad=True)
    out = {"weights": w, "sdf": torch.tensor([[0.0, -1.0, -2.0], [3.0, -1.8, -5.0]]),
           "s": torch.full((2, 3), 0.1)}
    term, share, near = off_band(F(), out, tc)
    assert term.item() == pytest.approx(0.1)  # (0.2 + 0) / 2 rays
    assert share.item() == pytest.approx(0.2 / 1.4)
    assert near.tolist() == [[True, True, False], [False, True, False]]
    term.backward()
    assert torch.allclose(w.grad, torch.tensor([[0, 0, 0.5], [0, 0, 0.5]]))


def test_free_space_term_hand_worked():
    """The free-space term: mean relu(-f) over the samples reached with transmittance above
    0.99 (T_i = 1 - the weight before i). Ray 0: T = 1, 1, 0.995, 0.5, so its first three
    samples are free, f = 0.2, -0.3, -0.1 -> 0, 0.3, 0.1; ray 1 misses its span (no sample).
    Mean 0.4 / 3; two of the three free samples are at f < 0."""
    from shells.config import TrainConfig
    from shells.train.stage1 import free_space

    tc = TrainConfig(free_weight=0.1)
    sdf = torch.tensor([[0.2, -0.3, -0.1, -0.5], [-1.0, -1.0, -1.0, -1.0]], requires_grad=True)
    out = {"weights": torch.tensor([[0.0, 0.005, 0.495, 0.5], [0.0, 0.0, 0.0, 0.0]]),
           "sdf": sdf, "hit": torch.tensor([True, False])}
    term, share = free_space(out, tc)
    assert term.item() == pytest.approx(0.4 / 3)
    assert share.item() == pytest.approx(2 / 3)
    term.backward()
    assert torch.allclose(sdf.grad, torch.tensor([[0, -1 / 3, -1 / 3, 0], [0, 0, 0, 0]]))
    with pytest.raises(InputError, match="train.free_transmittance"):
        toy_config().update({"train": {"free_transmittance": 1.0}}, "x.json")


def test_level_set_regulariser_points_come_from_weight_and_band(tiny_blender):
    """reg_rays 'level_set': the ray half of the points is drawn only where the weight is and
    among the near-level-set samples, half each; the other half stays uniform in the box."""
    from shells.data.datasets import load_dataset
    from shells.train.stage1 import build_field, reg_points

    cfg = _tiny_config()
    data = load_dataset(tiny_blender, "train")
    field = build_field(cfg, data.aabb, torch.device("cpu"))
    pts = torch.arange(2 * 4 * 3, dtype=torch.float32).reshape(2, 4, 3) / 100
    w = torch.zeros(2, 4)
    w[0, 1] = 0.7  # the only weight
    near = torch.zeros(2, 4, dtype=torch.bool)
    near[1, 2] = True  # the only sample near the level set
    out = reg_points(field, pts, 40, torch.Generator().manual_seed(0), weights=w, near=near)
    assert out.shape == (40, 3)
    ray = out[:20]
    assert (ray[:10] == pts[0, 1]).all() and (ray[10:] == pts[1, 2]).all()
    lo, hi = field.aabb
    assert ((out[20:] >= lo) & (out[20:] <= hi)).all()
    uniform = reg_points(field, pts, 40, torch.Generator().manual_seed(0))
    assert len({tuple(p.tolist()) for p in uniform[:20]}) > 2
    with pytest.raises(InputError, match="reg_rays"):
        cfg.update({"train": {"reg_rays": "weights"}}, "test")


def test_color_losses_hand_worked():
    """'l1' is the mean |error| over pixels and channels, 'l2' the mean squared error, 'rmse'
    its square root, with their gradients; any other name is a one-line config error in either stage."""
    from shells.train.loop import color_loss

    pred = torch.tensor([[0.5, 0.5, 0.5], [1.0, 0.0, 0.2]], requires_grad=True)
    target = torch.tensor([[0.3, 0.5, 0.9], [1.0, 0.6, 0.2]])
    l1 = color_loss(pred, target, "l1")
    assert l1.item() == pytest.approx((0.2 + 0.4 + 0.6) / 6)
    l2 = color_loss(pred, target, "l2")
    assert l2.item() == pytest.approx((0.04 + 0.16 + 0.36) / 6)
    l2.backward()
    assert torch.allclose(pred.grad, 2 * (pred - target).detach() / 6)
    # rmse: sqrt(0.56 / 6) = 0.3055; d/dpred = e / (6 rmse): the largest error pulls 3x the
    # smallest, and the gradient's L1 size mean|e| / rmse = 0.2 / 0.3055 stays below 1
    pred.grad = None
    rmse = color_loss(pred, target, "rmse")
    assert rmse.item() == pytest.approx(math.sqrt(0.56 / 6))
    rmse.backward()
    e = (pred - target).detach()
    assert torch.allclose(pred.grad, e / (6 * math.sqrt(0.56 / 6)))
    cfg = toy_config()
    for section in ("train", "finetune"):
        cfg.update({section: {"color_loss": "l2"}}, "test")
        with pytest.raises(InputError, match=f"{section}.color_loss"):
            cfg.update({section: {"color_loss": "huber"}}, "test")


def test_random_background_targets_hand_worked():
    """train.random_background: a pixel composited on white is recomposited on the drawn
    colour b exactly: straight colour c, alpha a -> a c + (1 - a) b."""
    from shells.train.stage1 import random_backgrounds

    c = torch.tensor([[0.2, 0.4, 0.6], [0.9, 0.1, 0.3], [0.5, 0.5, 0.5]])
    a = torch.tensor([0.25, 1.0, 0.0])
    white = torch.ones(3)
    pixels = a[:, None] * c + (1 - a[:, None]) * white  # as the loader stores them
    assert torch.allclose(pixels[0], torch.tensor([0.8, 0.85, 0.9]))
    idx = torch.tensor([2, 0, 1, 0])
    bg, target = random_backgrounds(idx, pixels, a, white, torch.Generator().manual_seed(3))
    want_bg = torch.rand(4, 3, generator=torch.Generator().manual_seed(3))
    assert torch.equal(bg, want_bg)  # one uniform colour per drawn pixel
    want = a[idx, None] * c[idx] + (1 - a[idx, None]) * want_bg
    torch.testing.assert_close(target, want, rtol=0, atol=1e-6)
    assert torch.equal(target[2], pixels[1])  # opaque: unchanged
    torch.testing.assert_close(target[0], want_bg[0], rtol=0, atol=1e-6)  # transparent: b
    assert not torch.allclose(bg[1], bg[3])  # the same pixel twice gets two colours


@pytest.mark.parametrize("sampler", ["box", "occupancy"])
def test_random_background_renders_each_ray_on_its_colour(tiny_blender, sampler):
    """A step with random backgrounds: a pixel whose ray carries no opacity is rendered as its
    own drawn colour, so a fully transparent one has zero error (not white against b)."""
    from shells.data.datasets import load_dataset
    from shells.render.volume import SpanGrid
    from shells.train.stage1 import build_field, random_backgrounds, stage1_step

    cfg = _tiny_config(sampler)
    data = load_dataset(tiny_blender, "train")
    assert data.alpha is not None and float(data.alpha.min()) == 0.0
    field = build_field(cfg, data.aabb, torch.device("cpu"))
    grid = None
    if sampler == "occupancy":
        grid = SpanGrid(field.aabb, 16, cfg.train.occ_k)
        grid.update(field)
    pixels = torch.ones_like(data.images.reshape(-1, 3))  # every pixel transparent (white
    alpha = torch.zeros(len(pixels))  # with alpha 0): the targets are the drawn colours
    for p in field.geo_mlp.parameters():  # a field with no opacity anywhere: f >> s
        p.data.zero_()
    field.geo_mlp[-1].bias.data[0] = 10.0
    cfg.train.color_loss = "l1"
    loss, logs = stage1_step(field, data, pixels, cfg.train, torch.ones(3),
                             torch.Generator().manual_seed(0), grid, 0, alpha)
    assert logs["color"] < 1e-4  # on white it would be |b - 1|, about 0.5
    loss_w, logs_w = stage1_step(field, data, pixels, cfg.train,
                                 torch.ones(3), torch.Generator().manual_seed(0), grid, 0, None)
    assert logs_w["color"] < 1e-4  # the same field on white against white targets
    _, target = random_backgrounds(torch.arange(4), pixels, alpha, torch.ones(3),
                                   torch.Generator().manual_seed(0))
    assert float((target - 1).abs().mean()) > 0.2
