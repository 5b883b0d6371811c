"""Named presets: the base configuration of a run, from the data set and a preset name.

``--preset``: "auto" (default) picks "paper" on CUDA, else "object"; "object" is one recipe for
every capture on the CPU, sized from the training cameras and images (`object_config`); "toy"
is the demo's short fixed schedule (`toy_config`); "paper" the paper's sizes (`Config()`).
`resolve_config` is the one sequence every caller uses (shells-train, the benchmarks): data
set + preset + scene + config file -> `Config`. Why each value is what it is, with the
measurements behind it: docs/configuration.md.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import torch

from shells.config import (Config, FieldConfig, FinetuneConfig, RenderConfig, ShellConfig,
                           TrainConfig, load_config)
from shells.data.datasets import (backdrop_colour, has_transparency, load_dataset, read_frames,
                                  region_of_interest, says_unbounded)
from shells.errors import InputError
from shells.fields.contraction import Similarity

PRESETS = ("auto", "toy", "object", "paper")
SCENES = ("auto", "bounded", "unbounded")

BASE_PIXELS = 870_000  # training pixels of the object preset's full schedules (lego at 1/8)
MIN_ITERS = 1000  # the shortest stage-1 schedule of the object preset


# ---------------------------------------------------------------------------------------------
# The named recipes
# ---------------------------------------------------------------------------------------------

def toy_config() -> Config:
    """Small field and short schedule for the CPU toy scenes (64x64 images, 2 cores): a 64 px
    image cannot use the paper's 2^22-entry tables and 4096^3 finest level."""
    cfg = Config()
    cfg.field = FieldConfig(n_levels=8, log2_hashmap_size=17, base_resolution=8,
                            max_resolution=256, geo_hidden=64, rad_hidden=64,
                            init_radius=0.5, init_kernel=0.05)
    # lr_mlp 1e-2: the geometric init starts the hash-feature weights at zero, and at 1e-3 they
    # grow too slowly for a 600-step schedule
    cfg.train = TrainConfig(iters=600, batch_rays=1024, n_samples=32, n_importance=16,
                            lr_mlp=1e-2, warmup_iters=50, checkpoint_every=250, log_every=25)
    # zeta 0.25 / 0.1 (paper 0.1 / 0.05): the fronts stop at |f| = zeta, and a fuzzy coat's
    # density reaches f ~ 0.2 outside the learned surface and ~0.06 inside it
    cfg.shell = ShellConfig(resolution=128, dilate_zeta=0.25, erode_zeta=0.1)
    # single-sample intervals up to 0.03, spacing 0.02: <= 3 samples per covered pixel
    cfg.render = RenderConfig(w_s=0.03, delta_s=0.02)
    # a short stage 2 at 3x / 10x the paper's learning rates
    cfg.finetune = FinetuneConfig(iters=500, batch_rays=1024, lr=3e-3, lr_mlp=1e-3,
                                  checkpoint_every=250, log_every=25)
    return cfg


def finest_resolution(extent: float, focal_px: float, distance: float) -> int:
    """Finest hash-grid resolution for images of ``focal_px`` pixels of focal length seen from
    ``distance``: a cell of half the pixel footprint (distance / focal_px) at the object, over
    the box's largest ``extent``, rounded up to a power of two (at least 64)."""
    cells = 2.0 * extent * focal_px / max(distance, 1e-6)
    return max(64, 2 ** math.ceil(math.log2(max(cells, 1.0))))


def pixel_share(pixels: float) -> float:
    """sqrt(pixels / BASE_PIXELS), at most 1: the share of the object preset's full schedules
    a data set of ``pixels`` training pixels gets."""
    return min(1.0, math.sqrt(max(pixels, 1.0) / BASE_PIXELS))


def object_iters(doublings: int, pixels: float) -> int:
    """Stage-1 steps of the object preset: 3000 per doubling of the finest level above 256
    (`object_config`), times `pixel_share`, rounded to 100, at least MIN_ITERS: a 64 px capture
    of 40 views (164 k pixels) trains 1300 steps, one of 128 px and 48 views 2900, lego at 1/8
    and 1/4 the full 3000 and 6000."""
    return max(MIN_ITERS, 100 * round(30 * (1 + doublings) * pixel_share(pixels)))


def object_finetune_iters(doublings: int, pixels: float) -> int:
    """Stage-2 steps of the object preset: 1500, 1000 more per doubling above 512, times
    `pixel_share`, rounded to 100, at least 500 (a small capture overfits a long stage 2)."""
    return max(500, 100 * round((5 + 10 * max(1, doublings)) * pixel_share(pixels)))


