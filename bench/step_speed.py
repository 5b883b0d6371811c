"""Training step time of one trained field: stage 1 under several sampler settings or grid
sizes, stage 2 against the number of ray shards a step is drawn in (no optimiser step).

    OMP_NUM_THREADS=1 python -m bench.step_speed stage1 RUN [--data DATA --downscale 8]
                                                 [--sizes [--profile]]
    python -m bench.step_speed stage2 RUN [--shards 1,4,1,8] [--steps 4] [--config X.json]
                                          [--calling-thread] [--anchor]
    python -m bench.step_speed allocator RUN [--steps 300] [--rounds 2]

RUN's training split (run.json's data set and downscale unless ``--data`` / ``--downscale``
say otherwise) is composited on the run's background. Each subcommand's --help says more.
Run it alone: the steps use all the cores.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import dataclasses
import json
import sys
import time
from types import SimpleNamespace

import torch

from bench.report import emit_json, run_command, subcommands
from shells.data.datasets import load_dataset
from shells.errors import InputError
from shells.run import RunDir, field_from_checkpoint, read_checkpoint, read_run

SIZES = [("fresh, the run's sizes", {}),
         ("fresh, 8 levels, 2^18, finest 256 (lego 1/8)",
          dict(n_levels=8, log2_hashmap_size=18, max_resolution=256)),
         ("fresh, 16 levels, 2^19, finest 512",
          dict(n_levels=16, log2_hashmap_size=19, max_resolution=512)),
         ("fresh, 9 levels, 2^17, finest 512",
          dict(n_levels=9, log2_hashmap_size=17, max_resolution=512))]

SETTINGS = [("box, 32 + 16, 4096 regulariser points", "box", 32, 16, 4096, 0.0),
            ("occupancy, 32 + 16, 2048", "occupancy", 32, 16, 2048, 0.0),
            ("occupancy, 32 + 16, 2048, culled below 1e-4", "occupancy", 32, 16, 2048, 1e-4),
            ("occupancy, 32 + 16, 2048, culled below 1e-3", "occupancy", 32, 16, 2048, 1e-3),
            ("occupancy, 16 + 16, 2048", "occupancy", 16, 16, 2048, 0.0),
            ("occupancy, 16 + 16, 2048, culled below 1e-4", "occupancy", 16, 16, 2048, 1e-4),
            ("occupancy, 24 + 8, 2048", "occupancy", 24, 8, 2048, 0.0),
            ("occupancy, 16 + 16, 1024", "occupancy", 16, 16, 1024, 0.0)]


def open_run(path: str, data: str | None = None, downscale: int | None = None
             ) -> SimpleNamespace:
    """RUN's stage-1 checkpoint, its field (train mode) and config, and the training split's
    pixels on the run's background."""
    run = RunDir(path)
    meta = read_run(run)
    ckpt = read_checkpoint(run, "stage1")
    field, cfg = field_from_checkpoint(ckpt, path)
    field.train()
    train = load_dataset(data or meta["data"], "train", background=cfg.data.background,
                         downscale=downscale or int(meta["downscale"]))
    return SimpleNamespace(run=run, ckpt=ckpt, field=field, cfg=cfg, data=train,
                           pixels=train.images.reshape(-1, 3),
                           bg=torch.tensor(cfg.data.background, dtype=torch.float32))


