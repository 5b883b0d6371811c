"""Shell meshes: marching cubes, cleanup, PLY I/O, extract_shells, write_shells, slice figure."""

from __future__ import annotations

import json
import math

import imageio.v3 as iio
import numpy as np
import pytest

from shells.config import ShellConfig
from shells.errors import InputError
from shells.levelset import extract as extract_mod
from shells.levelset.extract import extract_shells, normal_distances, write_shells
from shells.levelset.figure import slice_figure
from shells.levelset.mesh import (clean_mesh, empty_mesh, load_ply, marching_cubes,
                                  write_ply)

BOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def grid(res: int):
    x = np.linspace(-1, 1, res, dtype=np.float32)
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    return X, Y, Z, float(x[1] - x[0])


def sphere(res: int, r: float = 0.5, centre=(0.0, 0.0, 0.0)) -> np.ndarray:
    X, Y, Z, _ = grid(res)
    return np.sqrt((X - centre[0]) ** 2 + (Y - centre[1]) ** 2 + (Z - centre[2]) ** 2) - r


def mean_width(f: np.ndarray, s: float | np.ndarray, cfg=None) -> float:
    s_grid = np.broadcast_to(np.float32(s), f.shape) if np.isscalar(s) else s
    sh = extract_shells(f, s_grid, BOX, cfg or ShellConfig())
    return sh.stats["band_width"]["mean"]


def check_containment(sh, f: np.ndarray, rng, n_points: int = 600):
    """Grid points with f0 <= 0 lie inside M+; points inside M- have f0 <= 0 (on the grid, and
    via trimesh's ray-test `contains` on grid points and random points)."""
    assert (sh.sdf_plus <= f).all() and (sh.sdf_minus >= f).all()
    X, Y, Z, h = grid(f.shape[0])
    pts = np.stack([X, Y, Z], -1).reshape(-1, 3).astype(np.float64)
    fv = f.reshape(-1)
    # grid points clearly inside (1e-3 h: away from ray-test round-off on the surface)
    inside0 = pts[fv < -1e-3 * h]
    pick = rng.choice(len(inside0), min(n_points, len(inside0)), replace=False)
    assert sh.outer.contains(inside0[pick]).all()
    if len(sh.inner.faces):
        cand = rng.uniform(-1, 1, size=(n_points, 3))
        inside_inner = cand[sh.inner.contains(cand)]
        # f at those points by trilinear interpolation of the grid: <= 0 up to the marching
        # cubes' own linear-interpolation error (points lie inside M- = {SDF- <= 0} and
        # SDF- >= f0 on the grid)
        from scipy import ndimage
        idx = ((inside_inner - BOX[0]) / h).T
        f_at = ndimage.map_coordinates(f, idx, order=1)
        assert (f_at <= 1e-6).all()
        # and grid points inside M- have f0 <= 0 exactly
        sub = rng.choice(len(pts), n_points, replace=False)
        grid_in = sh.inner.contains(pts[sub])
        assert (fv[sub][grid_in] <= 0).all()


# ------------------------------------------------------------------------------------------
# marching cubes, cleanup, PLY
# ------------------------------------------------------------------------------------------

def test_marching_cubes_sphere_area_volume_orientation():
    m = marching_cubes(sphere(80), BOX)
    # area 4 pi r^2 = 3.14159, volume 4/3 pi r^3 = 0.523599
    assert m.area == pytest.approx(4 * math.pi * 0.25, rel=0.01)
    assert m.volume == pytest.approx(4 / 3 * math.pi * 0.125, rel=0.01)
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    # outward normals: face normal . centroid > 0 on a sphere around the origin
    assert (np.einsum("ij,ij->i", m.face_normals, m.triangles_center) > 0).all()


def test_marching_cubes_closes_surfaces_cut_by_the_box():
    f = np.minimum(sphere(48), sphere(48, 0.3, (0.9, 0, 0)))  # pokes out through x = 1
    m = clean_mesh(marching_cubes(f, BOX))
    assert m.is_watertight and m.volume > 0
    assert m.bounds[1, 0] == pytest.approx(1.0)  # capped on the box face, not beyond
    assert len(marching_cubes(np.ones((8, 8, 8)), BOX).faces) == 0


