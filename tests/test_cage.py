"""The tetrahedral cage and deformed rendering (paper §5): containment, point location, the
identity and rigid motions against the undeformed renderer, a bend without holes, the FEM
solver's forces and motion, motion files, and the shells-cage / shells-animate commands."""

from __future__ import annotations

import json
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import torch
import trimesh

from shells.config import RenderConfig
from shells.deform import fem
from shells.deform.motions import (ANALYTIC, AssetFrame, bend, read_motion_file, rigid,
                                   rigid_motion)
from shells.device import mitsuba_variant
from shells.errors import InputError
from shells.fields.drjit_field import FieldSample
from shells.levelset.cage import (TetLocator, boundary_faces, build_cage, is_watertight,
                                  orient, tet_volumes)
from shells.levelset.mesh import clean_mesh, marching_cubes
from shells.metrics import psnr
from shells.render.deformed import CageAsset
from shells.render.frame import render_rays
from shells.render.raycast import ShellScene
from shells.render.sampler import place_packed
from shells.render.shading import composite_packed, shade_samples

BOX = [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]


class CapsuleField:
    """Analytic field: a capsule along z (radius r, axis from -half to +half), constant kernel,
    a colour that varies with position (so motions are visible) and with the view direction
    (so the direction's transport is checked too)."""

    def __init__(self, r: float = 0.2, half: float = 0.6, s: float = 0.004) -> None:
        self.r, self.half, self.s = r, half, s

    def sdf_numpy(self, p: np.ndarray) -> np.ndarray:
        zc = np.clip(p[..., 2], -self.half, self.half)
        return np.sqrt(p[..., 0] ** 2 + p[..., 1] ** 2 + (p[..., 2] - zc) ** 2) - self.r

    def eval(self, x, d):
        x = mi.Point3f(x)
        zc = dr.clip(x.z, -self.half, self.half)
        v = mi.Vector3f(x.x, x.y, x.z - zc)
        dist = dr.norm(v)
        n = v / dr.maximum(dist, 1e-8)
        d = mi.Vector3f(d)
        rgb = mi.Color3f(0.5 + 0.3 * dr.sin(6 * x.x + 1) + 0.15 * d.x,
                         0.5 + 0.3 * dr.sin(5 * x.y + 2) + 0.15 * d.y,
                         0.5 + 0.3 * dr.sin(7 * x.z) + 0.15 * d.z)
        return FieldSample(sdf=dist - self.r, s=dr.full(mi.Float, self.s, dr.width(dist)),
                           normal=n, rgb=rgb)


def _grid_mesh(f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    m = clean_mesh(marching_cubes(f.astype(np.float32), BOX))
    return np.asarray(m.vertices), np.asarray(m.faces)


@pytest.fixture(scope="module")
def capsule():
    """The capsule field, shells 0.05 outside / inside its surface, and a cage around them."""
    mitsuba_variant()
    field = CapsuleField()
    g = np.linspace(-1, 1, 81)
    P = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1)
    f = field.sdf_numpy(P)
    outer, inner = _grid_mesh(f - 0.05), _grid_mesh(f + 0.05)
    cage, emb = build_cage(outer, inner, resolution=32, edge_length=0.05, threads=1)
    return field, outer, inner, cage, emb


