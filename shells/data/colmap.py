"""From a folder of photos to a posed data set: structure from motion with COLMAP (pycolmap),
written as an Instant-NGP ``transforms.json`` (`shells-process-data IMAGES --out DATA`).

Steps (each with a progress bar):

1. the photos are copied to DATA/images (optionally shrunk by an integer factor, area average);
2. SIFT features on the CPU, one shared camera (COLMAP's ``SIMPLE_RADIAL`` model by default:
   f, cx, cy, k1; ``OPENCV`` adds fy, k2, p1, p2 but registers only a few of lego's views
   where SIMPLE_RADIAL registers nearly all), exhaustive or sequential matching, then guided
   matching (a second pass along each pair's verified epipolar geometry: more matches for
   weakly linked views; it makes matching about 1.5-3x slower) and two-view RANSAC at ``max_error``
   pixels (2; COLMAP's default is 4);
3. incremental mapping (one thread, a fixed random seed: the same photos give the same poses)
   with the same ``max_error`` for the first pair, for triangulation and for dropping
   observations after bundle adjustment (3x it for registering a new view, COLMAP's ratio): on
   lego at 400x400 it brings every view within 1 degree / 1 %, which COLMAP's defaults miss for
   a few views (BENCHMARKS.md); the reconstruction with the most registered images is kept; fewer
   than half of the photos (or fewer than 3) registered is an error;
4. poses oriented and scaled as nerfstudio does: up = the mean of the cameras' up vectors,
   turned to +z; the centre is the point nearest to all optical axes (Instant-NGP's
   colmap2nerf; the mean of the camera positions, nerfstudio's default, lies above a
   hemispherical capture); the cameras fitted into the unit cube (largest |coordinate| = 1);
5. transforms.json: shared intrinsics fl_x, fl_y, cx, cy, w, h, k1, k2, p1, p2, OpenGL
   camera-to-world matrices, and the scene box ``aabb`` from the sparse points (2nd-98th
   percentile per axis, padded by 10 %) with ``aabb_scale`` 1.

Everything is written into a hidden folder beside DATA and renamed into place at the end: an
error leaves no DATA behind. COLMAP's own log goes to DATA/colmap/ (database, sparse model).
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from shells.data.datasets import area_downscale
from shells.errors import InputError
from shells.files import write_image
from shells.progress import tqdm

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")


def list_images(folder: Path) -> list[Path]:
    if not folder.is_dir():
        raise InputError(f"{folder}: no such folder of photos; pass the folder that holds them")
    images = sorted(p for p in folder.iterdir() if p.suffix in IMAGE_EXTS and p.is_file())
    if len(images) < 3:
        raise InputError(f"{folder}: {len(images)} photos (.png/.jpg); structure from motion "
                         "needs at least 3 overlapping photos")
    return images


def _copy_images(images: list[Path], dst: Path, downscale: int) -> None:
    import imageio.v3 as iio

    dst.mkdir(parents=True)
    for p in tqdm(images, desc="copy photos", unit="img"):
        if downscale == 1:
            shutil.copy2(p, dst / p.name)
            continue
        try:
            img = iio.imread(p)
        except Exception as exc:
            raise InputError(f"{p}: cannot read the photo ({type(exc).__name__}); remove or "
                             "replace it")
        if img.ndim == 2:
            img = img[..., None]
        small = area_downscale(torch.from_numpy(img.astype(np.float64)), downscale)
        small = small.round().numpy().astype(img.dtype)
        write_image(dst / p.name, small if small.shape[-1] > 1 else small[..., 0])


def focus_point(c2w: np.ndarray) -> np.ndarray:  # [N, 4, 4] OpenCV -> [3]
    """The point nearest (least squares) to all optical axes (camera z axes)."""
    a = np.zeros((3, 3))
    b = np.zeros(3)
    for m in c2w:
        d = m[:3, 2] / np.linalg.norm(m[:3, 2])
        p = np.eye(3) - np.outer(d, d)  # projector onto the plane normal to the axis
        a += p
        b += p @ m[:3, 3]
    return np.linalg.lstsq(a, b, rcond=None)[0]


def _rotation_to_z(up: np.ndarray) -> np.ndarray:
    """Rotation [3, 3] taking the unit vector ``up`` to +z (Rodrigues)."""
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(up, z)
    c = float(up @ z)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k * (1.0 / (1.0 + c))


def normalise_poses(c2w: np.ndarray, points: np.ndarray,
                    ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Orient (mean up -> +z), centre (focus point) and scale (cameras in the unit cube) OpenCV
    c2w [N, 4, 4] and points [M, 3]; returns them and the transform used."""
    up = -c2w[:, :3, 1].mean(0)
    up = up / max(np.linalg.norm(up), 1e-12)
    rot = _rotation_to_z(up)
    centre = focus_point(c2w)
    out = c2w.copy()
    out[:, :3, :3] = rot @ c2w[:, :3, :3]
    out[:, :3, 3] = (c2w[:, :3, 3] - centre) @ rot.T
    scale = 1.0 / max(float(np.abs(out[:, :3, 3]).max()), 1e-12)
    out[:, :3, 3] *= scale
    pts = (points - centre) @ rot.T * scale
    return out, pts, {"rotation": rot.tolist(), "centre": centre.tolist(), "scale": scale}


def scene_box(points: np.ndarray, c2w: np.ndarray) -> list[list[float]]:
    """The sparse points' 2nd-98th percentile box, padded by 10 % per side (a cube around the
    cameras' focus when there are too few points)."""
    if len(points) < 20:
        return [[-0.5] * 3, [0.5] * 3]
    lo, hi = np.percentile(points, 2, axis=0), np.percentile(points, 98, axis=0)
    pad = 0.1 * (hi - lo).max()
    return [(lo - pad).tolist(), (hi + pad).tolist()]


