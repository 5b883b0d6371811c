"""Geometry and kernel metrics of a trained stage-1 run on a toy scene (issue 3).

    python bench/field_metrics.py RUN [--json OUT]

Reads the scene record that `shells-scene` writes into transforms_train.json and reports:
- `sdf_abs_on_true_surface`: mean |f| over 20k points on the true opaque sphere(s)
  (`sphere`: radius 0.5; `core-fuzz`: the core), also as a fraction of the radius;
- `s_learned_surface`: median kernel size s over the vertices of the learned zero level set
  (marching cubes of f at 128^3) - "the kernel at the content's surface";
- for `core-fuzz`: median s on the true core sphere and on the learned surface outside it
  (the coat), and their ratio;
- `radial_profile`: median f and s over 2000 directions on spheres of radius 0.20 ... 0.64
  around the scene centre (where the kernel is sharp or wide relative to the zero level set);
- the run's test PSNR and training time from RUN/train_summary.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from shells.fields.network import fibonacci_sphere
from shells.levelset.grid import sample_grid
from shells.levelset.mesh import marching_cubes
from shells.run import RunDir, load_field, read_run

from report import emit_json


def field_metrics(run_dir: str | Path, resolution: int = 128) -> dict:
    run = RunDir(run_dir)
    field, cfg = load_field(run.root, stage="stage1")
    meta = read_run(run)
    scene = json.loads((Path(meta["data"]) / "transforms_train.json").read_text()).get("scene", {})
    out: dict = {"run": str(run.root), "scene": scene.get("name")}
    summary = run.summary("stage1")
    if summary.is_file():
        s = json.loads(summary.read_text())
        out["test_psnr"] = s.get("test", {}).get("psnr")
        out["train_seconds"] = s.get("seconds", s.get("train_seconds"))  # older runs: train_seconds
        out["steps"] = s.get("step")

    def geo(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        g = field.geometry(x)
        return g["sdf"], g["s"]

    with torch.no_grad():
        f, s, _ = sample_grid(geo, field.aabb.cpu().numpy(), resolution, 1 << 18)
        mesh = marching_cubes(f, field.aabb.cpu().numpy())
        verts = torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float32)
        s_surf = field.kernel(verts).numpy() if len(verts) else np.zeros(0)
        r = np.linalg.norm(np.asarray(mesh.vertices), axis=-1)
        out["s_learned_surface"] = float(np.median(s_surf)) if len(s_surf) else None
        out["learned_surface_radius_median"] = float(np.median(r)) if len(r) else None
        # the opaque sphere's radius (`fuzzy-sphere` has no hard surface: its radius is a bound)
        radius = {"sphere": scene.get("radius"),
                  "core-fuzz": scene.get("core_radius")}.get(scene.get("name"))
        if radius:
            pts = fibonacci_sphere(20000).float() * float(radius)
            fa = field.sdf(pts).abs()
            out["true_radius"] = float(radius)
            out["sdf_abs_on_true_surface"] = float(fa.mean())
            out["sdf_abs_fraction_of_radius"] = float(fa.mean() / radius)
            out["s_true_surface"] = float(field.kernel(pts).median())
        centre = torch.tensor(scene.get("center", [0.0, 0.0, 0.0]), dtype=torch.float32)
        dirs = fibonacci_sphere(2000).float()
        out["radial_profile"] = []
        for rad in np.arange(0.20, 0.65, 0.04):
            pts = centre + dirs * float(rad)
            out["radial_profile"].append({"r": round(float(rad), 2),
                                          "f_median": float(field.sdf(pts).median()),
                                          "s_median": float(field.kernel(pts).median())})
        if scene.get("name") == "core-fuzz" and radius and len(s_surf):
            coat = s_surf[r > float(radius) + 0.05]
            out["s_coat_learned_surface"] = float(np.median(coat)) if len(coat) else None
            out["s_core_true_surface"] = out["s_true_surface"]
            if len(coat):
                out["s_ratio_coat_over_core"] = out["s_coat_learned_surface"] / out["s_true_surface"]
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run")
    p.add_argument("--json", default=None, help="also write the metrics to this file")
    args = p.parse_args(argv)
    m = field_metrics(args.run)
    emit_json(m, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
