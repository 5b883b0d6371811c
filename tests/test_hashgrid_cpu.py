"""The compiled CPU path of the hash grid (`shells.fields.hashgrid._CompiledLookup`,
`shells.fields.hashgrid_cpu`) against its references: the lookup against `hashgrid_reference`
(bit for bit), the backward scatter against the torch path's ``index_add_`` and against
numpy's ordered ``np.add.at``, the same sums on 1 and 2 threads, and `GridAdam` with its
gradient sink against torch's Adam fed by autograd."""

import numpy as np
import pytest
import torch

from shells.fields import hashgrid_cpu
from shells.fields.hashgrid import hashgrid_reference
from tests.test_hashgrid import ODD, TOY, _grid  # ODD: F = 4, a table not a power of 2

ONE = (3, 1, 2 ** 10, 4, 64)  # one feature per level
BIG = (5, 2, 2 ** 17, 16, 512)  # larger tables
BIG_ODD = (5, 4, 70000, 8, 256)  # ... with F = 4 and a table that is not a power of 2


def _points(n, seed=1, res=None):
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, generator=gen)
    # cube corners and faces (keys reach res there), and points on the cell corners and faces
    # of a level (weights exactly 0 and 1)
    x[:6] = torch.tensor([[0, 0, 0], [1, 1, 1], [1, 0, 1], [0.5, 0.5, 0.5],
                          [1e-7, 1 - 1e-7, 0.999], [0.25, 1.0, 0.0]])
    if res is not None:
        k = torch.randint(0, res, (40, 3), generator=gen).float()
        x[6:46] = ((k - 0.5) / (res - 1)).clamp(0, 1)
        x[46:86, :2] = x[6:46, :2]
    return x


@pytest.mark.parametrize("cfg", [TOY, ODD, ONE])
def test_compiled_lookup_equals_the_reference_bit_for_bit(cfg):
    g = _grid(*cfg)
    x = _points(5000, res=g.levels[1].res)
    ref = hashgrid_reference(g.params.detach(), x, g.levels, g.n_features)
    out = g(x)  # with a gradient of the table: _CompiledLookup
    assert "CompiledLookup" in type(out.grad_fn).__name__
    assert torch.equal(out.detach(), ref)


def test_lookup_dispatch():
    """With a gradient of the table a lookup runs `_CompiledLookup` (``training_path`` "auto")
    and gives the reference's floats; points with a gradient and "torch" take the torch path."""
    g = _grid(*TOY)
    x = _points(3000)
    ref = hashgrid_reference(g.params.detach(), x, g.levels, g.n_features)
    out = g(x)
    assert "CompiledLookup" in type(out.grad_fn).__name__
    assert torch.equal(out.detach(), ref)
    g.training_path = "torch"
    assert "CompiledLookup" not in type(g(x).grad_fn).__name__
    g.training_path = "auto"
    xg = x.clone().requires_grad_()
    assert "CompiledLookup" not in type(g(xg).grad_fn).__name__


@pytest.mark.parametrize("cfg", [TOY, ODD, ONE, BIG, BIG_ODD])
def test_compiled_backward_matches_index_add(cfg):
    """The table's gradient of the compiled backward against the torch path's ``index_add_``
    (the same terms; the order of the sums differs: points outer, corners inner)."""
    g = _grid(*cfg, scale=0.1)
    x = _points(4000, res=g.levels[-1].res)
    cot = torch.randn(4000, g.out_dim, generator=torch.Generator().manual_seed(3))
    g.training_path = "torch"
    (ref,) = torch.autograd.grad((g(x) * cot).sum(), g.params)
    g.training_path = "auto"
    (got,) = torch.autograd.grad((g(x) * cot).sum(), g.params)
    torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-5)
    assert got.abs().max() > 0.1


