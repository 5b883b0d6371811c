"""Command-line entry points. Thin: parse arguments, call library functions, report.

Every command turns an `InputError`, or a write the system refuses (disk full, a read-only
folder), into one line on stderr and exit status 2; SIGINT / SIGTERM end it with status 130,
leaving its outputs as they were (or, for training, resumable). The commands that write a run
(shells-train, -extract, -finetune) hold its lock file, and shells-render that of its output
folder: a second command on the same run is refused at once (`shells.files.lock`).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import inspect
import os
import signal
import sys
import traceback
from dataclasses import dataclass
from typing import Callable, Sequence

from shells import allocator
from shells.errors import InputError, Interrupted, write_failure
from shells.files import final_commit, late_signal, uninterrupted


class _Lazy:
    """`shells.distributed`, imported when first used: it imports torch, which takes a second,
    and a Ctrl-C during that second should end the command like any other (one line, 130)."""

    def __getattr__(self, name: str) -> object:
        from shells import distributed as module

        return getattr(module, name)


distributed = _Lazy()


def _launched_world() -> int:
    """torchrun's world size; 1 when the command stopped before it imported torch."""
    return distributed.launched_world() if "shells.distributed" in sys.modules else 1


def _run(fn: Callable[[argparse.Namespace], int | None], parser: argparse.ArgumentParser,
         argv: Sequence[str] | None, preload: Sequence[str] = (), final: bool = True) -> int:
    """Parse, run ``fn``, report. The modules in ``preload`` (the command's heavy imports:
    torch, Dr.Jit, Mitsuba, ...) are imported first with SIGINT / SIGTERM held back: a library
    interrupted half-way through its import fails in its own odd ways, so a Ctrl-C then
    takes effect right after the imports. ``final``: the command's output commit is its last
    step (`final_commit`; not so for shells-demo, which commits one stage after another).

    Run as a program (``argv`` None), the command ignores SIGINT / SIGTERM once it has its
    status: a Ctrl-C while the interpreter shuts down (torch's and Dr.Jit's exit handlers take
    a moment) would otherwise print a traceback after the result."""
    args = parser.parse_args(argv)
    previous = signal.signal(signal.SIGTERM, _terminate)  # torchrun stops workers by SIGTERM
    status = 1
    try:
        with uninterrupted():
            for name in preload:
                importlib.import_module(name)
        with final_commit(then_ignore=argv is None) if final else contextlib.nullcontext():
            status = int(fn(args) or 0)
        if final and late_signal() is not None:
            print(f"{parser.prog}: {signal.Signals(late_signal()).name} came while the outputs "
                  "were being put in place; they are complete, the command had finished",
                  file=sys.stderr)
    except InputError as exc:
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        status = 2
    except Interrupted as exc:
        print(f"{parser.prog}: {exc}", file=sys.stderr)
        status = exc.status
    except KeyboardInterrupt:
        print(f"{parser.prog}: interrupted", file=sys.stderr)
        status = 130
    except Exception as exc:
        err = write_failure(exc) if isinstance(exc, OSError) else None
        if _interrupt_within(exc):  # Dr.Jit wraps an exception of a traced loop body
            print(f"{parser.prog}: interrupted", file=sys.stderr)
            status = 130
        elif err is not None:  # a refused write (disk full, read-only folder): one line, status 2
            print(f"{parser.prog}: error: {err}", file=sys.stderr)
            status = 2
        elif _launched_world() <= 1:
            raise
        else:
            traceback.print_exc()  # a torchrun worker leaves through os._exit: print it first
            status = 1
    finally:
        with uninterrupted():  # a signal held back here finds the program ignoring it
            if argv is None:
                signal.signal(signal.SIGINT, signal.SIG_IGN)
                signal.signal(signal.SIGTERM, signal.SIG_IGN)
            else:
                signal.signal(signal.SIGTERM, previous)
        if _launched_world() > 1:
            _leave_job(status)  # does not return
    return status


