"""Unbounded scenes (issue 14): the contracted field and its Dr.Jit twin, the world slope
normal, the ray parameter s of every sampler, and shells extracted in field space and mapped
back to the world (containment, watertightness)."""

from __future__ import annotations

import dataclasses
import math

import mitsuba as mi
import numpy as np
import pytest
import torch

from shells.config import RenderConfig, ShellConfig
from shells.presets import toy_config
from shells.device import mitsuba_variant
from shells.fields.contraction import Similarity, contract, contract_jacobian
from shells.fields.drjit_field import DrJitField
from shells.fields.network import ShellField
from shells.levelset.extract import extract_shells
from shells.levelset.unbounded import chord_deviation, to_world
from shells.render.raycast import Intervals, ShellScene
from shells.render.sampler import (band_samples, cast_start, far_intervals, field_warp,
                                   place_packed, place_padded, shell_intervals)
from shells.render.volume import render_volume_rays
from shells.render.warp import ray_span, s_of_t, t_of_s

CENTRE, RADIUS = (0.1, 0.0, -0.2), 1.5


def _field(seed: int = 0, randomise: bool = True) -> ShellField:
    torch.manual_seed(seed)
    cfg = dataclasses.replace(toy_config().field, unbounded=True, centre=CENTRE, radius=RADIUS)
    f = ShellField(cfg, torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    if randomise:
        with torch.no_grad():
            f.grid.params.uniform_(-0.5, 0.5)
            for p in list(f.geo_mlp.parameters()) + list(f.rad_mlp.parameters()):
                p.add_(torch.randn_like(p) * 0.2)
    return f


def _points(n: int, seed: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    u = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=1)
    r = RADIUS * 10 ** (2.5 * torch.rand(n, generator=g) - 1.0)  # 0.1 .. 30 radii
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=1)
    return torch.tensor(CENTRE) + u * r[:, None], d


def test_field_space_box_identity_inside_and_far_solid():
    f = _field()
    np.testing.assert_allclose(f.aabb.numpy(), [[-2.9, -3.0, -3.2], [3.1, 3.0, 2.8]], atol=1e-6)
    x, d = _points(4000)
    u = (x - torch.tensor(CENTRE)) / RADIUS
    inside = u.norm(dim=1) <= 1
    z = f.to_field(x)
    assert torch.equal(z[inside], x[inside])  # the identity in the ball of interest
    torch.testing.assert_close(z, torch.tensor(CENTRE) + RADIUS * contract(u))
    with torch.no_grad():
        geo = f.geometry(x)
        # beyond the far radius everything is solid, and the surface there is the far sphere
        yz = (z - torch.tensor(CENTRE)) / RADIUS
        beyond = yz.norm(dim=1) > f.cfg.far_radius
        assert beyond.sum() > 100 and (geo["sdf"][beyond] < 0).all()
        expect = RADIUS * (f.cfg.far_radius - yz.norm(dim=1))
        assert (geo["sdf"] <= expect + 1e-6).all()


def test_world_slope_normal_is_the_contraction_jacobian_applied_to_the_field_normal():
    f = _field()
    x, d = _points(3000)
    with torch.no_grad():
        geo = f.geometry(x)
    J = contract_jacobian(((x - torch.tensor(CENTRE)) / RADIUS).double()).float()
    jn = (J.transpose(1, 2) @ geo["n_unit"][..., None])[..., 0]
    torch.testing.assert_close(geo["normal"], jn, rtol=0, atol=1e-5)
    # where the far sphere is the surface, n is the exact gradient direction there, so the
    # slope normal is the world gradient of f itself (autograd through the contraction)
    xg = x.clone().requires_grad_(True)
    sdf = f.geometry(xg)["sdf"]
    (grad,) = torch.autograd.grad(sdf.sum(), xg)
    z = f.to_field(x)
    on_dome = sdf.detach() == f._dome(z)
    assert on_dome.sum() > 500
    torch.testing.assert_close(geo["normal"][on_dome], grad[on_dome], rtol=1e-4, atol=1e-6)
    # and |slope normal| <= 1 everywhere (the contraction only shrinks)
    assert float(geo["normal"].norm(dim=1).max()) <= 1.0 + 1e-5