@pytest.mark.parametrize("cfg", [TOY, BIG])
def test_scatter_the_same_on_one_and_two_threads(cfg):
    g = _grid(*cfg)
    x = _points(20000, res=g.levels[-1].res)
    cot = torch.randn(20000, g.out_dim, generator=torch.Generator().manual_seed(4))
    cot[:, -2:] = 0.0  # the last level switched off (coarse-to-fine): no update there
    lay = g._layout()
    sums = []
    for threads in (1, 2):
        table = np.zeros((lay.rows, g.n_features), np.float32)
        hashgrid_cpu.scatter(cot.numpy(), x.numpy(), lay, table, threads)
        sums.append(table)
    assert np.array_equal(sums[0], sums[1])
    assert not sums[0][g.levels[-1].offset:].any() and sums[0].any()


def test_grid_adam_equals_adam_through_autograd_and_clears_its_sink():
    """`GridAdam`: the table's gradient goes to the sink (``params.grad`` stays None after the
    backward), and three steps give the parameters of torch's fused Adam fed by the torch
    path's autograd gradients; the sink is empty after each step and after a zero_grad that
    follows a backward without a step; its state loads into the plain Adam and back."""
    from shells.train.optim import GridAdam, make_optimizer

    def model(seed):
        g = _grid(*TOY, scale=1e-2)
        torch.manual_seed(seed)
        return torch.nn.ModuleDict({"grid": g, "head": torch.nn.Linear(g.out_dim, 1)})

    fast, ref = model(0), model(0)
    ref["grid"].training_path = "torch"
    opt = make_optimizer(fast, 1e-2, 1e-3)
    plain = make_optimizer(ref, 1e-2, 1e-3, sink=False)
    assert isinstance(opt, GridAdam) and not isinstance(plain, GridAdam)
    g = fast["grid"]
    for k in range(3):
        x = _points(2000, seed=k)
        x[:, 0] *= 0.5  # half of the table's cells: rows without gradient too
        for m, o in ((fast, opt), (ref, plain)):
            o.zero_grad()
            m["head"](m["grid"](x)).square().mean().backward()
        assert g.params.grad is None and g.sink_dirty and g.grad_sink.any()
        opt.step()
        plain.step()
        assert not g.sink_dirty and not g.grad_sink.any() and g.params.grad is None
    for (name, p), q in zip(fast.named_parameters(), ref.parameters()):
        torch.testing.assert_close(p, q, rtol=1e-5, atol=1e-6, msg=name)
    fast["head"](g(_points(500))).square().mean().backward()
    opt.zero_grad()
    assert not g.sink_dirty and not g.grad_sink.any()
    plain.load_state_dict(opt.state_dict())
    again = make_optimizer(fast, 1e-2, 1e-3)
    again.load_state_dict(plain.state_dict())
    assert int(again.state[g.params]["step"]) == 3


@pytest.mark.parametrize("cfg", [ODD, BIG, BIG_ODD])
def test_scatter_adds_in_point_order_bit_for_bit(cfg):
    """Every row receives its terms w * g in point order, corners in order: equal bit for bit
    to numpy's unbuffered ``np.add.at`` over the torch path's rows and weights in that
    order."""
    g = _grid(*cfg)
    N, F = 3000, g.n_features
    x = _points(N, res=g.levels[-1].res)
    cot = torch.randn(N, g.out_dim, generator=torch.Generator().manual_seed(5))
    rows, wts = g.corner_rows_weights(x)  # [8, L, N]
    ref = np.zeros((g._layout().rows, F), np.float32)
    for lv in range(g.n_levels):
        r = rows[:, lv].T.reshape(-1).numpy()  # point-major, then corner
        v = (wts[:, lv].T[..., None] * cot[:, lv * F:(lv + 1) * F][:, None, :]).reshape(-1, F)
        np.add.at(ref, r, v.numpy())
    got = np.zeros_like(ref)
    hashgrid_cpu.scatter(cot.numpy(), x.numpy(), g._layout(), got, 2)
    assert np.array_equal(got, ref)
