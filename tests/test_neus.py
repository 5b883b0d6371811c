"""NeuS density, discrete alpha and compositing: hand-worked numbers, limits, gradients."""

import math

import pytest
import torch

from shells.fields.neus import composite, density, neus_alpha, phi


def test_composite_hand_worked():
    alpha = torch.tensor([[0.5, 0.5, 0.5], [0.2, 1.0, 0.7]])
    rgb = torch.eye(3).expand(2, 3, 3)  # sample i has colour e_i
    bg = torch.tensor([1.0, 1.0, 1.0])
    color, w, opacity = composite(alpha, rgb, bg)
    # row 0: transmittance [1, 0.5, 0.25] -> weights [0.5, 0.25, 0.125], opacity 0.875,
    #        colour (0.5, 0.25, 0.125) + 0.125 * white = (0.625, 0.375, 0.25)
    # row 1: transmittance [1, 0.8, 0] -> weights [0.2, 0.8, 0], opacity 1, colour (0.2, 0.8, 0)
    torch.testing.assert_close(w, torch.tensor([[0.5, 0.25, 0.125], [0.2, 0.8, 0.0]]))
    torch.testing.assert_close(opacity, torch.tensor([0.875, 1.0]))
    torch.testing.assert_close(color, torch.tensor([[0.625, 0.375, 0.25], [0.2, 0.8, 0.0]]))
    # per-ray background [R, 3]: only the unoccluded 12.5 % of row 0 sees it
    color2, _, _ = composite(alpha, rgb, torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]))
    torch.testing.assert_close(color2, torch.tensor([[0.5, 0.25, 0.25], [0.2, 0.8, 0.0]]))


