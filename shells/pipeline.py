"""Run-level steps: shell extraction and rendering of a trained run, and the whole toy pipeline
(shells-demo). The library functions below them stay independent of the run directory; these
read and write RUN through `shells.run`.

`render_run` (shells-render RUN) reads RUN/run.json (data set path, downscale), the chosen
checkpoint (stage 2 when present), RUN/shells/{outer,inner}.ply (band mode), renders every view
of the split with the Dr.Jit field (`shells.render.views.render_views`) and writes into OUT
(default RUN/render-MODE) the PNGs and metrics.json (psnr, ssim, samples/pixel, ms/frame,
resolution, mode, device, the stage loaded, protocol). Everything is rendered into a hidden
temporary folder beside OUT and moved in at the end, metrics.json last, so a failure leaves no
partial output.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from shells.config import override_config
from shells.train.health import CAUSES, SOLID_SHARE, degenerate_grid
from shells.errors import WRITE_ERRNOS, InputError, Interrupted
from shells.files import commit_files, staged_dir, write_image, write_json
from shells.metrics import PROTOCOL
from shells.run import (RunDir, field_from_checkpoint, load_field, load_shells, read_checkpoint,
                        read_run, resolve_stage, shells_source)


def extract_run(run_dir: str | Path, resolution: int | None = None,
                fixed_width: float | None = None,
                config: str | Path | None = None, progress: bool = False) -> dict[str, Any]:
    """Sample the stage-1 field on a grid, extract M+ and M-, write RUN/shells/; returns stats.

    ``fixed_width`` w gives the fixed band {|f| <= w} instead of the adaptive one (ablation);
    ``config``: a JSON file with a ``shell`` section overriding the run's shell settings;
    ``progress``: bars over the grid sampling and the evolutions.
    """
    run = RunDir(run_dir)
    try:
        return _extract(run, resolution, fixed_width, config, progress)
    except KeyboardInterrupt:
        raise Interrupted(f"shells-extract interrupted; {run.shells} is as it was before; run "
                          "it again", status=130) from None
    except OSError as exc:
        named = _named(exc, run.shells)
        if named is exc:
            raise
        raise named from exc


def _extract(run: RunDir, resolution: int | None, fixed_width: float | None,
             config: str | Path | None, progress: bool = False) -> dict[str, Any]:
    from shells.levelset.extract import extract_shells, write_shells
    from shells.levelset.grid import sample_grid_banded

    ckpt = read_checkpoint(run, "stage1")
    field, cfg = field_from_checkpoint(ckpt, str(run.checkpoint("stage1")))
    source = shells_source(run, ckpt["step"])
    del ckpt
    override_config(cfg, config, ("shell",), "shells-extract")
    if resolution is not None:
        cfg.update({"shell": {"resolution": resolution}}, "--resolution")
    sc = cfg.shell

    def fn(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:  # field-space grid points
        g = field.geometry_field(x)
        return g["sdf"], g["s"]

    t0 = time.perf_counter()
    # exact where the evolution and the meshes look (|f| < zeta or the fixed width, + 2 h),
    # coarse elsewhere
    h = float((field.aabb[1] - field.aabb[0]).max()) / (sc.resolution - 1)
    band = max(sc.dilate_zeta, sc.erode_zeta, fixed_width or 0.0) + 2.0 * h
    f, s, _, exact = sample_grid_banded(fn, field.aabb.cpu().numpy(), sc.resolution, band,
                                        sc.chunk, progress=progress)
    t_grid = time.perf_counter() - t0
    sim = field.similarity
    _refuse_degenerate(run, f, field)
    shells = extract_shells(f, s, field.aabb.cpu().numpy(), sc, fixed_width=fixed_width,
                            roi=None if sim is None else (sim.centre, sim.radius),
                            progress=progress)
    box = (field.aabb[1] - field.aabb[0]).double().prod().item()
    if sim is None and shells.stats["volume_outer"] > SOLID_SHARE * box:
        raise InputError(f"{run.checkpoint('stage1')}: the outer shell encloses "
                         f"{shells.stats['volume_outer'] / box:.0%} of the scene box: a "
                         f"degenerate field, not extracted; {CAUSES}")
    if field.similarity is not None:  # extracted in field space: the meshes back to the world
        _unbounded_to_world(shells, field)
    shells.stats["timings_s"]["sample_grid"] = t_grid
    shells.stats["grid_exact_fraction"] = exact
    shells.stats["timings_s"]["total"] = time.perf_counter() - t0
    shells.stats["source"] = source  # which run and stage-1 step (shells.run.check_shells)
    write_shells(shells, run.shells)
    return shells.stats


def _refuse_degenerate(run: RunDir, f: Any, field: Any) -> None:
    """A one-line error (nothing written) when the grid of SDF samples ``f`` [R, R, R] is
    degenerate (`shells.train.health.degenerate_grid`); an unbounded field is judged in the cube
    around its ball of interest (the far solid fills the corners of its box)."""
    f = torch.as_tensor(np.asarray(f))
    if field.similarity is not None:
        r = f.shape[0]
        f = f[r // 4:r - r // 4, r // 4:r - r // 4, r // 4:r - r // 4]
    why = degenerate_grid(f)
    if why is not None:
        raise InputError(f"{run.checkpoint('stage1')}: {why}: a degenerate field, not "
                         f"extracted; {CAUSES}")


def _unbounded_to_world(shells: Any, field: Any) -> None:
    """The shells of an unbounded field, extracted in field space, mapped to the world
    (`shells.levelset.unbounded.to_world`); the report goes into the stats."""
    from shells.levelset.unbounded import to_world

    t0 = time.perf_counter()
    h = float(np.max(shells.stats["spacing"]))
    report = {}
    for name in ("outer", "inner"):
        mesh, report[name] = to_world(getattr(shells, name), field.similarity, h,
                                      far=field.cfg.far_radius)
        setattr(shells, name, mesh)
        shells.stats[f"{name}_triangles"] = int(len(mesh.faces))
        shells.stats[f"{name}_vertices"] = int(len(mesh.vertices))
    sim = field.similarity
    shells.stats["unbounded"] = {"centre": list(sim.centre), "radius": sim.radius,
                                 "far_radius": field.cfg.far_radius, **report,
                                 "note": "grids, volumes and band widths are in field space"}
    shells.stats["timings_s"]["to_world"] = time.perf_counter() - t0


def _named(exc: OSError, out: Path) -> OSError:
    """A refused write without a file name (a full disk) named by the output it was for."""
    if exc.filename is None and exc.errno in WRITE_ERRNOS:
        return OSError(exc.errno, exc.strerror, str(out))
    return exc


def check_run(run: RunDir, mode: str) -> dict[str, Any]:
    """Fail early, before anything is loaded or written; returns run.json."""
    from shells.render.frame import MODES

    if mode not in MODES:
        raise InputError(f"--mode {mode}: expected one of {MODES}")
    meta = read_run(run)
    if not run.checkpoint("stage1").is_file() and not run.checkpoint("stage2").is_file():
        raise InputError(f"{run.checkpoint()}: no checkpoint; run shells-train first")
    if mode == "band" and not run.outer.is_file():
        raise InputError(f"{run.outer}: no outer shell; run shells-extract first")
    if mode == "baked" and not (run.baked / "asset.json").is_file():
        raise InputError(f"{run.baked / 'asset.json'}: no baked asset; run shells-bake "
                         f"{run.root} first")
    return meta


def render_out(run: RunDir, mode: str, path: str | None, out: str | Path | None) -> Path:
    """The folder a render writes: ``out``, else RUN/render-MODE (a split) or RUN/path-NAME."""
    if out is not None:
        return Path(out)
    if path:
        return run.root / f"path-{path if path in ('orbit', 'spiral', 'interpolate') else Path(path).stem}"
    return run.render_dir(mode)


def render_run(run_dir: str | Path, split: str = "test", mode: str = "band",
               width: int | None = None, height: int | None = None,
               out: str | Path | None = None, progress: bool = True,
               stage: str = "latest", config: str | Path | None = None,
               spp: int | None = None, path: str | None = None, frames: int = 120,
               fps: float | None = None,
               shard: tuple[int, int] | None = None,
               refine: int | None = None, shells: str = "fine") -> dict[str, Any]:
    """Render every view of ``split`` (or of a camera ``path``) and write images +
    metrics.json; returns the metrics.

    ``stage`` picks the checkpoint: 'latest' (stage 2 when present), 'stage1' or 'stage2';
    ``config``: a JSON file with a ``render`` section overriding the run's render settings;
    ``spp``: rays per pixel (overrides both); ``path``: orbit | spiral | interpolate | a
    nerfstudio camera_path.json (`shells.data.camera_paths`), ``frames`` long, written as PNGs and
    video.mp4 at ``fps`` (default: the file's, else 30); ``refine`` L: image-space adaptive
    refinement in band mode (`shells.render.refine`, render.refine_levels). Under torchrun,
    rank r of N renders views r, r + N, ... and rank 0 writes metrics.json and the video. ``shard`` (K, N): the
    same share for an independent process (no torchrun); see `_render_shard`. ``shells``:
    'fine' (RUN/shells) or 'lod' (RUN/shells/lod, shells-lod) for band mode.
    """
    from shells import distributed
    from shells.data.camera_paths import camera_path
    from shells.data.datasets import load_dataset
    from shells.device import mitsuba_variant
    from shells.fields.drjit_field import DrJitField

    run = RunDir(run_dir)
    meta = check_run(run, mode)
    loaded = resolve_stage(run, stage)
    field, cfg = load_field(run.root, device="cpu", stage=loaded)
    override_config(cfg, config, ("render",), "shells-render")
    if spp is not None:
        cfg.update({"render": {"spp": spp}}, "--spp")
    if refine is not None:
        cfg.update({"render": {"refine_levels": refine}}, "--refine")
    if cfg.render.refine_levels > 0 and (mode != "band" or cfg.render.spp != 1):
        raise InputError(f"--refine {cfg.render.refine_levels}: refinement is for band mode "
                         f"with one ray per pixel (here --mode {mode}, spp {cfg.render.spp}); "
                         "use --mode band --spp 1, or --refine 0")
    if fps is not None and not fps > 0:
        raise InputError(f"--fps {fps}: must be > 0 frames per second")
    rc, bg = cfg.render, tuple(cfg.data.background)
    variant = mitsuba_variant(rc.variant)
    scene = load_shells(run, variant, shells) if mode == "band" else None
    if mode == "baked":
        from shells.bake.format import read_asset
        from shells.bake.render import LayerScene

        scene = LayerScene.of(read_asset(run.baked), variant)
        if spp is None:  # as the asset was fitted (and as the browser's MSAA draws it)
            cfg.update({"render": {"spp": int(scene.asset.meta.get("fit", {}).get("spp", 1))}},
                       "the baked asset")
            rc = cfg.render
    data = load_dataset(meta["data"], "train" if path else split,
                        downscale=int(meta["downscale"]), background=bg)
    if path:
        cams, file_fps = camera_path(path, data.cameras, data.aabb, frames, width, height)
        fps = fps or file_fps or 30.0
        images, same_size = None, False
    else:
        cams = data.cameras.resized(width, height)
        same_size = (cams.width, cams.height) == (data.cameras.width, data.cameras.height)
        images = data.images if same_size else None
    dj = DrJitField(field)
    out = render_out(run, mode, path, out)
    extra = {
        "split": None if path else split, "path": path, "variant": variant,
        "stage": "baked" if mode == "baked" else loaded, "out": str(out),
        "shells": shells if mode == "band" else None,
        "device": "cuda" if variant.startswith("cuda") else "cpu",
        "background": list(bg), "data": str(meta["data"]),
        "downscale": int(meta["downscale"]),
        "protocol": PROTOCOL + ("" if same_size else
                                "; no reference images at this resolution or camera path: "
                                "no PSNR / SSIM"),
        "render_config": dataclasses.asdict(rc),
        **({"fps": fps} if path else {}),
        "stage1_health": _stage1_health(run),
    }
    if shard is not None:
        if distributed.launched_world() > 1:
            raise InputError("--shard K/N is for independent processes; under torchrun the "
                             "ranks share the frames by themselves")
        return _render_shard(dj, cams, images, rc, mode, scene, data.aabb, progress, bg, out,
                             shard, extra)
    try:
        return _render_all(dj, cams, images, rc, mode, scene, data.aabb, progress, bg, out,
                           extra)
    except KeyboardInterrupt:
        raise Interrupted(f"shells-render interrupted; {out} is as it was before; run it again",
                          status=130) from None
    except OSError as exc:
        named = _named(exc, out)
        if named is exc:
            raise
        raise named from exc


def _stage1_health(run: RunDir) -> dict[str, Any] | None:
    """The stage-1 summary's health record (`shells.train.health.Stage1Health`), None if absent."""
    import json

    try:
        return json.loads(run.summary("stage1").read_text()).get("health")
    except (OSError, ValueError):
        return None


def _render_all(dj: Any, cams: Any, images: Any, rc: Any, mode: str, scene: Any, aabb: Any,
                progress: bool, bg: tuple[float, float, float], out: Path,
                extra: dict[str, Any]) -> dict[str, Any]:
    """All frames by this process (or its share under torchrun) into a hidden folder beside
    OUT, moved into OUT when all are done."""
    from shells import distributed
    from shells.render.views import render_views

    w = distributed.world()  # the CPU group (gloo) coordinates; each rank renders on its own
    tmp = None
    if w.main:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}."))
    tmp = Path(distributed.broadcast_object(str(tmp) if tmp else None))
    try:
        metrics = render_views(dj, cams, images, rc, mode, scene, aabb, tmp, progress, bg,
                               world=w)
        distributed.barrier()  # every rank's frames are in tmp
        metrics.update(extra)
        if w.main:
            _finish(tmp, out, metrics)
        distributed.barrier()
    finally:
        if w.main:
            shutil.rmtree(tmp, ignore_errors=True)
    return metrics


