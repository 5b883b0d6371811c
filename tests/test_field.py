"""ShellField: geometric init is the analytic sphere, kernel clamp, shapes, gradients, checkpoint;
SH encoding against hand values and dr.sh_eval."""

import math

import drjit as dr
import pytest
import torch

from shells.config import Config, FieldConfig
from shells.presets import toy_config
from shells.errors import InputError
from shells.fields.encoding import sh_encode
from shells.fields.network import ShellField

BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
SLAB = torch.tensor([[0.0, -2.0, 1.0], [4.0, 0.0, 1.5]])  # anisotropic box, centre (2, -1, 1.25)


def _field(aabb=BOX, seed=0, **kw):
    torch.manual_seed(seed)
    cfg = toy_config().field
    for k, v in kw.items():
        setattr(cfg, k, v)
    return ShellField(cfg, aabb)


def _in_box(aabb, n, seed=1):
    torch.manual_seed(seed)
    return aabb[0] + torch.rand(n, 3) * (aabb[1] - aabb[0])


@pytest.mark.parametrize("aabb,radius", [(BOX, 0.5), (SLAB, 0.2)])
def test_init_is_sphere(aabb, radius):
    f = _field(aabb, init_radius=radius)
    x = _in_box(aabb, 3000)
    centre = aabb.mean(0)
    r = (x - centre).norm(dim=1)
    with torch.no_grad():
        sdf = f.sdf(x)
    # 64 Fibonacci directions average max(u . v, 0) to |v| / 4 within 1.6 % (measured 1.23 %),
    # plus the 1e-4 hash-table init times zero first-layer weights (no contribution)
    assert ((sdf - (r - radius)).abs() <= 0.016 * r + 1e-6).all()
    # sign convention: negative inside the sphere, positive outside
    assert (sdf[r < 0.95 * radius] < 0).all() and (sdf[r > 1.05 * radius] > 0).all()


def test_init_kernel_and_gradient():
    cfg_kernel = 0.05
    f = _field(init_kernel=cfg_kernel)
    x = _in_box(BOX * 0.9, 500)
    with torch.no_grad():
        s = f.kernel(x)
        g = f.sdf_gradient_fd(x, 1e-3)
    torch.testing.assert_close(s, torch.full_like(s, cfg_kernel), rtol=1e-5, atol=0)
    # grad of |x| - r is the unit radial direction; the ReLU init is a 64-facet cone, whose
    # gradient (a sum of active u_k) is off by up to ~10 degrees (measured min cos 0.983 on 20k
    # points, mean 0.998) with norm within 1.7 %
    radial = torch.nn.functional.normalize(x, dim=1)
    assert ((g.norm(dim=1) - 1).abs() < 0.03).all()
    cos = torch.cosine_similarity(g, radial, dim=1)
    assert (cos > 0.975).all() and cos.mean() > 0.995


def test_kernel_soft_clamp():
    f = _field(min_kernel=1e-4, init_kernel=0.05, max_kernel=1.0)
    z = torch.tensor([-1e4, -30.0, 0.0, 30.0, 1e4], requires_grad=True)
    s = f.kernel_from_logit(z)
    # z -> -inf: s_min; z = 0: init; z -> +inf: s_max (log-space sigmoid)
    torch.testing.assert_close(s.detach(), torch.tensor([1e-4, 1e-4, 0.05, 1.0, 1.0]),
                               rtol=1e-4, atol=0)
    (ds,) = torch.autograd.grad(s[2], z)
    assert ds[2] > 0  # differentiable at the init value


def test_sdf_gradient_fd_exact_on_linear_sdf():
    # zero the hidden layer except one unit: f = relu(u . x_world) * a - r is linear where the
    # unit is active, so central differences are exact (up to fp32)
    f = _field()
    with torch.no_grad():
        f.geo_mlp[0].weight[1:] = 0
        f.geo_mlp[0].weight[0, :3] = torch.tensor([0.6, 0.0, 0.8])  # x_n = x for BOX
        f.geo_mlp[2].weight[0] = 0
        f.geo_mlp[2].weight[0, 0] = 2.0
    x = torch.tensor([[0.3, 0.2, 0.4], [0.1, -0.5, 0.2]])  # u . x > 0
    with torch.no_grad():
        g = f.sdf_gradient_fd(x, 1e-2)
    torch.testing.assert_close(g, torch.tensor([[1.2, 0.0, 1.6]]).expand(2, 3),
                               atol=1e-4, rtol=0)  # fp32 (f(x+e) - f(x-e)) / 0.02


def test_regulariser_probe_matches_the_three_separate_calls_forward_and_backward():
    # the one batched evaluation of the regularisers = sdf_gradient_fd + geometry_field +
    # kernel at the noisy points, network alone, values and every parameter's gradient
    f = _field()
    with torch.no_grad():  # move the hash columns and the table off their init
        f.geo_mlp[0].weight[:, 3:].normal_(0, 0.3)
        f.grid.params.normal_(0, 0.1)
    x, y = _in_box(BOX * 0.9, 300, seed=2), _in_box(BOX * 0.9, 300, seed=3)
    probe = f.regulariser_probe(x, 1e-3, y)
    geo = f.geometry_field(x, far=False)
    ref = dict(grad=f.sdf_gradient_fd(x, 1e-3, far=False), normal=geo["normal"], s=geo["s"],
               s_extra=f.kernel(y, far=False))
    grads = []
    for out in (probe, ref):
        f.zero_grad()
        (out["grad"].norm(dim=-1).sub(1).square().mean() + out["normal"].sum()
         + out["s"].log().mean() - out["s_extra"].log().mean()).backward()
        grads.append([p.grad.clone() for p in f.parameters() if p.grad is not None])
    assert len(grads[0]) == len(grads[1]) == 5  # the hash table and the geometry MLP
    for k in ref:  # the same floats up to the matmul's blocking over a longer batch
        torch.testing.assert_close(probe[k], ref[k], rtol=1e-5, atol=1e-5)
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)


