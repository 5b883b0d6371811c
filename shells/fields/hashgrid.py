"""Multiresolution hash encoding Psi(x) (§4.1), laid out exactly like ``dr.nn.HashGridEncoding``.

The layout is written down once, in `level_layout`; the fast torch encoding (`HashGrid`, used for
training), the slow loop reference (`hashgrid_reference`) and the Dr.Jit inference twin
(``shells.fields.drjit_field``, which hands our flat parameter tensor to
``dr.nn.HashGridEncoding.set_params``) all follow it. Lookups that need no gradient (the
training renderer's sample-placement pass, occupancy-grid rebuilds, evaluation) go through
``dr.nn.HashGridEncoding`` itself on the CPU (`HashGrid.inference`): one fused LLVM kernel
on the same parameter memory, the same numbers bit for bit. The layout, per level l:

    scale_l  = 2**(l * log2(per_level_scale)) * base_resolution - 1      (float64, used as float32)
    res_l    = ceil(scale_l) + 1                                         (grid vertices per axis)
    size_l   = min(next_multiple(min(res_l**3, 2**31 - 1), F), hashmap_size)   (rows)
    offset_l = size_0 + ... + size_{l-1}                                 (levels back to back)

A point p in [0, 1]^3 is looked up as pos = p * scale_l + 0.5, p0 = floor(pos), w = pos - p0;
corner c (bits bx = c & 1, by = c >> 1 & 1, bz = c >> 2 & 1) has key k = p0 + b, weight
(wx * wy) * wz with w_axis = w or 1 - w, and row offset_l + (idx mod size_l), where idx is the
dense index kx + ky res + kz res^2 when res**3 <= size_l, else the hash
kx ^ ky * 2654435761 ^ kz * 805459861 (uint32 wrap-around). The flat parameter vector holds
row r, feature f at r * F + f; the output is ordered [l0f0, l0f1, l1f0, ...].
"""

from __future__ import annotations

import contextlib
import functools
import math
import threading
from collections.abc import Iterator
from dataclasses import dataclass

import drjit as dr
import numpy as np
import torch
from torch import nn

from shells.device import drjit_llvm
from shells.errors import InputError
from shells.fields import hashgrid_cpu

PRIMES = (1, 2654435761, 805459861)  # tiny-cuda-nn / Dr.Jit spatial-hash primes (x, y, z)
_MAX_PARAMS = 0xFFFFFFFF // 2  # Dr.Jit caps a dense level at 2^31 - 1 rows


@dataclass(frozen=True)
class Level:
    """One resolution level of the grid."""

    scale: float  # float64 value of scale_l; the lookup uses float32(scale)
    res: int  # grid vertices per axis
    size: int  # rows (feature vectors) stored for this level
    offset: int  # first row of this level in the table
    dense: bool  # True: dense indexing (res^3 <= size); False: spatial hash


def per_level_scale(n_levels: int, base_resolution: int, max_resolution: int) -> float:
    """Growth factor b between levels so that level L-1 has resolution max_resolution.

    Instant-NGP Eq. 3: b = exp((ln N_max - ln N_min) / (L - 1)).
    """
    if n_levels < 1 or base_resolution < 1 or max_resolution < base_resolution:
        raise InputError(f"hash grid: need n_levels >= 1 and 1 <= base_resolution <= "
                         f"max_resolution, got {n_levels}, {base_resolution}, {max_resolution}")
    if n_levels == 1:
        return 1.0
    return math.exp((math.log(max_resolution) - math.log(base_resolution)) / (n_levels - 1))


