"""Where a trained run's render error and rendering weight lie, and how steep its SDF is.

    python -m bench.diagnostics error RUN RENDER_DIR [RENDER_DIR ...]
    python -m bench.diagnostics ball RUN RENDER_DIR [RENDER_DIR ...] [--data DATA --downscale N]
    python -m bench.diagnostics weight RUN [--stage stage1] [--samples 64 --importance 32]
                                           [--slope normal|ray]
    python -m bench.diagnostics slope RUN [--stage stage1] [--resolution 160]
    python -m bench.diagnostics density RUN [--stage stage1] [--densities 1 2 4]
    python -m bench.diagnostics drift RUN [--points 400000]

RENDER_DIRs are `shells-render` outputs of RUN's test split (r_###.png). ``error`` and ``ball``
split the pooled squared error of each render by pixel class (silhouette edge, object,
background; or rays entering / missing an unbounded run's ball of interest); ``weight`` splits
the full-ray compositing weight by distance to the level set; ``slope`` prints |grad f| and
the kernel's world-space width at the level set; ``density`` scores the running curve's
held-out pixels with the trainer's renderer at several samples per ray; ``drift`` compares the
stage-2 field with the stage-1 field where the band does not sample. Each subcommand's --help
says more.
"""

from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path
from typing import Callable

import imageio.v3 as iio
import numpy as np
import torch

from bench.report import emit_json, run_command, subcommands
from shells.config import load_config
from shells.data.datasets import Dataset, load_dataset
from shells.errors import InputError
from shells.run import RunDir, load_field, read_run

S_EDGES = (0.0, 0.003, 0.01, 0.03, 0.1, 0.3, float("inf"))  # kernel size s (field units)
F_EDGES = (-float("inf"), -0.25, -0.1, -0.03, 0.0, 0.03, 0.1, 0.25, float("inf"))  # f


# ---------------------------------------------------------------------------------------------
# Shared: the run's test views, the renders' pooled errors
# ---------------------------------------------------------------------------------------------

def test_views(run: RunDir, background, data: str | None = None,
               downscale: int | None = None) -> Dataset:
    """RUN's test split (run.json's data set and downscale unless given), composited on
    ``background`` as the renderer does."""
    meta = read_run(run)
    return load_dataset(data or meta["data"], "test", background=tuple(background),
                        downscale=downscale or int(meta["downscale"]))


def pooled_errors(test: Dataset, renders: list[str],
                  classes: Callable[[int], dict[str, np.ndarray]]
                  ) -> tuple[dict[tuple[str, str], float], dict[str, int]]:
    """Squared error (mean over RGB) of every render's r_###.png against the test images,
    summed over the pixel classes ``classes(i)`` gives for view i ({name: bool [H, W]}), and
    each class's pixel count."""
    sse: dict[tuple[str, str], float] = {}
    count: dict[str, int] = {}
    for i in range(len(test.images)):
        masks = classes(i)
        for c, m in masks.items():
            count[c] = count.get(c, 0) + int(m.sum())
        gt = test.images[i].numpy()
        for r in renders:
            path = Path(r) / f"r_{i:03d}.png"
            if not path.is_file():
                raise InputError(f"{path}: missing; render RUN's test split into {r} first")
            err = ((iio.imread(path).astype(np.float32)[..., :3] / 255.0 - gt) ** 2).mean(-1)
            for c, m in masks.items():
                sse[r, c] = sse.get((r, c), 0.0) + float(err[m].sum())
    return sse, count


