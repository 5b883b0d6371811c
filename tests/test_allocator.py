"""glibc malloc settings of the commands (shells.allocator)."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

from shells import allocator

GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"

# 20 rounds of: malloc 4 blocks of 48 MiB (above glibc's largest mmap threshold, 32 MiB), touch
# every page, free; prints the minor page faults they took
CYCLES = """
import ctypes, resource, sys
from shells import allocator
print(allocator.tune(), file=sys.stderr)
libc = ctypes.CDLL(None)
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = (ctypes.c_void_p,)
n = 48 << 20
start = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    blocks = [libc.malloc(n) for _ in range(4)]
    for b in blocks:
        ctypes.memset(b, 1, n)
    for b in blocks:
        libc.free(b)
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - start)
"""


def faults(env_extra: dict[str, str]) -> int:
    env = {k: v for k, v in os.environ.items() if not allocator.user_variable(k)
           and k != allocator.OPT_OUT}
    env.update(env_extra)
    out = subprocess.run([sys.executable, "-c", CYCLES], env=env, capture_output=True,
                         text=True, check=True)
    return int(out.stdout.strip())


@pytest.mark.skipif(not GLIBC, reason="mallopt settings exist on glibc only")
def test_freed_buffers_are_not_faulted_in_again():
    # 20 rounds of 192 MiB are 20 x 49152 pages: with glibc's defaults every block is mapped
    # on malloc and unmapped on free, so every round faults it in again; tuned, only the first
    # round does.
    default = faults({allocator.OPT_OUT: "1"})
    tuned = faults({})
    pages = (4 * 48 << 20) // os.sysconf("SC_PAGE_SIZE")
    assert default > 10 * pages
    assert tuned < 3 * pages


def test_user_settings_and_the_opt_out_are_left_alone():
    assert allocator.tune({"MALLOC_TOP_PAD_": "0"}) is False
    assert allocator.tune({"MALLOC_MMAP_MAX_": "65536"}) is False
    assert allocator.tune({"GLIBC_TUNABLES": "glibc.malloc.trim_threshold=0"}) is False
    assert allocator.tune({allocator.OPT_OUT: "1"}) is False
    # applied (in a process of its own: the settings would stay with the test process)
    out = subprocess.run([sys.executable, "-c", "from shells import allocator; "
                          "print(allocator.tune({}))"], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == str(GLIBC)
