"""Hash-grid layout and encoding: Dr.Jit's layout, hand-worked lookups, fast path vs reference."""

import drjit as dr
import pytest
import torch

from shells.errors import InputError
from shells.fields.hashgrid import (PRIMES, HashGrid, hashgrid_reference, level_layout,
                                    n_params, per_level_scale)

TOY = (8, 2, 2 ** 15, 8, 256)  # L, F, T, base, max: toy_config()
PAPER = (14, 2, 2 ** 22, 16, 4096)  # the paper's sizes


def _grid(L, F, T, base, mx, seed=0, scale=1.0):
    torch.manual_seed(seed)
    g = HashGrid(L, F, T, base, per_level_scale(L, base, mx))
    with torch.no_grad():
        g.params.uniform_(-scale, scale)
    return g


def _drjit_encoding(g):
    from drjit.llvm.ad import Float
    enc = dr.nn.HashGridEncoding(Float, 3, n_levels=g.n_levels,
                                 n_features_per_level=g.n_features, hashmap_size=g.hashmap_size,
                                 base_resolution=g.base_resolution,
                                 per_level_scale=g.per_level_scale)
    enc.set_params(Float(g.params.detach()))
    return enc


def _points(n, seed=1):
    torch.manual_seed(seed)
    x = torch.rand(n, 3)
    # corners and faces of the unit cube: keys reach res there and wrap like Dr.Jit's
    x[:6] = torch.tensor([[0, 0, 0], [1, 1, 1], [1, 0, 1], [0.5, 0.5, 0.5],
                          [1e-7, 1 - 1e-7, 0.999], [0.25, 1.0, 0.0]])
    return x


def test_per_level_scale_reaches_max_resolution():
    # b = exp(ln(256 / 8) / 7) = 32^(1/7) = 1.640670...
    assert per_level_scale(8, 8, 256) == pytest.approx(32 ** (1 / 7), rel=1e-12)
    assert per_level_scale(1, 16, 16) == 1.0
    with pytest.raises(InputError):
        per_level_scale(4, 64, 16)


@pytest.mark.parametrize("cfg", [TOY, PAPER, (16, 4, 2 ** 19, 16, 2048)])
def test_layout_matches_drjit(cfg):
    from drjit.llvm.ad import Float
    L, F, T, base, mx = cfg
    pls = per_level_scale(L, base, mx)
    levels = level_layout(L, F, T, base, pls)
    enc = dr.nn.HashGridEncoding(Float, 3, n_levels=L, n_features_per_level=F, hashmap_size=T,
                                 base_resolution=base, per_level_scale=pls)
    assert [lv.offset for lv in levels] == enc._level_offsets[:-1]
    assert [lv.scale for lv in levels] == [enc._level_scale(i) for i in range(L)]  # exact
    assert n_params(levels, F) == enc.n_params


def test_layout_hand_worked_toy():
    levels = level_layout(*TOY[:4], per_level_scale(8, 8, 256))
    # level 0: scale = 8 - 1 = 7, res = 8, 8^3 = 512 rows, dense
    assert (levels[0].scale, levels[0].res, levels[0].size, levels[0].dense) == (7.0, 8, 512, True)
    # level 2: scale = 8 b^2 - 1 = 20.534..., res = 22, 22^3 = 10648 <= 2^15: dense, offset 512+2744
    assert (levels[2].res, levels[2].size, levels[2].offset) == (22, 10648, 512 + 14 ** 3)
    # level 3: res = 36, 36^3 = 46656 > 2^15: hashed, capped at 32768 rows
    assert (levels[3].res, levels[3].size, levels[3].dense) == (36, 2 ** 15, False)
    # level 7: scale = 256 - 1 = 255, res 256
    assert levels[7].scale == pytest.approx(255.0) and levels[7].res == 256