def error_table(sse: dict[tuple[str, str], float], count: dict[str, int], renders: list[str],
                labels: dict[str, str]) -> str:
    """Markdown: per class its share of the pixels and, per render, the pooled PSNR over the
    class and (in brackets) its summed squared error, the class's part of the pooled error
    (the per-frame PSNR averages of metrics.json differ from these pooled figures)."""
    total = max(sum(count.values()), 1)
    lines = ["| pixels | share | " + " | ".join(f"{Path(r).name}: PSNR (summed sq. error)"
                                               for r in renders) + " |",
             "|---|---|" + "---|" * len(renders)]
    for c, label in labels.items():
        cells = []
        for r in renders:
            mse = sse[r, c] / count[c] if count[c] else float("nan")
            db = -10 * math.log10(mse) if mse > 0 else float("inf")
            cells.append(f"{db:.2f} dB ({sse[r, c]:.1f})")
        lines.append(f"| {label} | {count[c] / total:.1%} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# The subcommands
# ---------------------------------------------------------------------------------------------

def error(a: argparse.Namespace) -> int:
    """Error by silhouette: pixels split by the reference alpha into "object" (alpha > 0.5),
    "edge" (object pixels on its one-pixel boundary and background pixels touching it) and
    "background" (the rest, which on the toy scenes includes thin translucent fuzz). Needs a
    data set with alpha (Blender RGBA PNGs)."""
    from scipy import ndimage

    run = RunDir(a.run)
    test = test_views(run, load_config(run.config).data.background)
    if test.alpha is None:
        raise InputError(f"{read_run(run)['data']}: the test images have no alpha; use `ball`")

    def classes(i: int) -> dict[str, np.ndarray]:
        inside = test.alpha[i].numpy() > 0.5
        edge = ((inside & ~ndimage.binary_erosion(inside))
                | (~inside & ndimage.binary_dilation(inside)))
        return {"edge": edge, "object": inside & ~edge, "background": ~inside & ~edge}

    sse, count = pooled_errors(test, a.renders, classes)
    print(error_table(sse, count, a.renders, {"edge": "silhouette edge", "object": "object",
                                              "background": "background"}))
    return 0


def ball(a: argparse.Namespace) -> int:
    """Error of an unbounded run by region: pixels whose ray enters the ball of interest (the
    object) against those whose ray misses it (the contracted background)."""
    run = RunDir(a.run)
    cfg = load_config(run.config)
    if not cfg.field.unbounded:
        raise InputError(f"{a.run}: not an unbounded run (config.json field.unbounded is false)")
    centre, radius = torch.tensor(cfg.field.centre, dtype=torch.float32), float(cfg.field.radius)
    test = test_views(run, cfg.data.background, a.data, a.downscale)
    H, W = test.images.shape[1:3]

    def classes(i: int) -> dict[str, np.ndarray]:
        o, d = test.cameras.pixel_rays(i, 1)
        ou = (o - centre) / radius
        b = (ou * d).sum(-1)
        hit = (b * b - ((ou * ou).sum(-1) - 1.0) > 0).reshape(H, W).numpy()
        return {"ball": hit, "outside": ~hit}

    sse, count = pooled_errors(test, a.renders, classes)
    print(error_table(sse, count, a.renders, {"ball": "ray enters the ball",
                                              "outside": "ray misses the ball"}))
    return 0


def _binned(w: torch.Tensor, x: torch.Tensor, edges: tuple[float, ...]) -> torch.Tensor:
    """Sum of the weights w whose x falls in each [edges[i], edges[i + 1])."""
    idx = torch.bucketize(x.contiguous(), torch.tensor(edges[1:-1], dtype=x.dtype), right=True)
    return torch.zeros(len(edges) - 1, dtype=torch.float64).index_add_(
        0, idx.reshape(-1), w.reshape(-1).double())


def weight(a: argparse.Namespace) -> int:
    """Where the full-ray rendering weight lies: renders the test views full-ray (the stage-1
    sampler, deterministic placement) and sums the compositing weights in three classes: near
    the level set, |f| < h + k s (`shells.fields.neus.may_have_density`, h the half diagonal of
    a `render.occ_resolution` cell, k = `render.occ_k`); f < 0 farther (inside a solid that a
    ray reached unabsorbed); f > 0 farther. The weight off the level set is what the occupancy
    grid and the band renderer cannot see. Prints the shares as JSON; for an unbounded field
    also inside (share_ball) and outside (share_outside) the ball of interest; by_s and by_f
    split the weight by the kernel size s and by f (bins S_EDGES, F_EDGES)."""
    from shells.fields.neus import half_cell_diagonal, may_have_density
    from shells.render.volume import render_volume_rays

    run = RunDir(a.run)
    field, cfg = load_field(run.root, stage=a.stage)
    data = test_views(run, cfg.data.background)
    h = half_cell_diagonal(field.aabb, cfg.render.occ_resolution)
    k = cfg.render.occ_k
    bg = torch.tensor(cfg.data.background)
    names = ("near_level_set", "inside_far", "outside_far")
    tot = {n: 0.0 for n in names}
    in_ball = {n: 0.0 for n in names}
    sim = field.similarity
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
                inb = (torch.ones_like(near) if sim is None else
                       torch.linalg.vector_norm(sim.to_unit(out["points"]), dim=-1) <= 1.0)
                for n, m in zip(names, (near, ~near & (f < 0), ~near & (f > 0))):
                    tot[n] += float(w[m].sum())
                    in_ball[n] += float(w[m & inb].sum())
                by_s += _binned(w, s, S_EDGES)
                by_f += _binned(w, f, F_EDGES)
    total = max(sum(tot.values()), 1e-12)

    def bins(x: torch.Tensor, edges: tuple[float, ...]) -> dict[str, float]:
        return {f"{edges[i]:g}..{edges[i + 1]:g}": float(x[i]) / total for i in range(len(x))}

    res = {"run": a.run, "stage": a.stage, "views": len(data.cameras), "h": h, "k": k,
           "share": {n: v / total for n, v in tot.items()},
           "by_s": bins(by_s, S_EDGES), "by_f": bins(by_f, F_EDGES)}
    if sim is not None:
        res["share_ball"] = {n: in_ball[n] / total for n in names}
        res["share_outside"] = {n: (tot[n] - in_ball[n]) / total for n in names}
    emit_json(res)
    return 0


def _percentiles(x: np.ndarray) -> dict[str, float]:
    p = np.percentile(x, [5, 25, 50, 75, 95])
    return {"p5": float(p[0]), "p25": float(p[1]), "p50": float(p[2]), "p75": float(p[3]),
            "p95": float(p[4]), "mean": float(x.mean())}


def slope(a: argparse.Namespace) -> int:
    """The SDF's slope |grad f| at the level set: the NeuS opacity falls off over s / |grad f|
    world units along a ray, which equals s only for an exact SDF (|grad f| = 1, what the
    Eikonal term asks for). Samples the field on a grid over its box, keeps the points with
    |f| < half a cell, and prints JSON percentiles of |grad f| (autograd), of s and of
    s / |grad f| there."""
    from shells.levelset.grid import grid_axes

    field, _ = load_field(a.run, stage=a.stage)
    box = field.aabb.cpu().numpy()
    axes = grid_axes(box, a.resolution)
    h = float(np.max((box[1] - box[0]) / (a.resolution - 1)))
    pts = torch.stack(torch.meshgrid(*[torch.as_tensor(ax, dtype=torch.float32) for ax in axes],
                                     indexing="ij"), dim=-1).reshape(-1, 3)
    keep = []
    with torch.no_grad():
        for chunk in pts.split(262144):
            keep.append(chunk[field.geometry_field(chunk)["sdf"].abs() < 0.5 * h])
    near = torch.cat(keep)
    if len(near) > a.max_points:
        near = near[torch.randperm(len(near), generator=torch.Generator().manual_seed(0))
                    [:a.max_points]]
    g_all, s_all = [], []
    for chunk in near.split(65536):
        x = chunk.clone().requires_grad_(True)
        geo = field.geometry_field(x)
        (grad,) = torch.autograd.grad(geo["sdf"].sum(), x)
        g_all.append(grad.norm(dim=-1).detach())
        s_all.append(geo["s"].detach())
    g = torch.cat(g_all).numpy().astype(np.float64)
    s = torch.cat(s_all).numpy().astype(np.float64)
    emit_json({"run": a.run, "stage": a.stage, "resolution": a.resolution,
               "level_set_points": int(len(g)), "grad_norm": _percentiles(g),
               "s": _percentiles(s), "s_world": _percentiles(s / np.maximum(g, 1e-6))})
    return 0


def density(a: argparse.Namespace) -> int:
    """What the trainer's renderer sees of the field at more samples a ray: the running curve's
    held-out pixels (`shells.train.stage1.RunningCurve`: the run's curve views, ``--pixels``
    a view, the same fixed draw) rendered with the stage-1 occupancy grid at k times the run's
    n_samples and n_importance for each k of ``--densities`` (``train.eval_density`` k).
    Prints JSON: the pooled PSNR per density. A sharp field's training samples step over its
    thin parts, so its PSNR keeps rising past density 1 until the samples resolve the kernel."""
    import dataclasses

    from shells.run import read_checkpoint
    from shells.train.stage1 import RunningCurve, eval_samples, stage1_grid

    run = RunDir(a.run)
    field, cfg = load_field(run.root, stage=a.stage)
    grid = stage1_grid(read_checkpoint(run, "stage1"), field, cfg)
    data = test_views(run, cfg.data.background)
    rows = []
    for k in a.densities:
        tc = dataclasses.replace(cfg.train, eval_density=k, curve_pixels=a.pixels)
        with tempfile.TemporaryDirectory() as tmp:  # the curve's file is not kept
            curve = RunningCurve(data, tc, Path(tmp) / "curve.jsonl", torch.device("cpu"))
            rec = curve.point(field, grid, 0, 0.0)
        rows.append({"density": k, "samples": list(eval_samples(tc)), "psnr": rec["psnr"],
                     "views": rec["views"], "pixels": rec["pixels"]})
    emit_json({"run": a.run, "stage": a.stage, "rows": rows})
    return 0


def drift(a: argparse.Namespace) -> int:
    """How far stage 2 moved the field away from the band: the stage-1 and stage-2 fields (the
    network alone, field space) at ``--points`` uniform points of the field's box. Prints JSON:
    the share of the points that pass the occupancy grids' test |f| < h + k s
    (`may_have_density`; h the half diagonal of a ``render.occ_resolution`` cell, k
    ``render.occ_k``) for each field, the share that passes for the stage-2 field only, and,
    at the points the stage-1 field leaves empty, percentiles of s2 / s1 and of f2 - f1."""
    from shells.fields.neus import half_cell_diagonal, may_have_density

    f1, _ = load_field(a.run, stage="stage1")
    f2, cfg = load_field(a.run, stage="stage2")
    lo, hi = f1.aabb[0], f1.aabb[1]
    z = lo + (hi - lo) * torch.rand(a.points, 3, generator=torch.Generator().manual_seed(0))
    rc = cfg.render
    h = half_cell_diagonal(f1.aabb, rc.occ_resolution)
    g = {}
    with torch.no_grad():
        for name, field in (("stage1", f1), ("stage2", f2)):
            parts = [field.geometry_field(c, far=False) for c in z.split(65536)]
            g[name] = {k: torch.cat([p[k] for p in parts]).double() for k in ("sdf", "s")}
    occ = {n: may_have_density(v["sdf"], v["s"], h, rc.occ_k) for n, v in g.items()}
    empty = ~occ["stage1"]
    ratio = (g["stage2"]["s"] / g["stage1"]["s"])[empty].numpy()
    shift = (g["stage2"]["sdf"] - g["stage1"]["sdf"])[empty].numpy()
    emit_json({"run": a.run, "points": a.points, "h": h, "k": rc.occ_k,
               "occupied_share": {n: float(o.double().mean()) for n, o in occ.items()},
               "newly_occupied_share": float((occ["stage2"] & empty).double().mean()),
               "empty_in_stage1": {"s2_over_s1": _percentiles(ratio),
                                   "f2_minus_f1": _percentiles(shift)}})
    return 0


def main(argv: list[str] | None = None) -> int:
    p, sub = subcommands("python -m bench.diagnostics", __doc__.split("\n\n")[0],
                         [error, ball, weight, slope, density, drift])
    for name in ("error", "ball"):
        sub[name].add_argument("renders", nargs="+", metavar="RENDER_DIR",
                               help="shells-render outputs of RUN's test split")
    for name in ("weight", "slope"):
        sub[name].add_argument("--stage", default="stage1",
                               choices=["stage1", "stage2", "latest"])
    sp = sub["ball"]
    sp.add_argument("--data", default=None, help="default: RUN's data set (run.json)")
    sp.add_argument("--downscale", type=int, default=None, help="default: RUN's")
    sp = sub["weight"]
    sp.add_argument("--samples", type=int, default=64)
    sp.add_argument("--importance", type=int, default=32)
    sp.add_argument("--chunk", type=int, default=8192)
    sp.add_argument("--slope", default="normal", choices=["normal", "ray"],
                    help="the opacity's slope (`train.slope`; default: what skipping renderers "
                         "use)")
    sp = sub["density"]
    sp.add_argument("--stage", default="stage1", choices=["stage1", "stage2"])
    sp.add_argument("--densities", type=int, nargs="+", default=[1, 2, 4],
                    help="multiples of the run's samples a ray (train.eval_density)")
    sp.add_argument("--pixels", type=int, default=16384, help="pixels a curve view")
    sub["drift"].add_argument("--points", type=int, default=400000)
    sp = sub["slope"]
    sp.add_argument("--resolution", type=int, default=160)
    sp.add_argument("--max-points", type=int, default=200000)
    return run_command(p, argv)


if __name__ == "__main__":
    raise SystemExit(main())