def test_drjit_twin_matches_torch_on_an_unbounded_field():
    mitsuba_variant()
    f = _field(seed=3)
    x, d = _points(8000, seed=4)
    with torch.no_grad():
        ref = f(x, d)
    twin = DrJitField(f)
    out = twin.eval_torch(x, d)
    for k in ("sdf", "s", "normal", "rgb"):
        torch.testing.assert_close(out[k], ref[k], rtol=0, atol=1e-4, msg=k)
    geo = twin.eval_torch(x)
    torch.testing.assert_close(geo["sdf"], ref["sdf"], rtol=0, atol=1e-4)
    # field-space evaluation (the occupancy grid's)
    z = f.to_field(x)
    r = twin.eval_geometry_field(mi.Point3f(*[mi.Float(z[:, i].contiguous()) for i in range(3)]))
    torch.testing.assert_close(r.sdf.torch(), ref["sdf"], rtol=0, atol=1e-4)


def test_ray_parameter_s_is_contracted_distance_from_the_centre():
    tb = torch.tensor([2.0, 3.0])
    t = torch.tensor([[0.5, 2.0, 4.0, 1e6], [1.0, 3.0, 6.0, 30.0]])
    s = s_of_t(t, tb[:, None])
    torch.testing.assert_close(t_of_s(s, tb[:, None])[:, :3], t[:, :3])
    # hand-worked: t_b = 2, t = 4 -> s = 4 - 4 / 4 = 3; s -> 2 t_b far away
    assert float(s[0, 2]) == pytest.approx(3.0)
    assert float(s[0, 3]) == pytest.approx(4.0, abs=1e-5)
    # continuous with slope 1 at t_b
    eps = 1e-4
    for b in tb.tolist():
        tt = torch.tensor([b - eps, b, b + eps], dtype=torch.float64)
        ss = s_of_t(tt, torch.tensor(b, dtype=torch.float64))
        assert float((ss[2] - ss[0]) / (2 * eps)) == pytest.approx(1.0, abs=1e-3)
    # a ray from the centre: s = radius x the contracted radius of its point
    o = torch.tensor([CENTRE])
    d = torch.nn.functional.normalize(torch.tensor([[0.3, -1.0, 0.2]]), dim=1)
    near1, tb1, t_far = ray_span(o, d, CENTRE, RADIUS, 1.95)
    assert float(near1) == 0.0  # from inside the ball: from the camera on
    assert float(tb1) == pytest.approx(RADIUS)
    ts = torch.tensor([0.7, 1.5, 3.0, 20.0, 400.0])
    y = contract((o + ts[:, None] * d - torch.tensor(CENTRE)) / RADIUS)
    torch.testing.assert_close(s_of_t(ts, tb1), RADIUS * y.norm(dim=1))
    # the last distance lies beyond the solid far sphere
    y_far = contract((o + t_far * d - torch.tensor(CENTRE)) / RADIUS)
    assert float(y_far.norm()) > 1.95


def test_band_sampler_counts_a_far_interval_in_s_and_tiles_it_in_t():
    mitsuba_variant()
    cfg = RenderConfig(w_s=0.01, delta_s=0.02, n_max=16)
    warp = (CENTRE, RADIUS, 1.95)
    o = torch.tensor([CENTRE, CENTRE])
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    # a near interval (inside the ball: s = t) and a far one, 30 -> 60 world units
    iv = Intervals.from_arrays([[0.5, 30.0], [30.0, 0.0]], [[0.56, 60.0], [60.0, 0.0]], [2, 1])
    p = place_packed(iv, cfg, warp=warp, o=o, d=d)
    t, delta, ray = (v.numpy() for v in (p.t, p.delta, p.ray))
    counts = p.count.numpy()
    # ray 0: [0.5, 0.56] in the ball: 4 samples as unwarped; [30, 60] is 0.0375 wide in s
    # (s = 2 t_b - t_b^2 / t, t_b = 1.5): 2 samples, not the 16 of its world width
    s30, s60 = 3.0 - 2.25 / 30.0, 3.0 - 2.25 / 60.0
    n_far = math.ceil((s60 - s30 - 0.01) / 0.02) + 1
    assert counts.tolist() == [4 + n_far, n_far]
    r0 = t[ray == 0]
    assert np.all(np.diff(r0) > 0) and r0[-1] < 60.0 and r0[4] > 30.0
    # the sections tile each interval exactly, in world units
    np.testing.assert_allclose(delta[ray == 0][:4].sum(), 0.06, rtol=1e-5)
    np.testing.assert_allclose(delta[ray == 0][4:].sum(), 30.0, rtol=1e-4)
    np.testing.assert_allclose(delta[ray == 1].sum(), 30.0, rtol=1e-4)
    tp, dp, mask, _ = place_padded(iv, cfg, warp, o, d)
    np.testing.assert_allclose(tp[mask].numpy(), t, rtol=1e-6)
    np.testing.assert_allclose(dp[mask].numpy(), delta, rtol=1e-6)