def test_hand_worked_lookup_centre_of_cell():
    # L=2, F=2, T=64, base 2, b = 2: level 0 scale 1, res 2, 8 rows (dense);
    # level 1 scale 3, res 4, 64 rows (dense), offset 8.
    g = HashGrid(2, 2, 64, 2, 2.0)
    with torch.no_grad():
        rows = torch.arange(g.params.numel() // 2, dtype=torch.float32)
        g.params.copy_(torch.stack([10 * rows, 10 * rows + 1], 1).view(-1))  # row r = (10r, 10r+1)
    out = g(torch.zeros(1, 3))
    # level 0: pos = 0 * 1 + 0.5, all 8 corners (rows 0..7) weigh 1/8: mean row 3.5 -> 35, 36
    # level 1: pos = 0.5, keys {0,1}^3, dense rows 8 + {0,1,4,5,16,17,20,21}, mean 18.5 -> 185, 186
    torch.testing.assert_close(out, torch.tensor([[35.0, 36.0, 185.0, 186.0]]))


def test_hand_worked_hashed_vertex():
    # At pos = x * scale + 0.5 integer, w = 0: only corner 0 (the key p0 itself) contributes.
    L, F, T, base, mx = TOY
    g = _grid(*TOY)
    lv = g.levels[5]  # hashed level, scale 94.1036...
    assert not lv.dense
    k = torch.tensor([40, 17, 73])
    scale32 = torch.tensor(lv.scale, dtype=torch.float32).double()
    x = ((k.double() - 0.5) / scale32).float()[None]
    pos = (x.double() * scale32 + 0.5).float()
    assert torch.equal(torch.floor(pos), pos)  # lands exactly on the vertex k
    h = (40 * PRIMES[0]) ^ ((17 * PRIMES[1]) & 0xFFFFFFFF) ^ ((73 * PRIMES[2]) & 0xFFFFFFFF)
    row = lv.offset + h % lv.size  # uint32 hash kx ^ ky 2654435761 ^ kz 805459861
    out = g(x).view(L, F)[5]
    torch.testing.assert_close(out, g.params.detach().view(-1, F)[row], rtol=0, atol=0)


ODD = (6, 4, 3000, 4, 64)  # F = 4 (generic scatter path), table not a power of 2 (mod path)


@pytest.mark.parametrize("cfg", [TOY, ODD])
def test_fast_equals_reference_and_drjit(cfg):
    g = _grid(*cfg)
    x = _points(4000)
    fast = g(x).detach()
    ref = hashgrid_reference(g.params.detach(), x, g.levels, g.n_features)
    # the fast path's sum order differs from the fma chain; measured: 0 on these inputs
    torch.testing.assert_close(fast, ref, rtol=0, atol=1e-6)
    enc = _drjit_encoding(g)
    from drjit.llvm.ad import Array3f, Float
    out = enc(Array3f(*[Float(x[:, i].contiguous()) for i in range(3)]))
    dj = torch.stack([o.torch() for o in out], dim=1)
    # reference does Dr.Jit's fp32 fmas in float64 rounded once: bit-exact
    assert torch.equal(ref, dj)


@pytest.mark.parametrize("cfg", [TOY, ODD])
def test_gradients_match_reference(cfg):
    g = _grid(*cfg, scale=0.1)
    x = _points(500).requires_grad_()
    cot = torch.randn(500, g.out_dim)
    gp, gx = torch.autograd.grad((g(x) * cot).sum(), (g.params, x))
    x2 = x.detach().clone().requires_grad_()
    p2 = g.params.detach().clone().requires_grad_()

    def ref_fn(p, xx):  # reference without the float64 rounding so autograd sees through it
        out = []
        table = p.view(-1, g.n_features)
        for lv in g.levels:
            pos = xx * float(torch.tensor(lv.scale, dtype=torch.float32)) + 0.5
            p0 = torch.floor(pos.detach())
            w1 = pos - p0
            acc = 0
            for c in range(8):
                b = [(c >> j) & 1 for j in range(3)]
                k = [p0[:, j].long() + b[j] for j in range(3)]
                wc = [w1[:, j] if b[j] else 1 - w1[:, j] for j in range(3)]
                if lv.dense:
                    idx = k[0] + k[1] * lv.res + k[2] * lv.res ** 2
                else:
                    m = 0xFFFFFFFF
                    idx = k[0] ^ ((k[1] * PRIMES[1]) & m) ^ ((k[2] * PRIMES[2]) & m)
                acc = acc + (wc[0] * wc[1] * wc[2])[:, None] * table[lv.offset + idx % lv.size]
            out.append(acc)
        return torch.cat(out, 1)

    rp, rx = torch.autograd.grad((ref_fn(p2, x2) * cot).sum(), (p2, x2))
    # pos = x * scale + 0.5 rounded in fp32 here but via float64 in HashGrid: at pos ~ 255 one
    # ulp is 1.5e-5, so weights (and param grads, sums of weight * cotangent) differ by ~1e-5;
    # dw/dx grows with scale (up to 255), hence the looser x tolerance
    torch.testing.assert_close(gp, rp, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(gx, rx, rtol=1e-4, atol=1e-3)


def test_init_range_and_bad_input():
    torch.manual_seed(0)
    g = HashGrid(*TOY[:4], per_level_scale(8, 8, 256))
    assert g.params.abs().max() <= 1e-4 and g.params.std() > 3e-5  # uniform(-1e-4, 1e-4)
    with pytest.raises(InputError):
        g(torch.zeros(4, 2))
    with pytest.raises(InputError):
        level_layout(2, 4, 2 ** 6 + 2, 2, 2.0)  # table size not a multiple of F


@pytest.mark.parametrize("cfg", [TOY, ODD])
def test_lookup_without_gradient_runs_drjit_and_matches_torch_bit_for_bit(cfg, monkeypatch):
    """``inference`` "auto": without gradient the lookup is ``dr.nn.HashGridEncoding`` on the
    parameter memory itself; the floats equal the torch lookup's, also after the parameters
    change in place (no stale copy)."""
    import shells.fields.hashgrid as hg

    g = _grid(*cfg)
    g.training_path = "torch"  # the lookup with gradient: the torch path
    x = _points(3000)
    calls = []
    real = hg._drjit_lookup
    monkeypatch.setattr(hg, "_drjit_lookup", lambda grid, p: calls.append(len(p)) or real(grid, p))
    for _ in range(2):
        torch_out = g(x).detach()  # gradient enabled, training_path "torch": the torch path
        with torch.no_grad():
            dj = g(x)
        assert torch.equal(dj, torch_out)
        with torch.no_grad():
            g.params.mul_(-0.5).add_(0.01)  # an optimiser step, in place
    assert calls == [3000, 3000]
    g.inference = "torch"
    with torch.no_grad():
        g(x)
    assert calls == [3000, 3000]
    # points that need a gradient keep the torch path even without parameter gradients
    g.inference = "auto"
    g.params.requires_grad_(False)
    xg = x.clone().requires_grad_()
    assert g(xg).requires_grad and calls == [3000, 3000]


def test_lookups_on_the_calling_thread_give_the_same_floats_and_the_pool_comes_back():
    """`drjit_on_calling_thread`: inside, Dr.Jit's pool is the calling thread alone and the
    lookup without gradient gives the pool's floats bit for bit; after it (also after an
    error inside) the pool has its size again."""
    from shells.fields.hashgrid import drjit_on_calling_thread

    g = _grid(*TOY)
    x = _points(20000)
    size = dr.thread_count()
    dr.set_thread_count(2)  # a pool with a worker, whatever this machine's default
    try:
        with torch.no_grad():
            pooled = g(x)
            with drjit_on_calling_thread():
                assert dr.thread_count() == 1
                alone = g(x)
        assert dr.thread_count() == 2
        assert torch.equal(alone, pooled)
        with pytest.raises(RuntimeError, match="inside"):
            with drjit_on_calling_thread():
                raise RuntimeError("inside")
        assert dr.thread_count() == 2
    finally:
        dr.set_thread_count(size)
