"""The compiled CPU backward of the hash-grid lookup (numba), split over the cores by a plain
thread pool.

The layout is `shells.fields.hashgrid`'s (Dr.Jit's); the torch `HashGrid` lookup with its
``index_add_`` is the reference (tests/test_hashgrid_cpu.py). The forward of the compiled path
is Dr.Jit's own kernel (`shells.fields.hashgrid._CompiledLookup`): a numba lookup written
beside it (the reference's floats, blocks of points on two threads) was slower in a training
step than Dr.Jit's on one thread.

- `scatter`: the backward. The rows and weights are recomputed from the points (arithmetic is
  cheaper than storing and re-reading [8, L, N] rows and weights), and the gradient of every
  corner is added into a persistent gradient table. The *levels* are split between the threads
  (each table row belongs to one level), so every row is written by one thread, in point order:
  no atomics, and the same sums on any number of threads. A level whose gradient is zero for a
  point is skipped (the coarse-to-fine mask). The gradient table may persist between steps
  (`shells.train.optim.GridAdam`).

Why a thread pool and not numba's ``parallel=True``: the kernels release the GIL and run on
`threads` Python threads, which sleep between calls; an OpenMP or TBB pool of numba's would
spin beside torch's own OpenMP threads on a 2-core machine. Measured and left out
(docs/notes/2026-12-08-stage1-speed.md): grouping the scatter's updates by table slab (a
stable counting sort, so that the writes stay in cache) was slower than the direct order.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np

P1, P2 = 2654435761, 805459861  # the spatial-hash primes of y and z (x: 1)
MASK32 = 0xFFFFFFFF


def _njit(fn):
    return numba.njit(nogil=True, cache=True, fastmath=False, error_model="numpy")(fn)


@_njit
def _row(kx, ky, kz, res, size, dense, pow2):  # table row of a grid vertex within its level
    if dense:
        # keys are <= res, so the index is < res^3 (1 + 1/res + 1/res^2) < 2 size: one
        # subtraction is the remainder (an integer division costs tens of cycles)
        i = kx + ky * res + kz * res * res
        return i - size if i >= size else i
    h = (kx & MASK32) ^ ((ky * P1) & MASK32) ^ ((kz * P2) & MASK32)
    if pow2:
        return h & (size - 1)
    return h % size


BLOCK = 256  # points whose corner rows are computed before their gradients are added


@_njit
def _corners(x, n0, nb, sc, res, size, offset, dense, pow2, rows, wts):
    """rows[i, c], wts[i, c] of the 8 corners of points n0 + i, i < nb, on one level: the
    position as one float64 fma rounded to float32, weights (wx wy) wz in float32."""
    one = np.float32(1.0)
    for i in range(nb):
        n = n0 + i
        px = np.float32(np.float64(x[n, 0]) * sc + 0.5)
        py = np.float32(np.float64(x[n, 1]) * sc + 0.5)
        pz = np.float32(np.float64(x[n, 2]) * sc + 0.5)
        fx, fy, fz = np.floor(px), np.floor(py), np.floor(pz)
        wx1, wy1, wz1 = px - fx, py - fy, pz - fz
        wx0, wy0, wz0 = one - wx1, one - wy1, one - wz1
        kx, ky, kz = np.int64(fx), np.int64(fy), np.int64(fz)
        for c in range(8):
            bx, by, bz = c & 1, (c >> 1) & 1, (c >> 2) & 1
            wts[i, c] = ((wx1 if bx else wx0) * (wy1 if by else wy0)) * (wz1 if bz else wz0)
            rows[i, c] = offset + _row(kx + bx, ky + by, kz + bz, res, size, dense, pow2)


@_njit
def _scatter(grad_out, x, scale, res, size, offset, dense, pow2, gtable, levels):
    """gtable[row] += w * grad_out[n, level] for every corner of every point, for the levels in
    `levels` (this thread's share), in point order, corners in order. A point whose gradient
    on a level is zero (a level switched off) is skipped there."""
    F = gtable.shape[1]
    N = x.shape[0]
    rows = np.empty((BLOCK, 8), dtype=np.int64)
    wts = np.empty((BLOCK, 8), dtype=np.float32)
    for i in range(levels.shape[0]):
        lv = levels[i]
        for n0 in range(0, N, BLOCK):
            nb = min(BLOCK, N - n0)
            _corners(x, n0, nb, scale[lv], res[lv], size[lv], offset[lv], dense[lv], pow2,
                     rows, wts)
            for j in range(nb):
                n = n0 + j
                nz = False
                for f in range(F):
                    if grad_out[n, lv * F + f] != 0.0:
                        nz = True
                if not nz:
                    continue
                for c in range(8):
                    row = rows[j, c]
                    for f in range(F):
                        gtable[row, f] += wts[j, c] * grad_out[n, lv * F + f]


# ---------------------------------------------------------------------------------------------
# Threads
# ---------------------------------------------------------------------------------------------

_POOL: ThreadPoolExecutor | None = None
_POOL_PID = 0
_POOL_LOCK = threading.Lock()


def threads() -> int:
    """Threads the kernels use: torch's intra-op thread count (``OMP_NUM_THREADS``), at most
    the cores this process may run on."""
    import torch

    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        cores = os.cpu_count() or 1
    return max(1, min(torch.get_num_threads(), cores))


def _run(jobs) -> list:
    """Run the callables in ``jobs``: the first on this thread, the rest on the pool."""
    global _POOL, _POOL_PID
    if len(jobs) == 1:
        return [jobs[0]()]
    with _POOL_LOCK:
        # a forked child inherits the pool object but not its threads: a new pool there
        if _POOL is None or _POOL._max_workers < len(jobs) - 1 or _POOL_PID != os.getpid():
            _POOL = ThreadPoolExecutor(max_workers=len(jobs) - 1,
                                       thread_name_prefix="hashgrid")
            _POOL_PID = os.getpid()
        pool = _POOL
    futures = [pool.submit(j) for j in jobs[1:]]
    first = jobs[0]()
    return [first] + [f.result() for f in futures]


class Layout:
    """The per-level constants of a grid, as the kernels take them."""

    def __init__(self, levels, n_features: int) -> None:
        f32 = np.float32
        self.scale = np.array([float(f32(lv.scale)) for lv in levels], dtype=np.float64)
        self.res = np.array([lv.res for lv in levels], dtype=np.int64)
        self.size = np.array([lv.size for lv in levels], dtype=np.int64)
        self.offset = np.array([lv.offset for lv in levels], dtype=np.int64)
        self.dense = np.array([lv.dense for lv in levels], dtype=np.bool_)
        self.pow2 = all((lv.size & (lv.size - 1)) == 0 for lv in levels if not lv.dense)
        self.n_features = n_features
        self.rows = int(self.offset[-1] + self.size[-1])
        # the levels' shares of the scatter, dealt out in turn (the fine levels cost most)
        self._deal: dict[int, list[np.ndarray]] = {}

    def args(self):
        return self.scale, self.res, self.size, self.offset, self.dense, self.pow2

    def deal(self, k: int) -> list[np.ndarray]:
        if k not in self._deal:
            L = len(self.scale)
            self._deal[k] = [a for a in (np.arange(i, L, k, dtype=np.int64)
                                         for i in range(min(k, L))) if len(a)]
        return self._deal[k]


def scatter(grad_out: np.ndarray,  # [N, L F] float32
            x: np.ndarray,  # [N, 3] float32 in [0, 1]
            layout: Layout, gtable: np.ndarray,  # [R, F] float32, added to
            n_threads: int | None = None) -> None:
    k = threads() if n_threads is None else n_threads
    if x.shape[0] < 2048:
        k = 1
    a = layout.args()
    _run([lambda lv=lv: _scatter(grad_out, x, *a, gtable, lv)
          for lv in layout.deal(k)])