def test_band_rays_are_cast_from_t_near_past_solids_no_sampler_sees():
    """A ray that misses the ball starts at its point nearest the centre (`ray_span`), as in
    stage 1; a solid blob (M+ and M- of a sphere) the field holds between the camera and that
    point must neither end the band ray there nor hide the shell behind it."""
    import trimesh

    mitsuba_variant()
    c = np.asarray(CENTRE)
    cam = c + np.array([-6.0 * RADIUS, 2.0 * RADIUS, 0.0])  # the ray passes 2 radii from c
    d = np.array([1.0, 0.0, 0.0])
    near = 6.0 * RADIUS  # t_near: the point nearest to c

    def ball(r, at):
        m = trimesh.creation.icosphere(subdivisions=3, radius=r)
        m.apply_translation(at)
        return m

    blob = cam + 2.0 * RADIUS * d  # before t_near
    wall = cam + 9.0 * RADIUS * d  # after it
    outer = trimesh.util.concatenate([ball(0.4 * RADIUS, blob), ball(0.4 * RADIUS, wall)])
    inner = trimesh.util.concatenate([ball(0.2 * RADIUS, blob), ball(0.2 * RADIUS, wall)])
    scene = ShellScene((np.float32(outer.vertices), np.int32(outer.faces)),
                       (np.float32(inner.vertices), np.int32(inner.faces)))
    o = torch.tensor(cam[None], dtype=torch.float32)
    dt = torch.tensor(d[None], dtype=torch.float32)
    warp = (CENTRE, RADIUS, 1.95)
    assert float(ray_span(o, dt, *warp)[0]) == pytest.approx(near, rel=1e-5)
    iv = shell_intervals(scene, o, dt, 8, warp).torch()
    assert iv["count"].tolist() == [1]  # the wall's band only
    np.testing.assert_allclose([iv["enter"][0, 0].item(), iv["exit"][0, 0].item(),
                                iv["t_inner"][0].item()],
                               np.array([8.6, 8.8, 8.8]) * RADIUS, rtol=2e-3)
    t, _, mask, solid = band_samples(scene, o, dt, RenderConfig(), warp)
    assert bool(solid[0]) and (t[mask] > 8.5 * RADIUS).all()
    # cast from the camera the blob ends the ray before t_near: no sample reaches the wall
    t0, _, m0, _ = place_padded(scene.intervals(o, dt, 8), RenderConfig(), warp, o, dt)
    assert not (t0[m0] > 8.5 * RADIUS).any()


