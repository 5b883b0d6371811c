"""Stage-2 step time against the number of ray shards a step is drawn in (`finetune.shards`).

    python bench/stage2_shards.py RUN [--shards 1,4,1,8] [--steps 4] [--config X.json]
                                      [--calling-thread]

RUN has a stage-1 checkpoint and shells (`shells-extract`). For each shard count in turn, one
warm-up step and then ``--steps`` timed steps of `shells.finetune.stage2_step` over the run's
`finetune.batch_rays` rays, forward and backward with the gradients of the shards averaged as
`shells.loop` does (its accumulation is private to the loop, so it is written out here; no
optimiser step, so the field stays the same). ``--config``: a JSON file
with `render` / `finetune` sections overriding the run's (the band sampling the step uses).
``--calling-thread``: the steps run in `drjit_on_calling_thread` (Dr.Jit's kernels, the shell
casts among them, on the calling thread alone), as stage 1 runs its steps; stage 2 does not
(no gain measured on fox; BENCHMARKS.md).
Prints s/step, rays/s and samples/s per shard count as JSON; counts listed twice show the drift
of the machine within the run. Run it alone: the step uses all the cores.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from shells.config import override_config  # noqa: E402
from shells.datasets import load_dataset  # noqa: E402
from shells.device import mitsuba_variant  # noqa: E402
from shells.fields.hashgrid import drjit_on_calling_thread  # noqa: E402
from shells.finetune import stage2_step  # noqa: E402
from shells.run import (RunDir, field_from_checkpoint, load_shells, read_checkpoint,  # noqa: E402
                        read_run)

from report import emit_json  # noqa: E402


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run")
    p.add_argument("--shards", default="1,4,1,8", help="comma-separated shard counts")
    p.add_argument("--steps", type=int, default=4, help="timed steps per shard count")
    p.add_argument("--config", default=None, help="JSON with render / finetune overrides")
    p.add_argument("--calling-thread", action="store_true",
                   help="Dr.Jit's kernels on the calling thread alone")
    a = p.parse_args()
    run = RunDir(a.run)
    meta = read_run(run)
    field, cfg = field_from_checkpoint(read_checkpoint(run, "stage1"), a.run)
    override_config(cfg, a.config, ("finetune", "render"), "stage2_shards")
    field.train()
    dev = torch.device("cpu")
    scene = load_shells(run, mitsuba_variant(cfg.render.variant, dev), "fine")
    data = load_dataset(meta["data"], "train", downscale=int(meta["downscale"]),
                        background=cfg.data.background)
    pixels = data.images.reshape(-1, 3)
    background = torch.tensor(cfg.data.background, dtype=torch.float32)
    rows = []
    with drjit_on_calling_thread() if a.calling_thread else contextlib.nullcontext():
        for shards in (int(x) for x in a.shards.split(",")):
            rows.append(time_shards(field, scene, data, pixels, cfg, background, shards,
                                    a.steps))
    emit_json({"run": a.run, "batch_rays": cfg.finetune.batch_rays,
               "render": {k: getattr(cfg.render, k) for k in ("dp_max", "w_s", "delta_s",
                                                               "n_max")},
               "threads": torch.get_num_threads(), "calling_thread": a.calling_thread,
               "steps": a.steps, "rows": rows})
    return 0


def time_shards(field, scene, data, pixels, cfg, background, shards: int,
                steps: int) -> dict[str, float]:
    """One warm-up step, then ``steps`` timed ones of ``shards`` shards."""
    fc = dataclasses.replace(cfg.finetune, shards=shards)
    gen = torch.Generator().manual_seed(0)

    def step() -> float:
        n = 0.0
        for _ in range(shards):
            loss, logs = stage2_step(field, scene, data, pixels, fc, cfg.render, background,
                                     gen)
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
    print(f"shards {shards}: {dt:.2f} s/step", file=sys.stderr, flush=True)
    return {"shards": shards, "s_per_step": dt, "rays_per_s": fc.batch_rays / dt,
            "samples_per_s": samples / steps / dt}


if __name__ == "__main__":
    raise SystemExit(main())
