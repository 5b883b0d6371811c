"""Stage-1 training curves: test PSNR against training wall time, old against new, one run.

    python bench/stage1_curve.py --data ../shared/data/lego --downscale 8 --out OUT \
        --iters-old 3000 [--old-commit 9e6bc1f]

Trains the same data twice, one after the other or interleaved (never two trainings at once: on
2 cores they slow each other ~10x):

* ``old``: the toy preset as it was before issue 13 (``sampler`` "box": every ray sampled over
  its whole chord through the scene box, 1024 rays per step);
* ``new``: what ``--preset auto`` picks for the data (`shells.training.preset_config`: on the
  CPU the "object" preset, with empty-space skipping).

Each run is cut into ``--segments`` equal pieces (``train(..., stop_at=k)`` then ``--resume``,
which retraces the uninterrupted run exactly); after each piece the checkpoint is scored on
the test views (full-ray, the run's own sampler), off the clock. The wall time of a point is
the sum of the pieces' training seconds. Writes OUT/curve.json (every point, rays/s and
samples/s of each run), OUT/curve.png (matplotlib) and prints a Markdown table. ``--iters-old``
and ``--iters-new`` set the runs' lengths (default: the presets' own); ``--only`` trains one;
``--config-new FILE`` applies a config file on top of the new run's preset; ``--variant
FILE:LABEL`` (repeatable) adds a run LABEL, the new preset with FILE on top, trained after the
others in the same invocation, so that its rays/s compare with the old run's on the same
machine state.
``--old-commit REV`` trains the old run with the code of REV instead (its tree from `git
archive`, run by `bench/stage1_curve_old.py` in a child process): the stage 1 of the day an
issue was filed, code and config, where the default old run is the old config on today's
code (every per-sample speed-up since included). The toy preset on today's code is then the
run "old config", trained as well (unless ``--no-old-config``).
``--interleave`` trains the runs piece by piece in turn, the order reversed every round (old,
new, new, old, old, new, ...), one never beside another: a drift of the machine's speed
during the invocation then falls on all runs alike instead of on whichever trained last.
``--replot A/curve.json[:LABEL] B/curve.json[:LABEL] ...`` trains nothing and draws the runs of
earlier invocations in one plot and table (a run named again gets " (LABEL)" appended).
An unbounded capture (fox; `shells.training.scene_similarity`) gets the contracted field and
sampler of ``shells-train --scene auto`` in every run (`unbounded_settings`, applied after the
config files, as the command does).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from shells.config import read_config_file, toy_config  # noqa: E402
from shells.datasets import load_dataset  # noqa: E402
from shells.run import RunDir, field_from_checkpoint, read_checkpoint  # noqa: E402
from shells.training import (evaluate, preset_config, scene_similarity, stage1_grid,  # noqa: E402
                             train, unbounded_settings)


def score(run: Path, test, device: torch.device) -> float:
    ckpt = read_checkpoint(RunDir(run))
    field, cfg = field_from_checkpoint(ckpt, str(run), device)
    grid = stage1_grid(ckpt, field, cfg)
    return evaluate(field, test, cfg.train, 0, device, grid)["psnr"]


def curve(name: str, cfg, args, test, device: torch.device):
    """The run ``name`` piece by piece: a generator that trains and scores one piece per
    step and returns (StopIteration.value) the run in `curve.json`'s form."""
    run = Path(args.out) / name
    shutil.rmtree(run, ignore_errors=True)
    iters = cfg.train.iters
    cuts = sorted({max(1, round(iters * (k + 1) / args.segments)) for k in range(args.segments)})
    points, seconds, rays, samples = [], 0.0, 0.0, 0.0
    for i, k in enumerate(cuts):
        s = train(args.data, run, cfg, device, downscale=args.downscale, resume=i > 0,
                  progress=False, stop_at=k, evaluate_test=False)
        seconds += s["seconds"]
        steps = k - (cuts[i - 1] if i else 0)
        rays += s["rays_per_s"] * s["seconds"]
        samples += s.get("samples_per_s", 0.0) * s["seconds"]
        t = time.perf_counter()
        p = score(run, test, device)
        points.append({"step": k, "seconds": seconds, "psnr": p})
        print(f"{name}: step {k} ({steps} steps in {s['seconds']:.0f} s), {seconds:.0f} s "
              f"trained, test PSNR {p:.2f} dB (scored in {time.perf_counter() - t:.0f} s)",
              flush=True)
        yield
    return {"iters": iters, "points": points, "seconds": seconds, "rays_per_s": rays / seconds,
            "samples_per_s": samples / seconds, "psnr": points[-1]["psnr"],
            "config": cfg.to_dict()}


