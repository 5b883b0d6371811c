"""Image-space adaptive refinement of band renders (``shells-render --refine L``).

Interpolated ray casting after González García et al. 2021, fitted to adaptive shells: the
shell cast is cheap next to the field evaluation and gives every pixel features before any
sample is taken, so a pixel whose neighbourhood is simple can be interpolated instead.

1. **Cast every pixel** against the shells (`ShellScene.intervals` and `first_hit`): interval
   count, whether the ray reaches M- (ends solid), whether every interval gets a single
   sample (Procedure 3: width <= w_s), the first hit's distance and face normal.
2. **Coarse image**: the pixels (x, y) with x and y multiples of S = 2^L are evaluated by the
   band renderer (`shells.render.frame.render_intervals`, the band renderer's own code on the
   intervals of step 1), which also returns each pixel's opacity and mean field normal.
3. **Up the pyramid**, for s = S/2, ..., 1: the new pixels of the s-grid have two (on an edge
   of a 2s-cell) or four (at its centre) parents on the 2s-grid. A new pixel is interpolated
   (the parents' mean colour, opacity and field normal) only when all of these hold, with the
   thresholds of ``render.refine_*``:

   * pixel and parents have the same interval count and the same M- status;
   * no interval of the pixel or of its parents takes more than refine_fuzzy_samples samples
     (1 by default: such fuzzy pixels are always evaluated);
   * their first-hit face normals agree with the pixel's (dot >= refine_normal_cos);
   * planar depth: |t - mean of the parents' t| <= refine_depth * t;
   * not grazing: |d . n| >= refine_grazing at the pixel's first hit;
   * the parents' colours differ by at most refine_colour per channel, and the parents are
     opaque (opacity >= refine_opaque; a ray ending on M- counts as opaque) — or all clear
     (opacity <= refine_clear, off by default: the part of a wide band the field leaves
     empty, where the field normal means nothing either);
   * the silhouette cue of Neural Image-Space Tessellation (Du et al. 2026): on every parent
     the M+ face normal and the field's normal agree (1 - n_face . n_field <=
     refine_field_normal); where they do not, the pixel sits near a silhouette the shell does
     not resolve.

   All other new pixels of the level are evaluated together (compacted, in ray batches). A
   ray without intervals has no samples: it is background, as in the band render, at every
   level, and is neither evaluated nor interpolated.

When fewer than ``refine_min_share`` of the covered coarse pixels could be interpolated at
all (not fuzzy, not grazing: judged on the cast of the coarse grid alone, before anything
else), the tile is simply band-rendered: the same image, without the refinement's cost.

Evaluated pixels are bit-identical to the band render (same intervals, same code). A frame
is refined in tiles of whole rows (a multiple of S) when it is larger than the memory budget
allows; pixels whose parents lie in the next tile are evaluated.
"""

from __future__ import annotations

from typing import Any

import drjit as dr
import mitsuba as mi
import torch

from shells.config import RenderConfig
from shells.errors import InputError
from shells.render.frame import rays_per_batch, render_image, render_intervals
from shells.render.raycast import Intervals, ShellScene, to_point3f
from shells.render.sampler import Warp, cast_start, field_warp, interval_counts
from shells.render.shading import WHITE

BYTES_PER_PIXEL = 256  # cast features and results of one pixel while refining (upper estimate)


