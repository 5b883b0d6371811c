"""Where a field's full-ray rendering weight lies: near its level set, or off it.

    python bench/weight_split.py RUN [--stage stage1|stage2] [--samples 64 --importance 32]

Renders RUN's test views in full-ray mode (`shells.render.volume.render_volume_rays`, the
stage-1 sampler with a deterministic placement) and sums the compositing weights of the
samples in three classes: near the level set, |f| < h + k s (the occupancy rule every
skipping renderer uses, `shells.fields.neus.may_have_density`, with h the half diagonal of a
`render.occ_resolution` cell and k = `render.occ_k`); f < 0 farther (density inside a solid
that a ray reached without being absorbed at the crossing: the predicted normal said it was
leaving there); f > 0 farther. The weight off the level set is what the occupancy grid and
the band renderer cannot see. Prints the three shares as JSON; for an unbounded field also
each class's share inside the ball of interest (|u| <= 1, the object) and outside it (the
contracted room), as ``share_ball`` and ``share_outside`` (of the whole weight).

On a soft field (large s) "near the level set" covers most of space and says little about
what shells with capped falloffs cut; ``by_s`` and ``by_f`` split the weight by the kernel size
s and by f at the sample (bin edges S_EDGES, F_EDGES), which shows where the weight lies
against the shells' `dilate_zeta` / `erode_zeta`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from shells.datasets import load_dataset  # noqa: E402
from shells.fields.neus import may_have_density  # noqa: E402
from shells.run import RunDir, field_from_checkpoint, read_checkpoint, read_run  # noqa: E402
from shells.render.volume import render_volume_rays  # noqa: E402

from report import emit_json  # noqa: E402


S_EDGES = (0.0, 0.003, 0.01, 0.03, 0.1, 0.3, float("inf"))  # kernel size s (field units)
F_EDGES = (-float("inf"), -0.25, -0.1, -0.03, 0.0, 0.03, 0.1, 0.25, float("inf"))  # f


def _binned(w: torch.Tensor, x: torch.Tensor, edges: tuple[float, ...]) -> torch.Tensor:
    """Sum of the weights w whose x falls in each [edges[i], edges[i + 1])."""
    idx = torch.bucketize(x.contiguous(), torch.tensor(edges[1:-1], dtype=x.dtype), right=True)
    return torch.zeros(len(edges) - 1, dtype=torch.float64).index_add_(
        0, idx.reshape(-1), w.reshape(-1).double())


def _label(lo: float, hi: float) -> str:
    return f"{lo:g}..{hi:g}"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run")
    p.add_argument("--stage", default="stage1", choices=["stage1", "stage2"])
    p.add_argument("--samples", type=int, default=64)
    p.add_argument("--importance", type=int, default=32)
    p.add_argument("--chunk", type=int, default=8192)
    p.add_argument("--slope", default="normal", choices=["normal", "ray"],
                   help="the opacity's slope (`train.slope`; default: what skipping renderers use)")
    a = p.parse_args()
    run = RunDir(a.run)
    meta = read_run(run)
    ckpt = read_checkpoint(run, a.stage)
    field, cfg = field_from_checkpoint(ckpt, a.run)
    data = load_dataset(meta["data"], "test", downscale=int(meta["downscale"]),
                        background=cfg.data.background)
    box = field.aabb
    h = 0.5 * float((box[1] - box[0]).norm()) / cfg.render.occ_resolution
    k = cfg.render.occ_k
    bg = torch.tensor(cfg.data.background)
    names = ("near_level_set", "inside_far", "outside_far")
    tot = {n: 0.0 for n in names}
    sim = field.similarity
    ball = {n: 0.0 for n in names}
    by_s = torch.zeros(len(S_EDGES) - 1, dtype=torch.float64)
    by_f = torch.zeros(len(F_EDGES) - 1, dtype=torch.float64)
    with torch.no_grad():
        for v in range(len(data.cameras)):
            o, d = data.cameras.pixel_rays(v, 1)
            for i in range(0, len(o), a.chunk):
                out = render_volume_rays(field, o[i:i + a.chunk], d[i:i + a.chunk],
                                         a.samples, a.importance, bg, slope=a.slope)
                w, f, s = out["weights"], out["sdf"], out["s"]
                near = may_have_density(f, s, h, k)
                classes = (near, ~near & (f < 0), ~near & (f > 0))
                inb = (torch.ones_like(near) if sim is None else
                       torch.linalg.vector_norm(sim.to_unit(out["points"]), dim=-1) <= 1.0)
                for n, m in zip(names, classes):
                    tot[n] += float(w[m].sum())
                    ball[n] += float(w[m & inb].sum())
                by_s += _binned(w, s, S_EDGES)
                by_f += _binned(w, f, F_EDGES)
    total = max(sum(tot.values()), 1e-12)
    res = {"run": a.run, "stage": a.stage, "views": len(data.cameras), "h": h, "k": k,
           "share": {n: v / total for n, v in tot.items()},
           "by_s": {_label(*S_EDGES[i:i + 2]): float(by_s[i]) / total for i in range(len(by_s))},
           "by_f": {_label(*F_EDGES[i:i + 2]): float(by_f[i]) / total for i in range(len(by_f))}}
    if sim is not None:
        res["share_ball"] = {n: ball[n] / total for n in names}
        res["share_outside"] = {n: (tot[n] - ball[n]) / total for n in names}
    emit_json(res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