def test_rays_start_where_they_enter_the_start_sphere():
    """``field.near_radius``: each ray starts where it enters the sphere of contracted radius
    near_radius (world radius 1 / (2 - near_radius) radii), from the camera when the camera is
    inside it, at its point nearest the centre when it misses it; t_b and t_far do not change.
    Hand-worked with a start sphere of 3 radii (near_radius 5/3), rays along +x, torch and
    Dr.Jit alike; with near_radius 1 the old rule (the ball of interest)."""
    mitsuba_variant()
    c = torch.tensor(CENTRE)
    # offsets from the centre in radii: passes 2 radii from it (misses the ball), passes half
    # a radius from it (enters the ball), starts inside the start sphere, passes 3.5 radii
    # from it (misses both spheres)
    off = torch.tensor([[-6.0, 2.0, 0.0], [-6.0, 0.5, 0.0], [-2.0, 1.0, 0.0], [-6.0, 3.5, 0.0]])
    o = c + RADIUS * off
    d = torch.tensor([[1.0, 0.0, 0.0]]).expand(4, 3)
    po = mi.Point3f(*[mi.Float(o[:, i].contiguous()) for i in range(3)])
    pd = mi.Vector3f(*[mi.Float(d[:, i].contiguous()) for i in range(3)])
    old = [t / RADIUS for t in ray_span(o, d, CENTRE, RADIUS, 1.95)]
    new = [t / RADIUS for t in ray_span(o, d, CENTRE, RADIUS, 1.95, 5.0 / 3.0)]
    ball_in = 6.0 - math.sqrt(0.75)  # enters the unit ball at 6 - sqrt(1 - 0.5^2)
    np.testing.assert_allclose(old[0].numpy(), [6.0, ball_in, 2.0, 6.0], rtol=1e-5)
    np.testing.assert_allclose(new[0].numpy(),
                               [6.0 - math.sqrt(5.0), 6.0 - math.sqrt(8.75), 0.0, 6.0],
                               rtol=1e-5)
    for a, b in zip(old[1:], new[1:]):  # t_b, t_far unchanged
        torch.testing.assert_close(a, b)
    assert (new[0] <= new[1]).all()  # t_near <= t_b: s = t there
    dj = ray_span(po, pd, CENTRE, RADIUS, 1.95, 5.0 / 3.0)
    for a, b in zip(new, dj):
        np.testing.assert_allclose(b.numpy() / RADIUS, a.numpy(), rtol=1e-5, atol=1e-6)
    # stage 1 and the shell cast start there too (the field's setting)
    f = _field(randomise=False)
    f.cfg = dataclasses.replace(f.cfg, near_radius=5.0 / 3.0)
    with torch.no_grad():
        out = render_volume_rays(f, o, d, 8, 0, torch.ones(3))
    first = (out["t"][:, 0] / RADIUS).numpy()  # stratified: half a stratum past the start
    assert (first >= new[0].numpy() - 1e-5).all() and (first < old[0].numpy()).any()
    assert field_warp(f) == (CENTRE, RADIUS, 1.95, 5.0 / 3.0)
    np.testing.assert_allclose(cast_start(o, d, field_warp(f)).numpy() / RADIUS,
                               new[0].numpy(), rtol=1e-5, atol=1e-6)


def test_every_sampler_reaches_the_far_background():
    """Stage 1 (torch) and the full-ray baseline (Dr.Jit) sample every ray out past the far
    sphere, evenly in s, so an untrained field already absorbs every ray."""
    mitsuba_variant()
    f = _field(randomise=False)
    g = torch.Generator().manual_seed(0)
    o = torch.tensor(CENTRE) + torch.nn.functional.normalize(torch.randn(64, 3, generator=g),
                                                             dim=1) * 2.5 * RADIUS
    d = torch.nn.functional.normalize(torch.randn(64, 3, generator=g), dim=1)
    with torch.no_grad():
        out = render_volume_rays(f, o, d, 32, 16, torch.ones(3))
    y_last = contract((out["points"][:, -1] - torch.tensor(CENTRE)) / RADIUS).norm(dim=1)
    assert (y_last > 1.9).all()  # the last sample lies in the far background
    _, _, t_far = ray_span(o, d, CENTRE, RADIUS, f.cfg.far_radius)
    y_end = contract((o + t_far[:, None] * d - torch.tensor(CENTRE)) / RADIUS).norm(dim=1)
    assert (y_end > f.cfg.far_radius).all()  # the ray ends inside the far solid
    assert (out["opacity"] > 0.999).all()  # which absorbs it (its kernel is sharp)
    po = mi.Point3f(*[mi.Float(o[:, i].contiguous()) for i in range(3)])
    pd = mi.Vector3f(*[mi.Float(d[:, i].contiguous()) for i in range(3)])
    p = place_packed(far_intervals(po, pd, (CENTRE, RADIUS, 1.95)), RenderConfig(), fixed=64,
                     warp=(CENTRE, RADIUS, 1.95), o=po, d=pd)
    assert p.count.numpy().tolist() == [64] * 64
    t = p.t.numpy().reshape(64, 64)
    x_last = o + torch.from_numpy(t[:, -1:]).float() * d
    assert (contract((x_last - torch.tensor(CENTRE)) / RADIUS).norm(dim=1) > 1.9).all()