def tile_rows(cfg: RenderConfig, width: int) -> int:
    """Rows of a refined tile: a multiple of 2^L whose pixels fit the memory budget."""
    S = 1 << cfg.refine_levels
    rows = (cfg.memory_mb << 20) // (BYTES_PER_PIXEL * max(width, 1))
    return max(S, rows // S * S)


def render_refined(field: Any,
                   origins: torch.Tensor,  # [H * W, 3] row-major pixel rays (spp 1)
                   dirs: torch.Tensor,  # [H * W, 3]
                   height: int, width: int,
                   cfg: RenderConfig,
                   scene: ShellScene,
                   background: tuple[float, float, float] = WHITE,
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """rgb [H, W, 3] float32, samples per pixel [H, W] int32 (0 where interpolated),
    evaluated [H, W] bool and covered [H, W] bool (the cast found intervals)."""
    L = cfg.refine_levels

    def band() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        rgb, spp = render_image(field, origins, dirs, height, width, cfg, "band", scene,
                                background=background)
        return rgb, spp, spp > 0, spp > 0

    if L == 0:
        return band()
    if cfg.spp != 1:
        raise InputError(f"--refine {L} with spp {cfg.spp}: refinement works on pixel-centre "
                         "rays; use --spp 1")
    R = height * width
    if origins.shape[0] != R or dirs.shape[0] != R:
        raise InputError(f"{origins.shape[0]} rays for a {width}x{height} image")
    o = origins.float().contiguous()
    d = dirs.float().contiguous()
    S = 1 << L
    probe = (torch.arange(0, height, S)[:, None] * width
             + torch.arange(0, width, S)[None, :]).reshape(-1)
    warp = field_warp(field)
    if not _hopeful(_cast(scene, o[probe], d[probe], cfg, warp), cfg):
        return band()  # little to gain (judged on the coarse pixels): the band render as is
    cast = _cast(scene, o, d, cfg, warp)
    bg = torch.tensor(background, dtype=torch.float32)
    colour = bg.repeat(R, 1)
    opacity = torch.zeros(R)
    nfield = torch.zeros(R, 3)
    spp = torch.zeros(R, dtype=torch.int32)
    evaluated = torch.zeros(R, dtype=torch.bool)

    def evaluate(idx: torch.Tensor) -> None:
        if len(idx) == 0:
            return
        chunk = rays_per_batch(cfg, "band")
        for a in range(0, len(idx), chunk):
            sel = idx[a:a + chunk]
            iv = Intervals.from_arrays(cast["enter"][sel], cast["exit"][sel],
                                       cast["count"][sel], cast["t_inner"][sel])
            c, n, op, nf = render_intervals(field, to_point3f(o[sel]),
                                            to_point3f(d[sel], mi.Vector3f), iv, cfg,
                                            background, extras=True)
            k = len(sel)
            colour[sel] = mi.TensorXf(dr.ravel(c), (k, 3)).torch().cpu()
            spp[sel] = mi.TensorXf(mi.Float(n), (k,)).torch().cpu().to(torch.int32)
            opacity[sel] = mi.TensorXf(op, (k,)).torch().cpu()
            nfield[sel] = mi.TensorXf(dr.ravel(nf), (k, 3)).torch().cpu()
        evaluated[idx] = True

    # a ray without intervals has no samples: background, never evaluated nor interpolated
    covered = cast["count"] > 0

    def grid(s: int) -> tuple[torch.Tensor, torch.Tensor]:  # pixels of the s-grid: x, y
        ys, xs = torch.meshgrid(torch.arange(0, height, s), torch.arange(0, width, s),
                                indexing="ij")
        return xs.reshape(-1), ys.reshape(-1)

    xs, ys = grid(S)
    idx = ys * width + xs
    evaluate(idx[covered[idx]])
    for level in range(L - 1, -1, -1):
        s = 1 << level
        px, py = grid(s)
        keep = ((px // s) % 2 == 1) | ((py // s) % 2 == 1)  # not on the 2s-grid
        px, py = px[keep], py[keep]
        idx = py * width + px
        keep = covered[idx]
        idx, px, py = idx[keep], px[keep], py[keep]
        odd_x, odd_y = ((px // s) % 2 == 1)[:, None], ((py // s) % 2 == 1)[:, None]
        # parents: left/right (odd x), up/down (odd y), the four corners (both odd); the
        # two-parent cases list each parent twice, so a mean over the four slots is theirs
        pm = torch.tensor([-s, s, -s, s])
        dx = torch.where(odd_x, pm, 0)
        dy = torch.where(odd_x & odd_y, torch.tensor([-s, -s, s, s]), torch.where(odd_y, pm, 0))
        par_x, par_y = px[:, None] + dx, py[:, None] + dy  # [N, 4]
        inside = ((par_x >= 0) & (par_x < width) & (par_y >= 0) & (par_y < height)).all(1)
        par = (par_y.clamp(0, height - 1) * width + par_x.clamp(0, width - 1))
        interp = inside & _agree(cast, idx, par, colour, opacity, nfield, cfg)
        j, pj = idx[interp], par[interp]
        colour[j] = colour[pj].mean(1)
        opacity[j] = opacity[pj].mean(1)
        nfield[j] = nfield[pj].mean(1)
        evaluate(idx[~interp])
    return (colour.reshape(height, width, 3), spp.reshape(height, width),
            evaluated.reshape(height, width), covered.reshape(height, width))


def _cast(scene: ShellScene, o: torch.Tensor, d: torch.Tensor,
          cfg: RenderConfig, warp: Warp | None = None) -> dict[str, torch.Tensor]:
    """Step 1 of the module docstring: per-pixel torch tensors (zero-copy views of Dr.Jit
    arrays, computed in one kernel). An unbounded field's rays (``warp``) are cast from t_near
    (`shells.render.sampler.shell_intervals`)."""
    start = cast_start(o, d, warp)
    iv = scene.intervals(o, d, cfg.dp_max, start=start)
    t_hit, n_hit = scene.first_hit(o, d, start)
    R, K = iv.enter.shape
    slot = dr.arange(mi.UInt32, R * K)
    count = mi.UInt32(iv.count.array)
    valid = (slot % K) < dr.repeat(count, K)
    n = interval_counts(dr.maximum(iv.exit.array - iv.enter.array, 0.0), cfg.w_s, cfg.delta_s,
                        cfg.n_max)  # Procedure 3
    n = dr.select(valid, n, 0)
    most = dr.block_reduce(dr.ReduceOp.Max, n, K) if K > 1 else n
    single = mi.Float(most <= cfg.refine_fuzzy_samples)  # not fuzzy
    solid = mi.Float(dr.isfinite(iv.t_inner.array) & (count > 0))
    cos = dr.abs(dr.dot(n_hit, to_point3f(d, mi.Vector3f)))
    dr.eval(single, solid, cos)
    out = iv.torch()
    out["t_hit"] = t_hit.torch()
    out["n_hit"] = torch.stack([n_hit[a].torch() for a in range(3)], 1)
    out["single"] = single.torch() > 0.5
    out["solid"] = solid.torch() > 0.5
    out["cos"] = cos.torch()
    return out


def _hopeful(cast: dict[str, torch.Tensor], cfg: RenderConfig) -> bool:
    """Whether at least refine_min_share of the covered pixels could be interpolated at all
    (not fuzzy, not grazing: the cast's own tests)."""
    covered = cast["count"] > 0
    could = covered & cast["single"] & (cast["cos"] >= cfg.refine_grazing)
    return int(could.sum()) >= cfg.refine_min_share * max(int(covered.sum()), 1)


def _agree(cast: dict[str, torch.Tensor], idx: torch.Tensor, par: torch.Tensor,
           colour: torch.Tensor, opacity: torch.Tensor, nfield: torch.Tensor,
           cfg: RenderConfig) -> torch.Tensor:
    """Which new pixels ``idx`` [N] may be interpolated from their parents ``par`` [N, 4].

    The tests are applied in stages, the pixel's own (cheap) first, each stage on the pixels
    that passed the previous ones."""
    ok = torch.zeros(len(idx), dtype=torch.bool)
    t = cast["t_hit"][idx]
    keep = cast["single"][idx] & (cast["cos"][idx] >= cfg.refine_grazing) & torch.isfinite(t)
    live = torch.nonzero(keep).squeeze(1)
    i, p, t = idx[live], par[live], t[live]
    count = cast["count"]
    keep = ((count[p] == count[i, None]) & (cast["solid"][p] == cast["solid"][i, None])
            & cast["single"][p]).all(1)
    keep &= (t - cast["t_hit"][p].mean(1)).abs() <= cfg.refine_depth * t
    live, i, p = live[keep], i[keep], p[keep]
    n_par = cast["n_hit"][p]  # [N, 4, 3]
    keep = ((n_par * cast["n_hit"][i][:, None, :]).sum(-1) >= cfg.refine_normal_cos).all(1)
    c = colour[p]  # [N, 4, 3]
    keep &= ((c.amax(1) - c.amin(1)) <= cfg.refine_colour).all(1)
    live, p, n_par = live[keep], p[keep], n_par[keep]
    a = opacity[p]
    clear = (a <= cfg.refine_clear).all(1)
    nf = nfield[p]
    nf = nf / nf.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    keep = (a >= cfg.refine_opaque).all(1)
    keep &= (1.0 - (nf * n_par).sum(-1) <= cfg.refine_field_normal).all(1)
    ok[live[keep | clear]] = True
    return ok