def old_code_curve(rev: str, args):
    """The old run trained by the code of commit ``rev`` (`bench/stage1_curve_old.py`), one
    child process per piece; a generator like `curve`."""
    repo = Path(__file__).resolve().parents[1]
    tree = Path(args.out) / "old_code"
    shutil.rmtree(tree, ignore_errors=True)
    tree.mkdir(parents=True)
    sha = subprocess.run(["git", "-C", str(repo), "rev-parse", "--verify", f"{rev}^{{commit}}"],
                         capture_output=True, text=True)
    if sha.returncode:
        raise SystemExit(f"--old-commit {rev}: not a commit of {repo}")
    archive = subprocess.Popen(["git", "-C", str(repo), "archive", sha.stdout.strip()],
                               stdout=subprocess.PIPE)
    subprocess.run(["tar", "-x", "-C", str(tree)], stdin=archive.stdout, check=True)
    if archive.wait():
        raise SystemExit(f"--old-commit {rev}: git archive failed")
    cmd = [sys.executable, str(repo / "bench" / "stage1_curve_old.py"), "--data", args.data,
           "--downscale", str(args.downscale), "--out", str(Path(args.out) / "old"),
           "--segments", str(args.segments)]
    if args.iters_old is not None:
        cmd += ["--iters", str(args.iters_old)]
    env = {**os.environ, "PYTHONPATH": str(tree.resolve())}
    points, seconds, rays, result = [], 0.0, 0.0, None
    for k in range(args.segments):
        proc = subprocess.Popen(cmd + ["--segment", str(k)], env=env, stdout=subprocess.PIPE,
                                text=True)
        result = None
        for line in proc.stdout:
            if line.startswith("RESULT "):
                result = json.loads(line[len("RESULT "):])
            else:
                print(line, end="", flush=True)
        if proc.wait() or result is None:
            raise SystemExit(f"--old-commit {rev}: piece {k} of the old run failed "
                             f"(exit {proc.returncode})")
        seconds += result["seconds"]
        rays += result["rays_per_s"] * result["seconds"]
        points.append({**result["points"][0], "seconds": seconds})
        yield
    per_ray = result["samples_per_s"] / result["rays_per_s"]  # the old sampler's fixed count
    return {**result, "points": points, "seconds": seconds, "rays_per_s": rays / seconds,
            "samples_per_s": rays / seconds * per_ray, "psnr": points[-1]["psnr"],
            "code": f"commit {sha.stdout.strip()[:12]}"}


def run_all(gens: dict, interleave: bool) -> dict:
    """Drive the runs' generators (`curve`, `old_code_curve`) to their results: one run
    after the other, or with ``interleave`` piece by piece in turn, the order reversed every
    round (old new new old old new ...), so that a drift of the machine's speed falls on
    every run alike."""
    res, live = {}, list(gens)
    while live:
        for name in (list(live) if interleave else live[:1]):
            try:
                next(gens[name])
            except StopIteration as stop:
                res[name] = stop.value
                live.remove(name)
        if interleave:
            live.reverse()
    return {name: res[name] for name in gens}


def plot(res: dict, path: Path, title: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.6), dpi=150)
    for name, r in res.items():
        xs = [0.0] + [p["seconds"] / 60 for p in r["points"]]
        ys = [None] + [p["psnr"] for p in r["points"]]
        code = f" ({r['code']})" if "code" in r else ""  # an --old-commit run
        ax.plot(xs[1:], ys[1:], marker="o",
                label=f"{name}{code}: {r['rays_per_s']:.0f} rays/s, "
                      f"{r['samples_per_s'] / 1e3:.0f}k samples/s")
    ax.set_xlabel("stage-1 training time (min)")
    ax.set_ylabel("test PSNR (dB)")
    ax.set_title(title, fontsize=8)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def table(res: dict) -> None:
    print("\n| run | steps | train s | rays/s | samples/s | test PSNR |")
    print("|---|---|---|---|---|---|")
    for name, r in res.items():
        print(f"| {name} | {r['iters']} | {r['seconds']:.0f} | {r['rays_per_s']:.0f} | "
              f"{r['samples_per_s']:.0f} | {r['psnr']:.2f} |")