def test_clean_mesh_drops_small_components():
    f = np.minimum(sphere(48), sphere(48, 0.08, (0.75, 0.75, 0.75)))  # floater ~3 % of faces
    m = marching_cubes(f, BOX)
    assert len(m.split(only_watertight=False)) == 2
    kept = clean_mesh(m, min_component_fraction=0.05)
    assert len(kept.split(only_watertight=False)) == 1 and kept.is_watertight
    assert len(clean_mesh(m, 0.0).split(only_watertight=False)) == 2


def test_ply_roundtrip_and_empty(tmp_path):
    m = marching_cubes(sphere(24), BOX)
    write_ply(tmp_path / "a.ply", m)
    V, F = load_ply(tmp_path / "a.ply")
    assert V.dtype == np.float32 and F.dtype == np.int32
    np.testing.assert_allclose(V, m.vertices, atol=1e-6)  # float32 storage
    np.testing.assert_array_equal(F, m.faces)
    write_ply(tmp_path / "e.ply", empty_mesh())
    V, F = load_ply(tmp_path / "e.ply")
    assert V.shape == (0, 3) and F.shape == (0, 3)
    with pytest.raises(InputError, match="not found"):
        load_ply(tmp_path / "missing.ply")
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat nonsense\n")
    with pytest.raises(InputError, match="bad.ply"):
        load_ply(tmp_path / "bad.ply")


# ------------------------------------------------------------------------------------------
# band width against the kernel size
# ------------------------------------------------------------------------------------------

def test_band_width_grows_with_kernel_size():
    f = sphere(64)
    s_values = [0.002, 0.005, 0.01, 0.02, 0.05]
    widths = [mean_width(f, s) for s in s_values]
    # thin for opaque kernels: dilation 5 * beta_d * s = 3 s (a little less: the falloff
    # omega(f) < 1 off the surface) plus erosion 5 * beta_e * s = 1.5 s, so about 4.5 s
    assert widths[0] == pytest.approx(4.5 * 0.002, rel=0.12)
    assert widths[1] == pytest.approx(4.5 * 0.005, rel=0.12)
    assert widths[2] == pytest.approx(4.5 * 0.01, rel=0.12)
    # wide for fuzzy kernels: dilation to the zeta limit 0.1 plus erosion ~0.045 (s = 0.05)
    assert widths[4] >= 0.12
    assert all(b > a for a, b in zip(widths, widths[1:])), widths


def test_sharp_core_and_fuzzy_coat():
    # two spheres: a sharp one (s = 0.003) at x = -0.45 and a fuzzy one (s = 0.05) at +0.45
    X, Y, Z, h = grid(72)
    f = np.minimum(sphere(72, 0.3, (-0.45, 0, 0)), sphere(72, 0.3, (0.45, 0, 0)))
    s = np.where(X < 0, 0.003, 0.05).astype(np.float32)
    cfg = ShellConfig(sigma_min=0.01)  # the threshold option: sharp surfaces do not grow
    sh = extract_shells(f, s, BOX, cfg)
    surface = marching_cubes(f, BOX)
    p, d_plus, d_minus = normal_distances(surface, sh.sdf_plus, sh.sdf_minus, BOX, cfg)
    width = d_plus + d_minus
    sharp, fuzzy = p[:, 0] < -0.05, p[:, 0] > 0.05
    # sharp: no dilation (s <= sigma_min), erosion 1.5 s = 0.0045
    assert np.nanmean(width[sharp]) <= 0.01 and np.nanmax(d_plus[sharp]) < 0.2 * h
    # fuzzy: dilation near zeta = 0.1, erosion near erode_zeta = 0.05
    assert np.nanmean(width[fuzzy]) >= 0.12 and np.nanmean(d_plus[fuzzy]) >= 0.085


# ------------------------------------------------------------------------------------------
# containment and validity for several fields
# ------------------------------------------------------------------------------------------

def noisy_field(res: int, rng) -> tuple[np.ndarray, np.ndarray]:
    from scipy import ndimage
    noise = ndimage.gaussian_filter(rng.normal(size=(res,) * 3), 1.5) * 4.0
    f = (sphere(res) + 0.1 * noise).astype(np.float32)
    s = np.exp(rng.uniform(np.log(0.002), np.log(0.08), size=f.shape)).astype(np.float32)
    return f, s