def stage1(a: argparse.Namespace) -> int:
    """Stage-1 step time: RUN is a stage-1 run of the "occupancy" sampler (its checkpoint
    holds the occupancy grid). Each sampler setting of SETTINGS runs 12 steps (forward +
    backward of `shells.train.stage1.stage1_step`) and times the last 10; prints ms/step, rays/s
    and rays per step. ``--sizes``: instead, the run's sampler settings on fresh fields of other
    hash-grid sizes (SIZES; the same rays and grid; 10 steps, medians of the last 8), forward +
    backward and the Adam step timed apart; ``--profile`` adds a torch.profiler table of 3
    steps of the trained field."""
    from shells.train.stage1 import stage1_grid, stage1_step

    r = open_run(a.run, a.data, a.downscale)
    field, cfg, data, pixels, bg = r.field, r.cfg, r.data, r.pixels, r.bg
    grid = stage1_grid(r.ckpt, field, cfg)
    if grid is None:
        raise InputError(f"{a.run}: not a run of the 'occupancy' sampler")
    if a.sizes:
        return grid_sizes(field, cfg, data, pixels, bg, grid, a.profile)
    print("| configuration | ms/step | rays/s | rays/step | samples with gradient |\n"
          "|---|---|---|---|---|")
    for name, sampler, ns, ni, reg, cull in SETTINGS:
        tc = dataclasses.replace(cfg.train, sampler=sampler, n_samples=ns, n_importance=ni,
                                 reg_points=reg, cull_weight=cull)
        times, rays, grads, samples = [], 0.0, 0.0, 0.0
        for k in range(12):
            t = time.perf_counter()
            loss, logs = stage1_step(field, data, pixels, tc, bg,
                                     torch.Generator().manual_seed(k),
                                     grid if sampler == "occupancy" else None)
            loss.backward()
            field.zero_grad()
            if k >= 2:
                times.append(time.perf_counter() - t)
                rays += logs["rays"]
                grads += logs["grad_samples"]
                samples += logs["samples"]
        dt = sum(times)
        print(f"| {name} | {dt / len(times) * 1000:.0f} | {rays / dt:.0f} | "
              f"{rays / len(times):.0f} | {grads / max(samples, 1):.1%} |", flush=True)
    return 0


def grid_sizes(trained, cfg, data, pixels, bg, grid, profile: bool) -> int:
    """``stage1 --sizes``: forward + backward and Adam ms of fresh fields of SIZES."""
    from shells.train.optim import make_optimizer
    from shells.train.stage1 import build_field, stage1_step

    print("| field | parameters | forward + backward ms | Adam ms |\n|---|---|---|---|")
    for name, change in [("the trained field", None)] + SIZES:
        if change is None:
            field = trained
        else:
            c = dataclasses.replace(cfg, field=dataclasses.replace(cfg.field, **change))
            field = build_field(c, data.aabb, torch.device("cpu"))
        field.train()
        opt = make_optimizer(field, cfg.train.lr, cfg.train.lr_mlp)
        fb, ad = [], []
        for k in range(10):
            t0 = time.perf_counter()
            loss, _ = stage1_step(field, data, pixels, cfg.train, bg,
                                  torch.Generator().manual_seed(k), grid)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            t1 = time.perf_counter()
            opt.step()
            if k >= 2:
                fb.append(t1 - t0)
                ad.append(time.perf_counter() - t1)
        n = sum(q.numel() for q in field.parameters())
        print(f"| {name} | {n / 1e6:.2f} M | {1000 * sorted(fb)[len(fb) // 2]:.0f} | "
              f"{1000 * sorted(ad)[len(ad) // 2]:.0f} |", flush=True)
    if profile:
        from torch.profiler import ProfilerActivity
        from torch.profiler import profile as torch_profile

        with torch_profile(activities=[ProfilerActivity.CPU]) as prof:
            for k in range(3):
                loss, _ = stage1_step(trained, data, pixels, cfg.train, bg,
                                      torch.Generator().manual_seed(k), grid)
                loss.backward()
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))
    return 0


PHASES = ("stage 1: draw pixels", "volume: coarse samples", "volume: fine placement",
          "volume: fine samples", "volume: weights, colours of light samples",
          "volume: samples with gradient", "stage 1: regularisers", "stage 1: backward",
          "stage 1: Adam")


