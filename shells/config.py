"""Dataclass configurations, one per component, with the paper's defaults.

Paper: "Adaptive Shells for Efficient Neural Radiance Field Rendering" (Wang et al. 2023).
Section numbers below refer to it. Every field carries a comment; the CLI assembles these
from defaults, an optional JSON file (``--config FILE``) and command-line flags.

A JSON config file has one object per component, e.g.::

    {"field": {"log2_hashmap_size": 19}, "train": {"iters": 2000}}

Unknown sections or keys are an error (a typo must not be silently ignored).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from shells.errors import InputError

# train.color_loss, finetune.color_loss (`shells.train.loop.color_loss`)
COLOR_LOSSES = ("l1", "l2", "rmse")


@dataclass
class DataConfig:
    """How the data set's images are read (one setting for every stage and renderer)."""

    background: tuple[float, float, float] = (1.0, 1.0, 1.0)  # RGB that RGBA images are
    # composited on and that every renderer shows behind the content (stage 1, stage 2, render)


@dataclass
class FieldConfig:
    """Hash-grid SDF field with a spatially varying kernel (§4.1)."""

    n_levels: int = 14  # hash-grid levels L
    n_features_per_level: int = 2  # features F per level
    log2_hashmap_size: int = 22  # table size T = 2**log2_hashmap_size entries per level
    base_resolution: int = 16  # coarsest grid resolution
    max_resolution: int = 4096  # finest grid resolution (per_level_scale derived from it)
    geo_hidden: int = 64  # hidden width of the geometry MLP (31 -> 64 -> 31 in the paper)
    geo_feature_dim: int = 26  # geometry feature passed to the radiance MLP
    rad_hidden: int = 64  # hidden width of the radiance MLP (48 -> 64 -> 64 -> 3)
    rad_layers: int = 2  # hidden layers of the radiance MLP
    sh_degree: int = 4  # degree of the spherical-harmonics direction encoding (16 values)
    init_radius: float = 0.5  # geometric init: SDF starts as a sphere of this radius (world units)
    init_kernel: float = 0.05  # initial kernel size s (world units) everywhere
    min_kernel: float = 1e-4  # lower clamp on s (numerical safety)
    max_kernel: float = 1.0  # upper clamp on s
    global_kernel: bool = False  # one learned s for the whole scene (ablation, paper Table 4)
    # unbounded captures (paper §4.7; shells/fields/contraction.py): the field lives in
    # contracted space, x -> centre + radius c((x - centre) / radius), over the box
    # centre +- 2 radius; the identity inside the ball of interest (so world units there)
    unbounded: bool = False  # set by shells-train --scene unbounded (or from the data set)
    centre: tuple[float, float, float] = (0.0, 0.0, 0.0)  # the ball of interest (world)
    radius: float = 1.0  # its radius (world units)
    far_radius: float = 1.95  # contracted radius (in radius units, in (1, 2)) beyond which
    # everything is solid: the far background every ray ends on (1.95: 20 radii away)
    near_radius: float = 1.0  # contracted radius (in radius units, in [1, far_radius)) of the
    # sphere where rays start (shells.render.warp.ray_span): 1 = the ball of interest, a ray
    # that misses it starting at its point nearest the centre; 1.5 = a sphere of 2 radii