def _interrupt_within(exc: BaseException) -> bool:
    """Whether ``exc`` was raised because of a KeyboardInterrupt (its cause or context, at any
    depth): Dr.Jit turns one raised inside a traced loop into "RuntimeError:
    dr.while_loop(): encountered an exception"."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False


def _leave_job(status: int) -> None:
    """End a torchrun worker: leave the process group with the others, flush, and exit without
    the interpreter's teardown. Its files are all written and closed by then; in about one run
    in ten, tearing down Dr.Jit's and gloo's threads together aborted a worker
    ("terminate called without an active exception"), which torchrun reports as a failure."""
    try:
        distributed.shutdown()
    except Exception as exc:  # the other ranks are gone: nothing left to wait for
        print(f"shells: leaving the process group: {exc}", file=sys.stderr)
        status = status or 1
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)


def _locked(path: object, command: str):  # -> context manager
    """The lock file ``path`` of an output folder (`shells.files.lock`), held by rank 0 of a
    torchrun job (its other ranks write nothing)."""
    from shells.files import lock

    return lock(path, command) if distributed.launched_rank() == 0 else contextlib.nullcontext()


def _locked_run(run: str, command: str):  # -> context manager
    """The lock of the run directory ``run`` (`shells.run.RunDir.lock`), as `_locked`."""
    from shells.run import RunDir

    return _locked(RunDir(run).lock, command)


def _terminate(signum: int, frame: object) -> None:
    """SIGTERM as Ctrl-C: files being written are removed, checkpoints stay intact."""
    raise KeyboardInterrupt


# --------------------------------------------------------------------------------------------
# Arguments several commands share
# --------------------------------------------------------------------------------------------

def _stage_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--stage", choices=["latest", "stage1", "stage2"], default="latest",
                   help="which checkpoint: stage 2 when present (latest, default), or explicit")


def _shells_arg(p: argparse.ArgumentParser, what: str = "which shells: RUN/shells (fine, "
                "default) or RUN/shells/lod (shells-lod)") -> None:
    p.add_argument("--shells", choices=["fine", "lod"], default="fine", help=what)


def _config_arg(p: argparse.ArgumentParser, sections: str, example: str) -> None:
    p.add_argument("--config", default=None, metavar="FILE",
                   help=f"JSON file with {sections} overriding the run's settings (see "
                        f"docs/configuration.md), e.g. {example}")


# --------------------------------------------------------------------------------------------
# shells-scene
# --------------------------------------------------------------------------------------------

def _scene_args(p: argparse.ArgumentParser) -> None:
    """Render a toy data set with Mitsuba in the Blender/NeRF-synthetic format (RGBA PNGs,
    transforms_train.json, transforms_test.json)."""
    from scenes import SCENES

    p.add_argument("name", choices=sorted(SCENES), help="which toy scene")
    p.add_argument("--out", required=True, help="output directory (created)")
    p.add_argument("--res", type=int, default=64, help="image width and height (default 64)")
    p.add_argument("--views", type=int, default=32, help="training views (default 32)")
    p.add_argument("--test-views", type=int, default=8, help="test views (default 8)")
    p.add_argument("--spp", type=int, default=64, help="samples per pixel (default 64)")
    p.add_argument("--seed", type=int, default=0, help="RNG seed (default 0)")
    p.add_argument("--backdrop", type=float, nargs=3, metavar=("R", "G", "B"), default=None,
                   help="store the views composited on this backdrop colour (sRGB in [0, 1]) "
                        "with an opaque alpha, like photos before a backdrop (default: "
                        "transparent background)")
    p.add_argument("--distance", type=float, default=None,
                   help="cameras within 5%% of this distance from the origin (default 2.6 to "
                        "3.0; lego's cameras are 4 box half-widths away)")


def _scene(args: argparse.Namespace) -> int:
    from scenes import make_scene

    make_scene(args.name, args.out, res=args.res, views=args.views, test_views=args.test_views,
               spp=args.spp, seed=args.seed, backdrop=args.backdrop, distance=args.distance)
    print(f"wrote {args.out}")
    return 0


# --------------------------------------------------------------------------------------------
# shells-process-data
# --------------------------------------------------------------------------------------------

def _process_data_args(p: argparse.ArgumentParser) -> None:
    """Camera poses for a folder of photos by structure from motion (COLMAP via pycolmap, on
    the CPU), written as an Instant-NGP transforms.json with the photos in DATA/images; then
    shells-train --data DATA."""
    p.add_argument("images", help="folder of photos (.png / .jpg) of one scene, one camera")
    p.add_argument("--out", required=True, help="data set folder to create")
    p.add_argument("--downscale", type=int, default=1,
                   help="shrink the photos by this integer factor first (faster; default 1)")
    p.add_argument("--matching", choices=["exhaustive", "sequential"], default="exhaustive",
                   help="feature matching: every pair (default) or neighbours in file order "
                        "(video frames)")
    p.add_argument("--camera-model", default="SIMPLE_RADIAL",
                   choices=["OPENCV", "PINHOLE", "SIMPLE_RADIAL", "SIMPLE_PINHOLE"],
                   help="COLMAP camera model shared by the photos (default SIMPLE_RADIAL: f, "
                        "cx, cy, k1, COLMAP's default; OPENCV: fx, fy, cx, cy, k1, k2, p1, p2 "
                        "for strongly distorted lenses)")
    p.add_argument("--max-error", type=float, default=2.0, metavar="PX",
                   help="reprojection error in pixels up to which a match counts as an inlier "
                        "(two-view RANSAC, triangulation, bundle-adjustment filtering; 3x it "
                        "for registering a view). Default 2: sharp photos; COLMAP's own "
                        "default, 4, suits blurred or badly distorted ones")
    p.add_argument("--no-guided-matching", dest="guided_matching", action="store_false",
                   help="skip the second, guided matching pass along each verified pair's "
                        "epipolar geometry (matching 1.5-3x faster; fewer views may register)")


def _process_data(args: argparse.Namespace) -> int:
    from shells.data.colmap import process_data

    s = process_data(args.images, args.out, args.downscale, args.matching, args.camera_model,
                     args.max_error, args.guided_matching)
    intr = s["intrinsics"]
    print(f"registered {s['registered']} of {s['photos']} photos ({s['camera_model']}, "
          f"fl_x {intr['fl_x']:.1f}, {intr['w']}x{intr['h']}) in {s['seconds']:.0f} s; "
          f"wrote {args.out}/transforms.json")
    return 0


# --------------------------------------------------------------------------------------------
# shells-train, shells-extract, shells-finetune, shells-render
# --------------------------------------------------------------------------------------------

def _train_args(p: argparse.ArgumentParser) -> None:
    """Stage 1: train the hash-grid SDF field with a spatially varying kernel by full-ray NeuS
    volume rendering."""
    p.add_argument("--data", default=None,
                   help="data set directory (Blender or Instant-NGP); not needed with --resume")
    p.add_argument("--out", required=True, help="run directory (created)")
    p.add_argument("--iters", type=int, default=None, help="training steps (overrides config)")
    p.add_argument("--config", default=None, help="JSON config file (see docs/configuration.md)")
    p.add_argument("--preset", choices=["auto", "toy", "object", "paper"], default="auto",
                   help="base configuration: 'object' (every capture on a CPU: empty-space "
                        "skipping, hash grid sized from the cameras, schedule from the number "
                        "of training pixels), 'toy' (the demo's short fixed schedule), 'paper' "
                        "(paper sizes, GPU); 'auto' (default) picks paper on CUDA, else object."
                        " Every preset trains on the images' own backdrop where it is baked "
                        "in (RGB, or RGBA without transparency)")
    p.add_argument("--scene", choices=["auto", "bounded", "unbounded"], default="auto",
                   help="'unbounded': a capture with a room or landscape around the object; the "
                        "field lives in contracted space (Mip-NeRF 360) and its shells reach "
                        "the far background; 'bounded': an object in the data set's box; "
                        "'auto' (default): unbounded when the data set says so (\"unbounded\": "
                        "true, or Instant-NGP aabb_scale > 1)")
    p.add_argument("--device", choices=["cpu", "cuda"], default=None,
                   help="torch device (default: cuda if available)")
    p.add_argument("--downscale", type=int, default=1, help="downscale images by this factor")
    p.add_argument("--resume", action="store_true", help="continue from RUN's last checkpoint")


def _train(args: argparse.Namespace) -> int:
    from shells.device import torch_device
    from shells.presets import resolve_config
    from shells.train.stage1 import train

    allocator.tune()  # training steps reuse their buffers (`shells.allocator`)
    device = torch_device(args.device)
    cfg, _ = resolve_config(args.data, device, args.preset, args.scene, args.downscale,
                            args.config, args.iters, args.resume)
    with _locked_run(args.out, "shells-train"):
        summary = train(args.data, args.out, cfg, device, downscale=args.downscale,
                        resume=args.resume, iters=args.iters)
    if "test" in summary and distributed.launched_rank() == 0:
        print(f"test PSNR {summary['test']['psnr']:.2f} dB over {summary['test']['n_views']} "
              f"views ({summary['seconds']:.0f} s, {summary['rays_per_s']:.0f} rays/s); "
              f"checkpoint {args.out}/checkpoint.pt")
    health = summary.get("health") or {}
    if not health.get("ok", True) and distributed.launched_rank() == 0:
        print(f"warning: stage 1 ended with a degenerate field ({', '.join(health['kinds'])};"
              f" {args.out}/train_summary.json, health)", file=sys.stderr)
    return 0


def _extract_args(p: argparse.ArgumentParser) -> None:
    """Extract the outer and inner shell meshes (RUN/shells/{outer,inner}.ply) by level-set
    dilation and erosion of the trained SDF."""
    p.add_argument("run", help="run directory written by shells-train")
    p.add_argument("--resolution", type=int, default=None,
                   help="grid points per axis (default: the run's config, 128 toy / 256 paper)")
    p.add_argument("--fixed-band", type=float, default=None, metavar="W",
                   help="instead of the adaptive band, the fixed band |f| <= W world units "
                        "(the paper's ablation baseline)")
    _config_arg(p, "a 'shell' section", '{"shell": {"dilate_zeta": 0.2}}')


def _extract(args: argparse.Namespace) -> int:
    from shells.pipeline import extract_run

    if args.fixed_band is not None and not args.fixed_band > 0:
        raise InputError(f"--fixed-band {args.fixed_band}: must be > 0 world units (e.g. 0.02)")
    with _locked_run(args.run, "shells-extract"):
        stats = extract_run(args.run, args.resolution, args.fixed_band, args.config,
                            progress=True)
    bw = stats.get("band_width", {})
    print(f"outer: {stats['outer_triangles']} triangles, inner: {stats['inner_triangles']} "
          f"triangles ({'empty: no interior termination' if stats['inner_empty'] else 'ok'})")
    if bw.get("count"):
        print(f"band width: mean {bw['mean']:.4f}, p5 {bw['p5']:.4f}, p95 {bw['p95']:.4f} "
              f"(world units); volume between shells {stats['volume_between']:.4f}")
    print(f"grid {stats['resolution'][0]}^3 in {stats['timings_s']['total']:.1f} s; wrote "
          f"{args.run}/shells/outer.ply, inner.ply, stats.json, slice.png")
    return 0


def _finetune_args(p: argparse.ArgumentParser) -> None:
    """Stage 2: fine-tune the field inside the narrow band (colour loss; the field outside
    M+ held at its stage-1 values)."""
    p.add_argument("run", help="run directory with a checkpoint and shells")
    p.add_argument("--iters", type=int, default=None, help="fine-tuning steps")
    p.add_argument("--resume", action="store_true",
                   help="continue from the last stage-2 checkpoint")
    p.add_argument("--device", choices=["cpu", "cuda"], default=None,
                   help="torch device (default: cuda if available); the Mitsuba variant follows "
                        "it unless the run's render.variant names one")
    _config_arg(p, "'finetune' and/or 'render' sections", '{"finetune": {"iters": 1000}}')
    _shells_arg(p)


def _finetune(args: argparse.Namespace) -> int:
    from shells.train.stage2 import finetune

    allocator.tune()  # as in shells-train
    with _locked_run(args.run, "shells-finetune"):
        summary = finetune(args.run, iters=args.iters, resume=args.resume, config=args.config,
                           device=args.device, shells=args.shells)
    if distributed.launched_rank() == 0:
        print(f"stage 2 done ({summary['step']} steps); checkpoint {args.run}/finetune.pt")
        check = summary.get("band_check")
        if check:
            print(f"band check on {check['pixels']} training pixels: band {check['band_psnr']:.2f}"
                  f" dB at {check['band_spp']:.2f} samples/px, full ray {check['full_psnr']:.2f}"
                  f" dB ({check['gap_db']:+.2f} dB)")
    return 0


def _render_args(p: argparse.ArgumentParser) -> None:
    """Render a split, or a camera path to a video, with narrow-band sampling between the
    shells (band) or a baseline; writes PNGs, metrics.json (and video.mp4 for a path). Under
    torchrun the frames are shared by the processes (frame i on rank i mod N)."""
    p.add_argument("run", help="run directory")
    p.add_argument("--split", default="test", help="data split to render (default test)")
    p.add_argument("--mode", choices=["band", "full", "occupancy", "baked"], default="band",
                   help="band: samples between the shells (default); full: dense samples along "
                        "the whole ray (baseline); occupancy: occupancy-grid ray marching with "
                        "empty-space skipping and early termination (Instant-NGP-style "
                        "baseline); baked: the layer meshes of shells-bake, as the browser "
                        "viewer draws them (no field evaluation)")
    p.add_argument("--width", type=int, default=None, help="output width (default: data set's)")
    p.add_argument("--height", type=int, default=None, help="output height")
    p.add_argument("--spp", type=int, default=None, metavar="N",
                   help="rays per pixel, N = k*k on a sub-pixel grid, averaged (anti-aliasing; "
                        "default: the run's render.spp, 1 = pixel centres)")
    p.add_argument("--path", default=None, metavar="orbit|spiral|interpolate|FILE",
                   help="render a camera path instead of a split: an orbit or a spiral around "
                        "the scene at the training cameras' distance and elevation, an "
                        "interpolation through the training cameras, or a nerfstudio "
                        "camera_path.json; writes r_###.png and video.mp4")
    p.add_argument("--frames", type=int, default=120,
                   help="frames of an orbit / spiral / interpolate path (default 120)")
    p.add_argument("--fps", type=float, default=None,
                   help="video frame rate (default: the camera path file's, else 30)")
    p.add_argument("--out", default=None,
                   help="output directory (default RUN/render-MODE, RUN/path-NAME for a path)")
    p.add_argument("--shard", default=None, metavar="K/N",
                   help="as one of N independent processes (no torchrun), render frames K, "
                        "K + N, ...; the last shard to finish merges all into OUT")
    _stage_arg(p)
    p.add_argument("--refine", type=int, default=None, metavar="L",
                   help="image-space adaptive refinement (band mode, spp 1): evaluate every "
                        "2^L-th pixel, then interpolate a pixel from its parents where the "
                        "shell cast and the parents agree, evaluate it otherwise; 0 = plain "
                        "band mode (default: the run's render.refine_levels, 0; thresholds: "
                        "render.refine_*)")
    _config_arg(p, "a 'render' section", '{"render": {"delta_s": 0.01}}')
    _shells_arg(p)


def _render(args: argparse.Namespace) -> int:
    from shells.pipeline import render_run

    shard = None
    if args.shard is not None:
        try:
            k, n = (int(v) for v in args.shard.split("/"))
        except ValueError:
            raise InputError(f"--shard {args.shard}: expected K/N, e.g. 0/4") from None
        if not (n >= 1 and 0 <= k < n):
            raise InputError(f"--shard {args.shard}: need 0 <= K < N")
        shard = (k, n)
    from shells.pipeline import render_out
    from shells.run import RunDir
    from shells.files import output_lock

    out = render_out(RunDir(args.run), args.mode, args.path, args.out)
    guard = (contextlib.nullcontext() if shard is not None  # shards share OUT by design
             else _locked(output_lock(out), "shells-render"))
    with guard:
        m = render_run(args.run, split=args.split, mode=args.mode, width=args.width,
                       height=args.height, out=args.out, stage=args.stage, config=args.config,
                       spp=args.spp, path=args.path, frames=args.frames, fps=args.fps,
                       shard=shard, refine=args.refine, shells=args.shells)
    if distributed.launched_rank() != 0:
        return 0
    if m.get("complete") is False:
        print(f"shard {m['shard'][0]}/{m['shard'][1]}: {m['views']} frames rendered; "
              f"{m['out']} is written when all shards are done")
        return 0
    fmt = lambda v, spec: "n/a" if v is None else format(v, spec)  # noqa: E731
    refined = m["render_config"].get("refine_levels", 0)
    extra = (f", refine {refined}: {100 * m['evaluated_fraction_of_covered']:.0f} % of covered "
             "pixels evaluated" if refined else "")
    print(f"{m['mode']}: PSNR {fmt(m.get('psnr'), '.2f')} dB, SSIM {fmt(m.get('ssim'), '.4f')}, "
          f"{m['samples_per_pixel']:.2f} samples/pixel, {m['ms_per_frame']:.1f} ms/frame "
          f"({m['width']}x{m['height']}, {m['variant']}{extra}) -> {m['out']}")
    return 0


def _demo_args(p: argparse.ArgumentParser) -> None:
    """The whole pipeline on a built-in toy scene: render the data set, train stage 1, extract
    the shells, fine-tune stage 2, render full vs band and print PSNR, samples/pixel and
    ms/frame."""
    from scenes import SCENES

    p.add_argument("--out", default="runs/demo", help="output directory (default runs/demo)")
    p.add_argument("--scene", choices=sorted(SCENES), default="core-fuzz")
    p.add_argument("--res", type=int, default=64, help="image size (default 64)")
    p.add_argument("--iters", type=int, default=None, help="stage-1 steps (default: toy config)")
    p.add_argument("--finetune-iters", type=int, default=None, help="stage-2 steps")


def _demo(args: argparse.Namespace) -> int:
    from shells.pipeline import demo

    demo(args.out, scene=args.scene, res=args.res, iters=args.iters,
         finetune_iters=args.finetune_iters)
    return 0


# --------------------------------------------------------------------------------------------
# shells-view
# --------------------------------------------------------------------------------------------

def _view_args(p: argparse.ArgumentParser) -> None:
    """Web viewer (viser): the shells, the training cameras and the band render of the
    browser's camera as the background, re-rendered as it moves. Runs headless and prints the
    URL to open. With --baked: the baked asset (shells-bake) drawn by the browser itself
    (three.js), served as a static folder; nothing is rendered on the server."""
    p.add_argument("run", help="run directory with a checkpoint and shells")
    p.add_argument("--host", default="0.0.0.0", help="address to listen on (default all)")
    p.add_argument("--port", type=int, default=8080, help="port (default 8080)")
    p.add_argument("--baked", action="store_true",
                   help="export RUN/baked (shells-export --web RUN/baked/web) and serve it: the "
                        "browser draws the layers")
    _stage_arg(p)
    p.add_argument("--resolution", type=int, default=320,
                   help="longer side of the resting render in pixels (default 320)")
    p.add_argument("--dump", default=None, metavar="DIR",
                   help="write every resting render and its camera to DIR (tests, debugging)")


def _view(args: argparse.Namespace) -> int:
    if args.baked:
        from shells.bake.run import view_baked

        view_baked(args.run, host=args.host, port=args.port)
        return 0
    from shells.viewer import view

    view(args.run, args.host, args.port, args.stage, args.resolution, args.dump)
    return 0


# --------------------------------------------------------------------------------------------
# shells-cage, shells-animate (paper §5)
# --------------------------------------------------------------------------------------------

def _cage_args(p: argparse.ArgumentParser) -> None:
    """Build a tetrahedral cage around the outer shell (dilated slightly, tetrahedralized with
    fTetWild) and embed the shells in it: RUN/cage/cage.npz, cage.vtu (ParaView), cage.json
    (counts, quality). shells-animate deforms the asset through it."""
    p.add_argument("run", help="run directory with shells (shells-extract)")
    p.add_argument("--margin", type=float, default=None, metavar="M",
                   help="distance of the cage's surface outside M+, world units (default 2.5 "
                        "cage-grid cells)")
    p.add_argument("--resolution", type=int, default=48,
                   help="cage-grid cells along the longest side of M+ (default 48)")
    p.add_argument("--edge-length", type=float, default=0.06, metavar="L",
                   help="target tetrahedron edge as a share of the box diagonal (default 0.06; "
                        "smaller: finer cage, smoother bends, slower)")
    p.add_argument("--threads", type=int, default=0, help="fTetWild threads (default all)")
    _shells_arg(p, "cage the fine shells (RUN/cage, default) or the LOD shells of shells-lod "
                   "(RUN/cage/lod)")


def _cage(args: argparse.Namespace) -> int:
    from shells.pipeline import cage_run

    with _locked_run(args.run, "shells-cage"):
        st = cage_run(args.run, args.margin, args.resolution, args.edge_length,
                      threads=args.threads, shells=args.shells)
    q = st["quality"]
    print(f"cage: {st['vertices']} vertices, {st['tetrahedra']} tetrahedra, watertight "
          f"{st['watertight']}, quality min {q['min']:.3f} / median {q['median']:.3f}; "
          f"contains all {st['contains_outer_vertices']} M+ and "
          f"{st['contains_inner_vertices']} M- vertices; "
          f"{sum(st['timings_s'].values()):.1f} s -> {st['out']}")
    return 0


def _animate_args(p: argparse.ArgumentParser) -> None:
    """Render the asset deformed through its cage (shells-cage): the shells move with the cage
    and every band sample is mapped back to the rest pose through its tetrahedron. Writes
    r_###.png, video.mp4, motion.npz (the cage poses) and metrics.json."""
    from shells.deform import MOTION_HELP

    p.add_argument("run", help="run directory with a checkpoint, shells and a cage")
    p.add_argument("--motion", required=True, metavar="NAME|FILE", help=MOTION_HELP)
    p.add_argument("--frames", type=int, default=48, help="frames (default 48)")
    p.add_argument("--fps", type=float, default=24.0,
                   help="frame rate of the video and of the simulation clock (default 24; a "
                        "motion file's own fps wins)")
    p.add_argument("--out", default=None, help="output directory (default RUN/animate-MOTION)")
    p.add_argument("--split", default="test", help="split whose camera looks (default test)")
    p.add_argument("--view", type=int, default=0, help="camera index in the split (default 0)")
    p.add_argument("--width", type=int, default=None, help="output width (default: data's)")
    p.add_argument("--height", type=int, default=None, help="output height")
    p.add_argument("--zoom", type=float, default=1.0,
                   help="focal length factor of the camera (default 1)")
    _stage_arg(p)
    _shells_arg(p, "deform the fine shells (default) or the LOD shells; their cage must exist "
                   "(shells-cage [--shells lod])")


