"""Peak memory (and wall time) of the two large jobs: an 8K band render and a 512^3 extraction.

    python -m bench.memory [--work DIR] [--width 7680 --height 4320] [--resolution 512]
                           [--skip render|extract]

Makes a toy run in WORK (default /tmp/shells-memory): the `sphere` toy scene at 32x32 with one
test view, a short stage 1 (toy preset, 30 steps), shells at the toy resolution. Then, each
in its own process under ``/usr/bin/time -v`` (or, without it, getrusage of the child), it runs

    shells-render RUN --width W --height H --out RUN/render-8k      (band mode, the test view)
    shells-extract RUN --resolution N

and prints their peak resident set size (the maximum RSS of the process) and wall time. The
work is split from the memory budgets `render.memory_mb` and `shell.memory_mb`
(shells/config.py).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

BIN = Path(sys.executable).parent


def peak(cmd: list[str]) -> dict:
    """Run cmd; its peak RSS (GiB) and wall seconds."""
    t0 = time.perf_counter()
    if Path("/usr/bin/time").exists():
        done = subprocess.run(["/usr/bin/time", "-v", *cmd], capture_output=True, text=True)
        m = re.search(r"Maximum resident set size \(kbytes\): (\d+)", done.stderr)
        kb = int(m.group(1)) if m else -1
    else:
        done = subprocess.run(cmd, capture_output=True, text=True)
        kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    if done.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed:\n{done.stderr[-2000:]}")
    return {"command": " ".join(Path(cmd[0]).name if i == 0 else c for i, c in enumerate(cmd)),
            "peak_rss_gib": kb / 2 ** 20, "seconds": time.perf_counter() - t0,
            "stdout": done.stdout.strip().splitlines()[-1:]}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--work", default="/tmp/shells-memory")
    p.add_argument("--width", type=int, default=7680)
    p.add_argument("--height", type=int, default=4320)
    p.add_argument("--resolution", type=int, default=512)
    p.add_argument("--skip", choices=["render", "extract"], default=None)
    args = p.parse_args(argv)
    work = Path(args.work)
    data, run = work / "data", work / "run"
    if not (run / "shells" / "outer.ply").is_file():
        shutil.rmtree(work, ignore_errors=True)

        def sh(*c) -> None:
            subprocess.run([str(BIN / c[0]), *map(str, c[1:])], check=True, capture_output=True)

        sh("shells-scene", "sphere", "--out", data, "--res", 32, "--views", 8, "--test-views", 1,
           "--spp", 16)
        sh("shells-train", "--data", data, "--out", run, "--preset", "toy", "--iters", 30,
           "--device", "cpu")
        sh("shells-extract", run)
    rows = []
    if args.skip != "render":
        rows.append(peak([str(BIN / "shells-render"), str(run), "--width", str(args.width),
                          "--height", str(args.height), "--out", str(run / "render-8k")]))
    if args.skip != "extract":
        rows.append(peak([str(BIN / "shells-extract"), str(run), "--resolution",
                          str(args.resolution)]))
    print(f"{'command':<70} {'peak RSS':>9} {'wall':>7}")
    for r in rows:
        print(f"{r['command'].replace(str(work), 'WORK'):<70} {r['peak_rss_gib']:7.2f} GiB "
              f"{r['seconds']:6.0f} s")
    (work / "memory.json").write_text(json.dumps(rows, indent=2) + "\n")
    print(f"threads: OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}; "
          f"details: {work / 'memory.json'}")


if __name__ == "__main__":
    main()