def replot(files: list[str], out: Path) -> int:
    res, metas = {}, []
    for spec in files:
        path, _, label = spec.partition(":")
        data = json.loads(Path(path).read_text())
        metas.append(data["meta"])
        for name, r in data["runs"].items():
            res[name if name not in res else f"{name} ({label or path})"] = r
    (out / "curve.json").write_text(json.dumps({"meta": metas, "runs": res}, indent=2) + "\n")
    m = metas[0]
    plot(res, out / "curve.png", f"{Path(m['data']).name} 1/{m['downscale']}, stage 1, "
                                 f"{m['torch_threads']} torch thread(s)")
    table(res)
    print(f"curve: {out / 'curve.png'}, {out / 'curve.json'}")
    return 0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", default=None)
    p.add_argument("--downscale", type=int, default=8)
    p.add_argument("--out", required=True)
    p.add_argument("--segments", type=int, default=6, help="test-PSNR points per curve")
    p.add_argument("--iters-old", type=int, default=None)
    p.add_argument("--iters-new", type=int, default=None)
    p.add_argument("--only", choices=["old", "new"], default=None,
                   help="train one of them (runs given by --variant always train)")
    p.add_argument("--config-new", default=None, metavar="JSON",
                   help="a config file applied on top of the new run's preset (a probe)")
    p.add_argument("--variant", action="append", default=[], metavar="JSON:LABEL",
                   help="one more run: the new preset with this config file on top")
    p.add_argument("--old-commit", default=None, metavar="REV",
                   help="train the old run with the code of this commit (e.g. 9e6bc1f, before "
                        "issue 13); the old config on today's code becomes \"old config\"")
    p.add_argument("--no-old-config", action="store_true",
                   help="with --old-commit: do not also train the old config on today's code")
    p.add_argument("--interleave", action="store_true",
                   help="train the runs piece by piece in turn instead of one after the other "
                        "(a drift of the machine's speed then falls on all runs alike)")
    p.add_argument("--replot", nargs="+", default=None, metavar="CURVE_JSON[:LABEL]")
    args = p.parse_args()
    variants = []
    for spec in args.variant:
        path, _, label = spec.rpartition(":")
        if not path or not label or label in ("old", "new", "old config"):
            p.error(f"--variant {spec}: give FILE:LABEL with a label other than old, new and "
                    f"old config")
        variants.append((label, read_config_file(path)))
    device = torch.device("cpu")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.replot:
        return replot(args.replot, out)
    if args.data is None:
        p.error("--data is required unless --replot is given")
    test = load_dataset(args.data, "test", downscale=args.downscale)
    sim = scene_similarity(args.data)  # an unbounded capture (fox): as shells-train does

    def preset(extra: dict | None, label: str):
        cfg, name = preset_config("auto", args.data, args.downscale, device, sim)
        if extra:
            cfg.update(extra, label)
        if sim is not None:
            unbounded_settings(cfg, sim)
        return cfg, name

    old = toy_config()
    if sim is not None:
        unbounded_settings(old, sim)
    new, preset_name = preset(read_config_file(args.config_new) if args.config_new else None,
                              str(args.config_new))
    for cfg, iters in ((old, args.iters_old), (new, args.iters_new)):
        if iters is not None:
            cfg.update({"train": {"iters": iters}}, "bench")
    # (name, config, the --only value that trains it: None for the variants, which always do)
    runs = [("old config" if args.old_commit else "old", old, "old"), ("new", new, "new")]
    if args.old_commit and args.no_old_config:
        runs = runs[1:]
    for label, extra in variants:
        cfg, _ = preset(extra, label)
        runs.append((label, cfg, None))
    gens = {}
    if args.old_commit and args.only in (None, "old"):
        gens["old"] = old_code_curve(args.old_commit, args)
    for name, cfg, only in runs:
        if args.only is None or only in (None, args.only):
            gens[name] = curve(name.replace(" ", "_"), cfg, args, test, device)
    res = run_all(gens, args.interleave)
    meta = {"data": args.data, "downscale": args.downscale, "new_preset": preset_name,
            "unbounded": sim is not None,
            "old_commit": args.old_commit,
            "config_new": args.config_new, "variants": args.variant,
            "interleave": args.interleave,
            "torch_threads": torch.get_num_threads(), "date": time.strftime("%Y-%m-%d")}
    (out / "curve.json").write_text(json.dumps({"meta": meta, "runs": res}, indent=2) + "\n")
    plot(res, out / "curve.png", f"{Path(args.data).name} 1/{args.downscale}, stage 1, "
                                 f"{torch.get_num_threads()} torch threads")
    table(res)
    if "old" in res:
        for name in res:
            if name != "old":
                print(f"{name} / old: rays/s "
                      f"{res[name]['rays_per_s'] / res['old']['rays_per_s']:.2f}x, samples/s "
                      f"{res[name]['samples_per_s'] / res['old']['samples_per_s']:.2f}x")
    print(f"curve: {out / 'curve.png'}, {out / 'curve.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
