"""Occupancy-grid baseline (shells.render.occupancy) on an analytic sphere, and the speed bench."""

from __future__ import annotations

import json
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import torch
import trimesh

from shells.config import Config, RenderConfig
from shells.device import mitsuba_variant
from shells.errors import InputError
from shells.fields.drjit_field import FieldSample
from shells.render.frame import MODES, render_image
from shells.render.occupancy import (OccupancyGrid, build_occupancy_grid, march_step,
                                     occupancy_grid, raycast_floor, render_occupancy)
from shells.render.raycast import ShellScene, box_intervals, to_point3f
from shells.render.sampler import place_packed
from shells.render.shading import composite_packed, shade_samples
from tests.test_render import camera_rays

AABB = [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]
RADIUS, S = 0.5, 0.01


class Sphere:
    """SDF of a sphere of radius 0.5, constant kernel s = 0.01, colour 0.5 + 0.5 n."""

    def eval_geometry(self, x):  # x: [M] 3-vector -> sdf [M], s [M]
        r = dr.norm(x)
        return FieldSample(sdf=r - RADIUS, s=dr.full(mi.Float, S, dr.width(r)), normal=None,
                           rgb=None)

    def eval(self, x, d):  # x, d: [M] 3-vectors -> sdf, s [M], normal, rgb [M]
        r = dr.norm(x)
        n = x / dr.maximum(r, 1e-8)
        return FieldSample(sdf=r - RADIUS, s=dr.full(mi.Float, S, dr.width(r)), normal=n,
                           rgb=mi.Color3f(0.5 + 0.5 * n))


def colours(c) -> np.ndarray:  # mi.Color3f [R] -> [R, 3]
    return np.asarray(c).T.copy()


def all_occupied(res: int = 8) -> OccupancyGrid:
    return OccupancyGrid(occ=dr.full(mi.Bool, True, res ** 3), lo=(-1.0, -1.0, -1.0),
                         cell=(2.0 / res,) * 3, resolution=res)


@pytest.fixture(scope="module")
def sphere():
    mitsuba_variant()
    return Sphere()


def test_grid_marks_the_surface_and_nothing_far(sphere):
    N, k = 32, 5.0  # cell 1/16, half diagonal h = 0.054; h + k s = 0.104
    grid = build_occupancy_grid(sphere, AABB, resolution=N, k=k, jitter=2)
    occ = grid.dense()  # [ix, iy, iz]
    assert occ.shape == (N, N, N) and grid.cell == (0.0625,) * 3
    # hand-checkable cells: the 8 around the centre (their points lie within r = 0.125, so
    # |f| >= 0.375, and so do their neighbours' points within r = 0.22: not even dilation
    # reaches them) and the box corners (|f| > 1) are empty
    assert not occ[15:17, 15:17, 15:17].any() and not occ[0, 0, 0] and not occ[-1, -1, -1]
    # cell (23, 15, 15) spans x in [0.4375, 0.5], y, z in [-0.0625, 0]: r = 0.5 crosses it
    assert occ[23, 15, 15] and occ[8, 16, 16] and occ[16, 8, 16]
    # every cell the sphere passes through is occupied; none far from it is
    i = torch.arange(N, dtype=torch.float64)
    lo = -1.0 + 0.0625 * torch.stack(torch.meshgrid(i, i, i, indexing="ij"), -1)  # [N, N, N, 3]
    hi = lo + 0.0625
    near = torch.linalg.norm(torch.clamp(torch.zeros(3, dtype=torch.float64), lo, hi), dim=-1)
    far = torch.linalg.norm(torch.maximum(lo.abs(), hi.abs()), dim=-1)
    crossing = (near < RADIUS) & (far > RADIUS)
    assert occ[crossing].all()
    # a cell is marked when some point of it has |f| < h + k s, then dilated by one cell:
    # an occupied cell's box lies within h + k s + one cell diagonal (2 h) of the surface
    gap = torch.maximum(near - RADIUS, RADIUS - far).clamp_min(0)  # box-to-surface distance
    h = 0.03125 * math.sqrt(3)
    assert not occ[gap > 3 * h + k * S].any()
    assert 0.05 < grid.fraction < 0.5  # a shell of cells, not the box


def test_grid_is_cached_per_field_and_config(sphere):
    cfg = RenderConfig(occ_resolution=8)
    g1 = occupancy_grid(sphere, AABB, cfg)
    assert occupancy_grid(sphere, AABB, cfg) is g1
    assert occupancy_grid(sphere, AABB, RenderConfig(occ_resolution=8, occ_k=4.0)) is not g1
    assert occupancy_grid(Sphere(), AABB, cfg) is not g1


class SmallSphere(Sphere):
    """The same sphere at radius 0.2."""

    def eval_geometry(self, x):
        r = dr.norm(x)
        return FieldSample(sdf=r - 0.2, s=dr.full(mi.Float, S, dr.width(r)), normal=None,
                           rgb=None)