def sharp_finetune_iters(base: int, pixels: float, batch_rays: int) -> int:
    """Stage-2 steps of the object preset's sharp fields: ``base`` (`object_finetune_iters`),
    or enough steps of ``batch_rays`` rays to draw SHARP_FINETUNE_SHARE of the ``pixels``
    training pixels if that is more, rounded to 100, at most SHARP_FINETUNE_MAX: lego at 800^2
    (55.7 M pixels) gets 30 000, a 32-view capture of 512^2 4600 (its base is 3500)."""
    share = 100 * round(SHARP_FINETUNE_SHARE * pixels / batch_rays / 100)
    return max(base, min(SHARP_FINETUNE_MAX, share))


def object_config(extent: float, focal_px: float, distance: float, pixels: float = BASE_PIXELS,
                  eikonal_weight: float = 0.005, cull_weight: float = 1e-4,
                  color_loss: str = "rmse") -> Config:
    """Real objects on the CPU (NeRF-synthetic, photos; 2 cores), sized from the data.

    The toy preset with stage 1's empty-space skipping (``sampler`` "occupancy", 32 + 16
    samples per ray on the occupied span), 2048 crossing rays per step at the base size (1024
    above it) and 2048 regulariser points; a hash grid whose finest level resolves half a pixel
    at the cameras' distance (`finest_resolution`), one level per doubling above 8 levels and a
    table twice as large per doubling from 2^18; 3000 stage-1 steps per doubling, fewer for
    small data sets (`object_iters`). A weak Eikonal term (0.005: a strong one holds the hash
    grid back), random backgrounds where the images are transparent (an unseen white solid
    otherwise fills the object's underside), the root-mean-squared colour error (small
    objects beside large ones survive, at L1's scale), culling of samples under 1e-4 of
    weight, and rescue sampling of pixels whose content the grid lost. Shells on a 256^3 grid,
    eroded 4 s (``beta_e`` 0.8). Stage 2: 1500 steps of 4096 rays, 1000 more per doubling
    above 512 (`object_finetune_iters`).
    """
    cfg = toy_config()
    res = finest_resolution(extent, focal_px, distance)
    doublings = max(0, int(round(math.log2(res / 256))))
    cfg.field = dataclasses.replace(cfg.field, max_resolution=res, n_levels=8 + doublings,
                                    log2_hashmap_size=min(21, 18 + doublings))
    cfg.train = dataclasses.replace(cfg.train, sampler="occupancy",
                                    iters=object_iters(doublings, pixels),
                                    batch_rays=2048 if doublings == 0 else 1024,
                                    reg_points=2048, eikonal_weight=eikonal_weight,
                                    random_background=True, cull_weight=cull_weight,
                                    color_loss=color_loss,
                                    occ_rescue=0.05, checkpoint_every=500, log_every=50,
                                    curve_every=500)
    cfg.shell = dataclasses.replace(cfg.shell, resolution=256, beta_e=0.8)
    cfg.finetune = dataclasses.replace(cfg.finetune,
                                       iters=object_finetune_iters(doublings, pixels),
                                       batch_rays=4096)
    cfg.check("object preset")
    return cfg


# The unbounded object preset's shells: wide, for a soft field whose weight lies far off its
# level set, with the 32 peels their layers need
UNBOUNDED_SHELLS = {"beta_d": 1.0, "dilate_zeta": 1.0, "beta_e": 1.0, "erode_zeta": 0.5,
                    "v_max": 0.1}
# ... their band sampling: an interval of the wide shells spans a few units of the ray
# parameter, so the cap of samples per interval (n_max) is raised
UNBOUNDED_BAND = {"dp_max": 32, "w_s": 0.04, "delta_s": 0.03, "n_max": 64}
# ... and stage 2 in 4 ray shards a step: at ~50 samples a ray one batch's activations
# outgrow the caches
UNBOUNDED_SHARDS = 4
# A bounded field whose finest level reaches SHARP_RESOLUTION (full-size NeRF-synthetic images)
# learns kernels under a 256^3 cell, and its fine parts fall between grid points: its shells
# are extracted at 512^3, keep every mesh piece (small pieces are real studs and rods) and
# reach further out; its f inside a solid stays within a few s of 0, so M- lies only where
# f < -(h + 3 s) (the density-support term; a shallower M- ends rays where the surface still
# absorbs, more so as the field sharpens); a ray crosses more shell layers than 8 peels;
# band mode stops a ray at transmittance 1e-4 (its rounds pay at 800^2: 1291 -> 1149 ms/frame on
# lego, where at 200^2 they cost 63 -> 70 ms and at 64^2 5.5 -> 16.7 ms); and the shells are
# peeled 8 hits at a time, only for the rays still letting light through (most of a sharp
# field's covered rays are opaque after their first intervals; smaller steps add more rounds
# of field evaluations than they save casts)
SHARP_RESOLUTION = 2048
SHARP_SHELLS = {"resolution": 512, "min_component_fraction": 0.0, "beta_d": 1.2, "beta_e": 0.3,
                "support_k_inner": 3.0}