def _animate(args: argparse.Namespace) -> int:
    from shells.pipeline import animate_out, animate_run
    from shells.run import RunDir
    from shells.files import output_lock

    out = animate_out(RunDir(args.run), args.motion, args.out)
    with _locked(output_lock(out), "shells-animate"):
        m = animate_run(args.run, args.motion, args.frames, args.fps, args.out, args.split,
                        args.view, args.width, args.height, args.zoom, args.stage,
                        shells=args.shells)
    print(f"{m['frames']} frames ({m['width']}x{m['height']}), {m['ms_per_frame']:.1f} ms/frame "
          f"(render {m['ms_render_per_frame']:.1f}), {m['samples_per_pixel']:.2f} samples/pixel "
          f"-> {m['out']}/video.mp4")
    return 0


# --------------------------------------------------------------------------------------------
# shells-lod
# --------------------------------------------------------------------------------------------

def _lod_args(p: argparse.ArgumentParser) -> None:
    """Simplified shells that contain the fine ones (coarse M+ around M+, coarse M- inside M-,
    so the band only grows): RUN/shells/lod/{outer,inner}.ply, stats.json. Render or fine-tune
    with them by --shells lod."""
    p.add_argument("run", help="run directory with shells (shells-extract)")
    p.add_argument("--ratio", type=float, default=10.0,
                   help="fine triangles per coarse triangle, each shell (default 10)")
    p.add_argument("--kappa", type=float, default=None,
                   help="offset of the alpha-wrap fallback for the outer shell, as a share of "
                        "the local band width (default 0.1; clamped to 0.25..2 grid cells)")
    p.add_argument("--parity-rays", type=int, default=100_000,
                   help="random rays of the enter/exit parity check (default 100000)")