@dataclass
class TrainConfig:
    """Stage-1 training by full-ray NeuS volume rendering (§3.1, §3.5, Eq. 8-12)."""

    iters: int = 20000  # optimisation steps
    batch_rays: int = 4096  # rays per step
    pixel_samples: int = 1  # rays per training pixel, k x k jittered sub-pixel positions whose
    # colours are averaged before the loss (box-filtered pixels; 1 = one ray at the centre);
    # a step takes batch_rays / pixel_samples pixels
    shards: int = 1  # a step's rays are drawn in this many shards, each from its own random
    # stream; N data-parallel processes take shards r, r + N, ... (N must divide it); the
    # default becomes the number of processes when a run starts under torchrun
    hashgrid: str = "compiled"  # the hash grid's lookups with gradient: "compiled" = the
    # compiled CPU kernels, the table's gradient in a persistent buffer (one process; under
    # torchrun the kernels with autograd's gradient; `shells.fields.hashgrid_cpu`,
    # `shells.train.optim`), "torch" = the torch lookup and autograd (the reference; CUDA
    # always); the same arithmetic up to the order of float sums
    sampler: str = "box"  # where a ray's samples go: "box" = its whole chord through the scene
    # box; "occupancy" = the span between the first and last occupied cell of an occupancy grid
    # rebuilt from the field (empty-space skipping; rays crossing no occupied cell are not
    # sampled, and a step draws rays until batch_rays of them cross one)
    occ_resolution: int = 64  # "occupancy": grid cells per axis over the scene box
    occ_k: float = 5.0  # "occupancy": occupied where |f| < half cell diagonal + occ_k * s
    occ_every: int = 32  # "occupancy": steps between grid rebuilds
    occ_warmup: int = 256  # "occupancy": steps with whole chords before the first grid build
    occ_rescue: float = 0.0  # "occupancy": a pixel whose rays cross no occupied cell but whose
    # target differs from the colour it would get (its background) by more than this in some
    # channel is rendered on its whole box chord, so content the grid lost can come back
    # (0 = off: such pixels get their background and no gradient)
    reg_points: int = 4096  # points per step for the Eikonal, normal and smoothness terms
    # (half of them ray samples, half uniform in the box)
    reg_rays: str = "uniform"  # how the ray half is drawn: "uniform" over the step's samples;
    # "level_set": half in proportion to the compositing weight, half uniformly among the
    # samples near the level set (|f| < h + occ_k s), so the normal term acts where rays end
    # and where they cross the surface (`shells.train.stage1.reg_points`)
    offband_weight: float = 0.0  # weight of the off-band term: the compositing weight that lies
    # inside a solid, off its level set (f < -(h + occ_k s), h the half diagonal of an
    # occ_resolution cell), which every skipping renderer (shells, occupancy grid) drops
    free_weight: float = 0.0  # weight of the free-space term: mean relu(-f) over the ray
    # samples a ray reaches with transmittance above free_transmittance, i.e. space the render
    # itself says is empty; an SDF is positive there, but NeuS lets the field keep a
    # transparent solid (f < 0, rising along the ray) that the shells would close
    # (`shells.train.stage1.free_space`); 0 = off
    free_transmittance: float = 0.99  # "free": the ray's transmittance before the sample
    coarse_to_fine_iters: int = 0  # Neuralangelo: the hash levels are switched on one by one
    # over this many steps (0 = all levels from the start)
    coarse_to_fine_start: int = 4  # levels active at step 0 when coarse_to_fine_iters > 0
    color_loss: str = "l1"  # the colour term: "l1" mean |error| (NeuS), "l2" mean squared
    # error, "rmse" its square root (`shells.train.loop.color_loss`)
    random_background: bool = False  # RGBA data: each training pixel on a random colour, drawn
    # per pixel and step, and its rays rendered on the same colour (Instant-NGP), so the field
    # cannot keep unseen matter coloured like the background; no effect on data whose alpha
    # holds no transparency (`shells.data.datasets.has_transparency`: the background is baked in)
    # or on an unbounded field (its rays all end on the far solid)
    cull_weight: float = 0.0  # samples whose compositing weight (from a pass without
    # gradient) is below this get no gradient pass: they keep their values, detached (nerfacc's
    # culling; the render is unchanged but for the colour of samples under UNLIT * this, at
    # most S UNLIT cull per ray, `shells.render.volume.render_volume_rays`); 0 = off
    slope: str = "normal"  # where stage 1's NeuS opacity takes the SDF's slope along a ray:
    # "normal" = d . n, the predicted normal (paper Eq. 8); "ray" = df/dt from the ray's own
    # samples (central differences), so density sits where f falls through zero along the
    # ray and the predicted normal is trained by the normal term only
    # (`shells.render.volume.render_volume_rays`); stage 2 and the band renderer use "normal"
    n_samples: int = 64  # uniform samples per ray inside the scene box
    n_importance: int = 64  # extra samples per ray drawn from the coarse weights (0 = off)
    lr: float = 1e-2  # Adam learning rate for hash-grid tables
    lr_mlp: float = 1e-3  # Adam learning rate for MLP weights
    warmup_iters: int = 200  # linear learning-rate warm-up
    lr_final_factor: float = 0.05  # cosine decay to lr * this factor at the last step
    eikonal_weight: float = 0.1  # Eq. 10: (|grad f| - 1)^2, finite differences
    kernel_smooth_weight: float = 0.01  # Eq. 11: |log s(x) - log s(x + N(0, eps^2))|
    normal_weight: float = 0.1  # Eq. 12: |n - grad f / |grad f||
    normal_delay: int = 0  # steps with the normal term off, then it rises linearly to
    normal_ramp: int = 0  # normal_weight over this many steps (0, 0: on from the start)
    smooth_eps: float = 0.01  # std of the kernel-smoothness perturbation (world units)
    fd_eps: float = 1e-3  # finite-difference step for grad f (world units)
    seed: int = 0  # RNG seed for sampling and init
    checkpoint_every: int = 500  # steps between atomic checkpoints
    log_every: int = 50  # steps between JSON-lines log records
    eval_max_views: int = 0  # test views scored at the end (0 = all)
    eval_density: int = 1  # the trainer's own renders (running curve, test PSNR, stage-1
    # renders) take this many times n_samples and n_importance per ray: a sharp field's
    # training samples step over its thin parts and under-report it
    curve_every: int = 0  # steps between points of the running test curve (RUN/train_curve.jsonl:
    # PSNR on a fixed pixel subset of curve_views test views against total wall time); 0 = off
    curve_views: int = 3  # test views of the running curve, evenly spaced over the split
    curve_pixels: int = 16384  # pixels per view of the running curve, fixed random ones


