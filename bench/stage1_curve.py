"""Stage-1 training curves: test PSNR against training wall time, of the toy preset's box
sampler against the preset ``--preset auto`` picks (and variants of it), in one invocation.

    OMP_NUM_THREADS=1 python -m bench.stage1_curve --data ../shared/data/lego --downscale 8 \
        --out OUT [--iters-toy 3000] [--iters-auto N] [--only toy|auto] [--config-auto FILE]
        [--variant FILE:LABEL ...] [--segments 6] [--interleave]
    python -m bench.stage1_curve --out OUT --replot A/curve.json[:LABEL] B/curve.json[:LABEL]

Trains the same data in turn (never two trainings at once: on 2 cores they slow each other
~10x):

* ``toy``: the toy preset (``sampler`` "box": every ray sampled over its whole chord through
  the scene box, 1024 rays per step);
* ``auto``: what ``--preset auto`` picks for the data (`shells.presets.preset_config`: on the
  CPU the "object" preset, with empty-space skipping).

Each run is cut into ``--segments`` equal pieces (``train(..., stop_at=k)`` then ``--resume``,
which retraces the uninterrupted run exactly); after each piece the checkpoint is scored on
the test views (full-ray, the run's own sampler), off the clock. The wall time of a point is
the sum of the pieces' training seconds. Writes OUT/curve.json (every point, rays/s and
samples/s of each run), OUT/curve.png (matplotlib) and prints a Markdown table. ``--iters-toy``
and ``--iters-auto`` set the runs' lengths (default: the presets' own); ``--only`` trains one;
``--config-auto FILE`` applies a config file on top of the auto run's preset; ``--variant
FILE:LABEL`` (repeatable) adds a run LABEL, the auto preset with FILE on top, trained after
the others in the same invocation, so that its rays/s compare with the toy run's on the same
machine state.
``--interleave`` trains the runs piece by piece in turn, the order reversed every round (toy,
auto, auto, toy, ...), one never beside another: a drift of the machine's speed during the
invocation then falls on all runs alike instead of on whichever trained last.
``--replot`` trains nothing and draws the runs of earlier invocations in one plot and table
(a run named again gets " (LABEL)" appended).
An unbounded capture (fox; `shells.presets.scene_similarity`) gets the contracted field and
sampler of ``shells-train --scene auto`` in every run (`unbounded_settings`, applied after the
config files, as the command does).
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import torch

from shells.data.datasets import load_dataset
from shells.presets import resolve_config
from shells.run import RunDir, field_from_checkpoint, read_checkpoint
from shells.train.stage1 import evaluate, stage1_grid, train


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


def run_all(gens: dict, interleave: bool) -> dict:
    """Drive the runs' generators (`curve`) to their results: one run after the other, or
    with ``interleave`` piece by piece in turn, the order reversed every round (toy auto auto
    toy toy auto ...), so that a drift of the machine's speed falls on every run alike."""
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
        ax.plot(xs[1:], ys[1:], marker="o",
                label=f"{name}: {r['rays_per_s']:.0f} rays/s, "
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


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", default=None)
    p.add_argument("--downscale", type=int, default=8)
    p.add_argument("--out", required=True)
    p.add_argument("--segments", type=int, default=6, help="test-PSNR points per curve")
    p.add_argument("--iters-toy", type=int, default=None)
    p.add_argument("--iters-auto", type=int, default=None)
    p.add_argument("--only", choices=["toy", "auto"], default=None,
                   help="train one of them (runs given by --variant always train)")
    p.add_argument("--config-auto", default=None, metavar="JSON",
                   help="a config file applied on top of the auto run's preset (a probe)")
    p.add_argument("--variant", action="append", default=[], metavar="JSON:LABEL",
                   help="one more run: the auto preset with this config file on top")
    p.add_argument("--interleave", action="store_true",
                   help="train the runs piece by piece in turn instead of one after the other "
                        "(a drift of the machine's speed then falls on all runs alike)")
    p.add_argument("--replot", nargs="+", default=None, metavar="CURVE_JSON[:LABEL]")
    args = p.parse_args(argv)
    variants = []
    for spec in args.variant:
        path, _, label = spec.rpartition(":")
        if not path or not label or label in ("toy", "auto"):
            p.error(f"--variant {spec}: give FILE:LABEL with a label other than toy and auto")
        variants.append((label, path))
    device = torch.device("cpu")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.replot:
        return replot(args.replot, out)
    if args.data is None:
        p.error("--data is required unless --replot is given")
    test = load_dataset(args.data, "test", downscale=args.downscale)

    def preset(name: str, config: str | None, iters: int | None):
        """The config `shells-train --preset NAME --config FILE` trains (unbounded scenes
        included), with ``iters`` steps when given."""
        cfg, resolved = resolve_config(args.data, device, name, downscale=args.downscale,
                                       config=config)
        if iters is not None:
            cfg.update({"train": {"iters": iters}}, "bench.stage1_curve")
        return cfg, resolved

    toy, _ = preset("toy", None, args.iters_toy)
    auto, preset_name = preset("auto", args.config_auto, args.iters_auto)
    # (name, config, the --only value that trains it: None for the variants, which always do)
    runs = [("toy", toy, "toy"), ("auto", auto, "auto")]
    runs += [(label, preset("auto", path, args.iters_auto)[0], None) for label, path in variants]
    gens = {name: curve(name.replace(" ", "_"), cfg, args, test, device)
            for name, cfg, only in runs if args.only is None or only in (None, args.only)}
    res = run_all(gens, args.interleave)
    meta = {"data": args.data, "downscale": args.downscale, "auto_preset": preset_name,
            "unbounded": auto.field.unbounded, "config_auto": args.config_auto,
            "variants": args.variant, "interleave": args.interleave,
            "torch_threads": torch.get_num_threads(), "date": time.strftime("%Y-%m-%d")}
    (out / "curve.json").write_text(json.dumps({"meta": meta, "runs": res}, indent=2) + "\n")
    plot(res, out / "curve.png", f"{Path(args.data).name} 1/{args.downscale}, stage 1, "
                                 f"{torch.get_num_threads()} torch threads")
    table(res)
    if "toy" in res:
        for name in res:
            if name != "toy":
                print(f"{name} / toy: rays/s "
                      f"{res[name]['rays_per_s'] / res['toy']['rays_per_s']:.2f}x, samples/s "
                      f"{res[name]['samples_per_s'] / res['toy']['samples_per_s']:.2f}x")
    print(f"curve: {out / 'curve.png'}, {out / 'curve.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