def _finish(tmp: Path, out: Path, metrics: dict[str, Any]) -> None:
    """Video (for a path) and metrics.json into tmp, then everything moved into out."""
    from shells.render.views import write_video

    if metrics.get("path"):
        write_video(sorted(tmp.glob("r_*.png")), tmp / "video.mp4", metrics["fps"])
    write_json(tmp / "metrics.json", metrics)
    commit_files(tmp, out, last="metrics.json")  # metrics.json last: it marks a complete render


def _render_shard(field: Any, cams: Any, images: Any, rc: Any, mode: str, scene: Any,
                  aabb: Any, progress: bool, bg: tuple[float, float, float], out: Path,
                  shard: tuple[int, int], extra: dict[str, Any]) -> dict[str, Any]:
    """Frames K, K + N, ... of an independent process (`shells-render --shard K/N`).

    Each shard renders into its own folder under the hidden OUT/../.OUT.shards/, and marks it
    done by renaming it to shard-K-of-N; the process that finds all N shards done merges them
    (heatmaps on one scale, metrics.json, the video) into OUT: the same files a single process
    writes. Until then OUT does not exist. Returns the merged metrics, or this shard's count.
    """
    import numpy as np

    from shells import distributed
    from shells.files import read_json
    from shells.render.views import render_frames, summarise

    k, n = shard
    stage = out.parent / f".{out.name}.shards"
    stage.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=stage, prefix=f".shard-{k}-"))
    try:
        views, warm, spps = render_frames(field, cams, images, rc, mode, scene, aabb, tmp,
                                          progress, bg, distributed.World(rank=k, size=n))
        np.savez_compressed(tmp / "spp.npz", **{str(i): s.numpy() for i, s in spps.items()})
        write_json(tmp / "record.json", {"views": views, "warm": warm})
        done = stage / f"shard-{k}-of-{n}"
        shutil.rmtree(done, ignore_errors=True)  # a re-run of this shard replaces it
        os.replace(tmp, done)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    parts = [stage / f"shard-{j}-of-{n}" for j in range(n)]
    if not all(p.is_dir() for p in parts):
        return {"shard": [k, n], "views": len(views), "complete": False, "out": str(out)}
    try:  # one merger: the first process to create the lock
        os.close(os.open(stage / "merge.lock", os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        return {"shard": [k, n], "views": len(views), "complete": False, "out": str(out)}
    merged = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}."))
    try:
        views, warm, spps = [], [], {}
        for p in parts:
            rec = read_json(p / "record.json", "shard record")
            views += rec["views"]
            warm += rec["warm"]
            with np.load(p / "spp.npz") as z:
                spps.update({int(i): torch.from_numpy(z[i]) for i in z.files})
            for f in p.glob("r_*.png"):
                shutil.copy2(f, merged / f.name)  # the shards stay until the merge is done
        metrics = summarise(views, warm, spps, merged, cams, mode, n,
                            cams.height * cams.width * rc.spp)
        metrics.update(extra)
        _finish(merged, out, metrics)
        shutil.rmtree(stage, ignore_errors=True)
    except BaseException:
        (stage / "merge.lock").unlink(missing_ok=True)  # a later shard run may merge again
        raise
    finally:
        shutil.rmtree(merged, ignore_errors=True)
    return {**metrics, "complete": True}


def demo(out: str | Path, scene: str = "core-fuzz", res: int = 64, views: int = 32,
         iters: int | None = None, finetune_iters: int | None = None) -> list[dict[str, Any]]:
    """Toy scene -> stage 1 -> shells -> stage 2 -> renders; returns the rows of the table."""
    from scenes import make_scene
    from shells.presets import toy_config
    from shells.train.stage2 import finetune
    from shells.train.stage1 import train

    out = Path(out)
    data, run = out / "data", out / "run"
    if RunDir(run).checkpoint().exists():
        raise InputError(f"{run}: a previous demo run is there; choose another --out or delete it")
    print(f"[1/5] rendering the toy scene '{scene}' -> {data}")
    make_scene(scene, data, res=res, views=views)
    cfg = toy_config()
    print("[2/5] stage 1: training the field (full-ray NeuS)")
    train(data, run, cfg, torch.device("cpu"), iters=iters)
    print("[3/5] extracting the shells")
    stats = extract_run(run)
    print("[4/5] stage 2: fine-tuning inside the band")
    finetune(run, iters=finetune_iters, device="cpu")
    print("[5/5] rendering the test views")
    rows = [render_run(run, mode="full", stage="stage1", out=run / "render-full-stage1"),
            render_run(run, mode="band", stage="stage1", out=run / "render-band-stage1"),
            render_run(run, mode="band", stage="stage2", out=run / "render-band")]
    names = ["full ray, stage 1", "band, stage 1", "band, stage 2 (fine-tuned)"]
    print()
    print(f"{'renderer':<28} {'PSNR':>7} {'SSIM':>7} {'samples/px':>11} {'ms/frame':>9}")
    for name, m in zip(names, rows):
        print(f"{name:<28} {m['psnr']:7.2f} {m['ssim']:7.4f} {m['samples_per_pixel']:11.2f} "
              f"{m['ms_per_frame']:9.1f}")
    print(f"\nshells: {RunDir(run).outer}, {RunDir(run).inner} "
          f"({stats['outer_triangles']} / {stats['inner_triangles']} triangles)")
    print(f"images: {run / 'render-band'} (band), {run / 'render-full-stage1'} (full)")
    return [{"renderer": n, **m} for n, m in zip(names, rows)]


# ---------------------------------------------------------------------------------------------
# Cage and animation (paper §5)
# ---------------------------------------------------------------------------------------------

def cage_run(run_dir: str | Path, margin: float | None = None, resolution: int = 48,
             edge_length: float = 0.06, epsilon: float = 1e-3,
             threads: int = 0, shells: str = "fine") -> dict[str, Any]:
    """Build the tetrahedral cage of RUN/shells (``shells`` 'lod': of RUN/shells/lod;
    `shells.levelset.cage.build_cage`) and write {cage.npz, cage.vtu, cage.json} into
    RUN/cage (RUN/cage/lod); returns the statistics."""
    from shells.levelset.cage import build_cage, write_cage
    from shells.run import require_bounded, run_id, shell_meshes, shells_digest

    run = RunDir(run_dir)
    read_run(run)
    require_bounded(run, "shells-cage", "tetrahedralizes the space around one object")
    outer, inner = shell_meshes(run, shells)
    cage, emb = build_cage(outer, inner, margin, resolution, edge_length, epsilon, threads)
    extra = {"run_id": run_id(run), "shells": shells, "shells_sha1": shells_digest(run, shells)}
    out = run.cage_dir(shells)
    with staged_dir(out, "shells-cage") as tmp:
        write_cage(tmp, cage, emb, extra)
        commit_files(tmp, out, last="cage.npz")  # the file the other commands read
    return {**cage.stats, **extra, "out": str(out)}


def cage_poses(motion: str, rest: np.ndarray, tets: np.ndarray, frames: int, fps: float,
               up: np.ndarray, progress: bool = True
               ) -> tuple[np.ndarray, dict[str, Any], float]:
    """Cage positions [frames, n, 3] of a motion name or file, what made them, and the fps."""
    from shells.deform import MOTION_HELP
    from shells.deform.fem import SIMULATED
    from shells.deform.motions import ANALYTIC, AssetFrame, analytic_poses, read_motion_file

    if motion in ANALYTIC:
        return (analytic_poses(motion, rest, frames, AssetFrame.of(rest, up)),
                {"kind": "analytic", "name": motion}, fps)
    if motion in SIMULATED:
        P, info = SIMULATED[motion](rest, tets, frames, fps, up=up, progress=progress)
        return P, {"kind": "fem", "name": motion, **info}, fps
    path = Path(motion)
    if path.suffix != ".npz" and not path.exists():
        raise InputError(f"--motion {motion}: expected {MOTION_HELP}")
    P, file_fps = read_motion_file(path, len(rest))
    return P, {"kind": "file", "name": str(path)}, file_fps or fps


def capture_up(root: str | Path, data: Any) -> np.ndarray:
    """The capture's up direction (unit [3]): the mean up vector of the training cameras
    (`shells.data.camera_paths.scene_frame`; within 2.5 degrees of +z on lego and fox), or of
    ``data``'s cameras when the set has no training split. Gravity and the analytic motions
    use it."""
    from shells.data.camera_paths import scene_frame
    from shells.data.datasets import read_frames

    try:
        cams = read_frames(root, "train").cameras
    except InputError:
        cams = data.cameras
    return scene_frame(cams, data.aabb)[1]


def animate_out(run: RunDir, motion: str, out: str | Path | None) -> Path:
    return Path(out) if out is not None else run.animate_dir(Path(motion).stem)


def animate_run(run_dir: str | Path, motion: str, frames: int = 48, fps: float = 24.0,
                out: str | Path | None = None, split: str = "test", view: int = 0,
                width: int | None = None, height: int | None = None, zoom: float = 1.0,
                stage: str = "latest", progress: bool = True,
                shells: str = "fine") -> dict[str, Any]:
    """Render the asset of RUN deformed by a cage motion, seen by camera ``view`` of ``split``
    (its focal length times ``zoom``): OUT (default RUN/animate-MOTION) gets r_###.png,
    video.mp4, motion.npz (the cage positions, reusable as --motion FILE) and metrics.json.
    ``shells`` 'lod': the LOD shells and their cage (shells-cage --shells lod)."""
    from shells.progress import tqdm

    from shells.data.datasets import read_frames
    from shells.device import mitsuba_variant
    from shells.fields.drjit_field import DrJitField
    from shells.render.deformed import CageAsset
    from shells.render.views import render_view, to_png, write_video
    from shells.run import load_cage, require_bounded

    if frames < 1:
        raise InputError(f"--frames {frames}: need at least 1")
    if not fps > 0:
        raise InputError(f"--fps {fps}: must be > 0 frames per second")
    if not zoom > 0:
        raise InputError(f"--zoom {zoom}: must be > 0")
    run = RunDir(run_dir)
    meta = check_run(run, "band")
    require_bounded(run, "shells-animate", "deforms one object through its cage")
    cage, emb, outer, inner = load_cage(run, shells)
    loaded = resolve_stage(run, stage)
    field, cfg = load_field(run.root, device="cpu", stage=loaded)
    rc, bg = cfg.render, tuple(cfg.data.background)
    data = read_frames(meta["data"], split)  # the cameras only: no image is decoded
    data.cameras = data.cameras.downscaled(int(meta["downscale"]))
    if not 0 <= view < len(data.cameras):
        raise InputError(f"--view {view}: the {split} split has views 0..{len(data.cameras) - 1}")
    cams = data.cameras[view:view + 1].resized(width, height)
    cams.fx, cams.fy = cams.fx * zoom, cams.fy * zoom
    up = capture_up(meta["data"], data)
    P, source, fps = cage_poses(motion, cage.vertices, cage.tets, frames, fps, up, progress)
    variant = mitsuba_variant(rc.variant)
    asset = CageAsset(DrJitField(field), cage.vertices, cage.tets, emb, outer[1], inner[1],
                      variant)
    out = animate_out(run, motion, out)
    total, render, spp_sum = [], [], 0.0
    with staged_dir(out, "shells-animate") as tmp:
        for k in tqdm(range(len(P)), desc=f"animate {Path(motion).stem}", unit="frame",
                      disable=not progress):
            t0 = time.perf_counter()
            dfield, scene = asset.pose(P[k])
            img, spp, seconds, _ = render_view(dfield, cams, 0, rc, "band", scene, data.aabb, bg)
            total.append(time.perf_counter() - t0)
            render.append(seconds)
            spp_sum += float(spp.double().mean())
            write_image(tmp / f"r_{k:03d}.png", to_png(img))
        write_video(sorted(tmp.glob("r_*.png")), tmp / "video.mp4", fps)
        with open(tmp / "motion.npz", "wb") as fh:
            np.savez(fh, positions=P, fps=fps)
        warm = total[1:] or total
        metrics = {
            "motion": source, "frames": len(P), "fps": fps, "split": split, "view": view,
            "shells": shells,
            "zoom": zoom, "width": cams.width, "height": cams.height, "stage": loaded,
            "variant": variant, "cage_vertices": len(cage.vertices),
            "cage_tetrahedra": len(cage.tets),
            "ms_per_frame": 1e3 * float(np.median(warm)),
            "ms_render_per_frame": 1e3 * float(np.median(render[1:] or render)),
            "ms_first_frame": 1e3 * total[0],
            "samples_per_pixel": spp_sum / len(P), "out": str(out),
        }
        write_json(tmp / "metrics.json", metrics)
        commit_files(tmp, out, last="metrics.json")
    return metrics


# ---------------------------------------------------------------------------------------------
# Shell levels of detail
# ---------------------------------------------------------------------------------------------

def lod_run(run_dir: str | Path, ratio: float = 10.0, parity_rays: int = 100_000,
            kappa: float | None = None, progress: bool = False) -> dict[str, Any]:
    """Coarse shells of RUN/shells that contain them (`shells.levelset.lod.make_lod`), written
    to RUN/shells/lod/{outer.ply, inner.ply, stats.json} all or nothing; returns the stats
    (triangles, file sizes, offsets used, the containment checks, ray parity). ``progress``:
    a bar over the construction's phases."""
    from shells.files import read_json
    from shells.levelset.lod import LodParams, make_lod
    from shells.levelset.mesh import write_ply
    from shells.run import require_bounded, shell_meshes, shells_digest

    import trimesh

    run = RunDir(run_dir)
    require_bounded(run, "shells-lod", "simplifies the shells of one object in its box")
    read_run(run)
    outer, inner = shell_meshes(run)
    fine = read_json(run.shells / "stats.json", "shell statistics; re-run shells-extract")
    if "aabb" not in fine or "spacing" not in fine:
        raise InputError(f"{run.shells / 'stats.json'}: no grid (aabb, spacing); re-run "
                         "shells-extract")
    box, h = np.asarray(fine["aabb"], np.float64), float(min(fine["spacing"]))
    p = LodParams() if kappa is None else LodParams(kappa=kappa)
    t0 = time.perf_counter()
    co, ci, stats = make_lod(outer, inner, ratio, box[0], h, p, parity_rays, box, progress)
    stats["seconds"] = time.perf_counter() - t0
    stats["shells_sha1"] = shells_digest(run)
    stats["source"] = fine.get("source")
    with staged_dir(run.lod, "shells-lod") as tmp:
        write_ply(tmp / "outer.ply", trimesh.Trimesh(*co, process=False))
        write_ply(tmp / "inner.ply", trimesh.Trimesh(*ci, process=False))
        stats["file_bytes"] = {
            "outer": (tmp / "outer.ply").stat().st_size, "inner": (tmp / "inner.ply").stat().st_size,
            "fine_outer": run.outer.stat().st_size,
            "fine_inner": run.inner.stat().st_size if run.inner.is_file() else 0}
        write_json(tmp / "stats.json", stats)
        commit_files(tmp, run.lod, last="stats.json")
    return stats