def level_layout(n_levels: int, n_features: int, hashmap_size: int, base_resolution: int,
                 per_level_scale: float) -> list[Level]:
    """Per-level (scale, res, size, offset, dense) exactly as dr.nn.HashGridEncoding computes."""
    if hashmap_size % n_features:
        raise InputError(f"hash grid: hashmap_size {hashmap_size} must be a multiple of "
                         f"n_features_per_level {n_features}")
    # Dr.Jit's own scalar exp2/log2: math.exp2 differs from dr.exp2 in the last bit on some levels
    log2_pls = dr.log2(per_level_scale)
    levels, offset = [], 0
    for lvl in range(n_levels):
        scale = dr.exp2(lvl * log2_pls) * base_resolution - 1.0
        res = int(math.ceil(scale)) + 1
        size = min(res ** 3, _MAX_PARAMS)
        size = min(-(-size // n_features) * n_features, hashmap_size)
        levels.append(Level(scale, res, size, offset, res ** 3 <= size))
        offset += size
    return levels


def n_params(levels: list[Level], n_features: int) -> int:
    """Length of the flat parameter vector."""
    return (levels[-1].offset + levels[-1].size) * n_features


def _f32(v: float) -> float:
    """Round a Python float to float32 (Dr.Jit bakes Python scalars into fp32 kernels)."""
    return float(torch.tensor(v, dtype=torch.float32))


class HashGrid(nn.Module):
    """Fast vectorised torch hash-grid encoding; `params` is Dr.Jit's flat parameter vector.

    All levels and all 8 corners are looked up with one gather (`_Lookup`: an `index_select`
    and a weighted sum, whose backward is one `index_add_`), the index math done once in int64.
    Gradients flow to `params` and to the input points (through the trilinear weights).

    ``inference`` "auto" (default): a lookup that needs no gradient, of CPU tensors, runs as
    ``dr.nn.HashGridEncoding`` on Dr.Jit's LLVM backend (`_drjit_lookup`), which reads `params`
    in place and gives the same floats; "torch": always the torch lookup. Dr.Jit's fused
    kernel does not pay off for the backward on the CPU (its atomic scatter took longer than
    the torch `index_add_`; BENCHMARKS.md).

    ``training_path`` "auto" (default): a lookup with a gradient of the table (and none of the
    points) of CPU float32 tensors runs compiled (`_CompiledLookup`: Dr.Jit's kernel forward,
    `shells.fields.hashgrid_cpu` backward, which recomputes the corners and scatters on every
    core, into the grid's gradient sink when `use_gradient_sink` is on);
    "torch": the torch `_Lookup`, the reference of that path. Gradients of the points always
    take the torch path.
    """

    inference: str = "auto"
    training_path: str = "auto"
    sink_dirty: bool = False  # the gradient sink holds a gradient (`use_gradient_sink`)

    def __init__(self, n_levels: int, n_features: int, hashmap_size: int, base_resolution: int,
                 per_level_scale: float, init_scale: float = 1e-4) -> None:
        super().__init__()
        self.n_levels, self.n_features = n_levels, n_features
        self.hashmap_size, self.base_resolution = hashmap_size, base_resolution
        self.per_level_scale = per_level_scale
        self.levels = level_layout(n_levels, n_features, hashmap_size, base_resolution,
                                   per_level_scale)
        # Instant-NGP init: uniform(-1e-4, 1e-4)
        self.params = nn.Parameter(
            torch.empty(n_params(self.levels, n_features)).uniform_(-init_scale, init_scale))
        self.n_dense = sum(lv.dense for lv in self.levels)
        assert all(lv.dense for lv in self.levels[:self.n_dense])  # dense levels come first
        L = n_levels
        f64 = dict(dtype=torch.float64)
        i64 = dict(dtype=torch.int64)
        self.register_buffer("_scale", torch.tensor([_f32(lv.scale) for lv in self.levels], **f64),
                             persistent=False)  # [L] float32 values held in float64
        self.register_buffer("_res", torch.tensor([lv.res for lv in self.levels], **i64),
                             persistent=False)  # [L]
        self.register_buffer("_size", torch.tensor([lv.size for lv in self.levels], **i64),
                             persistent=False)  # [L]
        self.register_buffer("_offset", torch.tensor([lv.offset for lv in self.levels], **i64),
                             persistent=False)  # [L]
        self._pow2 = all((lv.size & (lv.size - 1)) == 0 for lv in self.levels[self.n_dense:])
        self.out_dim = L * n_features

    # -- the compiled CPU path (shells.fields.hashgrid_cpu) ------------------------------------
    def _compiled_ok(self, x01: torch.Tensor) -> bool:
        return (x01.device.type == "cpu" and self.params.device.type == "cpu"
                and self.params.dtype == torch.float32 and drjit_llvm())

    def _layout(self) -> "hashgrid_cpu.Layout":
        lay = self.__dict__.get("_cpu_layout")
        if lay is None:
            lay = self.__dict__["_cpu_layout"] = hashgrid_cpu.Layout(self.levels, self.n_features)
        return lay

    @staticmethod
    def _points(x01: torch.Tensor) -> "np.ndarray":
        return x01.detach().float().contiguous().numpy()

    def use_gradient_sink(self, on: bool = True) -> None:
        """On: the compiled backward adds the table's gradient into a persistent buffer
        (`grad_sink`, [rows, F]; `sink_dirty` set) instead of giving autograd a table-sized
        gradient (``params.grad`` stays None); `shells.train.optim.GridAdam` steps with it and
        zeroes it. Off: gradients as usual."""
        if on and "grad_sink" not in self.__dict__:
            self.__dict__["grad_sink"] = torch.zeros(self.params.numel() // self.n_features,
                                                     self.n_features)
            self.sink_dirty = False
        elif not on:
            self.__dict__.pop("grad_sink", None)

    @property
    def sink_on(self) -> bool:
        return "grad_sink" in self.__dict__

    def extra_repr(self) -> str:
        return (f"levels={self.n_levels}, features={self.n_features}, "
                f"hashmap_size={self.hashmap_size}, res={self.levels[0].res}->"
                f"{self.levels[-1].res}, params={self.params.numel()}")

    def corner_rows_weights(self, x01: torch.Tensor  # [N, 3] in [0, 1]
                            ) -> tuple[torch.Tensor, torch.Tensor]:
        """Table rows [8, L, N] (int64) and trilinear weights [8, L, N] of the 8 corners.

        Corner-major (c = 4 bz + 2 by + bx), then level, then point: the index math is separable
        per axis (dense: a sum, hash: an XOR), so per-axis terms [2, L, N] are combined by
        broadcasting over the *outer* dims, which keeps every inner loop a long contiguous run
        (broadcasting over size-2 inner dims is several times slower on CPU).
        """
        N, L, nd = x01.shape[0], self.n_levels, self.n_dense
        # one fma in float64 rounded once to float32 == Dr.Jit's fp32 fma
        pos = torch.addcmul(torch.full((), 0.5, dtype=torch.float64, device=x01.device),
                            x01.double().t()[None], self._scale[:, None, None]).float()  # [L,3,N]
        p0 = torch.floor(pos)
        w1 = pos - p0
        key = p0.long()
        key = torch.stack((key, key + 1))  # [2, L, 3, N]: corner bit 0 / 1 per axis
        rows = torch.empty(2, 2, 2, L, N, dtype=torch.int64, device=x01.device)  # [bz, by, bx]
        if nd:  # dense: kx + ky res + kz res^2, wrapped mod size like Dr.Jit
            res = self._res[:nd, None]
            k = key[:, :nd]
            ax, ay, az = k[:, :, 0], k[:, :, 1] * res, k[:, :, 2] * (res * res)  # [2, nd, N]
            out = rows[..., :nd, :]
            torch.add((az[:, None] + ay[None])[:, :, None], ax[None, None], out=out)
            out.remainder_(self._size[:nd, None])
        if nd < L:  # hash: kx ^ ky p1 ^ kz p2 in uint32; mod 2^k distributes over XOR
            k = key[:, nd:]
            mask = (self._size[nd:, None] - 1) if self._pow2 else 0xFFFFFFFF
            hx = k[:, :, 0] & mask
            hy = (k[:, :, 1] * PRIMES[1]) & mask
            hz = (k[:, :, 2] * PRIMES[2]) & mask  # [2, L - nd, N]
            out = rows[..., nd:, :]
            torch.bitwise_xor((hz[:, None] ^ hy[None])[:, :, None], hx[None, None], out=out)
            if not self._pow2:
                out.remainder_(self._size[nd:, None])
        rows = rows.view(8, L, N).add_(self._offset[:, None])
        wx, wy, wz = torch.stack((1.0 - w1, w1)).unbind(2)  # [2, L, N] each
        # Dr.Jit multiplies (wx * wy) * wz; same order here for bit-exact weights
        wts = wz[:, None, None] * (wy[:, None] * wx[None])[None]
        return rows, wts.view(8, L, N)

    def forward(self, x01: torch.Tensor  # [N, 3] points in [0, 1]^3
                ) -> torch.Tensor:  # [N, L*F]
        if x01.ndim != 2 or x01.shape[1] != 3:
            raise InputError(f"HashGrid: points must be [N, 3], got {tuple(x01.shape)}")
        N = x01.shape[0]
        grad = torch.is_grad_enabled() and (self.params.requires_grad or x01.requires_grad)
        if (grad and not x01.requires_grad and self.training_path == "auto"
                and self._compiled_ok(x01)):
            return _CompiledLookup.apply(self.params, x01, self)
        if (self.inference == "auto" and x01.device.type == "cpu" and drjit_llvm()
                and not grad):
            return _drjit_lookup(self, x01)
        rows, wts = self.corner_rows_weights(x01)
        out = _Lookup.apply(self.params, rows.view(8, -1), wts.view(8, -1), self.n_features)
        return out.view(self.n_levels, N, self.n_features).transpose(0, 1).reshape(N, -1)


_ENCODING_LOCK = threading.Lock()


@contextlib.contextmanager
def drjit_on_calling_thread() -> Iterator[None]:
    """Within the block, Dr.Jit's LLVM kernels (the lookups without gradient) run on the calling
    thread alone; the pool's size is restored after it.

    For torch work between the lookups (training on the CPU). A worker of Dr.Jit's thread pool
    (nanothread) busy-waits for 500 000 attempts at new work after every kernel before it
    sleeps, and meanwhile holds a core that torch's OpenMP threads need: on 2 cores the torch
    work right after a lookup slows down markedly, and a stage-1 step runs faster with the
    lookups on the calling thread (BENCHMARKS.md, method notes). The lookups give
    the same floats on any number of threads (each point is computed alone)."""
    if not drjit_llvm():
        yield
        return
    size = dr.thread_count()
    dr.set_thread_count(1)
    try:
        yield
    finally:
        dr.set_thread_count(size)


@functools.cache
def _encoding(n_levels: int, n_features: int, hashmap_size: int, base_resolution: int,
              per_level_scale: float):
    """One ``dr.nn.HashGridEncoding`` per layout, reused; its ``data`` is set per call."""
    from drjit.llvm import Float

    return dr.nn.HashGridEncoding(Float, 3, n_levels=n_levels, n_features_per_level=n_features,
                                  hashmap_size=hashmap_size, base_resolution=base_resolution,
                                  per_level_scale=per_level_scale)


def _drjit_lookup(grid: HashGrid, x01: torch.Tensor) -> torch.Tensor:  # [N, 3] -> [N, L*F]
    """The encoding through ``dr.nn.HashGridEncoding`` (no gradient): the parameters and the
    points are handed over without a copy (DLPack), all levels run in one kernel, and reading
    the outputs back waits for it, so `params` may change again as soon as this returns."""
    from drjit.llvm import Float

    enc = _encoding(grid.n_levels, grid.n_features, grid.hashmap_size, grid.base_resolution,
                    grid.per_level_scale)
    x = x01.detach().float()
    with _ENCODING_LOCK:  # the shared encoding's data is set per call
        enc.data = Float(grid.params.detach().contiguous())
        try:
            out = enc([Float(x[:, i].contiguous()) for i in range(3)])
            dr.eval(out)  # one kernel for every output, not one per feature
            res = torch.stack([o.torch() for o in out], dim=1)
        finally:
            enc.data = Float()  # do not hold on to the torch parameter memory
    return res


class _CompiledLookup(torch.autograd.Function):
    """The lookup with gradient on the compiled CPU path: the forward is Dr.Jit's kernel
    (`_drjit_lookup`, the same floats as `hashgrid_reference`; nothing is saved but the
    points), the backward recomputes the corners and scatters (`hashgrid_cpu.scatter`) into a
    zeroed table, or, when the grid uses its gradient sink, into the sink (no gradient reaches
    ``params.grad``). Points take no gradient here (`HashGrid.forward` sends those to the torch
    path)."""

    @staticmethod
    def forward(ctx, params, x01, grid):  # [P], [N, 3], HashGrid -> [N, L F]
        ctx.grid, ctx.x = grid, grid._points(x01)
        return _drjit_lookup(grid, x01)

    @staticmethod
    def backward(ctx, grad):  # [N, L F]
        grid = ctx.grid
        if not ctx.needs_input_grad[0]:
            return None, None, None
        g = grad.float().contiguous().numpy()
        lay = grid._layout()
        if grid.sink_on:
            hashgrid_cpu.scatter(g, ctx.x, lay, grid.grad_sink.numpy())
            grid.sink_dirty = True
            return None, None, None
        table = torch.zeros(lay.rows, grid.n_features)
        hashgrid_cpu.scatter(g, ctx.x, lay, table.numpy())
        return table.view(-1), None, None


class _Lookup(torch.autograd.Function):
    """out[m] = sum_c w[c, m] table[rows[c, m]]: one gather for all levels and corners.

    For F = 2 the table is viewed as complex64, one 8-byte element per row: on one CPU thread
    the gather and the backward scatter (`index_add_`) take less than half their time on
    [R, 2] rows (`index_put_(accumulate=True)`, autograd's backward of `table[rows]`, is
    slower still).
    """

    @staticmethod
    def forward(ctx, params, rows, w, n_features):  # [P], [8, M] int64, [8, M] -> [M, F]
        C, M = rows.shape
        if n_features == 2:
            vals = torch.view_as_real(torch.view_as_complex(params.view(-1, 2))
                                      .index_select(0, rows.view(-1)))
        else:
            vals = params.view(-1, n_features).index_select(0, rows.view(-1))
        vals = vals.view(C, M, n_features)
        out = vals[0] * w[0, :, None]
        for c in range(1, C):
            out.addcmul_(vals[c], w[c, :, None])
        ctx.save_for_backward(rows, w, vals if w.requires_grad else None)
        ctx.n_features, ctx.n_params = n_features, params.numel()
        return out

    @staticmethod
    def backward(ctx, grad):  # [M, F]
        rows, w, vals = ctx.saved_tensors
        Fn = ctx.n_features
        grad_params = grad_w = None
        if ctx.needs_input_grad[0]:
            upd = w.unsqueeze(2) * grad.unsqueeze(0)  # [8, M, F]
            if Fn == 2:
                upd = torch.view_as_complex(upd)
                grad_params = torch.zeros(ctx.n_params // 2, dtype=upd.dtype, device=grad.device)
                # int32 rows (< 2^31: Dr.Jit's cap) scatter 1.6x faster on the CPU, the same sum
                # in the same order
                idx = rows.view(-1)
                grad_params.index_add_(0, idx.int() if idx.device.type == "cpu" else idx,
                                       upd.view(-1))
                grad_params = torch.view_as_real(grad_params).view(-1)
            else:
                grad_params = grad.new_zeros(ctx.n_params // Fn, Fn)
                grad_params.index_add_(0, rows.view(-1), upd.view(-1, Fn))
                grad_params = grad_params.view(-1)
        if ctx.needs_input_grad[2]:
            grad_w = (vals * grad.unsqueeze(0)).sum(-1)  # [8, M]
        return grad_params, None, grad_w, None


def hashgrid_reference(params: torch.Tensor,  # [P] flat, Dr.Jit layout
                       x01: torch.Tensor,  # [N, 3] in [0, 1]
                       levels: list[Level], n_features: int) -> torch.Tensor:  # [N, L*F]
    """Slow, obviously-correct loop over levels and corners, in Dr.Jit's evaluation order.

    Every fp32 fma of Dr.Jit (position, feature accumulation) is computed in float64 and rounded
    once to float32, so the result matches Dr.Jit bit for bit.
    """
    out = []
    table = params.view(-1, n_features)
    for lv in levels:
        pos = (x01.double() * _f32(lv.scale) + 0.5).float()  # [N, 3]
        p0 = torch.floor(pos)
        w1 = pos - p0
        w0 = 1.0 - w1
        acc = torch.zeros(x01.shape[0], n_features, dtype=torch.float32)
        for c in range(8):
            bits = [(c >> j) & 1 for j in range(3)]
            k = [p0[:, j].long() + bits[j] for j in range(3)]
            wc = [w1[:, j] if bits[j] else w0[:, j] for j in range(3)]
            weight = (wc[0] * wc[1]) * wc[2]
            if lv.dense:
                idx = k[0] + k[1] * lv.res + k[2] * lv.res * lv.res
            else:
                idx = k[0] * PRIMES[0]
                for j in (1, 2):
                    idx = idx ^ ((k[j] * PRIMES[j]) & 0xFFFFFFFF)
            row = lv.offset + (idx & 0xFFFFFFFF) % lv.size
            acc = (table[row].double() * weight.double()[:, None] + acc.double()).float()
        out.append(acc)
    return torch.cat(out, dim=1)
