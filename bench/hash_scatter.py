"""The hash grid's backward scatter on its own: one step's worth of random row updates.

    python bench/hash_scatter.py [--rows 2450000] [--updates 3538944]

Defaults: the rows of lego 1/4's `object` grid (9 levels, 2^19) and 49152 samples x 9 levels
x 8 corners. Times (median of 5) torch's `index_add_` on complex64 rows (what
`shells.fields.hashgrid._Lookup` does), on int32 rows, on a [R, 2] float table, two
`bincount`s, `scatter_add_`, sorted rows, and Dr.Jit's LLVM `scatter_reduce` in each mode,
with 1 and 2 torch threads.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch


def median_ms(f, n: int = 5) -> float:
    f()
    ts = []
    for _ in range(n):
        t = time.perf_counter()
        f()
        ts.append(time.perf_counter() - t)
    return 1000 * sorted(ts)[n // 2]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--rows", type=int, default=2_450_000)
    p.add_argument("--updates", type=int, default=49152 * 9 * 8)
    a = p.parse_args()
    R, M = a.rows, a.updates
    torch.manual_seed(0)
    rows = torch.randint(0, R, (M,))
    rows32 = rows.int()
    upd = torch.randn(M, 2)
    cupd = torch.view_as_complex(upd)

    def c64(idx=rows):
        torch.zeros(R, dtype=torch.complex64).index_add_(0, idx, cupd)

    variants = {
        "index_add_ complex64 (the field's)": c64,
        "index_add_ complex64, int32 rows": lambda: c64(rows32),
        "index_add_ [R, 2] float32": lambda: torch.zeros(R, 2).index_add_(0, rows, upd),
        "bincount x 2": lambda: (torch.bincount(rows, upd[:, 0], minlength=R),
                                 torch.bincount(rows, upd[:, 1], minlength=R)),
        "scatter_add_ flat": lambda: torch.zeros(2 * R).scatter_add_(
            0, torch.stack([2 * rows, 2 * rows + 1], 1).view(-1), upd.view(-1)),
        "index_add_ complex64, rows sorted first": lambda: c64(rows.sort()[0]),
    }
    print("| scatter of %d updates into %d rows | 1 thread ms | 2 threads ms |" % (M, R))
    print("|---|---|---|")
    for name, f in variants.items():
        ms = []
        for th in (1, 2):
            torch.set_num_threads(th)
            ms.append(median_ms(f))
        print(f"| {name} | {ms[0]:.0f} | {ms[1]:.0f} |", flush=True)

    import drjit as dr
    from drjit.llvm import Float, UInt32

    idx = UInt32(rows.numpy().astype(np.uint32))
    v0, v1 = Float(upd[:, 0].numpy()), Float(upd[:, 1].numpy())
    dr.eval(idx, v0, v1)
    for mode in (dr.ReduceMode.Auto, dr.ReduceMode.Direct, dr.ReduceMode.Local,
                 dr.ReduceMode.Expand):
        def run(mode=mode):
            t = dr.zeros(Float, 2 * R)
            dr.scatter_reduce(dr.ReduceOp.Add, t, v0, 2 * idx, mode=mode)
            dr.scatter_reduce(dr.ReduceOp.Add, t, v1, 2 * idx + 1, mode=mode)
            dr.eval(t)
            dr.sync_thread()
        print(f"| Dr.Jit LLVM scatter_reduce, {mode.name} | {median_ms(run):.0f} (its own "
              "threads) | |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