@dataclass
class ShellConfig:
    """Shell extraction by level-set dilation and erosion (§3.3, Procedures 1-2).

    Units (see shells/levelset/evolve.py): f and s in world units; speeds in world units per
    unit time; total time steps * dt = 5, so a free front moves 5 * v world units, and the
    falloff stops it at most zeta (world units of f) from the surface.
    """

    resolution: int = 256  # grid points per axis over the scene box (corners inclusive)
    steps: int = 50  # forward-Euler steps T (paper)
    dt: float = 0.1  # time step (paper); split into sub-steps when v_max * dt > cfl * h
    cfl: float = 0.5  # Courant number bounding each sub-step (not in the paper)
    dilate_zeta: float = 0.1  # soft-falloff width zeta for dilation (paper; world units of f)
    dilate_curvature: float = 0.01  # lambda_curv for dilation (paper; grid units, smoothing sign)
    erode_zeta: float = 0.05  # soft-falloff width zeta for erosion (paper)
    erode_curvature: float = 0.0  # lambda_curv for erosion (paper)
    beta_d: float = 0.6  # dilation speed per unit kernel size s, 1 / time: dilates ~3 s
    # (not in the paper; chosen on the toy sphere, see shells/levelset/evolve.py)
    sigma_min: float = 0.0  # threshold on the kernel size s: no dilation where s <= this
    beta_e: float = 0.3  # erosion speed per unit kernel size s: erodes 1.5 s (not in the paper)
    v_max: float = 0.035  # cap on both speeds, world units / time: 5 v_max = 0.175 > zeta,
    # and v_max dt < cfl h up to resolution 256 (one sub-step per step)
    support_k_outer: float = 0.0  # density support (not in the paper): M+ also encloses every
    # grid point with f < h + k s (h: half a cell's diagonal), the occupancy grid's rule
    # (`shells.fields.neus.may_have_density`) on the outside; 0 = the level-set shells only
    support_k_inner: float = 0.0  # and M- lies only where f < -(h + k s): a ray ends on M- only
    # past the layer that holds all but about e^-k of the surface's opacity; 0 = off
    min_component_fraction: float = 0.01  # drop mesh pieces smaller than this share of faces
    chunk: int = 262144  # grid points per field evaluation
    memory_mb: int = 2048  # memory budget of the level-set evolution, MiB: a band of more voxels
    # than fit (shells/levelset/evolve.py, BYTES_PER_BAND_VOXEL) is updated in chunks (same
    # result), so a 512^3 extraction stays in bounded memory


