"""Shell intervals against analytic ray-sphere intersections (icosphere shells)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from shells.device import mitsuba_variant
from shells.errors import InputError
from shells.render.raycast import Intervals, ShellScene, box_intervals, to_point3f


def sphere(radius: float, centre=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    m = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    m.apply_translation(centre)
    return m


def arrays(m: trimesh.Trimesh):
    return np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.int32)


def sagitta(m: trimesh.Trimesh, radius: float) -> float:
    """How far the flat faces lie inside the true sphere: radius - min face-plane distance.
    Icosphere vertices are on the sphere, so the surface is inside by at most this much."""
    c = m.triangles_center - m.center_mass
    plane = np.abs(np.einsum("ij,ij->i", c, m.face_normals))
    return float(radius - plane.min())


def ray_sphere(o, d, centre, r):
    """Analytic entry/exit distances of unit-direction rays (nan when missing)."""
    oc = np.asarray(o, np.float64) - centre
    b = np.einsum("ij,ij->i", oc, d)
    disc = b * b - np.einsum("ij,ij->i", oc, oc) + r * r
    s = np.sqrt(np.where(disc >= 0, disc, np.nan))
    return -b - s, -b + s


def tolerance(m, r, o, d, centre=(0, 0, 0)):
    """Error bound in t: the sagitta divided by the cosine of incidence at the hit, plus float32
    noise (|t| ~ 4 -> ~1e-6). The rays below keep cos >= 0.43, so the bound stays < 1e-3."""
    t0, _ = ray_sphere(o, d, np.asarray(centre), r)
    p = o + t0[:, None] * d - centre
    cos = np.abs(np.einsum("ij,ij->i", p / r, d))
    return sagitta(m, r) / cos + 2e-5


@pytest.fixture(scope="module")
def concentric():
    mitsuba_variant()
    outer, inner = sphere(1.0), sphere(0.5)
    return ShellScene(arrays(outer), arrays(inner)), outer, inner


def z_rays(offsets, z0=-3.0):
    o = np.array([[x, 0.0, z0] for x in offsets], np.float32)
    d = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (len(offsets), 1))
    return o, d


def test_sagitta_is_small():
    # icosphere(5): 20480 faces, edge ~ 0.033 r -> sagitta ~ r * edge^2 / 6 ~ 2e-4 r
    assert 1e-5 < sagitta(sphere(1.0), 1.0) < 5e-4


def test_concentric_enter_exit_and_inner_termination(concentric):
    scene, outer, inner = concentric
    offsets = [0.0, 0.3, 0.45, 0.6, 0.9]
    o, d = z_rays(offsets)
    iv = scene.intervals(torch.from_numpy(o), torch.from_numpy(d), dp_max=8).torch()
    assert iv["enter"].shape == (5, 4)  # K = dp_max / 2 slots
    assert iv["count"].tolist() == [1, 1, 1, 1, 1]
    t_out0, t_out1 = ray_sphere(o, d, np.zeros(3), 1.0)
    t_in0, _ = ray_sphere(o, d, np.zeros(3), 0.5)
    tol_out = tolerance(outer, 1.0, o, d)
    np.testing.assert_array_less(np.abs(iv["enter"][:, 0].numpy() - t_out0), tol_out)
    # rays through the inner sphere (offset < 0.5) stop at its surface: solid interior
    hits_inner = np.array(offsets) < 0.5
    tol_in = tolerance(inner, 0.5, o[hits_inner], d[hits_inner])
    expect_exit = np.where(hits_inner, t_in0, t_out1)
    got_exit = iv["exit"][:, 0].numpy()
    np.testing.assert_array_less(np.abs(got_exit[hits_inner] - expect_exit[hits_inner]), tol_in)
    np.testing.assert_array_less(np.abs(got_exit[~hits_inner] - expect_exit[~hits_inner]),
                                 tol_out[~hits_inner])
    t_inner = iv["t_inner"].numpy()
    np.testing.assert_array_less(np.abs(t_inner[hits_inner] - t_in0[hits_inner]), tol_in)
    assert np.isinf(t_inner[~hits_inner]).all()
    # unused slots stay zero
    assert (iv["enter"][:, 1:] == 0).all() and (iv["exit"][:, 1:] == 0).all()


def test_without_inner_shell_the_ray_exits_outer():
    outer = sphere(1.0)
    scene = ShellScene(arrays(outer), None)
    o, d = z_rays([0.0, 0.3])
    iv = scene.intervals(o, d, dp_max=8).torch()
    t0, t1 = ray_sphere(o, d, np.zeros(3), 1.0)
    tol = tolerance(outer, 1.0, o, d)
    np.testing.assert_array_less(np.abs(iv["enter"][:, 0].numpy() - t0), tol)
    np.testing.assert_array_less(np.abs(iv["exit"][:, 0].numpy() - t1), tol)
    assert iv["count"].tolist() == [1, 1] and np.isinf(iv["t_inner"].numpy()).all()


@pytest.fixture(scope="module")
def two_spheres():
    """M+ = two disjoint spheres of radius 0.5 at z = 0 and z = 1.5, no M-."""
    mitsuba_variant()
    a, b = sphere(0.5), sphere(0.5, (0.0, 0.0, 1.5))
    return ShellScene(arrays(trimesh.util.concatenate([a, b]))), a


def test_offset_second_shell_gives_two_bands(two_spheres):
    scene, a = two_spheres
    o, d = z_rays([0.0, 0.2])
    iv = scene.intervals(o, d, dp_max=8).torch()
    assert iv["count"].tolist() == [2, 2]
    e0, x0 = ray_sphere(o, d, np.zeros(3), 0.5)
    e1, x1 = ray_sphere(o, d, np.array([0, 0, 1.5]), 0.5)
    # axis ray: [2.5, 3.5] then [4.0, 5.0]
    tol = tolerance(a, 0.5, o, d)
    for got, want in ((iv["enter"][:, 0], e0), (iv["exit"][:, 0], x0),
                      (iv["enter"][:, 1], e1), (iv["exit"][:, 1], x1)):
        np.testing.assert_array_less(np.abs(got.numpy() - want), tol)


def test_peel_budget_caps_intervals(two_spheres):
    scene, _ = two_spheres
    o, d = z_rays([0.0])
    # hits along the axis: enter 2.5, exit 3.5, enter 4.0, exit 5.0
    counts = {dp: int(scene.intervals(o, d, dp_max=dp).count.torch()[0]) for dp in (1, 2, 3, 4)}
    # 1 hit: interval still open -> dropped; 3 hits: second interval open -> dropped
    assert counts == {1: 0, 2: 1, 3: 1, 4: 2}
    assert scene.intervals(o, d, dp_max=3).enter.shape == (1, 2)  # K = ceil(dp_max / 2)


def test_missing_rays(concentric):
    scene, _, _ = concentric
    o = np.array([[1.5, 0.0, -3.0], [0.0, 0.0, -3.0]], np.float32)
    d = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]], np.float32)  # beside / pointing away
    iv = scene.intervals(o, d, dp_max=8).torch()
    assert iv["count"].tolist() == [0, 0]
    assert np.isinf(iv["t_inner"].numpy()).all()


def test_ray_starting_inside_outer_shell(concentric):
    scene, outer, inner = concentric
    o = np.array([[0.0, 0.0, -0.75],  # between the shells, heading into M-: [0, 0.25]
                  [0.7, 0.0, 0.0],  # between the shells, misses M-: [0, sqrt(1 - 0.49)]
                  [0.7, 0.0, 0.0]], np.float32)  # heading +x out of M+: [0, 0.3]
    d = np.array([[0, 0, 1], [0, 0, 1], [1, 0, 0]], np.float32)
    iv = scene.intervals(o, d, dp_max=8).torch()
    assert iv["count"].tolist() == [1, 1, 1]
    assert iv["enter"][:, 0].tolist() == [0.0, 0.0, 0.0]
    want = np.array([0.25, math.sqrt(0.51), 0.3])
    # the exit hits are at incidence cos >= 0.7 -> sagitta / 0.7 < 5e-4
    np.testing.assert_allclose(iv["exit"][:, 0].numpy(), want, atol=5e-4)
    assert iv["t_inner"][0].item() == pytest.approx(0.25, abs=5e-4)


def test_a_cast_from_a_start_distance_ignores_the_shells_before_it(two_spheres, concentric):
    import mitsuba as mi

    scene, _ = two_spheres
    o, d = z_rays([0.0, 0.0, 0.0, 0.0])  # axis hits: enter 2.5, exit 3.5, enter 4.0, exit 5.0
    start = mi.Float([0.0, 3.7, 3.0, 4.5])  # before both / between / inside the first / second
    iv = scene.intervals(o, d, dp_max=8, start=start).torch()
    assert iv["count"].tolist() == [2, 1, 2, 1]
    tol = 5e-4  # sagitta / cos 1 and float noise
    np.testing.assert_allclose(iv["enter"][:, 0].numpy(), [2.5, 4.0, 3.0, 4.5], atol=tol)
    np.testing.assert_allclose(iv["exit"][:, 0].numpy(), [3.5, 5.0, 3.5, 5.0], atol=tol)
    np.testing.assert_allclose(iv["enter"][[0, 2], 1].numpy(), [4.0, 4.0], atol=tol)
    # the peel budget counts the hits past the start only: one interval (two hits) from 3.7
    one = scene.intervals(o[:1], d[:1], dp_max=2, start=mi.Float([3.7]))
    assert int(one.count.torch()[0]) == 1
    # the same with start 0 is the cast from the origin, bit for bit
    full = scene.intervals(o, d, dp_max=8).torch()
    zero = scene.intervals(o, d, dp_max=8, start=mi.Float([0.0] * 4)).torch()
    for k in full:
        assert torch.equal(full[k], zero[k]), k
    t, _ = scene.first_hit(o, d, start)
    np.testing.assert_allclose(t.numpy(), [2.5, 4.0, 3.5, 5.0], atol=tol)
    # past M-: the solid before the start does not end the ray
    inner_scene = concentric[0]
    o1, d1 = z_rays([0.0])  # M+ [2, 4], M- [2.5, 3.5]
    iv = inner_scene.intervals(o1, d1, dp_max=8, start=mi.Float([3.6])).torch()
    assert iv["count"].tolist() == [1] and np.isinf(iv["t_inner"].numpy()).all()
    np.testing.assert_allclose([iv["enter"][0, 0].item(), iv["exit"][0, 0].item()], [3.6, 4.0],
                               atol=tol)


def test_symbolic_and_evaluated_loops_agree(two_spheres):
    scene, _ = two_spheres
    g = torch.Generator().manual_seed(0)
    o = torch.rand(500, 3, generator=g) * 4 - 2
    d = torch.nn.functional.normalize(torch.randn(500, 3, generator=g), dim=-1)
    a = scene.intervals(o, d, 8, mode="symbolic").torch()
    b = scene.intervals(o, d, 8, mode="evaluated").torch()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    assert (a["count"] > 0).any()  # the random rays do hit something


def test_moved_shells_peel_as_shells_built_there():
    # The peel tells entries from exits by face normals made once per mesh; `move` must remake
    # them. Rotating both spheres' vertices 90 degrees about y leaves the spheres where they
    # were but turns every face: stale normals would call entries exits. The moved scene gives
    # the intervals of a scene built from the rotated vertices, bit for bit, and those of the
    # unmoved spheres within the faces' sagitta.
    mitsuba_variant()
    outer, inner = sphere(1.0), sphere(0.5)
    rot = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]], np.float32)
    Vo, Fo = arrays(outer)
    Vi, Fi = arrays(inner)
    moved = ShellScene((Vo, Fo), (Vi, Fi))
    moved.move(Vo @ rot.T, Vi @ rot.T)
    built = ShellScene((Vo @ rot.T, Fo), (Vi @ rot.T, Fi))
    g = torch.Generator().manual_seed(1)
    o = torch.nn.functional.normalize(torch.randn(400, 3, generator=g), dim=-1) * 3.0
    d = torch.nn.functional.normalize(-o + 0.6 * torch.randn(400, 3, generator=g), dim=-1)
    a = moved.intervals(o, d, 8).torch()
    b = built.intervals(o, d, 8).torch()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    ref = ShellScene((Vo, Fo), (Vi, Fi)).intervals(o, d, 8).torch()
    assert torch.equal(a["count"], ref["count"]) and int(a["count"].sum()) > 100
    assert (a["enter"] - ref["enter"]).abs().max() < 0.02
    assert (a["exit"] - ref["exit"]).abs().max() < 0.02


def test_a_peel_resumed_closes_the_intervals_of_one_peel():
    # Band rendering peels the first hits of every ray and resumes only the rays that still let
    # light through (`ShellScene.peel`, `resume`). Three spheres in a row as M+, a solid in the
    # middle one, rays from everywhere (some start inside): peeling 1, 2 or 3 hits at a time,
    # each time resuming only the rays still going, gives every ray the intervals, distances
    # and M- hit of one peel, bit for bit.
    import drjit as dr
    import mitsuba as mi

    mitsuba_variant()
    outer = trimesh.util.concatenate([sphere(0.5, (0.0, 0.0, z)) for z in (-1.5, 0.0, 1.5)])
    scene = ShellScene(arrays(outer), arrays(sphere(0.2)))
    g = torch.Generator().manual_seed(2)
    o = torch.rand(2000, 3, generator=g) * torch.tensor([1.2, 1.2, 5.0]) - torch.tensor(
        [0.6, 0.6, 2.5])
    d = torch.nn.functional.normalize(torch.randn(2000, 3, generator=g) * torch.tensor(
        [0.2, 0.2, 1.0]), dim=-1)
    dp_max = 7
    ref = scene.intervals(o, d, dp_max).torch()
    assert ref["count"].max() == 3 and (ref["count"] == 0).any()  # the budget binds on some
    assert torch.isfinite(ref["t_inner"]).any()
    O, D = to_point3f(o), to_point3f(d, mi.Vector3f)
    for step in (1, 2, 3):
        iv, state = scene.peel(O, D, dp_max, step)
        rows = [[] for _ in range(len(o))]
        t_inner = iv.t_inner.torch().clone()
        ids, reached = np.arange(len(o)), step
        while True:
            got = iv.torch()
            for r, i in enumerate(ids):
                rows[i] += [(got["enter"][r, k].item(), got["exit"][r, k].item())
                            for k in range(int(got["count"][r]))]
            t_inner[ids] = got["t_inner"]
            going = np.nonzero(state.going.numpy())[0]
            if reached >= dp_max or len(going) == 0:
                break
            idx = mi.UInt32(going.astype(np.uint32))
            ids, reached = ids[going], min(dp_max, reached + step)
            iv, state = scene.resume(dr.gather(mi.Point3f, O, mi.UInt32(ids.astype(np.uint32))),
                                     dr.gather(mi.Vector3f, D, mi.UInt32(ids.astype(np.uint32))),
                                     state.take(idx), dp_max, reached)
        for i in range(len(o)):
            c = int(ref["count"][i])
            want = [(ref["enter"][i, k].item(), ref["exit"][i, k].item()) for k in range(c)]
            assert rows[i] == want, (step, i)
        assert torch.equal(t_inner, ref["t_inner"])


def test_torch_views_share_memory(two_spheres):
    scene, _ = two_spheres
    iv = scene.intervals(*z_rays([0.0]), dp_max=4)
    view = iv.torch()["enter"]
    view[0, 0] = 42.0  # written through torch, read back through Dr.Jit: zero-copy
    assert iv.enter.numpy()[0, 0] == 42.0


def test_box_intervals():
    mitsuba_variant()
    o = to_point3f(np.array([[0, 0, -3], [0, 0, 0], [5, 0, -3]], np.float32))
    d = to_point3f(np.array([[0, 0, 1], [1, 0, 0], [0, 0, 1]], np.float32))
    iv = box_intervals(o, d, [[-1, -1, -1], [1, 1, 1]]).torch()
    # outside: [2, 4]; from the centre: [0, 1]; beside the box: none
    assert iv["count"].tolist() == [1, 1, 0]
    assert iv["enter"][:2, 0].tolist() == [2.0, 0.0] and iv["exit"][:2, 0].tolist() == [4.0, 1.0]


def test_bad_input_raises():
    mitsuba_variant()
    with pytest.raises(InputError):
        ShellScene((np.zeros((0, 3)), np.zeros((0, 3), np.int32)))
    with pytest.raises(InputError):
        ShellScene((np.zeros((3, 3)), np.array([[0, 1, 5]])))
    with pytest.raises(InputError):
        Intervals.from_arrays([[0.0]], [[1.0]], [1, 1])
    scene = ShellScene(arrays(sphere(1.0)))
    with pytest.raises(InputError):
        scene.intervals(torch.zeros(4, 2), torch.zeros(4, 2), 8)
