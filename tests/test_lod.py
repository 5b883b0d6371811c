"""Shell levels of detail (shells.levelset.lod): the coarse shells contain the fine ones, are
closed, free of self-intersections, and keep the enter/exit parity of rays; analytic shapes."""

from __future__ import annotations

import numpy as np
import pytest

from shells.errors import InputError
from shells.levelset.containment import (inside, is_closed, parity_check,
                                         self_intersecting_faces, verify)
from shells.levelset.lod import LodParams, Phases, make_lod
from shells.levelset.mesh import clean_mesh, marching_cubes

BOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
RES = 72
H = 2.0 / (RES - 1)


def _grid():
    x = np.linspace(-1, 1, RES, dtype=np.float32)
    return np.meshgrid(x, x, x, indexing="ij")


def capsule(r: float, half: float) -> np.ndarray:  # SDF of a capsule along x
    X, Y, Z = _grid()
    q = np.stack([np.maximum(np.abs(X) - half, 0), Y, Z])
    return np.sqrt((q ** 2).sum(0)) - r


def sphere(r: float) -> np.ndarray:
    X, Y, Z = _grid()
    return np.sqrt(X ** 2 + Y ** 2 + Z ** 2) - r


def shells_of(f: np.ndarray, w_out: float, w_in: float):
    outer = clean_mesh(marching_cubes(f - w_out, BOX))
    inner = clean_mesh(marching_cubes(f + w_in, BOX))
    return (outer.vertices, outer.faces), (inner.vertices, inner.faces)


@pytest.fixture(scope="module", params=["sphere", "capsule"])
def lod(request):
    f = sphere(0.5) if request.param == "sphere" else capsule(0.3, 0.35)
    outer, inner = shells_of(f, 0.06, 0.06)
    co, ci, stats = make_lod(outer, inner, 10.0, BOX[0], H, parity_rays=100_000, box=BOX)
    return f, outer, inner, co, ci, stats


def test_fewer_triangles(lod):
    _, outer, inner, co, ci, stats = lod
    # both shells reach the ratio (the issue's >= 10x; 9.8 for the decimation's rounding)
    assert stats["outer"]["reduction"] >= 9.8 and len(co[1]) * 9.8 <= len(outer[1])
    assert stats["inner"]["reduction"] >= 9.8 and len(ci[1]) * 9.8 <= len(inner[1])


def test_containment_of_vertices_and_grid_points(lod):
    f, outer, inner, co, ci, stats = lod
    assert stats["outer"]["check"]["passed"] and stats["inner"]["check"]["passed"]
    assert inside(*co, outer[0]).all()  # fine M+ vertices inside coarse M+
    assert not inside(*outer, co[0]).any()  # coarse M+ vertices outside fine M+
    assert not inside(*ci, inner[0]).any()  # fine M- vertices outside coarse M-
    assert inside(*inner, ci[0]).all()  # coarse M- vertices inside fine M-
    X, Y, Z = _grid()
    pts = np.stack([X, Y, Z], -1).reshape(-1, 3).astype(np.float64)
    content = pts[f.reshape(-1) <= 0]  # grid points with f <= 0: all inside coarse M+
    assert inside(*co, content).all()
    in_coarse_inner = inside(*ci, pts)  # grid points inside coarse M-: inside fine M- (f <= -w)
    assert (f.reshape(-1)[in_coarse_inner] <= -0.06 + 1e-3).all()


def test_closed_and_no_self_intersections(lod):
    _, _, _, co, ci, _ = lod
    for C in (co, ci):
        assert is_closed(C[1])
        assert not self_intersecting_faces(*C).any()


def test_parity_on_random_rays(lod):
    _, _, _, co, ci, stats = lod
    for C, name in ((co, "outer"), (ci, "inner")):
        par = parity_check(*C, 100_000, BOX, seed=1)
        assert par["rays_hitting"] > 10_000
        assert par["parity_fraction"] >= 0.9999  # grazing rays at an edge may double-count
        assert stats[name]["parity"]["parity_fraction"] >= 0.9999


def test_band_only_grows(lod):
    _, outer, inner, co, ci, stats = lod
    # offsets are on the allowed side, and tight: at most a few grid cells
    for name in ("outer", "inner"):
        off = stats[name]["offset_coarse_vertices_over_h"]
        assert off["min"] > -0.05 and off["p50"] < 2.0