@dataclass
class RenderConfig:
    """Narrow-band sampling and rendering (§3.4, Procedure 3)."""

    spp: int = 1  # rays per pixel at the centres of k x k sub-pixel cells, averaged (box
    # filter); 1 = one ray through the pixel centre. samples_per_pixel counts all of them
    dp_max: int = 8  # at most this many M+ hits are peeled per ray
    w_s: float = 0.01  # intervals narrower than this get a single mid sample (world units)
    delta_s: float = 0.01  # sample spacing inside wider intervals (world units)
    n_max: int = 16  # cap on samples per interval
    full_samples: int = 256  # samples per ray in `full` mode (baseline, whole box)
    variant: str | None = None  # Mitsuba variant; None: from the torch device (cuda_ad_rgb on
    # CUDA, llvm_ad_rgb on the CPU)
    chunk_samples: int = 1 << 24  # samples of a batch at most: full and occupancy batches
    # count their rays' worst case, band batches the samples their rays get after the cast
    memory_mb: int = 1024  # memory budget of the ray batches, MiB: a batch holds as many rays as
    # fit with their worst-case samples, a band batch its rays in half of it and its samples,
    # shaded in groups of rays, in the other half (shells/render/frame.py, rays_per_batch), and a
    # frame larger than one batch is rendered in tiles of rows, so an 8K frame stays in bounded
    # memory
    # `occupancy` mode (Instant-NGP / nerfacc baseline, shells/render/occupancy.py):
    occ_resolution: int = 128  # occupancy-grid cells per axis over the scene box
    occ_k: float = 5.0  # occupied where |f| < half cell diagonal + occ_k * s (residual T < e^-k)
    occ_jitter: int = 2  # random points per cell evaluated besides its centre (grid building)
    occ_step: float = 0.0  # ray-marching step dt (world units); 0 = scene-box diagonal / 1024
    occ_chunk: int = 16  # samples per ray marched, evaluated and composited per round
    ert_eps: float = 1e-4  # early ray termination once transmittance drops below this
    # band mode's early ray termination (shells/render/frame.py, `_composite_rounds`): the band
    # samples are shaded front to back in rounds of band_chunk per live ray (doubling as rays
    # drop out), and a ray stops once its transmittance is below band_ert_eps; 0 = every
    # sample of Procedure 3 (the torch band renderer's rule, which stage 2 trains with). The
    # rounds have a fixed cost that small frames do not earn back (shells/presets.py, SHARP_BAND)
    band_ert_eps: float = 0.0
    band_chunk: int = 2
    band_peel_step: int = 0  # with band_ert_eps: M+ hits peeled at a time; after each step's
    # samples are shaded only the rays still letting light through peel on, up to dp_max
    # (`ShellScene.resume`). 0 = all dp_max hits at once
    # image-space adaptive refinement (shells-render --refine L, shells/render/refine.py): a
    # pixel is interpolated from its parents only if every test passes, else evaluated
    refine_levels: int = 0  # L: the coarse image takes every 2^L-th pixel; 0 = band mode as is
    refine_fuzzy_samples: int = 1  # a pixel with an interval of more samples than this is
    # fuzzy, always evaluated (1: any interval with two samples, the rule of the issue)
    refine_normal_cos: float = 0.95  # M+ first-hit normals of pixel and parents: dot >= this
    refine_depth: float = 0.01  # planar depth: |t - mean of the parents' t| <= this * t
    refine_grazing: float = 0.3  # not grazing: |d . n| >= this at the pixel's first hit
    refine_colour: float = 0.03  # parents' colours: max - min <= this in every channel
    refine_opaque: float = 0.99  # parents' opacity >= this (1 on rays that end on M-), or
    refine_clear: float = 0.0  # ... all parents' opacity <= this (a halo of the band that the
    # field leaves empty; 0 = only opaque parents, the rule of the issue)
    refine_field_normal: float = 0.1  # parents: 1 - n_face . n_field <= this (silhouette cue)
    refine_min_share: float = 0.25  # below this share of the covered coarse pixels that
    # could be interpolated at all (not fuzzy, not grazing) the tile is band-rendered as is


@dataclass
class FinetuneConfig:
    """Stage-2 fine-tuning inside the band (§3.5): colour loss, and the anchor outside M+."""

    iters: int = 2000  # optimisation steps
    batch_rays: int = 4096  # rays per step
    pixel_samples: int = 1  # rays per training pixel (k x k jittered, averaged), as in stage 1
    shards: int = 1  # ray shards per step, as in stage 1
    hashgrid: str = "compiled"  # as train.hashgrid
    color_loss: str = "l1"  # the colour loss, as train.color_loss
    lr: float = 1e-3  # Adam learning rate for hash tables
    lr_mlp: float = 1e-4  # Adam learning rate for MLP weights
    warmup_iters: int = 0  # linear learning-rate warm-up
    lr_final_factor: float = 0.1  # cosine decay to lr * this factor at the last step
    # The field outside M+, which the band never samples, held at its stage-1 values: weight
    # of mean |log s - log s1| + |f - f1| / (longest side of the field's box) at
    # `anchor_points` uniform points of the box outside M+ each step (0: off)
    anchor_weight: float = 0.1
    anchor_points: int = 1024
    seed: int = 0  # RNG seed
    checkpoint_every: int = 500  # steps between atomic checkpoints
    log_every: int = 50  # steps between JSON-lines log records


