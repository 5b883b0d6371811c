"""glibc malloc settings for the commands' large, short-lived buffers.

A training step allocates and frees hundreds of MiB of activations, most of them in blocks of
tens of MiB. With glibc's defaults a block above the mmap threshold (at most 32 MiB, however
it adapts) is mapped on malloc and unmapped on free, and a freed heap top above 128 KiB goes
back to the kernel, so every step faults the same memory in again page by page: stage 1 of lego
at 800x800 spent 30 % of its CPU time in the kernel. `SETTINGS` keep all of it in the process:
no block is mmapped (the heap serves every size), and the heap is trimmed only when more than
``M_TRIM_THRESHOLD`` lies free at its top. The steps then reuse their memory, with identical
results; ``python -m bench.step_speed allocator`` measures the ratio. The cost is freed memory
held until it is reused or the process ends.

The settings are the ones glibc's environment variables ``MALLOC_MMAP_MAX_``,
``MALLOC_TRIM_THRESHOLD_`` and ``MALLOC_TOP_PAD_`` give, applied with mallopt(3) at the start of
the training commands (shells-train, shells-finetune): the others hold few short-lived large
buffers, and a heap that cannot unmap could raise their peaks (the 512^3 extraction's). They
are left alone where the user set any glibc malloc variable (or ``GLIBC_TUNABLES``), where
``SHELLS_SYSTEM_MALLOC=1`` asks for glibc's defaults, and off glibc.
"""

from __future__ import annotations

import ctypes
import os
import platform

M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_MAX = -1, -2, -4  # <malloc.h>
MiB = 1 << 20
SETTINGS = {  # mallopt parameter -> value
    M_MMAP_MAX: 0,  # no mmapped blocks: large buffers come from the heap and are reused
    M_TRIM_THRESHOLD: 1024 * MiB,  # return the heap top to the kernel only above 1 GiB free
    M_TOP_PAD: 256 * MiB,  # grow the heap in 256 MiB steps
}
OPT_OUT = "SHELLS_SYSTEM_MALLOC"


def user_variable(name: str) -> bool:
    """A variable by which the user sets glibc's malloc: MALLOC_*, GLIBC_TUNABLES."""
    return name.startswith("MALLOC_") or name == "GLIBC_TUNABLES"


def tune(environ: dict[str, str] | None = None) -> bool:
    """Apply `SETTINGS` with mallopt; True when all were applied, False when left alone."""
    env = os.environ if environ is None else environ
    if env.get(OPT_OUT, "") not in ("", "0") or any(user_variable(k) for k in env):
        return False
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return all(mallopt(param, value) == 1 for param, value in SETTINGS.items())