def _winding(mesh, pts: np.ndarray, chunk: int = 16) -> np.ndarray:
    """Generalised winding number of a triangle mesh at points (solid angles / 4 pi)."""
    tri = np.asarray(mesh.triangles, np.float64)
    out = np.empty(len(pts))
    for a in range(0, len(pts), chunk):
        p = pts[a:a + chunk, None, None, :]
        v = tri[None] - p  # [P, F, 3, 3]
        n = np.linalg.norm(v, axis=-1)
        a_, b_, c_ = v[..., 0, :], v[..., 1, :], v[..., 2, :]
        det = np.einsum("pfi,pfi->pf", a_, np.cross(b_, c_))
        den = (n[..., 0] * n[..., 1] * n[..., 2] + np.einsum("pfi,pfi->pf", a_, b_) * n[..., 2]
               + np.einsum("pfi,pfi->pf", b_, c_) * n[..., 0]
               + np.einsum("pfi,pfi->pf", c_, a_) * n[..., 1])
        # a point in a triangle's plane (off the surface) sees it under solid angle 0; atan2
        # would give +-pi there when den < 0 (marching cubes makes axis-aligned triangles)
        omega = np.where(np.abs(det) > 1e-14, 2.0 * np.arctan2(det, den), 0.0)
        out[a:a + chunk] = omega.sum(1) / (4 * np.pi)
    return out


def test_shells_in_field_space_mapped_to_the_world_contain_the_solid():
    """An analytic scene in field space (a ball of radius 0.3, a room beyond contracted radius
    1.6, solid beyond it): the world shells are closed and M+ holds every solid grid point
    (winding number 1; marching cubes closes the solid at the grid's box, which ends up
    clamped at contracted radius 1.99, 100 radii out), M- only solid ones."""
    sim = Similarity(CENTRE, RADIUS)
    res = 64
    box = np.array([np.asarray(CENTRE) - 2 * RADIUS, np.asarray(CENTRE) + 2 * RADIUS])
    ax = [np.linspace(box[0, i], box[1, i], res) for i in range(3)]
    Z = np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)
    y = np.linalg.norm((Z - np.asarray(CENTRE)) / RADIUS, axis=1)
    f = np.minimum(RADIUS * y - 0.3, RADIUS * (1.6 - y)).reshape(res, res, res)
    s = np.full_like(f, 0.03)
    cfg = ShellConfig(resolution=res, dilate_zeta=0.25, erode_zeta=0.1)
    sh = extract_shells(f, s, box, cfg, roi=(CENTRE, RADIUS))
    h = float((box[1, 0] - box[0, 0]) / (res - 1))
    outer, rep_o = to_world(sh.outer, sim, h)
    inner, rep_i = to_world(sh.inner, sim, h)
    assert outer.is_watertight and inner.is_watertight
    assert rep_o["within_tolerance"] and rep_i["within_tolerance"]
    assert rep_o["max_chord_deviation_h"] <= 0.1
    # the room's M+ lies about 1.6 radii out in field space: 1 / (2 - 1.6) = 2.5 radii away
    r_world = np.linalg.norm(np.asarray(outer.vertices) - np.asarray(CENTRE), axis=1)
    assert r_world.max() > 2.2 * RADIUS
    # the small ball is kept although the far parts have 100x its faces
    assert len(outer.split(only_watertight=False)) == 3
    rng = np.random.default_rng(0)
    fv = f.reshape(-1)
    solid = np.flatnonzero((fv < -1e-3 * h) & (y < 1.98))
    pick = rng.choice(solid, 400, replace=False)
    world = (contract_inv(Z[pick], sim))
    w_out = _winding(outer, world)
    np.testing.assert_allclose(w_out, 1.0, atol=1e-3)
    # grid points in free space well outside M+: winding 0 there
    free = np.flatnonzero(fv > 0.35)
    pick = rng.choice(free, 200, replace=False)
    np.testing.assert_allclose(_winding(outer, contract_inv(Z[pick], sim)), 0.0, atol=1e-3)
    # M- only holds solid: points with winding 1 of M- (inside its solid) have f <= 0
    pick = rng.choice(len(Z), 600, replace=False)
    keep = y[pick] < 1.98
    pts = contract_inv(Z[pick][keep], sim)
    in_inner = _winding(inner, pts) > 0.5
    assert in_inner.sum() > 50 and (fv[pick][keep][in_inner] <= 0).all()