@dataclass
class Config:
    """Everything a run needs; saved as RUN/config.json."""

    data: DataConfig = dataclasses.field(default_factory=DataConfig)
    field: FieldConfig = dataclasses.field(default_factory=FieldConfig)
    train: TrainConfig = dataclasses.field(default_factory=TrainConfig)
    shell: ShellConfig = dataclasses.field(default_factory=ShellConfig)
    render: RenderConfig = dataclasses.field(default_factory=RenderConfig)
    finetune: FinetuneConfig = dataclasses.field(default_factory=FinetuneConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "config") -> "Config":
        """A Config from a stored dict (config.json, a checkpoint), checked.

        Runs made before the one `data.background` setting stored it as `train.background`
        and `render.background`; those keys are read into `data.background`.
        """
        data = {k: dict(v) if isinstance(v, dict) else v for k, v in data.items()}
        for old in ("train", "render"):
            if isinstance(data.get(old), dict) and "background" in data[old]:
                bg = data[old].pop("background")
                data.setdefault("data", {}).setdefault("background", bg)
        cfg = cls()
        cfg.update(data, source)
        return cfg

    def update(self, data: dict[str, Any], source: str = "config") -> None:
        """Override fields from a nested dict, then check every value (`check`).

        Unknown sections or keys, a wrong type or a value out of range raise a one-line
        InputError naming ``source`` and the key; nothing is changed then.
        """
        if not isinstance(data, dict):
            raise InputError(f"{source}: expected a JSON object with sections "
                             f"{[f.name for f in dataclasses.fields(self)]}")
        sections = {f.name for f in dataclasses.fields(self)}
        new = copy.deepcopy(self)
        for name, values in data.items():
            if name not in sections:
                raise InputError(f"{source}: unknown section '{name}'; valid: {sorted(sections)}")
            sub = getattr(new, name)
            valid = {f.name: f for f in dataclasses.fields(sub)}
            if not isinstance(values, dict):
                raise InputError(f"{source}: section '{name}' must be a JSON object")
            for key, value in values.items():
                if key not in valid:
                    raise InputError(f"{source}: unknown key '{name}.{key}'; valid: {sorted(valid)}")
                if isinstance(value, list):
                    value = tuple(value)
                _check_type(value, valid[key].type, f"{source}: '{name}.{key}'")
                setattr(sub, key, value)
        new.check(source)
        for f in dataclasses.fields(self):
            setattr(self, f.name, getattr(new, f.name))

    def check(self, source: str = "config") -> None:
        """Every value in its range (`_RULES`); a one-line InputError for the first that is not."""
        for key, ok, want in _RULES:
            section, name = key.split(".")
            value = getattr(getattr(self, section), name)
            if not ok(value, self):
                raise InputError(f"{source}: '{key}' = {value!r}: {want}")


def _check_type(value: Any, annotation: Any, where: str) -> None:
    """One-line error when a config value has the wrong JSON type (int accepted for float)."""
    ann = annotation if isinstance(annotation, str) else getattr(annotation, "__name__", "")
    optional = ann.endswith("| None")
    if optional:
        if value is None:
            return
        ann = ann[:-len("| None")].strip()
    ok = {"float": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
          "int": lambda v: isinstance(v, int) and not isinstance(v, bool),
          "bool": lambda v: isinstance(v, bool),
          "str": lambda v: isinstance(v, str)}.get(ann.split("[")[0])
    if ann.startswith("tuple"):
        ok = lambda v: isinstance(v, tuple)  # noqa: E731
    if ok is not None and not ok(value):
        raise InputError(f"{where} = {value!r}: expected {ann}{' or null' if optional else ''}")


def _square(n: int) -> bool:
    return n >= 1 and math.isqrt(n) ** 2 == n


def _rgb(v: Any) -> bool:
    return (isinstance(v, tuple) and len(v) == 3
            and all(isinstance(c, (int, float)) and not isinstance(c, bool) and 0 <= c <= 1
                    for c in v))


