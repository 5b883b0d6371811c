"""Run-level baking, the offline web export and the client-side viewer of a baked asset.

    bake_run    RUN -> RUN/baked/{layers.glb, asset.json} (`shells.bake.fit`), all or nothing
    export_web  RUN/baked -> a folder that works offline: index.html and viewer.js (shells/
                webviewer/; stock.html: the file in a stock three.js scene, for checking it),
                three.js and its loader and controls (the npm package, copied),
                layers.glb, asset.json, cameras.json (the test views, for comparisons)
    serve       a static HTTP server on an export (shells-view RUN --baked): the browser draws
                the asset; nothing is rendered on the server
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from shells.errors import InputError
from shells.files import commit_files, staged_dir, write_json
from shells.run import (RunDir, load_field, load_shells, read_run, require_bounded,
                        shell_meshes)

WEBVIEWER = Path(__file__).resolve().parent.parent / "webviewer"
# the files of the npm package `three` an export needs, by their place in the package
THREE_FILES = ("build/three.module.js", "build/three.core.js",
               "examples/jsm/loaders/GLTFLoader.js", "examples/jsm/utils/BufferGeometryUtils.js",
               "examples/jsm/utils/SkeletonUtils.js", "examples/jsm/controls/OrbitControls.js",
               "LICENSE")


def bake_run(run_dir: str | Path, levels: tuple[float, ...] | None = None,
             resolution: int | None = None, size_mb: float | None = None,
             steps: int | None = None, teacher_views: int | None = None,
             tolerance_px: float | None = None, texel_px: float | None = None,
             progress: bool = False) -> dict[str, Any]:
    """Bake RUN's stage-2 field into RUN/baked (module docstring); returns asset.json's record."""
    from shells.bake.fit import BakeConfig, bake
    from shells.bake.format import write_asset
    from shells.data.camera_paths import scene_frame
    from shells.data.datasets import load_dataset

    run = RunDir(run_dir)
    meta = read_run(run)
    require_bounded(run, "shells-bake", "bakes the band of one object in its box")
    if not run.checkpoint("stage2").is_file():
        raise InputError(f"{run.checkpoint('stage2')}: no stage-2 checkpoint; run "
                         f"shells-finetune {run.root} first")
    cfg = BakeConfig()
    for name, value in (("levels", levels), ("size_mb", size_mb), ("steps", steps),
                        ("teacher_views", teacher_views), ("tolerance_px", tolerance_px),
                        ("texel_px", texel_px)):
        if value is not None:
            setattr(cfg, name, tuple(value) if name == "levels" else value)
    if teacher_views is not None and teacher_views < 0:
        raise InputError(f"--teacher-views {teacher_views}: must be >= 0")
    if cfg.tolerance_px < 0 or not cfg.texel_px > 0:
        raise InputError(f"--tolerance {cfg.tolerance_px} / --texel {cfg.texel_px}: need a "
                         "tolerance >= 0 and a texel size > 0 (training-pixel footprints)")
    if cfg.size_mb <= 0 or cfg.steps < 1 or not cfg.levels or 0.0 not in cfg.levels:
        raise InputError(f"--size-mb {cfg.size_mb} / --steps {cfg.steps} / --levels "
                         f"{list(cfg.levels)}: need a positive size, at least one step and "
                         "levels that include 0 (the surface)")
    outer, inner = shell_meshes(run)
    field, fcfg = load_field(run.root, stage="stage2")
    bg = tuple(fcfg.data.background)
    data = load_dataset(meta["data"], "train", downscale=int(meta["downscale"]), background=bg)
    aabb = field.aabb.cpu().numpy().astype(np.float64)
    footprint = pixel_footprint(data.cameras, aabb)
    cells = float(np.max(aabb[1] - aabb[0])) / footprint * cfg.cells_per_pixel
    res = int(resolution or min(fcfg.shell.resolution, max(16, math.ceil(cells))))
    if res < 16:
        raise InputError(f"--resolution {res}: must be at least 16")
    h = float((aabb[1] - aabb[0]).max()) / (res - 1)
    band = max(fcfg.shell.dilate_zeta, fcfg.shell.erode_zeta) + 2.0 * h
    up = tuple(float(x) for x in scene_frame(data.cameras, data.aabb)[1])
    views = [(data.cameras, data.images)]
    n_teacher = (cfg.teacher_per_view * len(data.cameras) if cfg.teacher_views is None
                 else int(cfg.teacher_views))
    if n_teacher > 0:
        views.append(render_teacher(run, field, fcfg, data, n_teacher, progress))
    asset = bake(field, aabb, outer, inner, views, bg, up, res, band, footprint, cfg,
                 fcfg.render.variant, progress)
    asset.meta["source"] = {"run": str(run.root), "stage": "stage2",
                            "data": str(meta["data"]), "downscale": int(meta["downscale"])}
    with staged_dir(run.baked, "shells-bake") as tmp:
        write_asset(asset, tmp)
        record = json.loads((tmp / "asset.json").read_text())
        commit_files(tmp, run.baked, last="asset.json")
    return record


def bake_summary(record: dict[str, Any]) -> str:
    """One line of asset.json's record: layers, triangles, atlas, size, fit PSNR, time."""
    fit, atlas = record["fit"], record["atlas"]
    return (f"baked {len(record['layers'])} layers, {fit['triangles']} triangles, atlas "
            f"{atlas['width']}x{atlas['height']}, {record['size_bytes'] / 1e6:.1f} MB, training "
            f"PSNR {fit['train_psnr_last']:.2f} dB, {fit['seconds']:.0f} s")


