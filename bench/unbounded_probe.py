"""Probe stage 1 of an unbounded toy: f at a few field-space points after a few steps (issue 14).

    python bench/unbounded_probe.py DATA OUT [--scene auto|bounded|unbounded]
                                   [--config JSON] [--steps 25 50 100 150] [--regularisers-only]

Trains stage 1 on DATA (a `shells-scene` toy, the auto preset) into OUT, stopping after each of
``--steps`` and resuming (the same steps as one run), and prints f at the field-space points
(0, 0, 0), (0.3, 0, 0), (0.6, 0, 0), (1.2, 0, 0): for the toy ball of radius 0.5 about -0.5,
-0.2, 0.1, 0.7 while the ball is kept. ``--config`` is a JSON object merged into the config
(e.g. '{"train": {"normal_weight": 0}}').

``--regularisers-only``: no data and no colour loss; Adam on the Eikonal, normal and
smoothness terms alone (`shells.training.regularisers`, uniform points), from the initial
sphere of the toy preset's field, bounded (``--scene bounded``) or unbounded (centre 0, radius
1); step k draws its points with seed k, and f is printed after steps k in ``--steps``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys

import torch

POINTS = [[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.6, 0.0, 0.0], [1.2, 0.0, 0.0]]


def _f(field) -> list[float]:
    with torch.no_grad():
        return [round(v, 3) for v in field.geometry_field(torch.tensor(POINTS))["sdf"].tolist()]


def regularisers_only(scene: str, steps: list[int], extra: dict) -> None:
    from shells.config import toy_config
    from shells.fields.network import ShellField
    from shells.loop import make_optimizer
    from shells.training import reg_points, regularisers

    cfg = toy_config()
    if extra:
        cfg.update(extra, "--config")
    fc = cfg.field
    if scene != "bounded":
        fc = dataclasses.replace(fc, unbounded=True, centre=(0.0, 0.0, 0.0), radius=1.0,
                                 max_resolution=2 * fc.max_resolution, n_levels=fc.n_levels + 1)
    torch.manual_seed(0)
    field = ShellField(fc, torch.tensor([[-1.0, -1, -1], [1, 1, 1]]))
    opt = make_optimizer(field, cfg.train.lr, cfg.train.lr_mlp)
    tc = cfg.train
    for k in range(max(steps) + 1):  # step k draws with seed k; printed after it (k + 1 done)
        g = torch.Generator().manual_seed(k)
        reg = regularisers(field, reg_points(field, torch.zeros(0, 3), tc.reg_points, g),
                           tc.fd_eps, tc.smooth_eps, g)
        loss = (tc.eikonal_weight * reg["eikonal"] + tc.normal_weight * reg["normal"]
                + tc.kernel_smooth_weight * reg["smooth"])
        opt.zero_grad()
        loss.backward()
        opt.step()
        if k in steps:
            print(k + 1, _f(field), {n: round(float(v), 4) for n, v in reg.items()}, flush=True)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("data", nargs="?", help="toy data set (not needed with --regularisers-only)")
    p.add_argument("out", nargs="?", help="run directory (replaced)")
    p.add_argument("--scene", default="auto", choices=["auto", "bounded", "unbounded"])
    p.add_argument("--config", default="{}", help="JSON object merged into the config")
    p.add_argument("--steps", type=int, nargs="+", default=[25, 50, 100, 150])
    p.add_argument("--regularisers-only", action="store_true")
    args = p.parse_args(argv)
    extra = json.loads(args.config)
    steps = sorted(args.steps)
    if args.regularisers_only:
        regularisers_only(args.scene, steps, extra)
        return 0
    if args.data is None or args.out is None:
        p.error("DATA and OUT are required")
    from shells.run import load_field
    from shells.training import preset_config, scene_similarity, train, unbounded_settings

    dev = torch.device("cpu")
    sim = scene_similarity(args.data, args.scene)
    cfg = preset_config("auto", args.data, 1, dev, sim)[0]
    if extra:
        cfg.update(extra, "--config")
    if sim is not None:
        unbounded_settings(cfg, sim)
    shutil.rmtree(args.out, ignore_errors=True)
    for i, stop in enumerate(steps):
        if i == 0:
            train(args.data, args.out, cfg, dev, stop_at=stop, progress=False)
        else:
            train(None, args.out, cfg, dev, resume=True, stop_at=stop, progress=False)
        print(stop, _f(load_field(args.out, stage="stage1")[0]), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
