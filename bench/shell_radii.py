"""Where the shells lie relative to a toy scene's true surfaces (issue 4, `sphere`, `core-fuzz`).

    python bench/shell_radii.py RUN [--json OUT]

The toy scenes are centred spheres, so each shell is summarised by its distance from the scene
centre along 2000 directions (a Fibonacci sphere): the first crossing of each mesh by the ray
from the centre (no crossing of M- in a direction = no solid interior there). Reported:
percentiles of the radius of M+ and M-, and, against the opaque sphere's true radius r
(`sphere`: 0.5, `core-fuzz`: the core 0.3):

- `inside_depth`: r - r(M-), how far the inner shell lies under the true opaque surface
  (the band's part inside the solid);
- `outside_height`: r(M+) - r, how far the outer shell reaches out (for `core-fuzz`, through
  the coat; its medium ends at 0.552);
- both as fractions of r.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import trimesh

from shells.fields.network import fibonacci_sphere
from shells.run import RunDir, read_run

from report import emit_json


def first_hit_radius(mesh: trimesh.Trimesh, dirs: np.ndarray) -> np.ndarray:  # [N] (nan = miss)
    """Distance from the origin to the first crossing of ``mesh`` along each direction."""
    origins = np.zeros_like(dirs)
    loc, idx_ray, _ = mesh.ray.intersects_location(origins, dirs, multiple_hits=True)
    r = np.full(len(dirs), np.nan)
    d = np.linalg.norm(loc, axis=-1)
    for i, di in zip(idx_ray, d):
        if np.isnan(r[i]) or di < r[i]:
            r[i] = di
    return r


def shell_radii(run_dir: str | Path) -> dict:
    rd = RunDir(run_dir)
    run = rd.root
    meta = read_run(rd)
    scene = json.loads((Path(meta["data"]) / "transforms_train.json").read_text()).get("scene", {})
    radius = {"sphere": scene.get("radius"),
              "core-fuzz": scene.get("core_radius")}.get(scene.get("name"))
    dirs = fibonacci_sphere(2000).double().numpy()
    out: dict = {"run": str(run), "scene": scene.get("name"), "true_radius": radius,
                 "n_directions": len(dirs)}
    pct = [5, 25, 50, 75, 95]
    for name in ("outer", "inner"):
        path = rd.outer if name == "outer" else rd.inner
        if not path.is_file() or path.stat().st_size == 0:
            out[name] = None
            continue
        r = first_hit_radius(trimesh.load(path, process=False), dirs)
        hit = ~np.isnan(r)
        out[name] = {"hit_fraction": float(hit.mean()),
                     "radius_percentiles": dict(zip(map(str, pct),
                                                    np.percentile(r[hit], pct).tolist()))
                     if hit.any() else None}
        if radius and hit.any():
            key = "outside_height" if name == "outer" else "inside_depth"
            v = (r[hit] - radius) if name == "outer" else (radius - r[hit])
            out[name][key] = {"median": float(np.median(v)), "mean": float(v.mean()),
                              "median_fraction_of_r": float(np.median(v) / radius)}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="run directory with RUN/shells/{outer,inner}.ply")
    p.add_argument("--json", default=None, help="also write the numbers to this file")
    args = p.parse_args(argv)
    emit_json(shell_radii(args.run), args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