@pytest.mark.parametrize("kind", ["sphere", "two_spheres", "noisy"])
def test_shells_contain_surface_and_are_watertight(kind):
    rng = np.random.default_rng(3)
    res = 56
    if kind == "sphere":
        f, s = sphere(res), np.full((res,) * 3, 0.02, np.float32)
    elif kind == "two_spheres":
        f = np.minimum(sphere(res, 0.35, (-0.4, 0, 0)), sphere(res, 0.3, (0.45, 0.1, 0)))
        s = np.full((res,) * 3, 0.03, np.float32)
    else:
        f, s = noisy_field(res, rng)
    cfg = ShellConfig(min_component_fraction=0.0)  # floaters are content too here
    sh = extract_shells(f, s, BOX, cfg)
    for m in (sh.outer, sh.inner):
        if len(m.faces):
            assert m.is_watertight and m.volume > 0
    assert sh.stats["outer_watertight"] and sh.stats["inner_watertight"]
    assert sh.stats["volume_outer"] >= sh.stats["volume_surface"] >= sh.stats["volume_inner"]
    check_containment(sh, f, rng)


def test_thin_part_has_no_inner_shell():
    # a sphere of radius 0.04 (8 grid points inside) with a fuzzy kernel: erosion (~0.045)
    # swallows it; the inner mesh is empty (valid: no interior termination)
    f = sphere(48, 0.04)
    sh = extract_shells(f, np.full(f.shape, 0.05, np.float32), BOX)
    assert len(sh.inner.faces) == 0 and sh.stats["inner_empty"]
    assert len(sh.outer.faces) > 0


@pytest.mark.parametrize("value, words", [(0.3, "f > 0 everywhere"), (-0.3, "f < 0 everywhere")])
def test_empty_and_all_inside_fields_are_rejected(value, words):
    f = np.full((16, 16, 16), value, np.float32)
    with pytest.raises(InputError, match=words):
        extract_shells(f, np.full_like(f, 0.01), BOX)


def test_bad_kernel_and_nan_are_rejected():
    f = sphere(16)
    with pytest.raises(InputError, match="non-positive"):
        extract_shells(f, np.zeros_like(f), BOX)
    f[3, 3, 3] = np.nan
    with pytest.raises(InputError, match="NaN"):
        extract_shells(f, np.full_like(f, 0.01), BOX)


# ------------------------------------------------------------------------------------------
# output files
# ------------------------------------------------------------------------------------------

def test_write_shells_files_and_stats(tmp_path):
    f = sphere(40)
    sh = extract_shells(f, np.full(f.shape, 0.02, np.float32), BOX)
    write_shells(sh, tmp_path / "shells")
    names = sorted(p.name for p in (tmp_path / "shells").iterdir())
    assert names == ["inner.ply", "outer.ply", "slice.png", "stats.json"]
    stats = json.loads((tmp_path / "shells" / "stats.json").read_text())
    assert stats["resolution"] == [40, 40, 40]
    assert stats["params"]["steps"] == 50 and stats["outer_triangles"] == len(sh.outer.faces)
    V, F = load_ply(tmp_path / "shells" / "outer.ply")
    assert len(F) == stats["outer_triangles"]
    assert [p.name for p in tmp_path.iterdir()] == ["shells"]  # no staging leftovers


def test_write_shells_is_all_or_nothing(tmp_path, monkeypatch):
    f = sphere(24)
    sh = extract_shells(f, np.full(f.shape, 0.02, np.float32), BOX)
    calls = []

    def failing_write_ply(path, mesh):  # the second mesh fails to write
        calls.append(path)
        if len(calls) == 2:
            raise OSError("disk full")
        write_ply(path, mesh)

    monkeypatch.setattr(extract_mod, "write_ply", failing_write_ply)
    with pytest.raises(OSError, match="disk full"):
        write_shells(sh, tmp_path / "shells")
    assert list(tmp_path.iterdir()) == []  # neither out_dir nor the staging folder
    # an existing result is left untouched by a failed rewrite
    monkeypatch.setattr(extract_mod, "write_ply", write_ply)
    write_shells(sh, tmp_path / "shells", figure=False)
    before = {p.name: p.read_bytes() for p in (tmp_path / "shells").iterdir()}
    sh.stats["bad"] = object()  # not JSON-serialisable: fails after both meshes are staged
    with pytest.raises(TypeError):
        write_shells(sh, tmp_path / "shells", figure=False)
    assert {p.name: p.read_bytes() for p in (tmp_path / "shells").iterdir()} == before
    assert [p.name for p in tmp_path.iterdir()] == ["shells"]