def _rule(key: str, ok: Any, want: str) -> tuple[str, Any, str]:
    """(key, predicate(value, config), what the value must be)."""
    n_args = ok.__code__.co_argcount - len(ok.__defaults__ or ())
    return key, (ok if n_args == 2 else lambda v, c: ok(v)), want


def _at_least(lo: float) -> tuple[Any, str]:
    return (lambda v: v >= lo), f"must be >= {lo:g}"


def _positive() -> tuple[Any, str]:
    return (lambda v: v > 0), "must be > 0"


def _fraction() -> tuple[Any, str]:
    return (lambda v: 0 <= v <= 1), "must be in [0, 1]"


_SQUARE = (_square, "must be a square number of rays (1, 4, 9, 16, ...)")
_RULES = [_rule(k, *r) for k, r in [
    ("data.background", (_rgb, "expected three values (R, G, B) in [0, 1]")),
    *[(f"field.{k}", _at_least(1)) for k in ("n_levels", "n_features_per_level",
                                             "log2_hashmap_size", "geo_hidden",
                                             "geo_feature_dim", "rad_hidden", "rad_layers")],
    ("field.base_resolution", _at_least(2)),
    ("field.max_resolution", (lambda v, c: v >= c.field.base_resolution,
                              "must be >= field.base_resolution")),
    ("field.sh_degree", ((lambda v: 1 <= v <= 4), "supported degrees are 1..4 (sh_encode)")),
    ("field.init_radius", _positive()),
    ("field.radius", _positive()),
    ("field.far_radius", ((lambda v: 1.0 < v < 2.0), "must be in (1, 2) (contracted space "
                          "ends at 2)")),
    ("field.near_radius", (lambda v, c: 1.0 <= v < c.field.far_radius,
                           "must be in [1, field.far_radius) (1: the ball of interest; "
                           "rays must start before the far solid)")),
    ("field.centre", ((lambda v: isinstance(v, tuple) and len(v) == 3
                       and all(isinstance(c, (int, float)) and math.isfinite(c) for c in v)),
                      "expected three finite numbers (x, y, z)")),
    ("train.sampler", (lambda v, c: not (c.field.unbounded and v == "occupancy"),
                       "the occupancy sampler is for bounded scenes; an unbounded field "
                       "samples evenly in contracted space (train.sampler 'box')")),
    ("field.min_kernel", _positive()),
    ("field.init_kernel", (lambda v, c: c.field.min_kernel < v < c.field.max_kernel,
                           "need field.min_kernel < init_kernel < max_kernel")),
    *[(f"{s}.{k}", _at_least(1)) for s in ("train", "finetune")
      for k in ("iters", "batch_rays", "checkpoint_every", "log_every")],
    *[(f"{s}.pixel_samples", _SQUARE) for s in ("train", "finetune")],
    *[(f"{s}.shards", _at_least(1)) for s in ("train", "finetune")],
    *[(f"{s}.batch_rays", (lambda v, c, s=s: v % getattr(c, s).shards == 0,
                           f"must be a multiple of {s}.shards"))
      for s in ("train", "finetune")],
    *[(f"{s}.batch_rays", (lambda v, c, s=s: v // getattr(c, s).shards
                           >= getattr(c, s).pixel_samples,
                           f"must be >= {s}.pixel_samples x {s}.shards (a pixel's rays per shard)"))
      for s in ("train", "finetune")],
    *[(f"{s}.{k}", _positive()) for s in ("train", "finetune") for k in ("lr", "lr_mlp")],
    *[(f"{s}.warmup_iters", _at_least(0)) for s in ("train", "finetune")],
    ("finetune.anchor_weight", _at_least(0)),
    ("finetune.anchor_points", _at_least(1)),
    *[(f"{s}.lr_final_factor", _fraction()) for s in ("train", "finetune")],
    ("train.n_samples", _at_least(1)),
    *[(f"train.{k}", _at_least(0)) for k in ("n_importance", "eikonal_weight",
                                            "kernel_smooth_weight", "normal_weight",
                                            "smooth_eps", "eval_max_views", "offband_weight",
                                            "cull_weight", "free_weight", "curve_every")],
    *[(f"train.{k}", _at_least(1)) for k in ("curve_views", "curve_pixels", "eval_density")],
    ("train.free_transmittance", ((lambda v: 0 < v < 1), "must be in (0, 1)")),
    *[(f"{s}.color_loss", ((lambda v: v in COLOR_LOSSES), f"must be one of {COLOR_LOSSES}"))
      for s in ("train", "finetune")],
    *[(f"{s}.hashgrid", ((lambda v: v in ("compiled", "torch")),
                         "must be 'compiled' or 'torch'")) for s in ("train", "finetune")],
    ("train.slope", ((lambda v: v in ("normal", "ray")), "must be 'normal' or 'ray'")),
    ("train.reg_rays", ((lambda v: v in ("uniform", "level_set")),
                        "must be 'uniform' or 'level_set'")),
    ("train.fd_eps", _positive()),
    ("train.sampler", ((lambda v: v in ("box", "occupancy")), "must be 'box' or 'occupancy'")),
    *[(f"train.{k}", _at_least(1)) for k in ("occ_resolution", "occ_every", "reg_points",
                                            "coarse_to_fine_start")],
    *[(f"train.{k}", _at_least(0)) for k in ("occ_k", "occ_warmup", "occ_rescue",
                                            "coarse_to_fine_iters",
                                            "normal_delay", "normal_ramp")],
    ("shell.resolution", _at_least(8)),
    *[(f"shell.{k}", _at_least(0)) for k in ("steps", "dilate_curvature", "erode_curvature",
                                            "beta_d", "sigma_min", "beta_e",
                                            "support_k_outer", "support_k_inner")],
    *[(f"shell.{k}", _positive()) for k in ("dt", "cfl", "dilate_zeta", "erode_zeta",
                                           "v_max")],
    ("shell.min_component_fraction", ((lambda v: 0 <= v < 1), "must be in [0, 1)")),
    ("shell.chunk", _at_least(1)),
    ("shell.memory_mb", _at_least(1)),
    ("render.spp", _SQUARE),
    *[(f"render.{k}", _at_least(1)) for k in ("dp_max", "n_max", "full_samples",
                                             "chunk_samples", "occ_resolution", "occ_chunk",
                                             "memory_mb")],
    *[(f"render.{k}", _at_least(0)) for k in ("w_s", "occ_jitter", "occ_step")],
    *[(f"render.{k}", _positive()) for k in ("delta_s", "occ_k")],
    ("render.ert_eps", ((lambda v: 0 <= v < 1), "must be in [0, 1)")),
    ("render.band_ert_eps", ((lambda v: 0 <= v < 1), "must be in [0, 1)")),
    ("render.band_chunk", _at_least(1)),
    ("render.band_peel_step", _at_least(0)),
    ("render.refine_levels", ((lambda v: 0 <= v <= 6), "must be in 0..6")),
    ("render.refine_fuzzy_samples", _at_least(1)),
    *[(f"render.{k}", _fraction()) for k in ("refine_normal_cos", "refine_grazing",
                                             "refine_opaque", "refine_clear",
                                             "refine_min_share")],
    *[(f"render.{k}", _at_least(0)) for k in ("refine_depth", "refine_colour",
                                             "refine_field_normal")],
]]