def contract_inv(z: np.ndarray, sim: Similarity) -> np.ndarray:
    from shells.fields.contraction import uncontract
    y = (z - np.asarray(sim.centre)) / sim.radius
    return uncontract(torch.from_numpy(y)).numpy() * sim.radius + np.asarray(sim.centre)


def test_to_world_splits_triangles_until_the_chords_fit():
    """A coarse far mesh (an icosphere at contracted radius 1.9) has chords far off its curved
    image; it is split into four until they fit, and stays closed; a loose tolerance needs no
    split."""
    import trimesh

    sim = Similarity(CENTRE, RADIUS)
    ico = trimesh.creation.icosphere(subdivisions=1, radius=1.9 * RADIUS)
    ico.apply_translation(CENTRE)
    world0 = contract_inv(np.asarray(ico.vertices), sim)
    dev0 = chord_deviation(ico, world0, sim).max()
    out, rep = to_world(ico, sim, spacing=1.0, tol=dev0 / 4.0)
    assert rep["splits"] >= 1 and rep["within_tolerance"]
    assert rep["max_chord_deviation_h"] <= dev0 / 4.0 and out.is_watertight
    assert len(out.faces) == len(ico.faces) * 4 ** rep["splits"]
    # the world vertices are the mapped (split) field-space vertices
    r = np.linalg.norm((np.asarray(out.vertices) - np.asarray(CENTRE)) / RADIUS, axis=1)
    assert r.max() == pytest.approx(1.0 / (2.0 - 1.9), rel=1e-6)
    same, rep0 = to_world(ico, sim, spacing=1.0, tol=2.0 * dev0)
    assert rep0["splits"] == 0 and len(same.faces) == len(ico.faces)


def _ring_data(root, outward: bool):
    """A Blender data set of 8 cameras on a ring of radius 0.2 around the origin, looking
    outwards (cameras inside the object) or inwards, marked unbounded."""
    import imageio.v3 as iio
    import json

    (root / "train").mkdir(parents=True)
    frames = []
    for k in range(8):
        a = 2 * math.pi * k / 8
        pos = np.array([0.2 * math.cos(a), 0.2 * math.sin(a), 0.0])
        back = pos / np.linalg.norm(pos) * (-1.0 if outward else 1.0)  # OpenGL: looks along -z
        up = np.array([0.0, 0.0, 1.0])
        right = np.cross(up, back)
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, np.cross(back, right), back, pos
        iio.imwrite(root / "train" / f"r_{k}.png", np.full((4, 4, 3), 100, np.uint8))
        frames.append({"file_path": f"train/r_{k}", "transform_matrix": c2w.tolist()})
    (root / "transforms_train.json").write_text(json.dumps(
        {"camera_angle_x": 0.7, "unbounded": True, "frames": frames}))
    return root


def test_bad_input_cameras_inside_the_object_and_bounded_only_commands(tmp_path, capsys):
    from shells.cli import cage_main, lod_main, train_main
    from shells.presets import scene_similarity

    def one_line_error(status: int) -> str:
        err = capsys.readouterr().err.strip().splitlines()
        assert status == 2 and len(err) == 1, err
        return err[0]

    bad = _ring_data(tmp_path / "out", outward=True)
    msg = one_line_error(train_main(["--data", str(bad), "--out", str(tmp_path / "run")]))
    assert "look outwards" in msg and str(bad) in msg
    assert not (tmp_path / "run").exists()  # nothing written
    good = _ring_data(tmp_path / "in", outward=False)
    sim = scene_similarity(good, "auto")  # the file says unbounded
    assert sim is not None and sim.radius == pytest.approx(1.5)  # half the default box side
    assert scene_similarity(good, "bounded") is None
    # an unbounded run refused by the commands for one bounded object
    run = tmp_path / "urun"
    run.mkdir()
    cfg = toy_config()
    cfg.update({"field": {"unbounded": True}}, "test")
    (run / "config.json").write_text(__import__("json").dumps(cfg.to_dict()))
    (run / "run.json").write_text('{"data": "x", "downscale": 1, "format": 1}')
    for main in (cage_main, lod_main):
        assert "unbounded scene" in one_line_error(main([str(run)]))