def _lod(args: argparse.Namespace) -> int:
    from shells.pipeline import lod_run

    if not args.ratio > 1:
        raise InputError(f"--ratio {args.ratio}: must be > 1 (e.g. 10)")
    if args.kappa is not None and not args.kappa > 0:
        raise InputError(f"--kappa {args.kappa}: must be > 0 (e.g. 0.1)")
    with _locked_run(args.run, "shells-lod"):
        st = lod_run(args.run, args.ratio, args.parity_rays, args.kappa, progress=True)
    for name in ("outer", "inner"):
        s = st[name]
        if "check" not in s:
            print(f"{name}: none")
            continue
        print(f"{name}: {s['fine_triangles']} -> {s['triangles']} triangles "
              f"({s['reduction']:.1f}x), contained {s['check'].get('contained', True)}, "
              f"parity {s.get('parity', {}).get('parity_fraction', 1.0):.5f}")
    print(f"{st['seconds']:.1f} s -> {args.run}/shells/lod/")
    return 0


# --------------------------------------------------------------------------------------------
# shells-bake, shells-export
# --------------------------------------------------------------------------------------------

def _bake_args(p: argparse.ArgumentParser) -> None:
    """Bake the band for real-time viewing: a few nested, semi-transparent layer meshes cut
    from the stage-2 field's level sets inside the shells, each decimated as far as its own
    geometric error allows, unwrapped into one texture atlas whose colour, opacity and
    view-dependent (degree-1 SH) colour are fitted to the training photos through the renderer
    the viewers use. Writes RUN/baked/layers.glb (glTF 2.0, PNG textures) and asset.json."""
    p.add_argument("run", help="run directory after shells-finetune")
    p.add_argument("--size-mb", type=float, default=None, metavar="MB",
                   help="texture budget: atlas texels x 13 bytes at most this (default 60); "
                        "the texels are made coarser until they fit")
    p.add_argument("--levels", type=float, nargs="+", default=None, metavar="U",
                   help="level sets u = f / s of the layers, 0 (the surface) included "
                        "(default -2 -1 0 1 2 3 4)")
    p.add_argument("--resolution", type=int, default=None,
                   help="marching-cubes grid of the layer meshes before decimation (default: "
                        "1.25 cells across a training pixel's footprint at the scene centre, at "
                        "most the shells' resolution)")
    p.add_argument("--steps", type=int, default=None,
                   help="fitting steps (default 600)")
    p.add_argument("--teacher-views", type=int, default=None, metavar="N",
                   help="band renders of the stage-2 field from N turned training cameras, "
                        "fitted beside the photos (default: 4 per training view; 0: photos only)")
    p.add_argument("--tolerance", type=float, default=None, metavar="PX",
                   help="how far each decimated layer may stray from its level set, in "
                        "training-pixel footprints (default 0.5; 0: no decimation)")
    p.add_argument("--texel", type=float, default=None, metavar="PX",
                   help="atlas texel size in training-pixel footprints (default 1)")