def test_slice_figure_draws_contours(tmp_path):
    f = sphere(33)
    s = np.full(f.shape, 0.05, np.float32)
    sh = extract_shells(f, s, BOX)
    img = slice_figure(f, s, sh.sdf_plus, sh.sdf_minus, BOX, tmp_path / "slice.png")
    back = iio.imread(tmp_path / "slice.png")
    np.testing.assert_array_equal(back, img)
    assert img.ndim == 3 and img.shape[2] == 3 and min(img.shape[:2]) >= 512
    colours = {tuple(c) for c in img.reshape(-1, 3)[::1]}
    assert (0, 0, 0) in colours  # f0 = 0
    assert (255, 140, 0) in colours  # SDF+ = 0 (orange)
    assert (0, 217, 242) in colours  # SDF- = 0 (cyan)


def test_fixed_band_baseline_is_the_level_sets_plus_minus_w():
    # the ablation's fixed band {|f| <= w}: on an exact sphere SDF (radius 0.5) the outer shell
    # is the sphere of radius 0.5 + w and the inner one of radius 0.5 - w, whatever s is
    f = sphere(64, 0.5)
    s = np.full(f.shape, 0.3, np.float32)  # a kernel this wide would give a huge adaptive band
    sh = extract_shells(f, s, BOX, fixed_width=0.05)
    r_out = np.linalg.norm(sh.outer.vertices, axis=1)
    r_in = np.linalg.norm(sh.inner.vertices, axis=1)
    assert abs(r_out.mean() - 0.55) < 2e-3 and abs(r_in.mean() - 0.45) < 2e-3
    assert sh.stats["band"] == "fixed +-0.05"
    assert sh.stats["band_width"]["mean"] == pytest.approx(0.1, abs=4e-3)
    with pytest.raises(InputError):
        extract_shells(f, s, BOX, fixed_width=0.0)


def test_banded_grid_sampling_gives_the_same_shells():
    # coarse-to-fine sampling (exact only near the surface) must not change the extraction
    import torch

    from shells.config import ShellConfig
    from shells.levelset.grid import sample_grid, sample_grid_banded

    def fn(x):  # a non-unit-gradient SDF (two blobs) with a kernel that varies in space
        f = torch.minimum(1.3 * ((x - torch.tensor([0.2, 0, 0])).norm(dim=-1) - 0.35),
                          0.8 * ((x + torch.tensor([0.3, 0.1, 0])).norm(dim=-1) - 0.25))
        s = 0.004 + 0.05 * torch.sigmoid(8 * x[:, 0])
        return f, s

    cfg = ShellConfig(resolution=65)
    h = 2.0 / 64
    f, s, _ = sample_grid(fn, BOX, 65)
    fb, sb, _, exact = sample_grid_banded(fn, BOX, 65, cfg.dilate_zeta + 2 * h)
    assert 0.0 < exact < 0.6  # most of the box was interpolated, not evaluated
    near = np.abs(f) < cfg.dilate_zeta + 2 * h
    np.testing.assert_array_equal(fb[near], f[near])
    assert (np.sign(fb) == np.sign(f)).all()
    a = extract_shells(f, s, BOX, cfg)
    b = extract_shells(fb, sb, BOX, cfg)
    # identical where the evolution acts, and identical meshes (all zero crossings lie there)
    np.testing.assert_array_equal(a.sdf_plus[near], b.sdf_plus[near])
    np.testing.assert_array_equal(a.sdf_minus[near], b.sdf_minus[near])
    np.testing.assert_array_equal(a.outer.vertices, b.outer.vertices)
    np.testing.assert_array_equal(a.inner.vertices, b.inner.vertices)
    np.testing.assert_array_equal(a.outer.faces, b.outer.faces)