def _rays(width: int, eye=(0.0, -3.0, 0.3), fov: float = 0.75):
    """Pinhole rays [W * W, 3] from ``eye`` looking at the origin, z up."""
    eye = np.asarray(eye, np.float64)
    fwd = -eye / np.linalg.norm(eye)
    right = np.cross(fwd, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    j, i = np.meshgrid(np.arange(width) + 0.5, np.arange(width) + 0.5, indexing="ij")
    f = 0.5 * width / math.tan(fov / 2)
    d = ((i - width / 2) / f)[..., None] * right - ((j - width / 2) / f)[..., None] * up + fwd
    d = (d / np.linalg.norm(d, axis=-1, keepdims=True)).reshape(-1, 3)
    return np.broadcast_to(eye, d.shape).copy(), d


def _render(field, scene, o, d, bg=(1.0, 1.0, 1.0)) -> np.ndarray:
    colour, _ = render_rays(field, o.astype(np.float32), d.astype(np.float32), RenderConfig(),
                            "band", scene=scene, background=bg)
    return np.asarray(colour).T.copy()


# --------------------------------------------------------------------------------------------
# The cage
# --------------------------------------------------------------------------------------------

def test_cage_contains_the_shells_and_is_watertight(capsule):
    field, outer, inner, cage, emb = capsule
    V, T = cage.vertices, cage.tets
    assert np.all(tet_volumes(V, T) > 0)
    bf = boundary_faces(T)
    assert is_watertight(bf) and cage.stats["watertight"]
    closed = trimesh.Trimesh(V, bf, process=False)
    assert closed.is_watertight and closed.volume == pytest.approx(tet_volumes(V, T).sum())
    for name, (Vm, _) in (("outer", outer), ("inner", inner)):
        tet, w = emb[f"{name}_tet"], emb[f"{name}_w"]
        assert len(tet) == len(Vm) and np.all(tet >= 0)  # every vertex in a tetrahedron
        assert np.all(w >= -1e-4) and np.allclose(w.sum(1), 1.0)
        np.testing.assert_allclose(np.einsum("kj,kjc->kc", w, V[T[tet]]), Vm, atol=1e-5)
    # and every point of the solid bounded by M+ (random points with f <= 0.05) too
    rng = np.random.default_rng(0)
    p = rng.uniform(-1, 1, (20000, 3))
    p = p[field.sdf_numpy(p) <= 0.05]
    tet, _ = TetLocator(V, T).locate_numpy(p)
    assert np.all(tet >= 0)


def test_locator_agrees_with_brute_force(capsule):
    _, _, _, cage, _ = capsule
    V, T = cage.vertices, cage.tets
    rng = np.random.default_rng(1)
    lo, hi = V.min(0) - 0.05, V.max(0) + 0.05
    p = rng.uniform(lo, hi, (3000, 3))
    tet, w = TetLocator(V, T).locate_numpy(p)
    D = np.stack([V[T[:, k]] - V[T[:, 0]] for k in (1, 2, 3)], -1)
    Dinv = np.linalg.inv(D)
    b = np.einsum("mij,pmj->pmi", Dinv, p[:, None, :] - V[T[:, 0]][None])
    bmin = np.minimum(1 - b.sum(-1), b.min(-1))  # [P, M] smallest barycentric coordinate
    inside_any = (bmin >= -1e-5).any(1)
    assert np.array_equal(tet >= 0, inside_any)
    found = tet >= 0
    assert np.all(bmin[np.flatnonzero(found), tet[found]] >= -1e-5)
    np.testing.assert_allclose(np.einsum("kj,kjc->kc", w[found], V[T[tet[found]]]), p[found],
                               atol=1e-5)


def test_building_a_cage_writes_nothing_into_the_working_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # fTetWild writes a debug file into its working folder
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    cage, _ = build_cage((sphere.vertices, sphere.faces), resolution=12, edge_length=0.2,
                         threads=1)
    assert len(cage.tets) > 0 and list(tmp_path.iterdir()) == []


def test_bad_cage_input_is_refused(capsule):
    _, outer, inner, _, _ = capsule
    with pytest.raises(InputError, match="outer shell is empty"):
        build_cage((outer[0][:0], outer[1][:0]))
    with pytest.raises(InputError, match="--margin"):
        build_cage(outer, inner, margin=-1.0)
    with pytest.raises(InputError, match="NaN"):
        TetLocator(np.full((4, 3), np.nan), np.array([[0, 1, 2, 3]]))


# --------------------------------------------------------------------------------------------
# Deformed rendering
# --------------------------------------------------------------------------------------------

def test_identity_deformation_equals_the_band_render(capsule):
    field, outer, inner, cage, emb = capsule
    o, d = _rays(48)
    want = _render(field, ShellScene(outer, inner), o, d)
    asset = CageAsset(field, cage.vertices, cage.tets, emb, outer[1], inner[1])
    dfield, dscene = asset.pose(cage.vertices.copy())
    got = _render(dfield, dscene, o, d)
    assert (want < 0.99).mean() > 0.1  # the capsule covers part of the frame
    assert np.abs(got - want).max() <= 1e-4


def test_rigid_motion_equals_the_moved_camera(capsule):
    """Cage moved by x -> R (x - c) + c + l, seen by camera C, equals the rest asset seen by
    the camera moved by the inverse motion."""
    field, outer, inner, cage, emb = capsule
    frame = AssetFrame.of(cage.vertices)
    t = 0.6
    R, lift = rigid_motion(t, frame)
    P = rigid(cage.vertices, t, frame)
    np.testing.assert_allclose(P, (cage.vertices - frame.centre) @ R.T + frame.centre + lift,
                               atol=1e-12)
    asset = CageAsset(field, cage.vertices, cage.tets, emb, outer[1], inner[1])
    dfield, dscene = asset.pose(P)
    o, d = _rays(64)
    got = _render(dfield, dscene, o, d)
    o_rest = (o - frame.centre - lift) @ R + frame.centre  # R^T (o - c - l) + c, rows
    d_rest = d @ R
    want = _render(field, ShellScene(outer, inner), o_rest, d_rest)
    assert (want < 0.99).mean() > 0.1
    value = psnr(torch.from_numpy(got).reshape(64, 64, 3), torch.from_numpy(want).reshape(64, 64, 3))
    assert value >= 40.0, value


def test_rigid_motion_of_a_trained_toy_run_equals_the_moved_camera(tmp_path):
    """The same check on a trained run: its torch-trained field (Dr.Jit twin), its extracted
    shells and an fTetWild cage of them."""
    from shells.data.datasets import load_dataset
    from shells.fields.drjit_field import DrJitField
    from shells.levelset.mesh import load_ply
    from shells.render.views import render_view
    from shells.run import RunDir, load_field, load_shells, read_run
    from tests.conftest import tiny_config, trained_run

    run = RunDir(trained_run(tmp_path, tiny_config(train_iters=30)))
    field, cfg = load_field(run.root)
    dj = DrJitField(field)
    outer, inner = load_ply(run.outer), load_ply(run.inner)
    cage, emb = build_cage(outer, inner, resolution=24, edge_length=0.1, threads=1)
    frame = AssetFrame.of(cage.vertices)
    R, lift = rigid_motion(0.6, frame)
    dfield, dscene = CageAsset(dj, cage.vertices, cage.tets, emb, outer[1],
                               inner[1]).pose(rigid(cage.vertices, 0.6, frame))
    data = load_dataset(read_run(run)["data"], "test")
    cams = data.cameras[:1].resized(48, 48)
    bg = tuple(cfg.data.background)
    got = render_view(dfield, cams, 0, cfg.render, "band", dscene, data.aabb, bg)[0]
    # the camera moved by the inverse motion x -> R^T (x - c - l) + c
    Rt = torch.as_tensor(R.T, dtype=torch.float32)
    c, l = (torch.as_tensor(v, dtype=torch.float32) for v in (frame.centre, lift))
    cams.c2w[0, :3, :3] = Rt @ cams.c2w[0, :3, :3]
    cams.c2w[0, :3, 3] = Rt @ (cams.c2w[0, :3, 3] - c - l) + c
    want = render_view(dj, cams, 0, cfg.render, "band", load_shells(run), data.aabb, bg)[0]
    assert (want - torch.tensor(bg)).abs().amax(-1).gt(0.05).float().mean() > 0.05  # visible
    value = psnr(got, want)
    assert value >= 40.0, value


def _opacity(field, scene, o, d) -> np.ndarray:
    """Opacity of the band render per ray, before the solid-end rule (a hole shows here even
    where the ray ends on M-)."""
    o, d = mi.Point3f(*o.T.astype(np.float32)), mi.Vector3f(*d.T.astype(np.float32))
    samples = place_packed(scene.intervals(o, d, 8), RenderConfig())
    alpha, rgb = shade_samples(field, samples, o, d)
    _, opacity = composite_packed(alpha, rgb, samples.start, samples.count, mi.Color3f(1.0))
    return opacity.numpy()


def test_bend_renders_without_holes(capsule):
    """Every pixel whose ray passes through the deformed solid (dense march through the same
    cage map, at least 0.02 deep: no grazing rays) is opaque in the band render."""
    field, outer, inner, cage, emb = capsule
    frame = AssetFrame.of(cage.vertices)
    P = bend(cage.vertices, 0.5, frame)  # the top turned by 60 degrees
    assert np.abs(P - cage.vertices).max() > 0.3  # a real bend
    asset = CageAsset(field, cage.vertices, cage.tets, emb, outer[1], inner[1])
    dfield, dscene = asset.pose(P)
    o, d = _rays(64, eye=(0.0, -3.2, 0.4))
    opacity = _opacity(dfield, dscene, o, d)
    ts = np.linspace(1.5, 4.5, 1500)  # the deformed asset lies within 1.2 of the origin
    x = (o[:, None, :] + ts[None, :, None] * d[:, None, :]).reshape(-1, 3)
    f = dfield.eval(mi.Point3f(*x.T.astype(np.float32)),
                    mi.Vector3f(*np.repeat(d, len(ts), 0).T.astype(np.float32))).sdf.numpy()
    inside = (f.reshape(len(o), len(ts)) < -0.02).any(1)
    assert inside.mean() > 0.05  # ~340 of the 4096 pixels
    assert opacity[inside].min() >= 0.99, f"{(opacity[inside] < 0.99).sum()} holes"


# --------------------------------------------------------------------------------------------
# FEM
# --------------------------------------------------------------------------------------------

def _cube_mesh(n: int = 3, size: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """A cube of n^3 cells, 6 tetrahedra per cell (Kuhn: around the cell's diagonal),
    positively oriented."""
    g = np.linspace(0, size, n + 1)
    X = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    idx = np.arange((n + 1) ** 3).reshape(n + 1, n + 1, n + 1)
    T = []
    for i in range(n):
        for j in range(n):
            for k in range(n):
                c = [idx[i + a, j + b, k + e] for a in (0, 1) for b in (0, 1) for e in (0, 1)]
                v0, v7 = c[0], c[7]
                for p in ((4, 6), (4, 5), (2, 6), (2, 3), (1, 5), (1, 3)):
                    T.append([v0, c[p[0]], c[p[1]], v7])
    return X, orient(X, np.array(T))


def test_fem_rest_state_has_no_force_and_forces_are_the_energy_gradient():
    X, T = _cube_mesh(2)
    el = fem.Elastic(X, T, fem.Material(young=1e4, poisson=0.3))
    assert np.abs(el.elastic_forces(X)).max() < 1e-9 and el.elastic_energy(X) == 0.0
    rng = np.random.default_rng(0)
    x = X + 0.03 * rng.standard_normal(X.shape)
    f = el.elastic_forces(x)
    np.testing.assert_allclose(f.sum(0), 0.0, atol=1e-9)  # internal forces: no net force
    h = 1e-6
    for v, c in [(0, 0), (5, 1), (13, 2), (26, 0)]:
        xp, xm = x.copy(), x.copy()
        xp[v, c] += h
        xm[v, c] -= h
        num = -(el.elastic_energy(xp) - el.elastic_energy(xm)) / (2 * h)
        assert f[v, c] == pytest.approx(num, rel=1e-5, abs=1e-7)
    # a rotation stores no energy (the model is frame-invariant)
    Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    assert el.elastic_energy(X @ Rz.T) == pytest.approx(0.0, abs=1e-9)


def test_fem_free_fall_is_rigid_and_follows_gravity():
    X, T = _cube_mesh(2)
    fps, frames = 10.0, 6
    P, info = fem.simulate(X, T, frames, fps, fem.Material(damping=0.0), fem.Scenario(),
                           progress=False)
    disp = P - X
    np.testing.assert_allclose(disp, disp[:, :1, :].repeat(len(X), 1), atol=1e-9)  # rigid
    dt, n = info["dt"], np.arange(frames) * info["substeps_per_frame"]
    want = -9.81 * dt * dt * n * (n + 1) / 2  # symplectic Euler: x_n = -g dt^2 n (n + 1) / 2
    np.testing.assert_allclose(disp[:, 0, 2], want, rtol=1e-9, atol=1e-12)
    t = np.arange(frames) / fps
    np.testing.assert_allclose(disp[:, 0, 2], -0.5 * 9.81 * t ** 2, atol=9.81 * dt * t.max())


def test_fem_drop_stays_above_ground_and_hang_keeps_its_pins():
    X, T = _cube_mesh(2)
    P, info = fem.drop(X, T, 30, 24.0, progress=False)
    assert P[0, :, 2].min() == pytest.approx(0.4 * 0.5)  # lifted by 40 % of its height
    assert P[:, :, 2].min() >= -1e-12  # never below the ground (its rest base, z = 0)
    assert P[-1, :, 2].min() < 1e-6  # it landed
    P, info = fem.hang(X, T, 20, 24.0, progress=False)
    top = X[:, 2] >= X[:, 2].max() - 0.05
    assert info["pinned_vertices"] == int(top.sum()) > 0
    np.testing.assert_array_equal(P[:, top], np.broadcast_to(X[top], P[:, top].shape))
    assert P[-1, ~top, 2].mean() < X[~top, 2].mean() - 1e-3  # the rest sags


# --------------------------------------------------------------------------------------------
# Motions
# --------------------------------------------------------------------------------------------

def test_analytic_motions_are_identity_at_the_start_and_finite():
    rng = np.random.default_rng(0)
    X = rng.uniform(-0.5, 0.5, (200, 3))
    frame = AssetFrame.of(X)
    for name, fn in ANALYTIC.items():
        P = fn(X, 0.0, frame)
        assert np.all(np.isfinite(fn(X, 0.37, frame)))
        if name != "wind":  # wind starts swaying at once (sin of a travelling phase)
            np.testing.assert_allclose(P, X, atol=1e-12)
    # the bend keeps the base and the centre line's length
    line = np.stack([np.zeros(50), np.zeros(50), np.linspace(-0.5, 0.5, 50)], 1)
    line_frame = AssetFrame(centre=np.zeros(3), up=np.array([0.0, 0, 1]),
                            side=np.array([1.0, 0, 0]), base=-0.5, height=1.0)
    B = bend(line, 0.5, line_frame)
    np.testing.assert_allclose(B[0], line[0], atol=1e-12)
    assert np.linalg.norm(np.diff(B, axis=0), axis=1).sum() == pytest.approx(1.0, rel=1e-3)


def test_motion_file_is_checked(tmp_path):
    good = tmp_path / "m.npz"
    np.savez(good, positions=np.zeros((3, 10, 3)), fps=12.0)
    P, fps = read_motion_file(good, 10)
    assert P.shape == (3, 10, 3) and fps == 12.0
    with pytest.raises(InputError, match=r"\[frames, 11, 3\]"):
        read_motion_file(good, 11)
    bad = tmp_path / "bad.npz"
    np.savez(bad, other=np.zeros(3))
    with pytest.raises(InputError, match="no 'positions'"):
        read_motion_file(bad, 10)
    with pytest.raises(InputError, match="no such motion file"):
        read_motion_file(tmp_path / "missing.npz", 10)


# --------------------------------------------------------------------------------------------
# Commands
# --------------------------------------------------------------------------------------------

def test_cage_and_animate_commands(tmp_path, capsys):
    import imageio.v2 as iio2
    import imageio.v3 as iio

    from shells.cli import animate_main, cage_main, render_main
    from tests.conftest import tiny_config, trained_run

    run = trained_run(tmp_path, tiny_config())
    capsys.readouterr()

    def one_line_error(status: int) -> str:
        err = capsys.readouterr().err.strip().splitlines()
        assert status == 2 and len(err) == 1, err
        return err[0]

    assert "run shells-cage" in one_line_error(
        animate_main([str(run), "--motion", "still", "--frames", "2"]))
    assert cage_main([str(run), "--threads", "1", "--resolution", "24",
                      "--edge-length", "0.1"]) == 0
    stats = json.loads((run / "cage" / "cage.json").read_text())
    assert stats["watertight"] and stats["tetrahedra"] > 0
    assert (run / "cage" / "cage.vtu").read_text().startswith("<?xml")
    assert "run shells-lod" in one_line_error(cage_main([str(run), "--shells", "lod"]))
    assert "--motion nonsense" in one_line_error(
        animate_main([str(run), "--motion", "nonsense", "--frames", "2"]))
    assert not (run / "animate-nonsense").exists()
    # the identity motion: every frame is the band render of the same camera
    assert animate_main([str(run), "--motion", "still", "--frames", "2"]) == 0
    assert render_main([str(run), "--split", "test"]) == 0
    a = iio.imread(run / "animate-still" / "r_001.png").astype(int)
    b = iio.imread(run / "render-band" / "r_000.png").astype(int)
    assert np.abs(a - b).max() <= 1
    assert animate_main([str(run), "--motion", "wind", "--frames", "3"]) == 0
    out = run / "animate-wind"
    assert len(iio2.mimread(out / "video.mp4")) == 3  # decodes with the ffmpeg plugin
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames"] == 3 and m["motion"]["name"] == "wind"
    with np.load(out / "motion.npz") as z:
        assert z["positions"].shape == (3, stats["vertices"], 3)
    # a motion file: the saved wind poses replayed give the same frames
    assert animate_main([str(run), "--motion", str(out / "motion.npz"), "--out",
                         str(tmp_path / "replay")]) == 0
    for k in range(3):
        assert np.array_equal(iio.imread(out / f"r_{k:03d}.png"),
                              iio.imread(tmp_path / "replay" / f"r_{k:03d}.png"))
