"""Level-set evolution (shells.levelset.evolve) and grid sampling (shells.levelset.grid)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from shells.config import ShellConfig
from shells.errors import InputError
from shells.fields.neus import may_have_density
from shells.levelset.evolve import (dilation_velocity, erosion_velocity, evolve, falloff,
                                    shell_sdfs, substeps)
from shells.levelset.grid import sample_grid

BOX = [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]


def grid(res: int):
    x = np.linspace(-1, 1, res, dtype=np.float32)
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    return X, Y, Z, float(x[1] - x[0])


def zero_crossing_x(f: np.ndarray, h: float) -> float:
    """x of the sign change of f along the +x axis through the grid centre (odd resolution)."""
    line = f[:, f.shape[1] // 2, f.shape[2] // 2].astype(np.float64)
    c = f.shape[0] // 2
    i = c + int(np.argmax(line[c:] > 0))  # first outside sample on the +x side
    t = line[i - 1] / (line[i - 1] - line[i])
    return -1.0 + (i - 1 + t) * h


# ------------------------------------------------------------------------------------------
# falloff and velocities: hand-worked numbers
# ------------------------------------------------------------------------------------------

def test_falloff_values():
    # w = (1 + cos(pi f / zeta)) / 2 with zeta = 0.1:
    # f = 0 -> 1; f = +-0.05 -> (1 + cos(pi/2)) / 2 = 0.5; f = 0.025 -> (1 + cos(pi/4)) / 2
    # = 0.853553; |f| >= 0.1 -> 0
    f = np.array([0.0, 0.05, -0.05, 0.025, 0.1, -0.3, 2.0])
    expect = [1.0, 0.5, 0.5, 0.8535534, 0.0, 0.0, 0.0]
    np.testing.assert_allclose(falloff(f, 0.1), expect, atol=1e-6)
    np.testing.assert_allclose(falloff(torch.tensor(f), 0.1).numpy(), expect, atol=1e-6)


def test_velocities_hand_worked():
    cfg = ShellConfig(beta_d=1.0, sigma_min=0.01, beta_e=0.3, v_max=0.04)
    s = np.array([0.002, 0.01, 0.02, 0.05, 0.5])
    # dilation: 0 where s <= 0.01, else min(1.0 s, 0.04) -> [0, 0, 0.02, 0.04, 0.04]
    np.testing.assert_allclose(dilation_velocity(s, cfg), [0, 0, 0.02, 0.04, 0.04], atol=1e-7)
    # erosion: min(0.3 s, 0.04) -> [0.0006, 0.003, 0.006, 0.015, 0.04]
    np.testing.assert_allclose(erosion_velocity(s, cfg), [0.0006, 0.003, 0.006, 0.015, 0.04],
                               atol=1e-7)


def test_substeps_keep_courant_number():
    # v dt / h = 0.04 * 0.1 / (2/255) = 0.51 > 0.5 -> 2 sub-steps; at 2/127: 0.254 -> 1
    assert substeps(0.04, 0.1, [2 / 255] * 3, cfl=0.5) == 2
    assert substeps(0.04, 0.1, [2 / 127] * 3, cfl=0.5) == 1
    assert substeps(0.0, 0.1, [0.01] * 3) == 1


# ------------------------------------------------------------------------------------------
# evolve: analytic fronts, limits, reference parity
# ------------------------------------------------------------------------------------------

def plane_front(v: float, res: int = 257) -> float:
    """Position of the zero set of f0 = x - 0.1 after T = 50 steps of dt = 0.1 at speed v, on
    a [res, 3, 3] grid (a 1-D problem: evolve takes any grid shape)."""
    x = np.linspace(-1, 1, res, dtype=np.float32)
    h = float(x[1] - x[0])
    f0 = np.broadcast_to((x - 0.1)[:, None, None], (res, 3, 3)).copy()
    line = evolve(f0, np.full_like(f0, v), (h, h, h), 50, 0.1, 0.1, 0.0)[:, 1, 1]
    i = int(np.argmax(line > 0))
    return -1 + (i - 1 + line[i - 1] / (line[i - 1] - line[i])) * h


def test_plane_front_moves_v_times_t():
    # v = +-0.01: the zero set moves at v w(0) = v for T dt = 5, i.e. by +-0.05 (no shock:
    # characteristics cross only after v t > 2 zeta / pi = 0.064). Measured at h = 1/128:
    # 0.0507 / -0.0508 (the grid error shrinks to 0.0504 at h = 1/256).
    assert plane_front(0.01) == pytest.approx(0.15, abs=0.002)
    assert plane_front(-0.01) == pytest.approx(0.05, abs=0.002)
    # v = 0.05 asks for 0.25, but the level set f0 = zeta = 0.1 never moves: 0.099 measured
    assert 0.19 < plane_front(0.05) <= 0.2


def test_sphere_dilation_and_zeta_limit():
    X, Y, Z, h = grid(65)
    f0 = np.sqrt(X**2 + Y**2 + Z**2) - 0.5
    # slow front: radius 0.5 + 5 * 0.01 = 0.55; measured 0.5455 at h = 1/32, where zeta = 3.2 h
    # resolves w(f) poorly (the plane test shows the error vanish on finer grids)
    out = evolve(f0, np.full_like(f0, 0.01), (h,) * 3, 50, 0.1, 0.1, 0.0)
    assert abs(zero_crossing_x(out, h) - 0.55) < 0.2 * h
    # fast front: v = 0.2 asks for 1.0, but level set f0 = zeta never moves -> r <= 0.6
    out = evolve(f0, np.full_like(f0, 0.2), (h,) * 3, 50, 0.1, 0.1, 0.0)
    r = zero_crossing_x(out, h)
    assert 0.58 < r <= 0.6 + 0.5 * h
    assert np.isfinite(out).all()


def test_curvature_term_smooths():
    # v = 0 and only the curvature term: a convex sphere recedes (mean-curvature flow sign),
    # by a hair with the paper's lambda (grid units): lambda h^2 kappa T dt = 0.01 * h^2 * 4 * 5.
    X, Y, Z, h = grid(33)
    f0 = np.sqrt(X**2 + Y**2 + Z**2) - 0.5
    zero = np.zeros_like(f0)
    r_big = zero_crossing_x(evolve(f0, zero, (h,) * 3, 50, 0.1, 0.1, 1.0), h)
    r_paper = zero_crossing_x(evolve(f0, zero, (h,) * 3, 50, 0.1, 0.1, 0.01), h)
    r0 = zero_crossing_x(f0, h)
    # lambda = 1: speed -h^2 * (2 / r) = -0.0156 per unit time, 5 units -> about -0.078
    # (the front slows as w(f) falls off; only the sign and rough size are asserted)
    assert r0 - 0.1 < r_big < r0 - 0.03
    assert r0 - 1e-3 < r_paper < r0


def reference_step(f, v, h, dt, zeta, lam):
    """Dense numpy forward-Euler step, np.gradient central differences (one-sided at the
    border): the obviously-correct twin of the banded torch loop."""
    g = np.gradient(f, h, edge_order=1)
    gn2 = g[0] ** 2 + g[1] ** 2 + g[2] ** 2
    gn = np.sqrt(gn2)
    speed = gn * v
    if lam > 0:
        num = np.zeros_like(f)
        fp = [np.roll(f, -1, a) for a in range(3)]
        fm = [np.roll(f, 1, a) for a in range(3)]
        for a in range(3):
            num += (fp[a] + fm[a] - 2 * f) / h**2 * (gn2 - g[a] ** 2)
        for a, b in ((0, 1), (0, 2), (1, 2)):
            gb = np.gradient(f, h, axis=b, edge_order=1)
            f_ab = np.gradient(gb, h, axis=a, edge_order=1)
            num -= 2 * g[a] * g[b] * f_ab
        kappa = np.clip(num / (gn2 * gn + 1e-12), -1 / h, 1 / h)
        speed = speed - lam * h**2 * kappa * gn
    return f - dt * speed * falloff(f, zeta)


@pytest.mark.parametrize("lam", [0.0, 0.01])
def test_banded_evolution_matches_dense_reference(lam):
    rng = np.random.default_rng(1)
    X, Y, Z, h = grid(20)
    f0 = (np.sqrt(X**2 + Y**2 + Z**2) - 0.6 + 0.05 * rng.normal(size=X.shape)).astype(np.float32)
    v = rng.uniform(0, 0.03, size=X.shape).astype(np.float32)
    zeta, steps, dt = 0.2, 4, 0.1
    assert substeps(float(v.max()), dt, (h,) * 3) == 1
    ref = f0.astype(np.float64)
    for _ in range(steps):
        ref = reference_step(ref, v, h, dt, zeta, lam)
    inner = (slice(1, -1),) * 3  # the rolled second differences differ only on the border
    out = evolve(f0, v, (h,) * 3, steps, dt, zeta, lam)
    # float32 vs float64 over 4 steps: differences ~1e-7 relative to |f| <= 1
    np.testing.assert_allclose(out[inner], ref[inner], atol=2e-6)


@pytest.mark.parametrize("memory_mb", [2048, 0])  # 0: the chunked path (1024-voxel chunks)
def test_progress_bar_counts_the_steps_and_changes_nothing(memory_mb, capsys):
    rng = np.random.default_rng(2)
    X, Y, Z, h = grid(16)
    f0 = (np.sqrt(X**2 + Y**2 + Z**2) - 0.5 + 0.02 * rng.normal(size=X.shape)).astype(np.float32)
    v = rng.uniform(0, 0.03, size=X.shape).astype(np.float32)
    quiet = evolve(f0, v, (h,) * 3, 6, 0.1, 0.2, 0.01, memory_mb=memory_mb)
    capsys.readouterr()
    shown = evolve(f0, v, (h,) * 3, 6, 0.1, 0.2, 0.01, memory_mb=memory_mb,
                   progress="dilate (M+)")
    err = capsys.readouterr().err
    np.testing.assert_array_equal(shown, quiet)
    assert "dilate (M+)" in err and "0/6 " in err  # one bar over the 6 steps


def test_noisy_field_stays_bounded_and_contained():
    # A rough field (noise everywhere) must not blow up: values change only inside the band
    # and by at most the band width; SDF+ <= f0 <= SDF- holds exactly on the grid.
    rng = np.random.default_rng(2)
    X, Y, Z, h = grid(40)
    f0 = (np.sqrt(X**2 + Y**2 + Z**2) - 0.5 + 0.08 * rng.normal(size=X.shape)).astype(np.float32)
    s = np.exp(rng.uniform(np.log(0.002), np.log(0.1), size=X.shape)).astype(np.float32)
    cfg = ShellConfig()
    plus, minus = shell_sdfs(f0, s, (h,) * 3, cfg)
    assert np.isfinite(plus).all() and np.isfinite(minus).all()
    assert (plus <= f0).all() and (minus >= f0).all()
    assert np.abs(plus - f0).max() <= 2 * cfg.dilate_zeta
    assert np.abs(minus - f0).max() <= 2 * cfg.erode_zeta
    outside = np.abs(f0) >= cfg.dilate_zeta
    assert (plus[outside] == f0[outside]).all()


def test_support_terms_move_the_shells_to_h_plus_k_s():
    # Hand-worked: with the fronts held still (beta 0), the outer shell of an exact sphere SDF is
    # the level set f = h + k s and the inner one f = -(h + k s), h half a cell's diagonal; f is
    # linear along the axis, so the linearly interpolated zero crossings are exact.
    X, Y, Z, h = grid(41)
    f0 = (np.sqrt(X**2 + Y**2 + Z**2) - 0.5).astype(np.float32)
    s = np.full_like(f0, 0.01)
    cfg = ShellConfig(beta_d=0.0, beta_e=0.0, support_k_outer=3.0, support_k_inner=2.0)
    plus, minus = shell_sdfs(f0, s, (h,) * 3, cfg)
    half_diagonal = 0.5 * math.sqrt(3) * h
    assert zero_crossing_x(plus, h) == pytest.approx(0.5 + half_diagonal + 0.03, abs=1e-5)
    assert zero_crossing_x(minus, h) == pytest.approx(0.5 - half_diagonal - 0.02, abs=1e-5)
    assert (plus <= f0).all() and (minus >= f0).all()


def test_support_terms_keep_a_flat_field_s_density_in_the_band():
    # A sharp field whose f inside the solid falls at a fifth of the distance (|grad f| = 0.2):
    # the level-set erosion moves M- a distance, which there is a fifth of the f it should be,
    # and M- cuts into the layer where the surface still absorbs (|f| < h + k s, the occupancy
    # grid's rule). With the support terms the band holds every such grid point.
    X, Y, Z, h = grid(41)
    r = np.sqrt(X**2 + Y**2 + Z**2) - 0.5
    f0 = np.where(r > 0, r, 0.2 * r).astype(np.float32)
    s = np.full_like(f0, 0.004)
    half_diagonal = 0.5 * math.sqrt(3) * h
    k = 3.0
    density = may_have_density(torch.from_numpy(f0), torch.from_numpy(s), half_diagonal, k).numpy()

    def holds(cfg):
        plus, minus = shell_sdfs(f0, s, (h,) * 3, cfg)
        return bool(((plus <= 0) & (minus >= 0))[density].all())

    assert not holds(ShellConfig(beta_d=1.2, beta_e=0.3))  # the level-set shells alone
    assert holds(ShellConfig(beta_d=1.2, beta_e=0.3, support_k_outer=k, support_k_inner=k))


# ------------------------------------------------------------------------------------------
# sample_grid
# ------------------------------------------------------------------------------------------

class SphereField(torch.nn.Module):
    def forward(self, x):  # [N, 3] -> ([N], [N])
        return x.norm(dim=-1) - 0.5, 0.01 + 0.0 * x[:, 0] + 0.1 * (x[:, 0] > 0)


def test_sample_grid_matches_formula_and_chunks():
    box = [[-1.0, -0.5, 0.0], [1.0, 0.5, 2.0]]
    f, s, spacing = sample_grid(SphereField(), box, 9, chunk=100)  # 729 points, ragged chunks
    np.testing.assert_allclose(spacing, [0.25, 0.125, 0.25])
    assert f.shape == s.shape == (9, 9, 9) and f.dtype == np.float32
    # [i, j, k] = (x, y, z): corner (8, 0, 4) is (1.0, -0.5, 1.0): f = sqrt(2.25) - 0.5 = 1.0
    assert f[8, 0, 4] == pytest.approx(1.0, abs=1e-6)
    assert f[0, 8, 0] == pytest.approx(math.sqrt(1.25) - 0.5, abs=1e-6)
    assert s[8, 0, 0] == pytest.approx(0.11) and s[0, 0, 0] == pytest.approx(0.01)


def test_sample_grid_rejects_bad_box():
    with pytest.raises(InputError, match="aabb"):
        sample_grid(SphereField(), [[0, 0, 0], [1, -1, 1]], 8)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_sample_grid_cuda_matches_cpu():
    f_cpu, s_cpu, _ = sample_grid(SphereField(), BOX, 17)
    f_gpu, s_gpu, _ = sample_grid(SphereField().cuda(), BOX, 17, device="cuda")
    np.testing.assert_allclose(f_gpu, f_cpu, atol=1e-6)
    np.testing.assert_allclose(s_gpu, s_cpu, atol=1e-7)


@pytest.mark.parametrize("lam", [0.0, 0.01])
def test_fused_cpu_kernel_matches_the_torch_step_and_chunks_change_nothing(lam, monkeypatch):
    """On the CPU each sub-step is one Dr.Jit kernel (`_integrate_llvm`, neighbours found from
    the flat index); the torch step (what CUDA runs) gives the same grid to float32 rounding,
    and the kernel run in 1024-voxel chunks (memory_mb 0) gives it bit for bit. Two sub-steps
    per step, the grid's border inside the band."""
    import shells.levelset.evolve as ev

    rng = np.random.default_rng(3)
    X, Y, Z, h = grid(18)
    f0 = (np.sqrt(X**2 + Y**2 + Z**2) - 0.7 + 0.03 * rng.normal(size=X.shape)).astype(np.float32)
    v = rng.uniform(0, 0.9, size=X.shape).astype(np.float32)
    assert substeps(float(v.max()), 0.1, (h,) * 3) == 2
    band = np.abs(f0) < 0.4
    assert band.sum() > 1024 and band[0].any()  # several chunks; border voxels in the band
    torch_steps = []
    step = ev._step
    monkeypatch.setattr(ev, "_step", lambda *a: torch_steps.append(1) or step(*a))
    fused = evolve(f0, v, (h,) * 3, 5, 0.1, 0.4, lam)
    chunked = evolve(f0, v, (h,) * 3, 5, 0.1, 0.4, lam, memory_mb=0)
    assert torch_steps == []
    monkeypatch.setattr(ev, "drjit_llvm", lambda: False)  # as on CUDA: the torch step
    reference = evolve(f0, v, (h,) * 3, 5, 0.1, 0.4, lam)
    assert len(torch_steps) == 10
    np.testing.assert_array_equal(chunked, fused)
    assert np.abs(fused - f0).max() > 0.05  # the front moved
    np.testing.assert_allclose(fused, reference, rtol=0, atol=2e-6)