SHARP_BAND = {"dp_max": 32, "band_ert_eps": 1e-4, "band_peel_step": 8}
# ... and the trainer's own renders (running curve, test PSNR) sample twice as densely as its
# steps: 32 + 16 samples over a span of lego at 800^2 lie about 12 kernel sizes apart and
# under-report its field by 1.4 dB; 64 + 32 come within 0.05 dB of 128 + 64
SHARP_TRAIN = {"eval_density": 2}
# ... and its stage 2 sees at least this share of the training pixels' rays: a sharp field's
# band keeps gaining with stage-2 steps up to about this share (one schedule of 30 000 steps of
# 4096 rays on lego at 800^2), up to SHARP_FINETUNE_MAX steps (BENCHMARKS.md, lego 800x800;
# docs/configuration.md)
SHARP_FINETUNE_SHARE = 2.25
SHARP_FINETUNE_MAX = 30_000
START_RADII = 2.0  # the unbounded object preset's rays start this many radii from the centre
CAMERA_SHARE = 0.8  # ... or at this share of the nearest training camera's distance, if less


def start_sphere(origins: torch.Tensor,  # [N, 3] training camera centres (world)
                 sim: Similarity) -> float:
    """``field.near_radius`` of the unbounded object preset: rays start where they enter the
    sphere of START_RADII radii around the centre (`shells.render.warp.ray_span`), or of
    CAMERA_SHARE of the nearest camera's distance when a camera is closer (no ray starts at a
    camera: no room for floaters in front of it), never inside the ball of interest; returned
    as a contracted radius. A ray started at the ball of interest that misses it would begin
    at its point nearest the centre, past the wall beside the object in oblique views."""
    centre = torch.tensor(sim.centre, dtype=torch.float64)
    nearest = float((origins.double() - centre).norm(dim=-1).min()) / sim.radius
    rho = min(START_RADII, max(1.0, CAMERA_SHARE * nearest))
    return 2.0 - 1.0 / rho


def _object_for(data_dir: str | Path, downscale: int, sim: Similarity | None) -> Config:
    frames = read_frames(data_dir, "train")
    cams = frames.cameras.downscaled(downscale)
    pixels = float(len(cams) * cams.width * cams.height)
    if sim is not None:  # sized for the field-space box, centre +- 2 radius
        centre = torch.tensor(sim.centre, dtype=torch.float64)
        distance = float((cams.c2w[:, :3, 3].double() - centre).norm(dim=-1).median())
        # the default Eikonal weight (the weak one cost the band on fox), no culling and L1
        # colour: the settings measured on unbounded captures
        cfg = object_config(4.0 * sim.radius, float(cams.fx.double().median()), distance,
                            pixels, eikonal_weight=TrainConfig.eikonal_weight, cull_weight=0.0,
                            color_loss="l1")
        # the opacity's slope from the ray's samples and the free-space term against the
        # soft background's floaters; rays start on the start sphere (`start_sphere`)
        cfg.update({"train": {"slope": "ray", "free_weight": 0.1},
                    "field": {"near_radius": start_sphere(cams.c2w[:, :3, 3], sim)},
                    "shell": UNBOUNDED_SHELLS, "render": UNBOUNDED_BAND,
                    "finetune": {"shards": UNBOUNDED_SHARDS}},
                   "object preset, unbounded")
        return cfg
    box = frames.aabb.double()
    centre = 0.5 * (box[0] + box[1])
    distance = float((cams.c2w[:, :3, 3].double() - centre).norm(dim=-1).median())
    focal = float(cams.fx.double().median())
    cfg = object_config(float((box[1] - box[0]).max()), focal, distance, pixels)
    if cfg.field.max_resolution >= SHARP_RESOLUTION:
        iters = sharp_finetune_iters(cfg.finetune.iters, pixels, cfg.finetune.batch_rays)
        cfg.update({"train": SHARP_TRAIN, "shell": SHARP_SHELLS, "render": SHARP_BAND,
                    "finetune": {"iters": iters}}, "object preset, sharp field")
    return cfg


def _toy_for(sim: Similarity | None) -> Config:
    cfg = toy_config()
    if sim is not None:
        f = cfg.field
        cfg.update({"field": {"max_resolution": 2 * f.max_resolution,
                              "n_levels": f.n_levels + 1}}, "toy preset, unbounded")
    return cfg


# ---------------------------------------------------------------------------------------------
# From the data set
# ---------------------------------------------------------------------------------------------