def read_config_file(path: str | Path) -> dict[str, Any]:
    """The JSON object of a config file (sections as in `Config`); one-line errors."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: config file not found; pass an existing JSON file to --config")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: malformed JSON ({exc.msg} at line {exc.lineno}); fix the file")
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a JSON object with sections "
                         f"{[f.name for f in dataclasses.fields(Config)]}")
    return data


def load_config(path: str | Path | None, base: Config | None = None) -> Config:
    """Read a JSON config file on top of ``base`` (default: paper defaults)."""
    cfg = base if base is not None else Config()
    if path is None:
        return cfg
    cfg.update(read_config_file(path), str(path))
    return cfg


def override_config(cfg: Config, path: str | Path | None, allowed: tuple[str, ...],
                    command: str) -> Config:
    """Apply a JSON config file to the config of a trained run, in place.

    Only the sections in ``allowed`` may appear: the field architecture and the stage-1 schedule
    are fixed once a run is trained, so e.g. ``shells-extract`` takes only ``shell``.
    """
    if path is None:
        return cfg
    data = read_config_file(path)
    bad = sorted(set(data) - set(allowed))
    if bad:
        raise InputError(f"{path}: {command} --config takes only the section(s) "
                         f"{list(allowed)}, got {bad}; those are fixed by the trained run")
    cfg.update(data, str(path))
    return cfg