def test_neus_alpha_hand_worked():
    # sigmoid(-a) / sigmoid(a) = exp(-a), so for sdf = 0 (sample on the surface):
    # alpha = 1 - Phi(f_next) / Phi(f_prev) = 1 - exp(-|cos| delta / s)
    sdf = torch.tensor([0.0, 0.0, 0.0, 10.0, -1.0])
    s = torch.tensor([1.0, 1.0, 1.0, 1.0, 0.01])
    cos = torch.tensor([-1.0, -0.5, 0.5, -1.0, -1.0])
    delta = torch.tensor([2.0, 2.0, 2.0, 2.0, 0.001])
    a = neus_alpha(sdf, s, cos, delta)
    expected = torch.tensor([
        1 - math.exp(-1.0),  # f_prev = 1, f_next = -1: 0.632121
        1 - math.exp(-0.5),  # f_prev = 0.5, f_next = -0.5: 0.393469
        0.0,  # exiting (cos > 0): c = -relu(-cos) = 0, f_prev = f_next
        # far outside, f_prev = 11, f_next = 9: 1 - (1 + e^-11)/(1 + e^-9) = 1.0666e-4
        1 - (1 + math.exp(-11)) / (1 + math.exp(-9)),
        # deep inside, f/s = -100 +- 0.05: both Phi ~ e^-100 = 4e-44 (fp32 denormals; the
        # naive ratio loses all digits), yet 1 - exp(-delta / s) = 0.0951626
        1 - math.exp(-0.1),
    ])
    # fp32: ~1e-7 absolute; the far-outside value is ~1e-4, checked to 1e-4 relative; deep
    # inside, f/s ~ 100 carries an fp32 ulp of 7.6e-6 on a difference of 0.1: 2e-4 relative
    torch.testing.assert_close(a[:4], expected[:4], rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(a[4], expected[4], rtol=2e-4, atol=0)
    assert torch.isfinite(a).all()


def test_neus_alpha_float64_and_broadcast_shapes():
    sdf = torch.linspace(-1, 1, 12, dtype=torch.float64).view(3, 4)
    a = neus_alpha(sdf, torch.full_like(sdf, 0.1), -torch.ones_like(sdf), torch.full_like(sdf, 0.2))
    assert a.dtype == torch.float64 and a.shape == (3, 4)
    assert ((a >= 0) & (a <= 1)).all()


def test_sharp_surface_limit():
    s = torch.full((4,), 1e-5)
    sdf = torch.tensor([0.0, 0.0, 0.01, 0.01])
    cos = torch.tensor([-1.0, 1.0, -1.0, -1.0])
    delta = torch.tensor([0.02, 0.02, 0.02, 0.01])
    a = neus_alpha(sdf, s, cos, delta)
    # straddling f = 0 entering: 1; exiting: 0; section [0.02, 0.0] just touching f = 0
    # from outside: Phi(0)/Phi(0.02/s) -> 1 - 0.5 = 0.5; section [0.015, 0.005] entirely outside: 0
    torch.testing.assert_close(a, torch.tensor([1.0, 0.0, 0.5, 0.0]), atol=1e-6, rtol=0)


def test_density_is_eq3():
    # sigma = -(dPhi/dtau) / Phi with Phi = sigmoid(f(tau) / s), f(tau) = 0.3 + cos * tau
    tau = torch.linspace(-1, 1, 41, dtype=torch.float64, requires_grad=True)
    for c in (-0.7, 0.4):
        s = 0.2
        p = phi(0.3 + c * tau, torch.tensor(s, dtype=torch.float64))
        (dp,) = torch.autograd.grad(p.sum(), tau)
        expected = torch.clamp(-dp / p, min=0)
        got = density(0.3 + c * tau.detach(), torch.tensor(s), torch.tensor(c))
        torch.testing.assert_close(got.double(), expected.detach(), rtol=1e-5, atol=1e-6)


def test_density_integrates_to_opaque_surface():
    # planar SDF f(t) = t0 - t along the ray (cos = -1), small kernel s: NeuS's T(t) =
    # Phi(f(t)) / Phi(f(0)), so opacity is ~0 before the surface, 0.5 at it, ~1 after it.
    t0, s = 0.5, 0.005
    t = torch.linspace(0, 1, 200001, dtype=torch.float64)
    sigma = density(t0 - t, torch.tensor(s, dtype=torch.float64), torch.tensor(-1.0))
    tau = torch.cat([torch.zeros(1, dtype=torch.float64),
                     torch.cumulative_trapezoid(sigma, t)])  # optical depth
    opacity = 1 - torch.exp(-tau)

    def at(x):
        return opacity[round(x * 200000)].item()

    assert at(t0 - 10 * s) < 1e-4
    assert at(t0) == pytest.approx(0.5, abs=1e-4)
    assert at(t0 + 10 * s) > 1 - 1e-4


def test_discrete_alpha_telescopes_on_a_plane():
    # For a plane with cos = -1 and constant s, prod_i (1 - alpha_i) = prod Phi(f_next)/Phi(f_prev)
    # telescopes to Phi(f at the far end) / Phi(f at the near end), for any sampling.
    t0, s = 0.43, 0.02
    edges = torch.tensor([0.0, 0.1, 0.3, 0.4, 0.5, 0.5, 0.9, 1.0])  # contiguous, one empty
    delta = (edges[1:] - edges[:-1])[None]
    mids = 0.5 * (edges[1:] + edges[:-1])[None]
    a = neus_alpha(t0 - mids, torch.full_like(mids, s), -torch.ones_like(mids), delta)
    _, w, opacity = composite(a, torch.zeros(1, 7, 3), torch.zeros(3))
    transmittance = torch.sigmoid(torch.tensor((t0 - 1.0) / s)) / torch.sigmoid(
        torch.tensor(t0 / s))
    torch.testing.assert_close(opacity, 1 - transmittance[None], atol=1e-6, rtol=0)
    assert w.argmax().item() == 3  # the section [0.4, 0.5] holds the surface


def test_gradcheck_float64():
    torch.manual_seed(0)
    R, S = 3, 5
    dbl = dict(dtype=torch.float64, requires_grad=True)
    sdf = (torch.randn(R, S, dtype=torch.float64) * 0.1).requires_grad_()
    s = (torch.rand(R, S, dtype=torch.float64) * 0.1 + 0.05).requires_grad_()
    cos = (-torch.rand(R, S, dtype=torch.float64) * 0.8 - 0.1).requires_grad_()  # away from 0
    delta = torch.full((R, S), 0.05, **dbl)
    assert torch.autograd.gradcheck(neus_alpha, (sdf, s, cos, delta))
    alpha = (torch.rand(R, S, dtype=torch.float64) * 0.8 + 0.1).requires_grad_()
    rgb = torch.rand(R, S, 3, **dbl)
    bg = torch.rand(R, 3, **dbl)
    assert torch.autograd.gradcheck(composite, (alpha, rgb, bg))
    assert torch.autograd.gradcheck(density, (sdf, s, cos))
