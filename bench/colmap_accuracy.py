"""Accuracy of `shells-process-data` poses against known ones (e.g. NeRF-synthetic lego).

    python -m bench.colmap_accuracy DATA TRUE_TRANSFORMS [--json OUT]
        [--eval-run RUN --true-data DIR --downscale N]

DATA is what shells-process-data wrote (transforms.json, images/NAME); TRUE_TRANSFORMS a
Blender / Instant-NGP transforms file whose frames name the same images (matched by file
stem). The recovered camera centres are aligned to the true ones by a similarity (Umeyama: scale,
rotation, translation, least squares); then per registered image the rotation error (degrees,
the angle of R_true^T R_aligned) and the position error as a fraction of the true cameras'
mean distance from their centroid (the camera-sphere radius). The similarity is fitted on the
images within 3x the median position error (at least 1 %), refitted until that set is stable,
so one wrong registration does not tilt the others; every image counts in the shares.

``--eval-run RUN`` (a stage-1 run trained on DATA) also scores that run on the *true* test
views of ``--true-data`` (e.g. lego's transforms_test.json): their cameras are mapped into
DATA's world by the inverse of the fitted similarity, so the run is compared on the same
images as a run trained on the true poses. Reports the registered share and
the share within 1 degree and 1 % of the radius, and the recovered focal length.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from bench.report import emit_json


def _frames(path: Path) -> dict[str, np.ndarray]:
    doc = json.loads(path.read_text())
    return {Path(f["file_path"]).stem: np.asarray(f["transform_matrix"], np.float64)
            for f in doc["frames"]}


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """s, R, t minimising sum |s R src_i + t - dst_i|^2 (src, dst [N, 3])."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, sig, vt = np.linalg.svd(b.T @ a / len(src))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ d @ vt
    scale = float(np.trace(np.diag(sig) @ d) / (a ** 2).sum(1).mean())
    return scale, rot, mu_d - scale * rot @ mu_s


def accuracy(data: Path, truth: Path) -> dict:
    est, ref = _frames(data / "transforms.json"), _frames(truth)
    names = sorted(set(est) & set(ref))
    if len(names) < 3:
        raise SystemExit(f"{data}: fewer than 3 images in common with {truth}")
    e = np.stack([est[n] for n in names])  # OpenGL c2w, both
    r = np.stack([ref[n] for n in names])
    radius = float(np.linalg.norm(r[:, :3, 3] - r[:, :3, 3].mean(0), axis=1).mean())
    keep = np.ones(len(names), bool)
    for _ in range(10):  # trimmed fit: one wrong registration must not tilt the others
        s, rot, t = umeyama(e[keep, :3, 3], r[keep, :3, 3])
        pos = (s * e[:, :3, 3] @ rot.T) + t
        pos_err = np.linalg.norm(pos - r[:, :3, 3], axis=1) / radius
        new = pos_err <= max(3.0 * float(np.median(pos_err)), 0.01)
        if (new == keep).all():
            break
        keep = new
    rel = np.einsum("nji,jk,nkl->nil", r[:, :3, :3], rot, e[:, :3, :3])  # R_true^T R R_est
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    rot_err = np.degrees(np.arccos(cos))
    good = (rot_err <= 1.0) & (pos_err <= 0.01)
    accuracy.similarity = (s, rot, t)  # est world -> true world, for --eval-run
    doc = json.loads((data / "transforms.json").read_text())
    return {"data": str(data), "truth": str(truth), "true_images": len(ref),
            "registered": len(names), "registered_fraction": len(names) / len(ref),
            "aligned_on": int(keep.sum()),
            "within_1deg_1pct": int(good.sum()), "within_fraction_of_all": float(good.sum()
                                                                                 / len(ref)),
            "rotation_error_deg": {"median": float(np.median(rot_err)),
                                   "max": float(rot_err.max())},
            "position_error_of_radius": {"median": float(np.median(pos_err)),
                                         "max": float(pos_err.max())},
            "fl_x": doc.get("fl_x"), "fl_y": doc.get("fl_y"), "w": doc.get("w")}


def eval_on_true_views(run: Path, true_data: Path, downscale: int,
                       similarity: tuple) -> dict:
    """Full-ray test PSNR of RUN's stage-1 field on the true test views mapped into its world."""
    import dataclasses

    import torch

    from shells.data.datasets import load_dataset
    from shells.run import load_field
    from shells.train.stage1 import evaluate

    s, rot, t = similarity
    field, cfg = load_field(run, stage="stage1")
    test = load_dataset(true_data, "test", downscale=downscale, background=cfg.data.background)
    c2w = test.cameras.c2w.double().numpy().copy()  # OpenCV axes, true world
    inv = rot.T
    c2w[:, :3, :3] = inv @ c2w[:, :3, :3]
    c2w[:, :3, 3] = ((c2w[:, :3, 3] - t) @ inv.T) / s
    cams = dataclasses.replace(test.cameras, c2w=torch.from_numpy(c2w).float())
    res = evaluate(field, dataclasses.replace(test, cameras=cams), cfg.train)
    return {"run": str(run), "true_test_psnr": res["psnr"], "n_views": res["n_views"]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("data", type=Path)
    p.add_argument("truth", type=Path)
    p.add_argument("--json", default=None)
    p.add_argument("--eval-run", type=Path, default=None)
    p.add_argument("--true-data", type=Path, default=None)
    p.add_argument("--downscale", type=int, default=1, help="of --true-data's images")
    args = p.parse_args(argv)
    out = accuracy(args.data, args.truth)
    if args.eval_run:
        out["eval"] = eval_on_true_views(args.eval_run, args.true_data or args.truth.parent,
                                         args.downscale, accuracy.similarity)
    emit_json(out, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