def process_data(images_dir: str | Path, out: str | Path, downscale: int = 1,
                 matching: str = "exhaustive",
                 camera_model: str = "SIMPLE_RADIAL", max_error: float = 2.0,
                 guided_matching: bool = True) -> dict[str, Any]:
    """The whole command; returns a summary (registered images, intrinsics, timings)."""
    import time

    import pycolmap

    images_dir, out = Path(images_dir), Path(out)
    if out.exists():
        raise InputError(f"{out}: already exists; choose another --out or delete it")
    if downscale < 1:
        raise InputError(f"--downscale {downscale}: must be at least 1")
    if matching not in ("exhaustive", "sequential"):
        raise InputError(f"--matching {matching}: expected exhaustive or sequential")
    if not max_error > 0:
        raise InputError(f"--max-error {max_error}: must be a positive number of pixels")
    photos = list_images(images_dir)
    out.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}."))
    try:
        t0 = time.perf_counter()
        _copy_images(photos, stage / "images", downscale)
        colmap = stage / "colmap"
        (colmap / "sparse").mkdir(parents=True)
        db = colmap / "database.db"
        steps = tqdm(total=3, desc="COLMAP", unit="step")
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = camera_model
        # one thread everywhere and a fixed seed: the same photos give the same poses
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = 1
        matcher = pycolmap.FeatureMatchingOptions()
        matcher.num_threads = 1
        matcher.guided_matching = guided_matching
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.max_error = max_error
        pycolmap.set_random_seed(0)
        steps.set_postfix_str("SIFT features")
        pycolmap.extract_features(db, stage / "images", camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction,
                                  device=pycolmap.Device.cpu)
        steps.update(1)
        steps.set_postfix_str(f"{matching} matching")
        match = (pycolmap.match_exhaustive if matching == "exhaustive"
                 else pycolmap.match_sequential)
        match(db, matching_options=matcher, verification_options=verification,
              device=pycolmap.Device.cpu)
        steps.update(1)
        steps.set_postfix_str("incremental mapping")
        mapper = pycolmap.IncrementalPipelineOptions()
        mapper.num_threads, mapper.random_seed = 1, 0
        mapper.mapper.init_max_error = max_error
        mapper.mapper.abs_pose_max_error = 3.0 * max_error
        mapper.mapper.filter_max_reproj_error = max_error
        mapper.triangulation.merge_max_reproj_error = max_error
        mapper.triangulation.complete_max_reproj_error = max_error
        recs = pycolmap.incremental_mapping(db, stage / "images", colmap / "sparse",
                                            options=mapper)
        steps.update(1)
        steps.close()
        if not recs:
            raise InputError(f"{images_dir}: COLMAP registered no images; take more photos with "
                             "overlap (each scene point seen from several nearby views)")
        rec = max(recs.values(), key=lambda r: r.num_reg_images())
        n_reg = rec.num_reg_images()
        if n_reg < max(3, (len(photos) + 1) // 2):
            raise InputError(f"{images_dir}: only {n_reg} of {len(photos)} photos registered; "
                             "take more photos with overlap (or --matching exhaustive)")
        summary = _write_transforms(rec, stage, len(photos))
        summary["seconds"] = time.perf_counter() - t0
        (stage / "process_data.json").write_text(json.dumps(summary, indent=1) + "\n")
        os.replace(stage, out)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    return summary


def _write_transforms(rec: Any, stage: Path, n_photos: int) -> dict[str, Any]:
    cams = list(rec.cameras.values())
    if len(cams) != 1:
        raise InputError(f"COLMAP made {len(cams)} cameras; the photos must share one camera")
    cam = cams[0]
    names, c2w = [], []
    for image in sorted(rec.images.values(), key=lambda im: im.name):
        if not image.has_pose:
            continue
        w2c = np.eye(4)
        w2c[:3, :4] = image.cam_from_world().matrix()
        names.append(image.name)
        c2w.append(np.linalg.inv(w2c))
    c2w_cv = np.stack(c2w)
    points = np.array([p.xyz for p in rec.points3D.values()]) if rec.points3D else np.zeros((0, 3))
    c2w_cv, points, transform = normalise_poses(c2w_cv, points)
    c2w_gl = c2w_cv * np.array([1.0, -1.0, -1.0, 1.0])  # OpenCV -> OpenGL camera axes
    p = list(cam.params)
    model = cam.model.name
    intr: dict[str, Any] = {"w": int(cam.width), "h": int(cam.height), "camera_model": model}
    if model == "OPENCV":
        intr.update(fl_x=p[0], fl_y=p[1], cx=p[2], cy=p[3], k1=p[4], k2=p[5], p1=p[6], p2=p[7])
    elif model == "PINHOLE":
        intr.update(fl_x=p[0], fl_y=p[1], cx=p[2], cy=p[3])
    elif model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        intr.update(fl_x=p[0], fl_y=p[0], cx=p[1], cy=p[2])
        if model != "SIMPLE_PINHOLE":
            intr.update(k1=p[3], k2=p[4] if model == "RADIAL" else 0.0)
    else:
        raise InputError(f"camera model {model}: use OPENCV, PINHOLE or SIMPLE_RADIAL")
    doc = {**intr, "aabb_scale": 1, "aabb": scene_box(points, c2w_cv),
           "frames": [{"file_path": f"images/{n}", "transform_matrix": m.tolist()}
                      for n, m in zip(names, c2w_gl)],
           "colmap_transform": transform}
    (stage / "transforms.json").write_text(json.dumps(doc, indent=1) + "\n")
    return {"registered": len(names), "photos": n_photos, "camera_model": model,
            "intrinsics": {k: v for k, v in intr.items() if k != "camera_model"},
            "points": int(len(points))}
