"""Stage 1: the field trained by full-ray NeuS volume rendering and its losses (§3.1-3.2, §3.5).

Loss (Eq. 8-12): L = L1 colour + w_eik (|grad f| - 1)^2 + w_smooth |log s(x) - log s(x + n)|
+ w_normal |n(x) - grad f / |grad f||, n ~ N(0, eps^2), grad f by central differences; w_normal
may be switched on late and ramped in (``normal_delay``, ``normal_ramp``: `normal_factor`).
The regularisers are evaluated on a subset of the ray samples plus uniform points in the box
(``reg_rays``: which samples). Logged as ``off_band``: the share of the compositing weight inside
a solid off its level set, which the shells and the occupancy grid cannot see (`off_band`;
``offband_weight`` > 0 makes it a loss term).

Sampling (`TrainConfig.sampler`): "box" samples every ray over its whole chord through the
scene box; "occupancy" keeps an occupancy grid of the field (`shells.render.volume.SpanGrid`,
rebuilt every ``occ_every`` steps after ``occ_warmup``, stored in the checkpoints), samples each
ray only over the span of occupied cells it crosses and skips the rays that cross none. Those
rays cost nothing and still enter the loss (as background), and a step draws pixels until
``batch_rays`` of them cross an occupied cell, so the number of field samples per step stays
fixed while the number of rays grows as the grid empties. With ``occ_rescue``, a skipped pixel
whose target is not its background is sampled over its whole chord instead (content the grid
lost); with ``cull_weight``, samples of negligible weight get no gradient pass
(`shells.render.volume.render_volume_rays`). Coarse-to-fine (Neuralangelo,
``coarse_to_fine_iters``): the hash levels are switched on one by one.

The steps run in `shells.train.loop.optimise` (schedule, progress, logs, checkpoints, exact resume);
the run directory is read and written through `shells.run`.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from torch.profiler import record_function

from shells import distributed
from shells.config import Config, TrainConfig
from shells.data.datasets import Dataset, has_transparency, load_dataset
from shells.errors import InputError
from shells.files import write_json
from shells.fields.hashgrid import drjit_on_calling_thread
from shells.fields.network import ShellField
from shells.fields.neus import half_cell_diagonal, may_have_density
from shells.metrics import psnr
from shells.progress import tqdm
from shells.render.volume import SpanGrid, ray_aabb, render_volume_image, render_volume_rays
from shells.run import (RunDir, append_log, field_from_checkpoint, read_checkpoint, read_run,
                        truncate_log, write_run)
from shells.train.health import Stage1Health, probe_points, psnr_floor, solid_share
from shells.train.loop import Schedule, color_loss, join, optimise, psnr_of
from shells.train.optim import make_optimizer, use_hashgrid

MAX_DRAWS = 8  # "occupancy" sampler: at most this many rounds of pixels drawn per shard


def build_field(cfg: Config, aabb: torch.Tensor, device: torch.device) -> ShellField:
    torch.manual_seed(cfg.train.seed)
    return ShellField(cfg.field, aabb.to(device)).to(device)


# ---------------------------------------------------------------------------------------------
# Losses
# ---------------------------------------------------------------------------------------------

def regularisers(field: ShellField,
                 points: torch.Tensor,  # [M, 3] field-space points (the world if bounded)
                 fd_eps: float,
                 smooth_eps: float,
                 gen: torch.Generator,
                 ) -> dict[str, torch.Tensor]:
    """Eikonal (Eq. 10), kernel smoothness (Eq. 11) and normal (Eq. 12) terms on `points`.

    All three act in field space: an unbounded field is an SDF of the contracted point z
    (|grad_z f| = 1), not of the world point, whose metric stretches without bound far away;
    there the kernel and the level-set grid live too, so the terms keep their meaning (and
    fd_eps, smooth_eps their units) everywhere. And they act on the network alone, without
    the far solid: that solid is an exact SDF with exact normals, so on min(f_net, solid) the
    terms fell to zero once f_net rose above the solid everywhere, and they drove it there
    (the toy ball was gone within 150 steps of the regularisers alone; BENCHMARKS.md)."""
    noise = torch.randn(points.shape, generator=gen, device=points.device) * smooth_eps
    probe = field.regulariser_probe(points, fd_eps, points + noise)  # one batched evaluation
    grad = probe["grad"]  # [M, 3]
    gnorm = grad.norm(dim=-1)
    eikonal = ((gnorm - 1.0) ** 2).mean()
    target = grad.detach() / gnorm.detach().clamp_min(1e-6)[:, None]
    normal = (probe["normal"] - target).norm(dim=-1).mean()
    smooth = (torch.log(probe["s"]) - torch.log(probe["s_extra"])).abs().mean()
    return {"eikonal": eikonal, "normal": normal, "smooth": smooth}


def reg_points(field: ShellField, ray_points: torch.Tensor, n: int,
               gen: torch.Generator, weights: torch.Tensor | None = None,
               near: torch.Tensor | None = None) -> torch.Tensor:
    """Field-space points: half from the ray samples (where the image loss acts), half uniform
    in the field's box (all uniform when there are no ray samples). An unbounded field's
    uniform points are split between its box and the cube around the ball of interest (which
    holds 1/8 of that box's volume, and the object).

    The ray half is drawn uniformly over the samples, or (``weights`` and ``near`` given, the
    shape of ``ray_points[..., 0]``: ``train.reg_rays`` "level_set") half in proportion to the
    compositing weight and half uniformly among the samples near the level set: there a
    predicted normal that disagrees with grad f decides whether a ray is absorbed at the
    crossing or passes into the solid."""
    flat = field.to_field(ray_points.detach().reshape(-1, 3))
    n_ray = n // 2 if flat.shape[0] else 0
    if weights is None or n_ray == 0:
        pick = torch.randint(0, max(1, flat.shape[0]), (n_ray,), generator=gen,
                             device=flat.device)
    else:
        w = weights.detach().reshape(-1).clamp_min(0) + 1e-12
        m = near.reshape(-1).to(w.dtype) + 1e-12  # uniform over all when none is near
        n_w = n_ray // 2
        pick = torch.cat([torch.multinomial(w, n_w, replacement=True, generator=gen),
                          torch.multinomial(m, n_ray - n_w, replacement=True, generator=gen)])
    lo, hi = field.aabb[0], field.aabb[1]
    uni = lo + (hi - lo) * torch.rand(n - n_ray, 3, generator=gen, device=flat.device)
    if field.similarity is not None:  # the second half of them in the ball's cube
        k = (n - n_ray) // 2
        uni[k:] = 0.5 * (lo + hi) + 0.5 * (uni[k:] - 0.5 * (lo + hi))
    return torch.cat([flat[pick], uni])


def off_band(field: ShellField, out: dict[str, torch.Tensor], tc: TrainConfig,
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The weight a skipping renderer drops, of the rays in ``out`` (`render_volume_rays`).

    A sample is near the level set when |f| < h + occ_k s (`may_have_density`, h the half
    diagonal of an ``occ_resolution`` cell of the field's box), and off the band inside a
    solid when f < -(h + occ_k s): a ray reaches such a sample only if it was not absorbed
    where it crossed f = 0 (the predicted normal said it was leaving there), and neither the
    shells nor an occupancy grid sample it. Returns (the mean over rays of the weight there,
    with gradient: the off-band term; its share of all the weight, detached; near [R, S])."""
    h = half_cell_diagonal(field.aabb, tc.occ_resolution)
    f = out["sdf"].detach()
    near = may_have_density(f, out["s"].detach(), h, tc.occ_k)
    off = (f < 0) & ~near
    w = out["weights"]
    term = (w * off).sum(1).mean()
    share = term.detach() / w.detach().sum(1).mean().clamp_min(1e-12)
    return term, share, near


def free_space(out: dict[str, torch.Tensor], tc: TrainConfig,
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """The free-space term of the rays in ``out`` (`render_volume_rays`): the mean of relu(-f)
    over the samples reached with transmittance T_i = 1 - sum_{j<i} w_j (detached) above
    ``free_transmittance``, with gradient through f; and the share of those samples at f < 0
    (detached, for the log)."""
    w = out["weights"].detach()
    trans = 1.0 - (torch.cumsum(w, dim=1) - w)  # before each sample
    free = (trans > tc.free_transmittance) & out["hit"][:, None]
    n = free.sum().clamp_min(1)
    term = (torch.relu(-out["sdf"]) * free).sum() / n
    share = ((out["sdf"].detach() < 0) & free).sum() / n
    return term, share


def draw_pixels(data: Dataset, grid: SpanGrid, n_rays: int, spp: int, gen: torch.Generator,
                ) -> tuple[torch.Tensor, ...]:
    """Pixels drawn in rounds of ``n_rays / spp`` until that many cross an occupied cell (at
    most MAX_DRAWS rounds), cut after the pixel that completes the count.

    Returns idx [P], origins, dirs [P * spp, 3], near, far, hit [P * spp] (the rays' spans)
    and crosses [P] (the pixel has a ray that crosses an occupied cell)."""
    want = max(1, n_rays // spp)
    parts, got = [], 0
    for _ in range(MAX_DRAWS):
        idx, o, d = data.sample_pixel_rays(n_rays, spp, gen)
        near, far, hit = grid.spans(o, d)
        crosses = hit.view(-1, spp).any(1)
        count = crosses.cumsum(0)
        if got + int(count[-1]) >= want:
            cut = int(torch.searchsorted(count, want - got)) + 1  # pixels kept
            r = cut * spp
            parts.append((idx[:cut], o[:r], d[:r], near[:r], far[:r], hit[:r], crosses[:cut]))
            break
        parts.append((idx, o, d, near, far, hit, crosses))
        got += int(count[-1])
    return tuple(torch.cat(p) for p in zip(*parts))


def normal_factor(step: int, tc: TrainConfig) -> float:
    """Share of ``normal_weight`` at ``step``: 0 for the first ``normal_delay`` steps, then
    rising linearly to 1 over ``normal_ramp`` steps (1 throughout with both 0)."""
    if step < tc.normal_delay:
        return 0.0
    if tc.normal_ramp <= 0:
        return 1.0
    return min(1.0, (step - tc.normal_delay + 1) / tc.normal_ramp)


def random_backgrounds(idx: torch.Tensor,  # [P] flat pixel indices of a step
                       pixels: torch.Tensor,  # [N, 3] training pixels composited on `background`
                       alpha: torch.Tensor,  # [N] their alpha
                       background: torch.Tensor,  # [3] the data's compositing colour
                       gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """``train.random_background``: a uniform random colour b per pixel and the pixel
    recomposited on it, c + (b - background) (1 - alpha), exact because compositing is linear
    (also after area downscaling). Returns b [P, 3] and the targets [P, 3]."""
    bg = torch.rand(len(idx), 3, generator=gen, device=gen.device).to(pixels.device)
    return bg, pixels[idx] + (bg - background) * (1.0 - alpha[idx])[:, None]


def stage1_step(field: ShellField, data: Dataset, pixels: torch.Tensor, tc: TrainConfig,
                background: torch.Tensor, gen: torch.Generator,
                grid: SpanGrid | None = None, step: int = 0,
                alpha: torch.Tensor | None = None,
                ) -> tuple[torch.Tensor, dict[str, float]]:
    """Loss of one shard of step ``step`` and its scalar logs. "box" sampler (``grid`` None):
    ``batch_rays / shards`` random rays drawn with ``gen``; "occupancy": `draw_pixels`. The
    normal term's weight follows `normal_factor`. ``alpha`` [N] (the pixels' alpha): each
    pixel on a random background (`random_backgrounds`); None: all on ``background``."""
    spp = tc.pixel_samples
    n_rays = tc.batch_rays // tc.shards
    with record_function("stage 1: draw pixels"):
        if grid is None:
            idx, o, d = data.sample_pixel_rays(n_rays, spp, gen)
        else:
            idx, o, d, near, far, hit, crosses = draw_pixels(data, grid, n_rays, spp, gen)
    if alpha is None:
        target, pixel_bg = pixels[idx], background.expand(len(idx), 3)
    else:
        pixel_bg, target = random_backgrounds(idx, pixels, alpha, background, gen)
    ray_bg = pixel_bg.repeat_interleave(spp, dim=0)  # [P * spp, 3], a pixel's rays contiguous
    rescued = 0
    if grid is not None and tc.occ_rescue > 0:  # lost content: the whole chord
        lost = ~crosses & ((target - pixel_bg).abs().amax(-1) > tc.occ_rescue)
        if lost.any():
            r = lost.repeat_interleave(spp)
            n0, f0, h0 = ray_aabb(o[r], d[r], field.aabb)
            near, far, hit = near.clone(), far.clone(), hit.clone()
            near[r], far[r], hit[r] = n0, f0, h0
            crosses = crosses | lost
            rescued = int(lost.sum())
    if grid is None:
        out = render_volume_rays(field, o, d, tc.n_samples, tc.n_importance, ray_bg, gen,
                                 cull=tc.cull_weight, slope=tc.slope)
        pred = out["color"].reshape(len(idx), spp, 3).mean(1)  # box filter
        rendered = len(o)
    else:
        m = crosses.repeat_interleave(spp)  # the rays of the pixels that cross
        pred = pixel_bg.clone()
        rendered = int(m.sum())
        out = None
        if rendered:
            out = render_volume_rays(field, o[m], d[m], tc.n_samples, tc.n_importance,
                                     ray_bg[m], gen,
                                     span=(near[m], far[m], hit[m]), cull=tc.cull_weight,
                                     slope=tc.slope)
            pred[crosses] = out["color"].reshape(-1, spp, 3).mean(1)  # box filter
    color = color_loss(pred, target, tc.color_loss)
    zero = color.new_zeros(())
    if out is None:
        points, off, share, near_ls = o.new_zeros(0, 3), zero, zero, None
        free, free_share = zero, zero
        grad_samples = 0
    else:
        grad_samples = int(out["grad"].sum())
        points = out["points"]
        off, share, near_ls = off_band(field, out, tc)
        free, free_share = free_space(out, tc)
    level_set = tc.reg_rays == "level_set" and out is not None
    with record_function("stage 1: regularisers"):
        pts = reg_points(field, points, tc.reg_points // tc.shards, gen,
                         weights=out["weights"] if level_set else None,
                         near=near_ls if level_set else None)
        reg = regularisers(field, pts, tc.fd_eps, tc.smooth_eps, gen)
    w_normal = tc.normal_weight * normal_factor(step, tc)
    loss = (color + tc.eikonal_weight * reg["eikonal"] + tc.kernel_smooth_weight * reg["smooth"]
            + w_normal * reg["normal"])
    if tc.offband_weight > 0:
        loss = loss + tc.offband_weight * off
    if tc.free_weight > 0:
        loss = loss + tc.free_weight * free
    with torch.no_grad():
        mse = ((pred.clamp(0, 1) - target) ** 2).mean().item()
    return loss, {"loss": loss.item(), "color": color.item(),
                  "eikonal": reg["eikonal"].item(), "normal": reg["normal"].item(),
                  "smooth": reg["smooth"].item(), "w_normal": w_normal, "psnr": psnr_of(mse),
                  "off_band": float(share), "free_negative": float(free_share),
                  "rays": float(len(idx) * spp),
                  "samples": float(rendered * (tc.n_samples + tc.n_importance)),
                  "grad_samples": float(grad_samples), "rescued": float(rescued)}


def active_levels(step: int, tc: TrainConfig, n_levels: int) -> int | None:
    """Hash levels in use at ``step`` (coarse-to-fine); None = all."""
    if tc.coarse_to_fine_iters <= 0 or step >= tc.coarse_to_fine_iters:
        return None
    start = min(tc.coarse_to_fine_start, n_levels)
    return min(n_levels, start + step * (n_levels - start) // tc.coarse_to_fine_iters)


def before_step(field: ShellField, grid: SpanGrid | None, tc: TrainConfig, step: int) -> None:
    """Stage 1's own schedule: the active hash levels, then the occupancy-grid rebuilds."""
    field.active_levels = active_levels(step, tc, field.cfg.n_levels)
    if grid is not None and step >= tc.occ_warmup and (step - tc.occ_warmup) % tc.occ_every == 0:
        grid.update(field)


# ---------------------------------------------------------------------------------------------
# Evaluation and the stage
# ---------------------------------------------------------------------------------------------

def eval_samples(tc: TrainConfig) -> tuple[int, int]:
    """Samples per ray of the trainer's own renders (running curve, test PSNR,
    `stage1_renderer`): ``eval_density`` times the training's (n_samples, n_importance)."""
    return tc.n_samples * tc.eval_density, tc.n_importance * tc.eval_density


def stage1_grid(ckpt: dict[str, Any], field: ShellField, cfg: Config) -> SpanGrid | None:
    """The occupancy grid stored in a stage-1 checkpoint of the "occupancy" sampler (None for
    "box"): what stage 1's own renderer (`evaluate`) samples with."""
    if cfg.train.sampler != "occupancy":
        return None
    grid = SpanGrid(field.aabb, cfg.train.occ_resolution, cfg.train.occ_k)
    grid.load_state_dict(ckpt.get("extra") or {})
    return grid


def stage1_renderer(run_dir: str | Path, data_dir: str | Path
                  ) -> tuple[Dataset, Callable[[int], tuple[np.ndarray, np.ndarray]]]:
    """The test split of ``data_dir`` on the run's background, and a function that renders its
    view i with the run's stage-1 field as stage 1 samples it (full ray, the checkpoint's
    occupancy grid where it has one, `eval_samples` a ray): (colour [H, W, 3], opacity
    [H * W]) as numpy arrays."""
    ckpt = read_checkpoint(RunDir(run_dir))
    field, cfg = field_from_checkpoint(ckpt, "stage 1")
    grid = stage1_grid(ckpt, field, cfg)
    test = load_dataset(data_dir, "test", background=cfg.data.background)
    H, W = test.images.shape[1:3]
    bg = torch.tensor(cfg.data.background)

    def render(i: int) -> tuple[np.ndarray, np.ndarray]:
        ro, rd = test.cameras.pixel_rays(i, 1)
        with torch.no_grad():
            img = render_volume_image(field, ro, rd, *eval_samples(cfg.train), bg, grid=grid,
                                      slope=cfg.train.slope)
        return img["color"].reshape(H, W, 3).numpy(), img["opacity"].numpy()

    return test, render


class RunningCurve:
    """Stage 1's running test curve: every ``train.curve_every`` steps, the full-ray PSNR of a
    fixed random subset of pixels (``curve_pixels`` per view) of ``curve_views`` test views
    spread over the split (`eval_samples` a ray), appended with the step and the wall time to
    RUN/train_curve.jsonl. Uniformly drawn pixels give an unbiased estimate of the views' mean
    squared error at a small share of a full render's cost; the training's random streams are
    not touched."""

    def __init__(self, test: Dataset, tc: TrainConfig, path: Path, device: torch.device) -> None:
        n_views, k = len(test), min(tc.curve_views, len(test))
        self.views = sorted({round(i * (n_views - 1) / max(1, k - 1)) for i in range(k)})
        gen = torch.Generator().manual_seed(tc.seed)
        H, W = test.images.shape[1:3]
        rays, targets = [], []
        for i in self.views:
            pick = torch.randperm(H * W, generator=gen)[:tc.curve_pixels]
            o, d = test.cameras.pixel_rays(i, 1)
            rays.append((o[pick], d[pick]))
            targets.append(test.images[i].reshape(-1, 3)[pick])
        self.origins = torch.cat([o for o, _ in rays]).to(device)
        self.dirs = torch.cat([d for _, d in rays]).to(device)
        self.target = torch.cat(targets).numpy()
        self.background = torch.tensor(test.background, device=device)
        self.tc, self.path = tc, path

    def point(self, field: ShellField, grid: SpanGrid | None, step: int, wall_s: float
              ) -> dict[str, Any]:
        """Render the curve's pixels, append the record to the curve's file and return it."""
        with torch.no_grad():
            img = render_volume_image(field, self.origins, self.dirs, *eval_samples(self.tc),
                                      self.background, grid=grid, slope=self.tc.slope)
        record = {"step": step, "wall_s": wall_s,
                  "psnr": psnr(img["color"].cpu().numpy()[:, None],
                               self.target[:, None]),  # [P, 1, 3]
                  "views": self.views, "pixels": len(self.target)}
        append_log(self.path, record)
        return record


def evaluate(field: ShellField, data: Dataset, tc: TrainConfig, max_views: int = 0,
             device: torch.device | None = None, grid: SpanGrid | None = None,
             ) -> dict[str, Any]:
    """Full-ray test PSNR (deterministic sample placement, `eval_samples` a ray) over the
    views of `data`; with ``grid``, each ray is sampled on its occupied span as in training."""
    device = device or field.aabb.device
    bg = torch.tensor(data.background, device=device)
    n = len(data.cameras) if max_views <= 0 else min(max_views, len(data.cameras))
    scores = []
    for i in range(n):
        o, d = data.cameras.pixel_rays(i, tc.pixel_samples)
        img = render_volume_image(field, o.to(device), d.to(device), *eval_samples(tc), bg,
                                  grid=grid, slope=tc.slope)
        pred = img["color"].reshape(-1, tc.pixel_samples, 3).mean(1)  # box filter
        pred = pred.reshape(data.images.shape[1:]).cpu()
        scores.append(psnr(pred.numpy(), data.images[i].numpy()))
    return {"psnr": float(sum(scores) / len(scores)), "psnr_per_view": scores, "n_views": n}


def train(data_dir: str | Path | None, run_dir: str | Path, cfg: Config, device: torch.device,
          downscale: int = 1, resume: bool = False, progress: bool = True,
          stop_at: int | None = None, evaluate_test: bool = True,
          iters: int | None = None) -> dict[str, Any]:
    """Stage-1 training. On resume, the run's saved config is used (`iters` may extend it).

    `stop_at` ends early after that step (used to test kill/resume).
    """
    run = RunDir(run_dir)
    ckpt = None
    if resume:
        meta = read_run(run)
        data_dir, downscale = meta["data"], int(meta["downscale"])
        ckpt = read_checkpoint(run, "stage1")
        cfg = Config.from_dict(ckpt["config"], str(run.checkpoint()))
    elif run.checkpoint().exists():
        raise InputError(f"{run.checkpoint()}: the run already has a checkpoint; pass --resume "
                         f"to continue it or choose another --out")
    if iters is not None:
        cfg.update({"train": {"iters": iters}}, "--iters")
    device = distributed.rank_device(device)
    w = join(cfg, "train", ckpt is None, device)  # before anything is written
    tc = cfg.train
    data = load_dataset(data_dir, "train", downscale=downscale, background=cfg.data.background)
    field = build_field(cfg, data.aabb, device)
    use_hashgrid(field, tc.hashgrid)
    opt = make_optimizer(field, tc.lr, tc.lr_mlp)
    if ckpt is None and w.main:
        write_run(run, data_dir, downscale, str(device), cfg)
    pixels = data.images.reshape(-1, 3).to(device)
    background = torch.tensor(cfg.data.background, device=device, dtype=torch.float32)
    # random backgrounds where a background shows: data whose alpha holds transparency (a
    # backdrop baked into the colours can only be reproduced on its own colour) and a bounded
    # field (every ray of an unbounded one ends on its far solid)
    alpha = (data.alpha.reshape(-1).to(device) if tc.random_background
             and has_transparency(data.alpha) and field.similarity is None else None)
    grid = (SpanGrid(field.aabb, tc.occ_resolution, tc.occ_k)
            if tc.sampler == "occupancy" else None)
    at = [0]  # the step being taken (before_step runs first)
    health = Stage1Health(psnr_floor(pixels, background), tc.iters)
    box = field.aabb
    if field.similarity is not None:  # the cube around the ball of interest (no far solid)
        box = 0.5 * (box[0] + box[1]) + 0.5 * (box - 0.5 * (box[0] + box[1]))
    probe, probed = probe_points(box), [0, 0.0]  # [step, solid share] of the last probe

    def before(k: int) -> None:
        at[0] = k
        before_step(field, grid, tc, k)

    curve = None
    if tc.curve_every > 0 and w.main:
        truncate_log(run.curve, int(ckpt["step"]) if ckpt is not None else 0)
        try:
            curve = RunningCurve(load_dataset(data_dir, "test", downscale=downscale,
                                              background=cfg.data.background),
                                 tc, run.curve, device)
        except InputError:
            pass  # a data set without a test split: no curve

    def after(done: int, wall_s: float) -> None:
        if curve is not None and (done % tc.curve_every == 0 or done == tc.iters):
            curve.point(field, grid, done, wall_s)

    def shard(gen: torch.Generator) -> tuple[torch.Tensor, dict[str, float]]:
        loss, rec = stage1_step(field, data, pixels, tc, background, gen, grid, at[0], alpha)
        done = at[0] + 1
        if done % tc.log_every == 0 or done == tc.iters:  # the health probe, once a step
            if probed[0] != done:  # the step's first shard
                with torch.no_grad():
                    probed[:] = [done, solid_share(field.geometry_field(probe)["sdf"])]
                for line in health.update(done, rec["psnr"], probed[1]):
                    if w.main:
                        tqdm.write(f"warning: {line}", file=sys.stderr)
            rec["solid"] = probed[1]
        return loss, rec

    with drjit_on_calling_thread():  # torch work between the lookups (its docstring)
        summary = optimise(field, opt, cfg, Schedule.of("stage 1", tc), shard,
                           run.checkpoint("stage1"), run.log("stage1"), device, resume=ckpt,
                           stop_at=stop_at, progress=progress, before_step=before, state=grid,
                           after_step=after)
        summary["health"] = health.summary()
        summary["background"] = {"colour": list(cfg.data.background),
                                  "random": alpha is not None}
        field.active_levels = None  # what the checkpoint's users evaluate: every level
        if summary["finished"] and w.main:  # the summary (with the health) of a whole run
            test = None
            if evaluate_test:
                try:
                    test = load_dataset(data_dir, "test", downscale=downscale,
                                        background=cfg.data.background)
                except InputError:
                    pass  # a data set without a test split: nothing to score
            if test is not None:
                summary["test"] = evaluate(field, test, tc, tc.eval_max_views, device, grid)
            write_json(run.summary("stage1"), summary)
    return summary