def paths(a: argparse.Namespace) -> int:
    """Stage-1 steps on the compiled hash-grid path with its gradient sink against the torch
    path, interleaved: four copies of RUN's stage-1 field, optimiser state and occupancy grid
    continue its training ("torch": the torch lookup with gradient and its ``index_add_`` into
    a zeroed table that autograd hands to the fused Adam, as main trained before the compiled
    path; "compiled": `shells.fields.hashgrid_cpu` and `shells.train.optim.GridAdam`; each with
    the run's step generators and those of the next seed, whose difference is the run-to-run
    spread of the losses; Dr.Jit's lookups without gradient on the calling thread in all, as
    `shells-train` runs them). Each takes ``--warmup`` untimed steps, then ``--steps`` steps
    in pieces of ``--chunk``, the order of the copies reversed each piece. The learning rate
    follows a schedule of ``--schedule`` steps (default: the run's). Then ``--profile`` steps
    of each under torch.profiler give the split of a step into phases (the stage's
    ``record_function`` ranges; "other" is the rest). Prints ms/step, samples/s, rays/s, the
    mean losses (all timed steps, the last 100) and the mean |loss difference| per step
    against "torch", as JSON."""
    import statistics

    from torch.profiler import ProfilerActivity, profile, record_function

    from shells.data.datasets import has_transparency
    from shells.fields.hashgrid import drjit_on_calling_thread
    from shells.train.loop import lr_factor, step_generator
    from shells.train.optim import make_optimizer, use_hashgrid
    from shells.train.stage1 import before_step, stage1_grid, stage1_step

    r = open_run(a.run)
    cfg, tc = r.cfg, r.cfg.train
    base = int(r.ckpt["step"])
    schedule = a.schedule or tc.iters
    alpha = (r.data.alpha.reshape(-1) if tc.random_background
             and has_transparency(r.data.alpha) and r.field.similarity is None else None)
    variants = [("torch", 0), ("torch, seed + 1", 1), ("compiled", 0), ("compiled, seed + 1", 1)]
    state = {}
    for name, dseed in variants:
        field = copy.deepcopy(r.field)
        compiled = name.startswith("compiled")
        use_hashgrid(field, "compiled" if compiled else "torch")
        opt = make_optimizer(field, tc.lr, tc.lr_mlp, sink=compiled)
        kernels = [{"fused": g["fused"], "foreach": g["foreach"]} for g in opt.param_groups]
        opt.load_state_dict(r.ckpt["optimizer"])
        for g, k in zip(opt.param_groups, kernels):
            g.update(k)
        state[name] = SimpleNamespace(field=field, opt=opt, grid=stage1_grid(r.ckpt, field, cfg),
                                      seed=tc.seed + dseed, done=0, losses=[], seconds=0.0,
                                      samples=0.0, rays=0.0)

    def step(v: SimpleNamespace) -> None:
        k = base + v.done
        before_step(v.field, v.grid, tc, k)
        for g in v.opt.param_groups:
            g["lr"] = g["base_lr"] * lr_factor(k, schedule, tc.warmup_iters, tc.lr_final_factor)
        v.opt.zero_grad(set_to_none=True)
        loss, logs = stage1_step(v.field, r.data, r.pixels, tc, r.bg,
                                 step_generator(v.seed, k, torch.device("cpu")), v.grid, k,
                                 alpha)
        with record_function("stage 1: backward"):
            loss.backward()
        with record_function("stage 1: Adam"):
            v.opt.step()
        v.done += 1
        v.losses.append(logs["loss"])
        v.samples += logs["samples"]
        v.rays += logs["rays"]

    order = [n for n, _ in variants]
    with drjit_on_calling_thread():
        for name in order:  # compiles the kernels, fills the caches: not timed
            for _ in range(a.warmup):
                step(state[name])
            state[name].samples = state[name].rays = 0.0
        for piece in range(-(-a.steps // a.chunk)):
            for name in (order if piece % 2 == 0 else order[::-1]):
                v = state[name]
                n = min(a.chunk, a.warmup + a.steps - v.done)
                t = time.perf_counter()
                for _ in range(n):
                    step(v)
                v.seconds += time.perf_counter() - t
            print(f"piece {piece + 1}: " + ", ".join(
                f"{n} {state[n].seconds / max(state[n].done - a.warmup, 1) * 1000:.0f} ms/step"
                for n in order), file=sys.stderr, flush=True)
        split = {}
        for name in order:
            v = state[name]
            with profile(activities=[ProfilerActivity.CPU]) as prof:
                t = time.perf_counter()
                for _ in range(a.profile):
                    step(v)
                total = (time.perf_counter() - t) / a.profile * 1000
            ev = {e.key: e.cpu_time_total / 1000 / a.profile for e in prof.key_averages()
                  if e.key in PHASES}
            ph = {p: round(ev.get(p, 0.0), 1) for p in PHASES}
            ph["other"] = round(total - sum(ph.values()), 1)
            ph["step (profiled)"] = round(total, 1)
            split[name] = ph
    ref = state["torch"]
    last = min(100, a.steps)
    out = {}
    for name in order:
        v = state[name]
        timed = slice(a.warmup, a.warmup + a.steps)
        out[name] = {"ms_per_step": 1000 * v.seconds / a.steps,
                     "samples_per_s": v.samples / v.seconds, "rays_per_s": v.rays / v.seconds,
                     "loss_mean": statistics.fmean(v.losses[timed]),
                     "loss_mean_last": statistics.fmean(v.losses[timed][-last:]),
                     "mean_abs_loss_diff_vs_torch": statistics.fmean(
                         abs(x - y) for x, y in zip(v.losses[timed], ref.losses[timed])),
                     "phases_ms": split[name]}
    both = [(out[f"compiled{s}"]["samples_per_s"], out[f"torch{s}"]["samples_per_s"])
            for s in ("", ", seed + 1")]
    out["ratio samples/s compiled / torch"] = sum(c for c, _ in both) / sum(t for _, t in both)
    emit_json({"run": a.run, "from_step": base, "steps": a.steps, "schedule": schedule,
               "threads": torch.get_num_threads(), "variants": out,
               "losses": {n: state[n].losses for n in order}})
    return 0


def grid(a: argparse.Namespace) -> int:
    """The hash grid's own kernels: RUN's stage-1 grid (its trained table), ``--points`` points
    on a thin spherical shell around the box centre (radius 0.3 +- 0.02 of the unit cube, the
    kind of set a step's samples near a surface make): the lookup with gradient and its
    backward (torch `_Lookup` with ``index_add_`` and the compiled path, each into a zeroed
    table-sized gradient through autograd; the compiled path into the grid's gradient sink,
    cleared after), the lookup without gradient (torch, Dr.Jit on the calling thread, Dr.Jit
    on its pool), and torch's fused Adam on the table. Medians of ``--repeat`` calls, ms, as
    JSON; the variants of a row alternate."""
    import statistics

    import drjit as dr

    from shells.fields.hashgrid import drjit_on_calling_thread

    gen = torch.Generator().manual_seed(0)
    d = torch.randn(a.points, 3, generator=gen)
    r = 0.3 + 0.02 * torch.randn(a.points, 1, generator=gen)
    x = (0.5 + r * d / d.norm(dim=1, keepdim=True)).clamp(0, 1).float()
    rows = []
    field, _ = field_from_checkpoint(read_checkpoint(RunDir(a.run), "stage1"), a.run)
    for name, grid in [(f"{a.run}: {field.grid.extra_repr()}", field.grid)]:
        gout = torch.randn(a.points, grid.out_dim, generator=gen)

        def fwd_bwd(path: str) -> None:
            grid.training_path = path
            grid.params.grad = None
            (grid(x) * gout).sum().backward()

        def nograd(path: str) -> None:
            grid.inference = path  # "auto": Dr.Jit
            with torch.no_grad():
                grid(x)

        def drjit_calling() -> None:
            with drjit_on_calling_thread():
                nograd("auto")

        opt = torch.optim.Adam([grid.params], lr=1e-2, betas=(0.9, 0.99), eps=1e-15,
                               fused=True)

        grid.use_gradient_sink(True)  # allocated once, as an optimiser does
        sink = {"grad_sink": grid.__dict__.pop("grad_sink")}

        def sink_fwd_bwd() -> None:
            grid.__dict__.update(sink)
            grid.params.grad = None
            (grid(x) * gout).sum().backward()
            grid.grad_sink.zero_()
            grid.__dict__.pop("grad_sink")

        def adam() -> None:
            grid.params.grad = torch.zeros_like(grid.params)
            opt.step()
            grid.params.grad = None

        cases = {"fwd+bwd torch (autograd, zeroed table)": lambda: fwd_bwd("torch"),
                 "fwd+bwd compiled (autograd, zeroed table)": lambda: fwd_bwd("auto"),
                 "fwd+bwd compiled into the sink, cleared": sink_fwd_bwd,
                 "no-grad torch": lambda: nograd("torch"),
                 "no-grad Dr.Jit, calling thread": drjit_calling,
                 "no-grad Dr.Jit, pool": lambda: nograd("auto"),
                 "Adam fused, the table": adam}
        times: dict[str, list[float]] = {k: [] for k in cases}
        for k in range(a.repeat + 1):
            for case, fn in cases.items():
                t = time.perf_counter()
                fn()
                if k:
                    times[case].append(time.perf_counter() - t)
        grid.__dict__.update(sink)
        (grid(x) * gout).sum().backward()
        row = {"grid": name, "params_M": grid.params.numel() / 1e6,
               "touched_rows": int(grid.grad_sink.ne(0).any(1).sum()),
               "rows": len(grid.grad_sink),
               **{c: 1000 * statistics.median(t) for c, t in times.items()}}
        grid.use_gradient_sink(False)
        print(json.dumps(row), file=sys.stderr, flush=True)
        rows.append(row)
    emit_json({"points": a.points, "threads": torch.get_num_threads(),
               "drjit_threads": dr.thread_count(), "rows": rows})
    return 0


def stage2(a: argparse.Namespace) -> int:
    """Stage-2 step time against the number of ray shards (`finetune.shards`): RUN has a
    stage-1 checkpoint and shells (`shells-extract`). For each shard count in turn, one warm-up
    step and then ``--steps`` timed steps of `shells.train.stage2.stage2_step` over the run's
    `finetune.batch_rays` rays, forward and backward with the shards' gradients averaged as
    `shells.train.loop` does (no optimiser step, so the field stays the same). ``--config``: a
    JSON file with `render` / `finetune` sections overriding the run's. ``--calling-thread``:
    the steps run in `drjit_on_calling_thread` (Dr.Jit's kernels, the shell casts among them,
    on the calling thread alone), as stage 1 runs its steps. ``--anchor``: each shard count
    is timed without and then with stage 2's anchor (`finetune.anchor_weight`, the frozen
    stage-1 field: the field itself, so the term is 0 but costs what it costs). Prints s/step,
    rays/s and samples/s per shard count as JSON; counts listed twice show the drift of the
    machine."""
    from shells.config import override_config
    from shells.device import mitsuba_variant
    from shells.fields.hashgrid import drjit_on_calling_thread
    from shells.run import load_shells
    from shells.train.stage2 import frozen

    r = open_run(a.run)
    cfg = override_config(r.cfg, a.config, ("finetune", "render"), "bench.step_speed stage2")
    scene = load_shells(r.run, mitsuba_variant(cfg.render.variant, torch.device("cpu")), "fine")
    rows = []
    stage1s = [None] + ([frozen(copy.deepcopy(r.field))] if a.anchor else [])
    with drjit_on_calling_thread() if a.calling_thread else contextlib.nullcontext():
        for shards in (int(x) for x in a.shards.split(",")):
            for stage1 in stage1s:
                rows.append(time_shards(r.field, scene, r.data, r.pixels, cfg, r.bg, shards,
                                        a.steps, stage1))
    emit_json({"run": a.run, "batch_rays": cfg.finetune.batch_rays,
               "render": {k: getattr(cfg.render, k) for k in ("dp_max", "w_s", "delta_s",
                                                               "n_max")},
               "threads": torch.get_num_threads(), "calling_thread": a.calling_thread,
               "steps": a.steps, "rows": rows})
    return 0


def time_shards(field, scene, data, pixels, cfg, background, shards: int,
                steps: int, stage1=None) -> dict[str, float]:
    """One warm-up step, then ``steps`` timed ones of ``shards`` shards (with the anchor
    against ``stage1`` when given)."""
    from shells.train.stage2 import stage2_step

    fc = dataclasses.replace(cfg.finetune, shards=shards)
    gen = torch.Generator().manual_seed(0)

    def step() -> float:
        n = 0.0
        for _ in range(shards):
            loss, logs = stage2_step(field, scene, data, pixels, fc, cfg.render, background,
                                     gen, stage1)
            (loss / shards).backward()
            n += logs["spp"] * (fc.batch_rays // shards) / fc.pixel_samples
        field.zero_grad(set_to_none=True)
        return n

    step()
    samples = 0.0
    t0 = time.perf_counter()
    for _ in range(steps):
        samples += step()
    dt = (time.perf_counter() - t0) / steps
    anchor = stage1 is not None and fc.anchor_weight > 0
    print(f"shards {shards}{', anchor' if anchor else ''}: {dt:.3f} s/step", file=sys.stderr,
          flush=True)
    return {"shards": shards, "anchor": anchor, "s_per_step": dt,
            "rays_per_s": fc.batch_rays / dt, "samples_per_s": samples / steps / dt}


def allocator(a: argparse.Namespace) -> int:
    """glibc malloc settings against glibc's defaults: fresh `shells-train` runs of --steps
    steps on RUN's data set (run.json; the default preset, scored on one test view),
    alternately with the training commands' settings (`shells.allocator`) and with
    SHELLS_SYSTEM_MALLOC=1, --rounds times each, who goes first alternating; prints each run's
    training seconds (train_summary.json: the steps alone), minor page faults and last loss
    (the same seed and data: the losses must agree), and the ratio of the medians."""
    import json
    import os
    import resource
    import statistics
    import subprocess
    import tempfile
    from pathlib import Path

    from shells import allocator as malloc_settings

    info = read_run(RunDir(a.run))
    env = {k: v for k, v in os.environ.items() if not malloc_settings.user_variable(k)
           and k != malloc_settings.OPT_OUT}
    rows: dict[str, list[dict[str, float]]] = {"tuned": [], "glibc": []}
    with tempfile.TemporaryDirectory(dir=a.tmp) as tmp:
        cfg = Path(tmp) / "one-view.json"
        cfg.write_text(json.dumps({"train": {"eval_max_views": 1}}))
        for r in range(a.rounds):
            order = ("tuned", "glibc") if r % 2 == 0 else ("glibc", "tuned")
            for name in order:
                out = Path(tmp) / f"{name}-{r}"
                e = dict(env, **({malloc_settings.OPT_OUT: "1"} if name == "glibc" else {}))
                cmd = [sys.executable, "-c", "import sys; from shells.cli import train_main; "
                       "sys.exit(train_main())", "--data", info["data"], "--downscale",
                       str(info["downscale"]), "--out", str(out), "--iters", str(a.steps),
                       "--config", str(cfg)]
                before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_minflt
                subprocess.run(cmd, env=e, check=True, capture_output=True)
                faults = resource.getrusage(resource.RUSAGE_CHILDREN).ru_minflt - before
                summary = json.loads((out / "train_summary.json").read_text())
                rows[name].append({"seconds": summary["seconds"], "minor_faults": faults,
                                   "loss": summary["last"]["loss"]})
                print(f"{name} round {r}: {summary['seconds']:.1f} s, {faults} minor faults",
                      file=sys.stderr, flush=True)
    med = {k: statistics.median(x["seconds"] for x in v) for k, v in rows.items()}
    emit_json({"data": info["data"], "downscale": info["downscale"], "steps": a.steps, "runs": rows,
               "speedup": med["glibc"] / med["tuned"],
               "settings": {str(k): v for k, v in malloc_settings.SETTINGS.items()}})
    return 0


def main(argv: list[str] | None = None) -> int:
    p, sub = subcommands("python -m bench.step_speed", __doc__.split("\n\n")[0],
                         [stage1, paths, grid, stage2, allocator])
    sp = sub["stage1"]
    sp.add_argument("--data", default=None, help="default: RUN's data set (run.json)")
    sp.add_argument("--downscale", type=int, default=None, help="default: RUN's")
    sp.add_argument("--sizes", action="store_true", help="fresh fields of other grid sizes")
    sp.add_argument("--profile", action="store_true", help="with --sizes: a profiler table")
    sp = sub["paths"]
    sp.add_argument("--steps", type=int, default=300, help="steps of each variant")
    sp.add_argument("--chunk", type=int, default=25, help="steps per piece")
    sp.add_argument("--warmup", type=int, default=3, help="untimed steps of each first")
    sp.add_argument("--schedule", type=int, default=None,
                    help="length of the learning-rate schedule (default: the run's iters)")
    sp.add_argument("--profile", type=int, default=3, help="profiled steps of each")
    sp = sub["grid"]
    sp.add_argument("--points", type=int, default=30000, help="lookup points")
    sp.add_argument("--repeat", type=int, default=10, help="timed calls per variant")
    sp = sub["stage2"]
    sp.add_argument("--shards", default="1,4,1,8", help="comma-separated shard counts")
    sp.add_argument("--steps", type=int, default=4, help="timed steps per shard count")
    sp.add_argument("--config", default=None, help="JSON with render / finetune overrides")
    sp.add_argument("--anchor", action="store_true",
                    help="time each shard count without and with stage 2's anchor")
    sp.add_argument("--calling-thread", action="store_true",
                    help="Dr.Jit's kernels on the calling thread alone")
    sp = sub["allocator"]
    sp.add_argument("--steps", type=int, default=300, help="stage-1 steps per timed run")
    sp.add_argument("--rounds", type=int, default=2, help="timed runs of each setting")
    sp.add_argument("--tmp", default=None, help="folder for the run copies (default: $TMPDIR)")
    return run_command(p, argv)


if __name__ == "__main__":
    raise SystemExit(main())