def pixel_footprint(cams: Any, aabb: np.ndarray) -> float:
    """A training pixel's size at the scene centre (the median camera's): the unit of the
    bake's grid, texels and decimation tolerance (finer than the photos' pixels is seen by too
    few rays to be fitted, much coarser blurs the texture)."""
    from shells.data.camera_paths import scene_frame

    _, _, radius, _ = scene_frame(cams, aabb)
    return float(radius / float(torch.median(cams.fx)))


def turned_cameras(cams: Any, aabb: Any, n: int, seed: int = 0) -> Any:
    """``n`` novel cameras: training cameras (cycled) turned about the capture's up axis through
    the scene centre by random angles, so they keep the training distances and elevations."""
    from shells.data.camera_paths import scene_frame

    centre, up, _, _ = scene_frame(cams, aabb)
    rng = np.random.default_rng(seed)
    k = np.array([[0, -up[2], up[1]], [up[2], 0, -up[0]], [-up[1], up[0], 0]])
    idx = np.arange(n) % len(cams)
    c2w = cams.c2w[idx].double().cpu().numpy().copy()
    for j, angle in enumerate(rng.uniform(-np.pi, np.pi, n)):
        R = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)  # Rodrigues
        c2w[j, :3, :3] = R @ c2w[j, :3, :3]
        c2w[j, :3, 3] = centre + R @ (c2w[j, :3, 3] - centre)
    out = cams[torch.from_numpy(idx)]
    out.c2w = torch.from_numpy(c2w).to(cams.c2w)
    return out


def render_teacher(run: RunDir, field: Any, fcfg: Any, data: Any, n: int,
                  progress: bool = False) -> tuple[Any, torch.Tensor]:
    """The band render of the stage-2 field (one ray per pixel) from ``n`` `turned_cameras`:
    (cameras, images [n, H, W, 3])."""
    from shells.device import mitsuba_variant
    from shells.fields.drjit_field import DrJitField
    from shells.progress import tqdm
    from shells.render.views import render_view

    cams = turned_cameras(data.cameras, data.aabb, n)
    rc = dataclasses.replace(fcfg.render, spp=1, refine_levels=0)
    scene = load_shells(run, mitsuba_variant(rc.variant))
    dj = DrJitField(field)
    bg = tuple(fcfg.data.background)
    images = torch.stack([render_view(dj, cams, i, rc, "band", scene, data.aabb, bg)[0]
                          for i in tqdm(range(len(cams)), desc="teacher views",
                                        disable=not progress)])
    return cams, images


def three_dir(explicit: str | Path | None = None) -> Path:
    """The npm package `three`: ``explicit``, $SHELLS_THREE, or web/node_modules/three of the
    source tree (``npm ci --prefix web``)."""
    candidates = [Path(explicit)] if explicit else []
    if os.environ.get("SHELLS_THREE"):
        candidates.append(Path(os.environ["SHELLS_THREE"]))
    candidates.append(Path(__file__).resolve().parents[2] / "web" / "node_modules" / "three")
    for c in candidates:
        if all((c / f).is_file() for f in THREE_FILES):
            return c
    raise InputError(f"three.js not found (looked in {', '.join(map(str, candidates))}); run "
                     "`npm ci --prefix web` in the source tree, or pass --three DIR (the npm "
                     "package's folder)")