def test_grid_from_another_field_takes_the_place_of_the_fields_own(sphere):
    # the baseline bench.render_speed --grid-stage gives a stage-2 field: the grid of another
    # field (the run's stage-1 one), cached where the field's own would be
    cfg = RenderConfig(occ_resolution=16)
    field = Sphere()
    own = occupancy_grid(field, AABB, cfg)
    small = SmallSphere()
    g = occupancy_grid(field, AABB, cfg, source=small)
    assert occupancy_grid(field, AABB, cfg) is g
    want = build_occupancy_grid(small, AABB, 16, cfg.occ_k, cfg.occ_jitter)
    assert torch.equal(g.dense(), want.dense())
    assert not torch.equal(g.dense(), own.dense())
    assert g.fraction < own.fraction  # the smaller sphere's cells


def test_occupancy_matches_dense_full_render_with_far_fewer_samples(sphere):
    W = H = 32
    o, d = camera_rays(W, H)
    cfg = RenderConfig(occ_resolution=64)  # cell 1/32, half diagonal 0.027
    colour, opacity, count = render_occupancy(sphere, o, d, cfg, AABB)
    # reference: `full` mode's own sample placement with 1024 samples per ray (section 0.002)
    full_n = 1024
    po, pd = to_point3f(o), to_point3f(d, mi.Vector3f)
    samples = place_packed(box_intervals(po, pd, AABB), cfg, fixed=full_n)
    alpha, rgb = shade_samples(sphere, samples, po, pd)
    bg = mi.Color3f(1.0, 1.0, 1.0)  # render_occupancy's default background
    want, want_opacity = composite_packed(alpha, rgb, samples.start, samples.count, bg)
    diff = np.abs(colours(colour) - colours(want))
    # Skipped space holds opacity <= e^-(k + margins / s), here e^-(5 + 5.8) ~ 2e-5 (module
    # docstring); both renders use the NeuS section formula, exact for an SDF that is linear
    # along the section, at different positions and lengths (0.0034 vs 0.002): they differ
    # only where the ray bends around the sphere, at the silhouette. Measured 3e-5 mean, 5e-4 max.
    assert diff.mean() < 1e-3 and diff.max() < 2e-2
    op_diff = np.abs(opacity.numpy() - want_opacity.numpy())
    assert op_diff.mean() < 1e-3 and op_diff.max() < 2e-2
    # the sphere is visible and opaque in the middle: colour of n = (0, 0, -1) is (0.5, 0.5, 0)
    centre = (H // 2) * W + W // 2
    np.testing.assert_allclose(colours(colour)[centre], [0.5, 0.5, 0.0], atol=0.03)
    assert opacity.numpy()[centre] > 1 - cfg.ert_eps
    # samples: far fewer than full mode, and than the same march with every cell occupied
    n = count.numpy().astype(np.float64)
    steps = 2.0 / march_step(AABB, cfg)  # ~592 steps across the box along z
    assert n.mean() < full_n / 4 and n.mean() < steps / 4
    assert n.max() < steps  # no ray marches more steps than fit in the box


def test_early_termination_stops_rays_in_the_opaque_sphere(sphere):
    cfg = RenderConfig()  # ert_eps = 1e-4, occ_chunk = 16
    grid = all_occupied()  # no empty-space skipping: only termination can shorten a ray
    dt = march_step(AABB, cfg)  # diagonal / 1024 = 0.00338
    o = torch.tensor([[0.0, 0.0, -2.5], [0.0, 0.9, -2.5]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])  # ray 0 hits the sphere, ray 1 misses
    colour, opacity, count = render_occupancy(sphere, o, d, cfg, AABB, grid=grid)
    n_hit, n_miss = count.numpy().tolist()
    # ray 1 crosses the whole box (z from -1 to 1) without termination: ceil(2 / dt) samples
    assert n_miss == math.ceil(2.0 / dt)
    # ray 0 reaches the surface (t = 0.5 after the box entry) after 148 steps; T = sigmoid(f/s)
    # drops below 1e-4 at f = -s ln(1e4) = -0.092, 27 steps further (176 samples in all, measured
    # T = 7e-5 after them); then it stops at the end of that round (rounds of 16 samples here;
    # +1 for where the threshold falls within a section)
    first_below = math.ceil((0.5 + S * math.log(1e4)) / dt)
    assert first_below <= n_hit <= first_below + 16
    assert n_hit < n_miss / 3
    assert 1.0 - opacity.numpy()[0] < cfg.ert_eps
    # without termination the ray runs to the far side of the box; the colour barely changes
    no_ert = RenderConfig(ert_eps=0.0)
    colour2, _, count2 = render_occupancy(sphere, o, d, no_ert, AABB, grid=grid)
    assert count2.numpy().tolist() == [n_miss, n_miss]
    assert np.abs(colours(colour) - colours(colour2)).max() < 2 * cfg.ert_eps


def test_render_image_occupancy_mode_and_errors(sphere):
    assert "occupancy" in MODES
    o, d = camera_rays(16, 16)
    cfg = RenderConfig(occ_resolution=32, occ_chunk=4, chunk_samples=4 * 100)  # 100-ray chunks
    img, spp = render_image(sphere, o, d, 16, 16, cfg, "occupancy", aabb=AABB)
    colour, _, count = render_occupancy(sphere, o, d, cfg, AABB)
    assert img.shape == (16, 16, 3) and spp.shape == (16, 16)
    # the batches of render_image change the rounds (K grows as a batch's rays die), so rays
    # may stop a round earlier or later: colours agree to the termination threshold
    np.testing.assert_allclose(img.reshape(-1, 3).numpy(), colours(colour), atol=2 * cfg.ert_eps)
    assert torch.equal(spp.reshape(-1) > 0, torch.from_numpy(count.numpy() > 0))
    # rays that miss the box show the background and take no samples
    colour, opacity, count = render_occupancy(
        sphere, torch.tensor([[0.0, 3.0, -2.5]]), torch.tensor([[0.0, 0.0, 1.0]]), cfg, AABB)
    assert count.numpy().tolist() == [0] and opacity.numpy().tolist() == [0.0]
    np.testing.assert_allclose(colours(colour), [[1.0, 1.0, 1.0]])
    with pytest.raises(InputError, match="aabb"):
        render_image(sphere, o, d, 16, 16, cfg, "occupancy")
    with pytest.raises(InputError, match="occ_step"):  # checked when a config is loaded
        Config().update({"render": {"occ_step": -1.0}}, "x.json")


def test_raycast_floor_hits_the_outer_shell():
    mitsuba_variant()
    outer = trimesh.creation.icosphere(subdivisions=4, radius=0.6)
    scene = ShellScene((outer.vertices, outer.faces))
    o = torch.tensor([[0.0, 0.0, -2.5], [0.0, 0.9, -2.5]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    hit, t = raycast_floor(scene, o, d)
    assert hit.numpy().tolist() == [True, False]
    # the icosphere's faces lie just inside its circumscribed sphere of radius 0.6
    assert 1.9 <= t.numpy()[0] < 1.91 and math.isinf(t.numpy()[1])


def test_render_speed_bench_end_to_end(tmp_path, tiny_blender, capsys):
    """bench.render_speed on a run as the pipeline leaves it (untrained field: geometric-init
    sphere r = 0.5, shells at 0.6 / 0.4), with small settings."""
    from shells.presets import toy_config
    from shells.files import write_json
    from shells.train.optim import make_optimizer
    from shells.run import save_checkpoint
    from shells.train.stage1 import build_field

    run = tmp_path / "run"
    cfg = toy_config()
    torch.manual_seed(0)
    field = build_field(cfg, torch.tensor(AABB), torch.device("cpu"))
    save_checkpoint(run / "checkpoint.pt", field, make_optimizer(field, 1e-2, 1e-3), 0, cfg)
    write_json(run / "run.json", {"data": str(tiny_blender), "downscale": 1})
    (run / "shells").mkdir()
    trimesh.creation.icosphere(subdivisions=3, radius=0.6).export(run / "shells" / "outer.ply")
    trimesh.creation.icosphere(subdivisions=3, radius=0.4).export(run / "shells" / "inner.ply")

    from bench import render_speed as bench

    md = tmp_path / "BENCH.md"
    md.write_text("# Benchmarks\n")
    rc = bench.main([str(run), "--views", "1", "--full-samples", "32", "--occ-resolution", "16",
                     "--out", str(tmp_path / "out"), "--append", str(md)])
    assert rc == 0
    text = md.read_text()
    assert text.startswith("# Benchmarks\n") and "llvm_ad_rgb" in text
    for label in bench.LABELS.values():
        assert f"| {label} |" in text
    out = tmp_path / "out"
    assert (out / "render_speed.md").is_file() and (out / "render_speed.json").is_file()
    assert (out / "occupancy" / "r_000.png").is_file()
    assert "render_speed.png" in capsys.readouterr().out
    assert (out / "render_speed.png").is_file()
    # a subset of the modes, the grid from a named stage's field: those rows only, speed-up
    # against the occupancy grid, and the grid's stage in the notes and the JSON
    out2 = tmp_path / "out2"
    assert bench.main([str(run), "--views", "1", "--occ-resolution", "16", "--modes", "band",
                       "occupancy", "--grid-stage", "stage1", "--out", str(out2)]) == 0
    part = (out2 / "render_speed.md").read_text()
    assert f"| {bench.LABELS['band']} |" in part and f"| {bench.LABELS['full']} |" not in part
    assert "speed-up vs occupancy" in part and "grid of the stage1 field" in part
    assert json.loads((out2 / "render_speed.json").read_text())["grid_stage"] == "stage1"
    assert not (out2 / "full").exists()
