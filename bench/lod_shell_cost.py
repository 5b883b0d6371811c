"""What a coarse shell (shells-lod) costs in band samples, by how it is built: samples per
covered pixel of each candidate inner or outer shell against the fine one.

    python -m bench.lod_shell_cost RUN OUT [--shell inner|outer] [--staged D:R ...]
                                   [--only NAME ...]

The band renderer takes N = min(ceil(max(w - w_s, 0) / delta_s) + 1, N_max) samples in an
interval of width w, so a coarse shell that sits farther from the fine one, or that leaves
out a thin part of it, adds samples. This script renders the stage-1 field of RUN through
one fine shell and each candidate for the other (`shells-render --stage stage1 --shells lod`
on a scratch copy of the run) and reports samples per covered pixel against both fine
shells, with each candidate's triangles, containment check, volume and components.
Candidates (D in grid cells h, R the triangle ratio):

* ``shift-D``: the fine shell moved D along its vertex normals (in for M-, out for M+; not
  contained in general: the cost of the distance alone);
* ``offset-D``: `DistanceGrid.offset` at D (exact signed distance, marching cubes, deepened
  where it fails its check; one distance grid for all of them), undecimated;
* ``offset-D-xR``: that, then `decimate_staged` to 1/R of the fine triangles;
* inner only: ``voxel-subK``, the grid cells of h / K that M- does not meet, in groups whose
  winding number says inside, meshed half a cell in, undecimated (a voxel construction, for
  comparison with the offset), and ``voxel-sub1-x10``, that decimated as `decimate_staged`
  does;
* outer only: ``wrap-x10``, `wrap_outer` (CGAL's alpha wrap, ratio 10);
* ``lod``: what shells-lod builds with the default parameters, ratio 10.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree

from shells.levelset import containment
from shells.levelset import lod as L
from shells.levelset.mesh import write_ply
from shells.run import RunDir, shell_meshes, shells_digest


def voxel_interior(S: L.Mesh, origin: np.ndarray, h: float, depth: np.ndarray, sub: int
                   ) -> L.Mesh:
    """voxel-subK of the module docstring (``depth`` [n]: erosion per fine vertex)."""
    from shells.levelset.mesh import clean_mesh, marching_cubes

    V, F = np.asarray(S[0], np.float64), np.asarray(S[1], np.int64)
    cell = h / sub
    lo = np.floor((V.min(0) - origin) / cell).astype(int) - 2
    hi = np.ceil((V.max(0) - origin) / cell).astype(int) + 2
    shape = tuple(int(x) for x in hi - lo)
    labels, solid = L.solid_groups(~L.touched_cells(V, F, origin, cell, lo, shape), V, F,
                                   lambda idx: origin + (idx + lo + 0.5) * cell)
    interior = solid[labels]
    sd = np.where(interior, -ndimage.distance_transform_edt(interior),
                  ndimage.distance_transform_edt(~interior)).astype(np.float32)
    cells = np.argwhere(interior)
    _, near = cKDTree(V).query(origin + (cells + lo + 0.5) * cell)
    extra = np.zeros(shape, np.float32)
    extra[tuple(cells.T)] = depth[near] / cell
    box = np.stack([origin + (lo + 0.5) * cell, origin + (hi - 0.5) * cell])
    m = clean_mesh(marching_cubes(sd + 0.5 + extra, box))
    return np.asarray(m.vertices), np.asarray(m.faces, np.int32)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run")
    ap.add_argument("out")
    ap.add_argument("--shell", choices=("inner", "outer"), default="inner")
    ap.add_argument("--staged", nargs="+", default=None,
                    help="offset-D-xR candidates, as D:R (default: inner 0.25:4 0.3:10 0.4:10, "
                         "outer 0.15:10 0.2:10 0.3:10)")
    ap.add_argument("--only", nargs="+", default=None, help="these candidates (and fine)")
    args = ap.parse_args(argv)
    run = RunDir(args.run)
    out = Path(args.out)
    scratch = out / "run"
    if scratch.exists():
        shutil.rmtree(scratch)
    (scratch / "shells" / "lod").mkdir(parents=True)
    for name in ("checkpoint.pt", "config.json", "run.json"):
        shutil.copy(run.root / name, scratch / name)
    for name in ("outer.ply", "inner.ply", "stats.json"):
        shutil.copy(run.shells / name, scratch / "shells" / name)
    other = "inner" if args.shell == "outer" else "outer"
    shutil.copy(run.shells / f"{other}.ply", scratch / "shells" / "lod" / f"{other}.ply")
    (scratch / "shells" / "lod" / "stats.json").write_text(
        json.dumps({"shells_sha1": shells_digest(RunDir(scratch))}))
    fine_stats = json.loads((run.shells / "stats.json").read_text())
    origin, h = np.asarray(fine_stats["aabb"][0], np.float64), float(min(fine_stats["spacing"]))
    outer, inner = shell_meshes(run)
    Mo = (np.asarray(outer[0], np.float64), np.asarray(outer[1], np.int64))
    Mi = (np.asarray(inner[0], np.float64), np.asarray(inner[1], np.int64))
    S, side = (Mi, -1) if args.shell == "inner" else (Mo, +1)
    fine = trimesh.Trimesh(*S, process=False)
    p = L.LodParams()
    staged = args.staged or (["0.25:4", "0.3:10", "0.4:10"] if side < 0
                             else ["0.15:10", "0.2:10", "0.3:10"])

    grids: list[L.DistanceGrid] = []

    def offset(d: float) -> L.Mesh:  # the shell's distance grid is built once, when needed
        if not grids:
            grids.append(L.DistanceGrid(S, origin, h))
        return grids[0].offset(d * h, side)[0]

    def candidates():
        yield "fine", lambda: S, False
        for d in (0.15, 0.25, 0.5, 1.0):
            yield f"shift-{d:g}", (lambda d=d: (S[0] + side * d * h * fine.vertex_normals,
                                                S[1])), False
        for d in (0.1, 0.25):
            yield f"offset-{d:g}", (lambda d=d: offset(d)), True
        for dr in staged:
            d, r = (float(x) for x in dr.split(":"))
            yield (f"offset-{d:g}-x{r:g}", (lambda d=d, r=r: L.decimate_staged(
                offset(d), S, side, int(len(S[1]) / r), h, p)[0]), True)
        if side < 0:
            lam = L.band_allowance(Mi[0], Mo[0], h, p)
            for k in (1, 2):
                yield f"voxel-sub{k}", (lambda k=k: voxel_interior(
                    S, origin, h, np.maximum(lam - h / k, 0.0), k)), True
            yield "voxel-sub1-x10", (lambda: L.decimate_staged(voxel_interior(
                S, origin, h, np.maximum(lam - h, 0.0), 1), S, -1, int(len(S[1]) / 10), h,
                p)[0]), True
            yield "lod", lambda: L.lod_inner(S, 10.0, origin, h, p)[0], True
        else:
            lam = L.band_allowance(Mo[0], Mi[0], h, p)
            yield "wrap-x10", lambda: L.wrap_outer(S, lam, 10.0, h)[0], True
            yield "lod", lambda: L.lod_outer(S, lam, 10.0, origin, h, p)[0], True

    rows = []
    for name, build, check in candidates():
        if args.only and name != "fine" and name not in args.only:
            continue
        t0 = time.perf_counter()
        C = build()
        seconds = time.perf_counter() - t0
        write_ply(scratch / "shells" / "lod" / f"{args.shell}.ply",
                  trimesh.Trimesh(*C, process=False))
        dest = out / f"render-{name}"
        subprocess.run([str(Path(sys.executable).with_name("shells-render")), str(scratch),
                        "--stage", "stage1", "--shells", "lod", "--out", str(dest)],
                       check=True, capture_output=True)
        m = json.loads((dest / "metrics.json").read_text())
        T = trimesh.Trimesh(*C, process=False)
        far, _ = cKDTree(C[0]).query(S[0])
        depth = side * containment.signed_distance(C, S) / h
        rows.append({"name": name, "triangles": int(len(C[1])), "build_s": seconds,
                     "contained": (containment.verify(C, S, side)["passed"] if check else None),
                     "volume_fraction": float(T.volume / fine.volume),
                     "components": len(T.split(only_watertight=False)),
                     "fine_vertices_over_3h_away": float((far > 3 * h).mean()),
                     "depth_over_h_p50": float(np.median(depth)),
                     "psnr": m["psnr"], "samples_per_covered_pixel":
                         m["samples_per_covered_pixel"]})
        print(json.dumps(rows[-1]), flush=True)
    base = rows[0]["samples_per_covered_pixel"]
    print(f"| {args.shell} shell | triangles | contained | volume | components "
          "| M- verts > 3h away | median distance (h) | samples / covered px | vs fine |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['name']} | {r['triangles']} | {r['contained']} | "
              f"{100 * r['volume_fraction']:.1f} % | {r['components']} | "
              f"{100 * r['fine_vertices_over_3h_away']:.1f} % | {r['depth_over_h_p50']:.2f} | "
              f"{r['samples_per_covered_pixel']:.2f} | "
              f"{100 * (r['samples_per_covered_pixel'] / base - 1):+.1f} % |")
    (out / f"lod_{args.shell}_depth.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