def scene_similarity(data_dir: str | Path, scene: str = "auto") -> Similarity | None:
    """``shells-train --scene``: the similarity of an unbounded scene (`region_of_interest`),
    or None for a bounded one. "auto": unbounded when the data set says so
    (`says_unbounded`). The training cameras must look at a common region
    (`Similarity.from_cameras`: a one-line error otherwise, e.g. cameras inside the object)."""
    if scene not in SCENES:
        raise InputError(f"--scene {scene}: expected one of {list(SCENES)}")
    if scene == "bounded":
        return None
    frames = read_frames(data_dir, "train")
    if scene == "auto" and not says_unbounded(frames):
        return None
    c2w = frames.cameras.c2w.double().numpy()
    Similarity.from_cameras(c2w[:, :3, 3], c2w[:, :3, 2],
                            f"{frames.root}: the training cameras of an unbounded scene")
    centre, radius = region_of_interest(frames)
    return Similarity(centre, radius)


def unbounded_settings(cfg: Config, sim: Similarity) -> None:
    """Make ``cfg`` the config of an unbounded scene with similarity ``sim``: the contracted
    field (`ShellField`, field.unbounded) and stage 1 sampling evenly in contracted space."""
    cfg.update({"field": {"unbounded": True, "centre": list(sim.centre), "radius": sim.radius},
                "train": {"sampler": "box"}}, "--scene unbounded")


BACKGROUND_VIEWS = 16  # training views read to tell the data's background (evenly spaced)


def data_background(data_dir: str | Path, downscale: int) -> tuple[float, float, float] | None:
    """The background a run of this data set is trained and rendered on, if the images fix it:
    None when their alpha channel holds transparency (they are composited on
    ``data.background``, and may be recomposited on random colours) or when no uniform backdrop
    shows on their border; else the backdrop's colour (`backdrop_colour`), baked into RGB files
    and into RGBA files whose alpha is opaque. Rendered on another colour, a baked-in backdrop
    can only be reproduced by matter filling the box. Read from BACKGROUND_VIEWS views spread
    over the training split (all of them when it has fewer)."""
    n = len(read_frames(data_dir, "train").paths)
    k = min(n, BACKGROUND_VIEWS)
    views = sorted({round(i * (n - 1) / max(1, k - 1)) for i in range(k)})
    data = load_dataset(data_dir, "train", downscale=downscale, views=views)
    if has_transparency(data.alpha):
        return None
    return backdrop_colour(data.images)


def preset_config(name: str, data_dir: str | Path, downscale: int,
                  device: torch.device, sim: Similarity | None = None) -> tuple[Config, str]:
    """The base config of ``shells-train --preset NAME`` and the preset's resolved name. With
    ``sim`` (an unbounded scene) the object preset is sized for the field-space box (centre +-
    2 radius) and the toy preset's finest level doubles with one more level. Every preset
    takes the data's own background where the images have it baked in (`data_background`)."""
    if name not in PRESETS:
        raise InputError(f"--preset {name}: expected one of {list(PRESETS)}")
    if name == "paper" or (name == "auto" and device.type == "cuda"):
        cfg, resolved = Config(), "paper"
    elif name == "toy":
        cfg, resolved = _toy_for(sim), "toy"
    else:
        cfg, resolved = _object_for(data_dir, downscale, sim), "object"
    background = data_background(data_dir, downscale)
    if background is not None:
        cfg.update({"data": {"background": list(background)}}, "the data's backdrop")
    return cfg, resolved


def resolve_config(data_dir: str | Path | None, device: torch.device, preset: str = "auto",
                   scene: str = "auto", downscale: int = 1, config: str | Path | None = None,
                   iters: int | None = None, resume: bool = False) -> tuple[Config, str]:
    """The config of a stage-1 run as ``shells-train`` builds it, and the preset's resolved
    name: the preset for the data (`preset_config`), then the config file on top, then the
    unbounded scene's settings (`unbounded_settings`). On ``resume`` the run's own config is
    used, so the preset is not built ("resume" is returned); ``iters`` is only checked here
    (the training loop applies it, on resume too)."""
    if downscale < 1:
        raise InputError(f"--downscale {downscale}: must be at least 1")
    if iters is not None:  # checked before the data set is read for the preset
        Config().update({"train": {"iters": iters}}, "--iters")
    if resume:
        return load_config(config, Config()), "resume"
    if data_dir is None:
        raise InputError("--data DIR is required (the data set to train on)")
    sim = scene_similarity(data_dir, scene)
    cfg, name = preset_config(preset, data_dir, downscale, device, sim)
    cfg = load_config(config, cfg)
    if sim is not None:
        unbounded_settings(cfg, sim)
    return cfg, name