def test_forward_shapes_ranges_and_consistency():
    f = _field()
    x = _in_box(BOX, 64)
    d = torch.nn.functional.normalize(torch.randn(64, 3), dim=1)
    out = f(x, d)
    G = f.cfg.geo_feature_dim
    assert out["sdf"].shape == (64,) and out["s"].shape == (64,)
    assert out["feat"].shape == (64, G) and out["normal"].shape == (64, 3)
    assert out["rgb"].shape == (64, 3)
    assert ((out["rgb"] > 0) & (out["rgb"] < 1)).all()
    torch.testing.assert_close(out["normal"].norm(dim=1), torch.ones(64))
    torch.testing.assert_close(out["sdf"], f.sdf(x))
    torch.testing.assert_close(out["s"], f.kernel(x))
    assert f.geo_mlp[0].in_features == 3 + 8 * 2  # x + Psi for L=8, F=2
    assert f.rad_mlp[0].in_features == 16 + G + 3 + 3  # paper: 48


def test_paper_sizes():
    f = ShellField(FieldConfig(log2_hashmap_size=12), BOX)  # paper MLPs, small table
    assert f.geo_mlp[0].in_features == 31 and f.geo_mlp[2].out_features == 31
    assert [m.out_features for m in f.rad_mlp if isinstance(m, torch.nn.Linear)] == [64, 64, 3]
    assert f.rad_mlp[0].in_features == 48


def test_gradients_reach_hash_table_and_kernel():
    f = _field()
    x = _in_box(BOX, 256)
    d = torch.nn.functional.normalize(torch.randn(256, 3), dim=1)
    out = f(x, d)
    loss = out["sdf"].square().mean() + out["s"].mean() + out["rgb"].mean()
    loss.backward()
    # hash columns of the first layer start at zero but receive gradient; the table then does
    assert f.geo_mlp[0].weight.grad[:, 3:].abs().sum() > 0
    assert f.geo_mlp[2].weight.grad[1].abs().sum() > 0  # kernel row
    # table gradient is zero until the hash columns move away from zero
    with torch.no_grad():
        f.geo_mlp[0].weight[:, 3:].normal_(0, 0.1)
    f.zero_grad()
    f.sdf(x).square().mean().backward()
    assert f.grid.params.grad.abs().sum() > 0


def test_state_dict_round_trip():
    f = _field(seed=0)
    with torch.no_grad():
        f.grid.params.uniform_(-0.1, 0.1)
    g = _field(seed=5)
    g.load_state_dict(f.state_dict())
    x = _in_box(BOX, 100)
    d = torch.nn.functional.normalize(torch.randn(100, 3), dim=1)
    a, b = f(x, d), g(x, d)
    for k in ("sdf", "s", "normal", "rgb"):
        assert torch.equal(a[k], b[k])
    assert "aabb" in f.state_dict()


def test_bad_inputs():
    with pytest.raises(InputError):
        ShellField(toy_config().field, torch.tensor([[0.0, 0, 0], [1.0, -1, 1]]))
    with pytest.raises(InputError, match="init_kernel"):  # checked when a config is loaded
        Config().update({"field": {"min_kernel": 0.1, "init_kernel": 0.05}}, "x.json")
    with pytest.raises(InputError):
        _field().sdf(torch.zeros(5, 2))
    with pytest.raises(InputError):
        sh_encode(torch.zeros(3, 3), degree=5)


def test_sh_hand_values():
    d = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    sh = sh_encode(d, 4)
    c0 = 0.28209479177387814  # 1 / (2 sqrt(pi))
    # d = +z: only m = 0 terms: Y_1^0 = sqrt(3/(4pi)) = 0.488603,
    # Y_2^0 = 2 sqrt(5/(16pi)) = 0.630783, Y_3^0 = 2 sqrt(7/(16pi)) = 0.746353
    up = torch.zeros(16)
    up[[0, 2, 6, 12]] = torch.tensor([c0, 0.488603, 0.630783, 0.746353])
    # d = +x: Y_1^1 = -0.488603 (Condon-Shortley sign), Y_2^0 = -0.315392, Y_2^2 = 0.546274,
    # Y_3^1 = 0.457046 * -1 (tcnn sign), Y_3^3 = -0.590044
    east = torch.zeros(16)
    east[[0, 3, 6, 8, 13, 15]] = torch.tensor([c0, -0.488603, -0.315392, 0.546274, 0.457046,
                                               -0.590044])
    torch.testing.assert_close(sh, torch.stack([up, east]), atol=1e-6, rtol=0)
    assert sh_encode(d, 2).shape == (2, 4)


def test_sh_matches_drjit():
    from drjit.llvm.ad import Array3f, Float
    torch.manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(1000, 3), dim=1)
    ours = sh_encode(d, 4)
    ref = dr.sh_eval(Array3f(*[Float(d[:, i].contiguous()) for i in range(3)]), 3)
    ref = torch.stack([torch.full((1000,), r[0]) if dr.width(r) == 1 else r.torch()
                       for r in ref], dim=1)
    torch.testing.assert_close(ours, ref, atol=1e-6, rtol=0)
    assert math.isclose(ours[:, 0].mean().item(), 0.28209479177387814, rel_tol=1e-6)