def export_web(run_dir: str | Path, out: str | Path, three: str | Path | None = None,
               split: str = "test") -> dict[str, Any]:
    """A self-contained, offline viewer folder of RUN/baked at ``out`` (module docstring)."""
    from shells.bake.format import read_asset, up_matrix
    from shells.data.datasets import load_dataset

    run = RunDir(run_dir)
    meta = read_run(run)
    asset_json = run.baked / "asset.json"
    if not asset_json.is_file():
        raise InputError(f"{asset_json}: no baked asset; run shells-bake {run.root} first")
    asset = read_asset(run.baked)  # checks the files
    src = three_dir(three)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder; pick another --web folder")
    data = load_dataset(meta["data"], split, downscale=int(meta["downscale"]),
                        background=asset.background)
    cams = data.cameras
    with staged_dir(out, "shells-export") as tmp:
        for f in ("index.html", "viewer.js", "pixels.js", "stock.html", "stock.js"):
            shutil.copyfile(WEBVIEWER / f, tmp / f)
        lib = tmp / "lib"
        for f in THREE_FILES:
            dest = lib / ("three-LICENSE" if f == "LICENSE" else
                          f.replace("build/", "").replace("examples/jsm/", "jsm/"))
            dest.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src / f, dest)
        shutil.copyfile(run.baked / "layers.glb", tmp / "layers.glb")
        shutil.copyfile(asset_json, tmp / "asset.json")
        aabb = np.asarray(data.aabb, np.float64)
        write_json(tmp / "cameras.json", {
            "split": split, "width": cams.width, "height": cams.height,
            "world_to_gltf": up_matrix(asset.up).tolist(),
            "centre": ((aabb[0] + aabb[1]) / 2).tolist(),
            "views": [{"c2w_opencv": cams.c2w[i].tolist(), "fx": float(cams.fx[i]),
                       "fy": float(cams.fy[i]), "cx": float(cams.cx[i]),
                       "cy": float(cams.cy[i])} for i in range(len(cams))]})
        if (out / "lib").is_dir():  # an earlier export's: a folder is not replaced by a move
            shutil.rmtree(out / "lib")
        commit_files(tmp, out, last="index.html")
    return {"out": str(out), "files": sorted(str(p.relative_to(out)) for p in out.rglob("*")
                                             if p.is_file())}


def static_server(folder: str | Path, host: str = "127.0.0.1", port: int = 8080) -> Any:
    """A threading HTTP server of the files of ``folder`` (not started: call serve_forever);
    quiet, and a port in use is the usual one-line error."""
    import functools
    import http.server

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args: Any) -> None:
            pass

    handler = functools.partial(Quiet, directory=str(folder))
    http.server.ThreadingHTTPServer.allow_reuse_address = True
    try:
        return http.server.ThreadingHTTPServer((host, port), handler)
    except OSError as exc:
        raise InputError(f"--port {port}: cannot listen on {host}:{port} ({exc.strerror}); "
                         "pick another port") from None


def serve(folder: str | Path, host: str = "127.0.0.1", port: int = 8080,
          ready: Any = None) -> None:
    """Serve ``folder`` over HTTP until interrupted (``ready(url)`` once listening)."""
    server = static_server(folder, host, port)
    url = f"http://{host}:{server.server_address[1]}/"
    (ready or (lambda u: print(f"baked viewer: {u}", flush=True)))(url)
    try:
        server.serve_forever(poll_interval=0.2)
    finally:
        server.server_close()


def view_baked(run_dir: str | Path, out: str | Path | None = None, host: str = "127.0.0.1",
               port: int = 8080, three: str | Path | None = None) -> None:
    """shells-view RUN --baked: export RUN/baked to ``out`` (default RUN/baked/web) and serve it."""
    run = RunDir(run_dir)
    folder = Path(out) if out else run.baked / "web"
    t0 = time.perf_counter()
    export_web(run.root, folder, three)
    print(f"exported {folder} in {time.perf_counter() - t0:.1f} s", flush=True)
    serve(folder, host, port)
