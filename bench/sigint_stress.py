"""Ctrl-C at random moments of `shells-render`, many times: every run must end in one of the
two promised states, with no traceback and no hidden file (staging folder, lock) left.

    python -m bench.sigint_stress RUN [--runs 40] [--seed 5] [--from 0.55] [--to 0.95]

RUN is a run with shells. Each trial first writes an older 8x8 render into the output folder,
then starts a 24x24 render of the training views over it and sends SIGINT after a delay drawn
uniformly from [from, to] x the time of an uninterrupted render. Accepted outcomes:
status 130 with the output folder's files exactly as before (PNG bytes, file names), or
status 0 with the frames of an uninterrupted render. Prints each failure and a summary of the
exit statuses. The test suite's `test_sigint_during_render_then_rerun` is three such trials.
"""

from __future__ import annotations

import argparse
import hashlib
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _state(folder: Path) -> dict[str, object]:
    """The PNG bytes and the file names of an output folder (metrics.json holds timings)."""
    files = sorted(folder.glob("*"))
    return {"names": [p.name for p in files],
            **{p.name: hashlib.md5(p.read_bytes()).hexdigest() for p in files
               if p.suffix == ".png"}}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run")
    p.add_argument("--runs", type=int, default=40)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--from", dest="lo", type=float, default=0.55)
    p.add_argument("--to", dest="hi", type=float, default=0.95)
    args = p.parse_args(argv)
    exe = str(Path(sys.executable).with_name("shells-render"))
    root = Path(tempfile.mkdtemp(prefix="sigint-stress-"))
    new = [exe, args.run, "--split", "train", "--width", "24", "--height", "24", "--out"]
    old = [exe, args.run, "--split", "train", "--width", "8", "--height", "8", "--out"]
    t0 = time.monotonic()
    subprocess.run(new + [str(root / "ref")], check=True, capture_output=True)
    seconds = time.monotonic() - t0
    ref = _state(root / "ref")
    rng, statuses, bad = random.Random(args.seed), {}, 0
    out = root / "out"
    for i in range(args.runs):
        shutil.rmtree(out, ignore_errors=True)
        subprocess.run(old + [str(out)], check=True, capture_output=True)
        before = _state(out)
        proc = subprocess.Popen(new + [str(out)], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        delay = rng.uniform(args.lo, args.hi) * seconds
        try:
            proc.wait(timeout=delay)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGINT)
        _, err = proc.communicate()
        now = _state(out)
        hidden = [x.name for x in root.iterdir() if x.name.startswith(".")]
        ok = ("Traceback" not in err and not hidden
              and ((proc.returncode == 130 and now == before)
                   or (proc.returncode == 0 and now == ref)))
        statuses[proc.returncode] = statuses.get(proc.returncode, 0) + 1
        if not ok:
            bad += 1
            print(f"trial {i}: SIGINT after {delay:.2f} s -> status {proc.returncode}, hidden "
                  f"{hidden}, unchanged {now == before}, complete {now == ref}\n{err[-2000:]}")
    shutil.rmtree(root, ignore_errors=True)
    print(f"{args.runs} trials (render {seconds:.2f} s): exit statuses {statuses}, "
          f"{bad} failed")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