def test_verify_detects_a_cut():
    f = sphere(0.5)
    outer, _ = shells_of(f, 0.06, 0.06)
    small, _ = shells_of(f, 0.0, 0.06)  # the surface itself: inside M+, not containing it
    check = verify(small, outer, +1)
    assert not check["contained"] and not check["passed"]


def test_phases_bar_ends_full_after_a_retry(capsys):
    ph = Phases(3, enabled=True)
    ph.start("outer: signed distance")
    ph.start("outer: offset 0.2 h")
    ph.add(2)  # a retry
    ph.start("outer: offset 0.4 h")
    ph.start("outer: snap")
    assert ph.bar.n == 3 and ph.bar.total == 5
    ph.start("outer: ray parity")
    ph.close()
    assert ph.bar.n == ph.bar.total == 5
    assert "outer: ray parity" in capsys.readouterr().err
    quiet = Phases()  # disabled: counts, prints nothing
    quiet.start("x")
    quiet.close()
    assert capsys.readouterr().err == ""


def test_bad_ratio():
    f = sphere(0.5)
    outer, inner = shells_of(f, 0.06, 0.06)
    with pytest.raises(InputError, match="--ratio"):
        make_lod(outer, inner, 1.0, BOX[0], H, LodParams())


def test_check_names_the_vertices_where_an_inner_shell_fails():
    """`check_side` (whose named vertices `decimate_staged` and `snap` act on): a coarse inner
    sphere of radius 0.8 inside a fine one of radius 1 passes with no vertex named; pushed
    out to 1.2, one coarse vertex is named (with the vertices of its faces, which now cross),
    and the fine vertices its spike swallows are named too; everything else is not."""
    import trimesh

    from shells.levelset.containment import check_side

    fine = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    coarse = trimesh.creation.icosphere(subdivisions=2, radius=0.8)
    S = (np.asarray(fine.vertices), np.asarray(fine.faces))
    V, F = np.asarray(coarse.vertices).copy(), np.asarray(coarse.faces)
    rec, bad_coarse, bad_fine = check_side((V, F), S, -1)
    assert rec["passed"] and not bad_coarse.any() and not bad_fine.any()
    V[7] *= 1.2 / 0.8
    rec, bad_coarse, bad_fine = check_side((V, F), S, -1)
    ring = np.unique(F[(F == 7).any(1)])  # vertex 7 and its neighbours
    assert not rec["passed"] and bad_coarse[7]
    assert set(np.nonzero(bad_coarse)[0]) <= set(ring.tolist())
    swallowed = np.linalg.norm(S[0] - V[7] / np.linalg.norm(V[7]), axis=1) < 0.25
    assert bad_fine.any() and (bad_fine <= swallowed).all()
    assert rec["fine_vertices_ok"] == len(S[0]) - bad_fine.sum()


def test_touched_cells_are_the_cells_a_large_triangle_meets():
    """The conservative rasterisation on cells much smaller than the triangle: every cell
    holding a point of a dense sampling of the triangle is marked, and every marked cell lies
    within half a cell diagonal (grown by 1e-3 cells) of the triangle."""
    import trimesh

    from shells.levelset.lod import touched_cells

    V = np.array([[0.03, 0.11, 0.07], [0.91, 0.23, 0.52], [0.37, 0.87, 0.13]])
    F = np.array([[0, 1, 2]])
    cell, lo, shape = 0.05, np.array([-2, -2, -2]), (25, 25, 25)
    origin = np.zeros(3)
    t = touched_cells(V, F, origin, cell, lo, shape)
    a, b = np.meshgrid(np.linspace(0, 1, 400), np.linspace(0, 1, 400), indexing="ij")
    keep = a + b <= 1
    pts = V[0] + a[keep, None] * (V[1] - V[0]) + b[keep, None] * (V[2] - V[0])
    cells = np.floor((pts - origin) / cell).astype(int) - lo
    assert t[cells[:, 0], cells[:, 1], cells[:, 2]].all()
    centres = origin + (np.argwhere(t) + lo + 0.5) * cell
    near = trimesh.triangles.closest_point(np.repeat(V[None], len(centres), 0), centres)
    d = np.linalg.norm(near - centres, axis=1)
    assert d.max() <= np.sqrt(3) / 2 * cell * (1 + 2e-3) + 1e-9