def _bake(args: argparse.Namespace) -> int:
    from shells.bake.run import bake_run, bake_summary

    with _locked_run(args.run, "shells-bake"):
        rec = bake_run(args.run, levels=args.levels, resolution=args.resolution,
                       size_mb=args.size_mb, steps=args.steps,
                       teacher_views=args.teacher_views, tolerance_px=args.tolerance,
                       texel_px=args.texel, progress=True)
    print(f"{bake_summary(rec)} -> {args.run}/baked/layers.glb")
    return 0


def _export_args(p: argparse.ArgumentParser) -> None:
    """Export a baked asset (shells-bake) as a self-contained folder that works offline: the
    layers as glTF 2.0 (layers.glb; Blender or any glTF viewer opens it), asset.json,
    cameras.json, and a static three.js viewer (orbit controls, fps, layers per pixel). Serve
    it with `python -m http.server -d OUT`."""
    p.add_argument("run", help="run directory after shells-bake")
    p.add_argument("--web", required=True, metavar="OUT", help="the folder to write")
    p.add_argument("--three", default=None, metavar="DIR",
                   help="the npm package three (default: $SHELLS_THREE, or web/node_modules/"
                        "three of the source tree after `npm ci --prefix web`)")


def _export(args: argparse.Namespace) -> int:
    from shells.bake.run import export_web

    rec = export_web(args.run, args.web, args.three)
    print(f"{len(rec['files'])} files -> {rec['out']}; serve it: python -m http.server -d "
          f"{rec['out']}")
    return 0