def test_regularisers_act_on_the_network_not_on_the_far_solid():
    """The far solid is an exact SDF with exact normals and a constant kernel: on
    min(f_net, solid) the Eikonal, normal and smoothness terms could be zeroed by raising
    f_net above it. They see the network alone."""
    from shells.train.stage1 import regularisers

    f = _field(seed=5)
    g = torch.Generator().manual_seed(0)
    u = torch.nn.functional.normalize(torch.randn(500, 3, generator=g), dim=1)
    z = torch.tensor(CENTRE) + u * RADIUS * 1.97  # all beyond the far radius
    with torch.no_grad():
        assert torch.equal(f.sdf(z), f._dome(z))  # the solid is what renders there
        reg = regularisers(f, z, 1e-3, 1e-2, torch.Generator().manual_seed(1))
        grad = f.sdf_gradient_fd(z, 1e-3, far=False)
        eik = ((grad.norm(dim=-1) - 1.0) ** 2).mean()
        # on the solid the terms would be 0 (|grad| = 1, normal = -y / |y|, constant s)
        assert float(f.sdf_gradient_fd(z, 1e-3).norm(dim=-1).sub(1).abs().max()) < 1e-2
    torch.testing.assert_close(reg["eikonal"], eik)
    assert float(reg["eikonal"]) > 1e-3 and float(reg["normal"]) > 1e-3
    assert float(reg["smooth"]) > 0.0


def test_occupancy_and_band_baselines_agree_with_full_rays_on_an_unbounded_field():
    """The untrained field (the init sphere inside the far solid): the occupancy-grid march in
    s and the band render of its shells give the full-ray colours with far fewer samples."""
    from shells.levelset.grid import sample_grid
    from shells.render.frame import render_rays
    from shells.render.raycast import ShellScene

    mitsuba_variant()
    f = _field(randomise=False)
    with torch.no_grad():  # a little colour and view dependence, so the colours differ
        f.rad_mlp[-1].bias.copy_(torch.tensor([0.3, -0.2, 0.1]))
    twin = DrJitField(f)
    g = torch.Generator().manual_seed(0)
    o = torch.tensor(CENTRE) + torch.nn.functional.normalize(torch.randn(300, 3, generator=g),
                                                             dim=1) * 2.0 * RADIUS
    aim = torch.tensor(CENTRE) + 0.6 * torch.randn(300, 3, generator=g)
    d = torch.nn.functional.normalize(aim - o, dim=1)
    cfg = dataclasses.replace(RenderConfig(), full_samples=1024, occ_resolution=64)
    full, n_full = render_rays(twin, o, d, cfg, "full")
    occ, n_occ = render_rays(twin, o, d, cfg, "occupancy")
    ref = full.numpy()
    assert np.abs(occ.numpy() - ref).max() < 0.03
    assert n_occ.numpy().mean() < 0.5 * n_full.numpy().mean()
    # shells of the same field, extracted in field space and mapped to the world
    with torch.no_grad():
        fz, sz, _ = sample_grid(lambda z: (f.geometry_field(z)["sdf"],
                                           f.geometry_field(z)["s"]), f.aabb.numpy(), 96)
    sh = extract_shells(fz, sz, f.aabb.numpy(), ShellConfig(resolution=96),
                        roi=(CENTRE, RADIUS))
    h = float((f.aabb[1, 0] - f.aabb[0, 0]) / 95)
    outer, _ = to_world(sh.outer, f.similarity, h, far=f.cfg.far_radius)
    inner, _ = to_world(sh.inner, f.similarity, h, far=f.cfg.far_radius)
    scene = ShellScene((np.asarray(outer.vertices), np.asarray(outer.faces)),
                       (np.asarray(inner.vertices), np.asarray(inner.faces)))
    band, n_band = render_rays(twin, o, d, cfg, "band", scene)
    assert np.abs(band.numpy() - ref).max() < 0.03
    assert n_band.numpy().mean() < 0.1 * n_full.numpy().mean()
    # early termination, and the peel on demand from t_near: within the light left
    ert = dataclasses.replace(cfg, band_ert_eps=1e-3)
    one, _ = render_rays(twin, o, d, ert, "band", scene)
    steps, _ = render_rays(twin, o, d, dataclasses.replace(ert, band_peel_step=1), "band",
                           scene)
    assert np.abs(steps.numpy() - one.numpy()).max() <= 1e-3 + 1e-6