def test_inside_on_grid_aligned_points():
    """Winding-number inside test of a marching-cubes cube at the grid's own nodes and cell
    centres, where rays along fixed directions run through the mesh's edges and vertices:
    it agrees with the analytic cube at every point at least a quarter cell from its surface."""
    X, Y, Z = _grid()
    f = np.maximum(np.maximum(np.abs(X), np.abs(Y)), np.abs(Z)) - 0.5
    m = clean_mesh(marching_cubes(f, BOX))
    x = np.linspace(-1, 1, RES)
    xs = np.concatenate([x, 0.5 * (x[1:] + x[:-1])])
    P = np.stack(np.meshgrid(xs, xs, xs[::7], indexing="ij"), -1).reshape(-1, 3)
    g = np.abs(P).max(1) - 0.5
    far = np.abs(g) >= 0.25 * H
    assert np.array_equal(inside(m.vertices, m.faces, P[far]), g[far] < 0)


def test_inner_offset_of_a_hollow_ball_leaves_its_cavity_out():
    """A ball of radius 0.6 with a cavity of radius 0.3 (one mesh, the cavity's faces facing
    into it): the grid nodes in the cavity are not reached from outside, yet they are outside
    the solid, so the inner offset surface lies in the shell between the two spheres, at the
    offset asked from both, and passes the containment check."""
    from shells.levelset.lod import DistanceGrid

    X, Y, Z = _grid()
    r = np.sqrt(X ** 2 + Y ** 2 + Z ** 2)
    m = clean_mesh(marching_cubes(np.maximum(r - 0.6, 0.3 - r), BOX))
    S = (np.asarray(m.vertices), np.asarray(m.faces))
    (V, F), info = DistanceGrid(S, BOX[0], H).offset(0.3 * H, -1)
    rv = np.linalg.norm(V, axis=1)
    assert len(F) and info["check"]["passed"] and is_closed(F)
    assert rv.min() > 0.3 + 0.2 * H and rv.max() < 0.6 - 0.2 * H
    assert np.abs(rv - 0.6).min() < 0.5 * H and np.abs(rv - 0.3).min() < 0.5 * H  # both sides


def test_outer_offset_contains_and_sits_at_its_offset():
    """The outer offset of a sphere of radius 0.5 at 0.3 cells: contains it, and its vertices
    lie 0.3 cells out (to a tenth of a cell: marching cubes of an exact distance)."""
    from shells.levelset.lod import DistanceGrid

    f = sphere(0.5)
    m = clean_mesh(marching_cubes(f, BOX))
    S = (np.asarray(m.vertices), np.asarray(m.faces))
    (V, F), info = DistanceGrid(S, BOX[0], H).offset(0.3 * H, +1)
    assert info["check"]["passed"] and len(info["rounds"]) == 1
    d = np.linalg.norm(V, axis=1) - np.linalg.norm(S[0], axis=1).mean()
    assert np.abs(d - 0.3 * H).max() < 0.1 * H


def test_snap_moves_a_coarse_inner_shell_toward_the_fine_one_and_keeps_it_inside():
    """A coarse sphere of radius 0.8 inside a fine one of radius 1 (h = 0.02): three passes at
    0.4 of the distance bring it from 0.2 to within 0.06 of the fine sphere on average, and it
    still passes the containment check (chords of a convex shell stay inside)."""
    import trimesh

    from shells.levelset.containment import check_side
    from shells.levelset.lod import snap

    fine = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    coarse = trimesh.creation.icosphere(subdivisions=2, radius=0.8)
    S = (np.asarray(fine.vertices), np.asarray(fine.faces))
    (V, F), info = snap((np.asarray(coarse.vertices), np.asarray(coarse.faces)), S, -1, 0.02,
                        LodParams())
    r = np.linalg.norm(V, axis=1)
    assert info["check"]["passed"] and check_side((V, F), S, -1)[0]["passed"]
    assert r.max() < 1.0 and 1.0 - r.mean() < 0.06 and len(info["passes"]) == 3