# --------------------------------------------------------------------------------------------
# The commands: one row each (console scripts in pyproject.toml)
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Command:
    """A console script: its arguments (a function whose docstring is the --help description),
    its handler, and how `_run` runs it."""
    arguments: Callable[[argparse.ArgumentParser], None]
    handler: Callable[[argparse.Namespace], int | None]
    preload: tuple[str, ...] = ()  # heavy imports done with signals held back (`_run`)
    final: bool = True  # the output commit is the command's last step (`_run`)


COMMANDS = {
    "shells-scene": Command(_scene_args, _scene),
    "shells-process-data": Command(_process_data_args, _process_data),
    "shells-train": Command(_train_args, _train, ("shells.train.stage1",)),
    "shells-extract": Command(_extract_args, _extract, ("shells.pipeline",
                                                         "shells.levelset.extract",
                                                         "shells.levelset.figure")),
    "shells-finetune": Command(_finetune_args, _finetune, ("shells.train.stage2",
                                                            "shells.levelset.mesh")),
    "shells-render": Command(_render_args, _render, ("shells.pipeline", "shells.render.views",
                                                      "shells.fields.drjit_field",
                                                      "shells.data.camera_paths",
                                                      "shells.levelset.mesh")),
    "shells-demo": Command(_demo_args, _demo, final=False),
    "shells-view": Command(_view_args, _view),
    "shells-cage": Command(_cage_args, _cage, ("shells.pipeline", "shells.levelset.cage")),
    "shells-animate": Command(_animate_args, _animate, ("shells.pipeline",
                                                         "shells.render.deformed")),
    "shells-lod": Command(_lod_args, _lod, ("shells.pipeline", "shells.levelset.lod")),
    "shells-bake": Command(_bake_args, _bake, ("shells.bake.run", "shells.bake.fit",
                                               "shells.bake.render")),
    "shells-export": Command(_export_args, _export, ("shells.bake.run",)),
}


