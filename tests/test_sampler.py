"""Procedure 3 sample placement on hand-worked intervals; packed and padded layouts agree."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

import mitsuba as mi

from shells.config import RenderConfig
from shells.device import mitsuba_variant
from shells.render.raycast import Intervals, ShellScene
from shells.render.sampler import (band_samples, interval_counts, place_packed, place_padded,
                                   solid_end)

CFG = RenderConfig(w_s=0.01, delta_s=0.01, n_max=16)


@pytest.fixture(autouse=True)
def _variant():
    mitsuba_variant()


def test_interval_counts_hand_worked():
    w = mi.Float([0.004, 0.0149, 0.035, 0.0, 1.0])
    # 0.004 < w_s          -> 1 (middle sample)
    # 0.0149: ceil(0.49)+1 -> 2
    # 0.035:  ceil(2.5)+1  -> 4
    # 0.0 (tangent)        -> 1
    # 1.0:    ceil(99)+1 = 100, capped at N_max -> 16
    assert interval_counts(w, 0.01, 0.01, 16).numpy().tolist() == [1, 2, 4, 1, 16]


def hand_intervals() -> Intervals:
    # ray 0: [1.000, 1.005] and [1.035, 1.070]; ray 1: [2.000, 2.004]; ray 2: nothing
    return Intervals.from_arrays([[1.0, 1.035], [2.0, 2.004], [0.0, 0.0]],
                                 [[1.005, 1.07], [2.004, 0.0], [0.0, 0.0]], [2, 1, 0])


def test_packed_placement_hand_worked():
    p = place_packed(hand_intervals(), CFG)
    # ray 0, interval 0: w = 0.005 < w_s -> 1 sample at 1.0025, delta 0.005
    # ray 0, interval 1: w = 0.035 -> N = 4 at 1.035 + 0.035 * [1, 2, 3, 4] / 5
    #                    = [1.042, 1.049, 1.056, 1.063], delta = 0.035 / 4 = 0.00875
    # ray 1: w = 0.004 -> 1 sample at 2.002, delta 0.004; ray 2: no samples
    t = [1.0025, 1.042, 1.049, 1.056, 1.063, 2.002]
    delta = [0.005, 0.00875, 0.00875, 0.00875, 0.00875, 0.004]
    np.testing.assert_allclose(p.t.numpy(), t, atol=1e-6)  # float32 at |t| ~ 2: ulp 2.4e-7
    np.testing.assert_allclose(p.delta.numpy(), delta, atol=1e-6)
    assert p.ray.numpy().tolist() == [0, 0, 0, 0, 0, 1]
    assert p.start.numpy().tolist() == [0, 5, 6]
    assert p.count.numpy().tolist() == [5, 1, 0]
    assert p.max_count == 5 and p.size == 6


def test_solid_end_rule_hand_worked():
    # ray 0 reached M- after its intervals, ray 1 left the shells (no M- hit), ray 2 hit M- but
    # took no samples (nothing to end on): only ray 0 ends on its last sample
    e, x, c = ([[1.0, 1.035], [2.0, 2.004], [0.0, 0.0]], [[1.005, 1.07], [2.004, 0.0], [0.0, 0.0]],
               [2, 1, 0])
    iv = Intervals.from_arrays(e, x, c, t_inner=[1.07, float("inf"), 0.5])
    assert solid_end(iv.t_inner.array, mi.UInt32([5, 1, 0])).numpy().tolist() == [True, False,
                                                                                 False]
    assert place_packed(iv, CFG).solid.numpy().tolist() == [True, False, False]
    assert place_padded(iv, CFG)[3].tolist() == [True, False, False]
    # the scene box of `full` mode has no M-: no ray ends solid
    assert place_padded(hand_intervals(), CFG)[3].tolist() == [False, False, False]


def test_padded_placement_hand_worked():
    t, delta, mask, _ = place_padded(hand_intervals(), CFG)
    assert t.shape == delta.shape == mask.shape == (3, 5)  # S = largest per-ray count
    assert mask.tolist() == [[True] * 5, [True] + [False] * 4, [False] * 5]
    np.testing.assert_allclose(t[0].numpy(), [1.0025, 1.042, 1.049, 1.056, 1.063], atol=1e-6)
    assert t[1, 0].item() == pytest.approx(2.002, abs=1e-6)
    assert (t[~mask] == 0).all() and (delta[~mask] == 0).all()


def test_fixed_count_is_uniform_linspace():
    # full mode: one interval [0, 1] with 4 samples -> t = 0.2, 0.4, 0.6, 0.8, delta = 1/4
    iv = Intervals.from_arrays([[0.0]], [[1.0]], [1])
    p = place_packed(iv, CFG, fixed=4)
    np.testing.assert_allclose(p.t.numpy(), [0.2, 0.4, 0.6, 0.8], atol=1e-7)
    np.testing.assert_allclose(p.delta.numpy(), [0.25] * 4)


def test_packed_and_padded_agree_on_random_intervals():
    g = torch.Generator().manual_seed(1)
    R, K = 300, 4
    widths = torch.rand(R, K, generator=g) ** 3 * 0.3  # many narrow, a few capped at N_max
    gaps = torch.rand(R, K, generator=g) * 0.1
    enter = torch.cumsum(gaps + torch.roll(widths, 1, 1) * (torch.arange(K) > 0), 1) + 1.0
    exit_ = enter + widths
    count = torch.randint(0, K + 1, (R,), generator=g)
    iv = Intervals.from_arrays(enter, exit_, count)
    p = place_packed(iv, CFG)
    t, delta, mask, _ = place_padded(iv, CFG)
    start, cnt = p.start.numpy(), p.count.numpy()
    assert (mask.sum(1).numpy() == cnt).all()
    for r in range(R):
        a, n = start[r], cnt[r]
        np.testing.assert_array_equal(t[r, :n].numpy(), p.t.numpy()[a:a + n])
        np.testing.assert_array_equal(delta[r, :n].numpy(), p.delta.numpy()[a:a + n])
        assert (p.ray.numpy()[a:a + n] == r).all()
        assert (np.diff(t[r, :n].numpy()) > 0).all()  # front to back
    # sections tile each interval: per ray, sum(delta) = total width of its valid intervals
    valid = torch.arange(K)[None] < count[:, None]
    np.testing.assert_allclose((delta * mask).sum(1).numpy(),
                               (widths * valid).sum(1).numpy(), atol=1e-5)


def test_band_samples_on_concentric_spheres():
    outer = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    inner = trimesh.creation.icosphere(subdivisions=5, radius=0.5)
    scene = ShellScene((outer.vertices, outer.faces), (inner.vertices, inner.faces))
    o = torch.tensor([[0.0, 0.0, -3.0], [3.0, 0.0, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    t, delta, mask, solid = band_samples(scene, o, d, CFG)
    # axis ray: interval [2.0, 2.5] (outer at z = -1, inner at z = -0.5), w = 0.5
    # N = min(ceil(0.49 / 0.01) + 1, 16) = 16 -> t = 2 + 0.5 * (j + 1) / 17, delta = 0.5 / 16
    # tolerance: icosphere sagitta ~2e-4 on each end (see test_raycast)
    assert mask.sum(1).tolist() == [16, 0]
    assert solid.tolist() == [True, False]  # the axis ray ends on M-, the other misses both
    np.testing.assert_allclose(t[0].numpy(), 2.0 + 0.5 * np.arange(1, 17) / 17, atol=5e-4)
    np.testing.assert_allclose(delta[0].numpy(), 0.5 / 16, atol=5e-5)
    assert t.dtype == torch.float32 and mask.dtype == torch.bool