def parser(prog: str) -> argparse.ArgumentParser:
    """The argument parser of the command ``prog`` (e.g. "shells-train")."""
    arguments = COMMANDS[prog].arguments
    p = argparse.ArgumentParser(prog=prog, description=inspect.getdoc(arguments))
    arguments(p)
    return p


def _main_of(prog: str) -> Callable[[Sequence[str] | None], int]:
    def main(argv: Sequence[str] | None = None) -> int:
        c = COMMANDS[prog]
        return _run(c.handler, parser(prog), argv, c.preload, c.final)

    main.__name__ = main.__qualname__ = prog.removeprefix("shells-").replace("-", "_") + "_main"
    main.__doc__ = f"``{prog}``: parse ``argv`` (default: the command line), run, report."
    return main


scene_main = _main_of("shells-scene")
process_data_main = _main_of("shells-process-data")
train_main = _main_of("shells-train")
extract_main = _main_of("shells-extract")
finetune_main = _main_of("shells-finetune")
render_main = _main_of("shells-render")
demo_main = _main_of("shells-demo")
view_main = _main_of("shells-view")
cage_main = _main_of("shells-cage")
animate_main = _main_of("shells-animate")
lod_main = _main_of("shells-lod")
bake_main = _main_of("shells-bake")
export_main = _main_of("shells-export")
