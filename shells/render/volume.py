"""Full-ray NeuS volume rendering in torch (stage-1 training and its evaluation).

A ray r(t) = o + t d (unit d) is clipped to the scene box [near, far]; samples are placed by
stratified uniform sampling, then refined by inverse-CDF sampling of the coarse weights (NeuS
up-sampling). Each sample i owns the section between the mid-points to its neighbours (the first
and last sections end at near and far), so the sections tile [near, far] and the discrete NeuS
alpha of `shells.fields.neus` applies per sample with its own kernel size s(x_i). The field is
evaluated once per sample: the coarse samples (with gradient) give the weights that place the
fine ones, and both sets are merged in distance order.

Empty-space skipping (`SpanGrid`, the Instant-NGP / nerfacc occupancy grid for an SDF): a
binary grid over the box, rebuilt from the field during training with the occupancy rule of
every renderer (`shells.fields.neus.may_have_density`), gives each ray the span between the
first and the last occupied cell it crosses (widened by a cell diagonal on both sides). The
same hierarchical sampling then runs on that span instead of the whole box chord, and a ray
that crosses no occupied cell is not sampled at all: its colour is the background.

Culling (``cull``, `TrainConfig.cull_weight`): in training, the samples whose compositing weight
is negligible (empty space in front of the surface, occluded space behind it) are evaluated
without gradient only, and for placing the samples only the geometry is evaluated: the
radiance MLP runs on the samples that carry weight (with gradient) and on the few light ones
whose colour still shows (``UNLIT``), not on the rest, in empty or occluded space (62 % of
the samples of a trained lego 1/8 field; BENCHMARKS.md).
"""

from __future__ import annotations

import contextlib
import math

import torch
from torch.profiler import record_function

from shells.fields.neus import composite, half_cell_diagonal, may_have_density, neus_alpha
from shells.render.warp import ray_span, s_of_t, t_of_s

UNLIT = 0.01  # culled samples under UNLIT * cull of weight get no colour (render_volume_rays)


def ray_aabb(origins: torch.Tensor,  # [R, 3]
             dirs: torch.Tensor,  # [R, 3]
             aabb: torch.Tensor,  # [2, 3] (min, max)
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Slab test: returns near [R], far [R] (near >= 0) and hit [R] bool (far > near)."""
    inv = 1.0 / torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    t0 = (aabb[0] - origins) * inv
    t1 = (aabb[1] - origins) * inv
    near = torch.minimum(t0, t1).amax(dim=-1).clamp_min(0.0)
    far = torch.maximum(t0, t1).amin(dim=-1)
    hit = far > near
    far = torch.where(hit, far, near)
    return near, far, hit


class SpanGrid:
    """Occupancy over the scene box for stage-1 sampling; ``occ`` is [N, N, N] bool indexed
    [ix, iy, iz], or None before the first `update` (then every ray gets its whole chord)."""

    def __init__(self, aabb: torch.Tensor,  # [2, 3] scene box
                 resolution: int, k: float, chunk: int = 1 << 18) -> None:
        self.aabb = aabb.detach().float()
        self.N, self.k, self.chunk = int(resolution), float(k), int(chunk)
        self.cell = (self.aabb[1] - self.aabb[0]) / self.N  # [3]
        self.h = half_cell_diagonal(self.aabb, self.N)
        self.occ: torch.Tensor | None = None

    @torch.no_grad()
    def update(self, field: torch.nn.Module) -> None:
        """Occupied where |f| < h + k s at the cell centre, dilated by one cell (3^3 max pool):
        a deterministic function of the field."""
        N, dev = self.N, self.aabb.device
        ax = torch.arange(N, device=dev, dtype=torch.float32) + 0.5
        occ = torch.empty(N ** 3, dtype=torch.bool, device=dev)
        ix = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
        for a in range(0, N ** 3, self.chunk):
            x = self.aabb[0] + ix[a:a + self.chunk] * self.cell
            geo = field.geometry(x)  # bounded fields only (train.sampler rule)
            occ[a:a + len(x)] = may_have_density(geo["sdf"], geo["s"], self.h, self.k)
        grid = occ.reshape(1, 1, N, N, N).float()
        grid = torch.nn.functional.max_pool3d(grid, 3, stride=1, padding=1)
        self.occ = grid.reshape(N, N, N) > 0.5

    @property
    def fraction(self) -> float:
        """Share of occupied cells (1 before the first update)."""
        return 1.0 if self.occ is None else float(self.occ.float().mean())

    def spans(self, origins: torch.Tensor,  # [R, 3]
              dirs: torch.Tensor,  # [R, 3] unit
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """near [R], far [R], hit [R]: the box chord cut to the occupied cells the ray crosses.

        Probes at half the smallest cell size find the first and last occupied cell; the span is
        widened by the cell diagonal on both sides (a probe can sit anywhere in its cell)."""
        near, far, hit = ray_aabb(origins, dirs, self.aabb)
        if self.occ is None:
            return near, far, hit
        step = 0.5 * float(self.cell.min())
        n = max(1, int(math.ceil(float((far - near).max()) / step)))
        j = torch.arange(n, device=origins.device, dtype=origins.dtype) + 0.5
        t = near[:, None] + step * j  # [R, n]
        N, flat = self.N, None  # the probes' cells ix N^2 + iy N + iz, an axis at a time
        for a in range(3):
            x = origins[:, a:a + 1] + t * dirs[:, a:a + 1]  # [R, n]
            c = ((x - self.aabb[0, a]) / self.cell[a]).floor_().clamp_(0, N - 1).int()
            flat = c if flat is None else flat.mul_(N).add_(c)
        m = self.occ.reshape(-1)[flat] & (t < far[:, None])  # [R, n]
        anyocc = m.any(1) & hit
        first = m.float().argmax(1)
        last = n - 1 - m.flip(1).float().argmax(1)
        margin = 2.0 * self.h
        lo = torch.maximum(near, near + step * (first + 0.5) - margin)
        hi = torch.minimum(far, near + step * (last + 0.5) + margin)
        return lo, torch.where(anyocc, hi, lo), anyocc

    def state_dict(self) -> dict[str, torch.Tensor | None]:
        return {"occ": None if self.occ is None else self.occ.cpu()}

    def load_state_dict(self, state: dict[str, torch.Tensor | None]) -> None:
        occ = state.get("occ")
        self.occ = None if occ is None else occ.to(self.aabb.device)


def stratified_samples(near: torch.Tensor,  # [R]
                       far: torch.Tensor,  # [R]
                       n: int,
                       generator: torch.Generator | None = None,
                       ) -> torch.Tensor:  # [R, n]
    """One sample per equal-width stratum; jittered when a generator is given, else centred."""
    u = torch.arange(n, device=near.device, dtype=near.dtype)
    if generator is None:
        u = (u + 0.5).expand(near.shape[0], n)
    else:
        u = u + torch.rand(near.shape[0], n, generator=generator, device=near.device,
                           dtype=near.dtype)
    return near[:, None] + (far - near)[:, None] * (u / n)


def sample_pdf(t: torch.Tensor,  # [R, S] sorted sample positions
               weights: torch.Tensor,  # [R, S]
               near: torch.Tensor,  # [R]
               far: torch.Tensor,  # [R]
               n: int,
               generator: torch.Generator | None = None,
               ) -> torch.Tensor:  # [R, n]
    """Inverse-CDF sampling of the piecewise-constant pdf given by the weights on the sections."""
    edges = section_edges(t, near, far)  # [R, S+1]
    w = weights + 1e-5
    cdf = torch.cumsum(w / w.sum(-1, keepdim=True), dim=-1)
    cdf = torch.cat([torch.zeros_like(cdf[:, :1]), cdf], dim=-1)  # [R, S+1]
    if generator is None:
        u = ((torch.arange(n, device=t.device, dtype=t.dtype) + 0.5) / n).expand(t.shape[0], n)
    else:
        u = torch.rand(t.shape[0], n, generator=generator, device=t.device, dtype=t.dtype)
    u = u.contiguous()
    idx = torch.searchsorted(cdf, u, right=True).clamp(1, cdf.shape[-1] - 1)
    c0, c1 = cdf.gather(-1, idx - 1), cdf.gather(-1, idx)
    e0, e1 = edges.gather(-1, idx - 1), edges.gather(-1, idx)
    frac = ((u - c0) / (c1 - c0).clamp_min(1e-8)).clamp(0, 1)
    return e0 + frac * (e1 - e0)


def ray_slope(sdf: torch.Tensor,  # [R, S] at the samples
              t: torch.Tensor,  # [R, S] sorted ray distances (world units)
              ) -> torch.Tensor:  # [R, S]
    """df/dt along each ray from the samples themselves (``slope`` "ray" of
    `render_volume_rays`): central differences (f_{i+1} - f_{i-1}) / (t_{i+1} - t_{i-1}) inside,
    one-sided at the two ends; 0 where the samples coincide (a ray that misses its span)."""
    if sdf.shape[1] < 2:
        return torch.zeros_like(sdf)
    f = torch.cat([sdf[:, :1], sdf, sdf[:, -1:]], dim=1)
    x = torch.cat([t[:, :1], t, t[:, -1:]], dim=1)
    df, dt = f[:, 2:] - f[:, :-2], x[:, 2:] - x[:, :-2]
    return torch.where(dt > 1e-12, df / dt.clamp_min(1e-12), torch.zeros_like(df))


def section_edges(t: torch.Tensor,  # [R, S] sorted
                  near: torch.Tensor,  # [R]
                  far: torch.Tensor,  # [R]
                  ) -> torch.Tensor:  # [R, S+1]
    """Boundaries of the sections owned by the samples: near, mid-points, far."""
    mids = 0.5 * (t[:, 1:] + t[:, :-1])
    return torch.cat([near[:, None], mids, far[:, None]], dim=-1)


def render_volume_rays(field: torch.nn.Module,
                origins: torch.Tensor,  # [R, 3]
                dirs: torch.Tensor,  # [R, 3] unit
                n_samples: int,
                n_importance: int,
                background: torch.Tensor,  # [3] or [R, 3]
                generator: torch.Generator | None = None,
                span: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
                cull: float = 0.0,
                slope: str = "normal",
                ) -> dict[str, torch.Tensor]:
    """Render rays through the field's scene box (`field.aabb`), or through ``span`` = (near,
    far, hit) [R] each when given (`SpanGrid.spans`). An unbounded field (`field.similarity`)
    is sampled in the ray parameter s of `shells.render.warp` from the camera to the far
    background instead: the same stratified and importance sampling, evenly in s.

    ``cull`` > 0 with gradient enabled (training): the samples are placed from the geometry
    alone, without gradient, and only those whose compositing weight reaches ``cull`` are
    evaluated again, in full and with gradient (nerfacc's culling of transparent and occluded
    samples). The others keep their values, detached, and only their own gradient is
    dropped: d color / d rgb_i = w_i < cull, and for a sample with weight w_i < cull in front
    of the surface, d alpha_i / d sdf_i ~ alpha_i / s. Their colour comes from one more pass
    without gradient over those with w_i >= ``UNLIT`` cull; the rest (most of them: empty
    space and occluded space, w_i ~ 0) get no colour at all, so the forward is the render
    without culling less sum w_i rgb_i over those samples: at most S UNLIT cull per ray and
    channel (4.8e-5 for 48 samples at cull 1e-4), and no radiance MLP runs on them.

    ``slope`` (`TrainConfig.slope`): where the NeuS opacity takes the SDF's slope along the ray
    from. "normal": cos = d . n with n the field's predicted normal (the paper; what the band
    and Dr.Jit renderers do). "ray": df/dt from the ray's own samples (`ray_slope`), so a ray
    is absorbed where f falls through zero whatever the predicted normal says, and it cannot
    pass a crossing to be absorbed deeper inside the solid, where no skipping renderer samples.

    Returns color [R, 3], opacity [R], depth [R] (expected t), weights [R, S], points [R, S, 3],
    s [R, S], hit [R] and grad [R, S] (the samples evaluated with gradient). Rays that miss the
    box (or their span) get the background.
    """
    sim = getattr(field, "similarity", None)
    if sim is not None and span is None:  # u = s: even in contracted space
        t_near, tb, t_far = ray_span(origins, dirs, sim.centre, sim.radius,
                                     field.cfg.far_radius, field.cfg.near_radius)
        near, far = t_near, s_of_t(t_far, tb)  # t_near <= t_b: s = t there
        hit = torch.ones_like(tb, dtype=torch.bool)
        def to_t(u: torch.Tensor) -> torch.Tensor:
            return t_of_s(u, tb[:, None])
    else:  # u = t
        near, far, hit = ray_aabb(origins, dirs, field.aabb) if span is None else span
        def to_t(u: torch.Tensor) -> torch.Tensor:
            return u
    if slope not in ("normal", "ray"):
        raise ValueError(f"slope must be 'normal' or 'ray', got {slope!r}")

    def cos_of(out: dict[str, torch.Tensor], d: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        if slope == "ray":
            return ray_slope(out["sdf"], t)
        return (out["normal"] * d).sum(-1)

    u = stratified_samples(near, far, n_samples, generator)
    R = u.shape[0]
    culled = cull > 0 and torch.is_grad_enabled()
    colour = not culled  # culled: the colours once the weights are known
    with torch.no_grad() if culled else contextlib.nullcontext():
        with record_function("volume: coarse samples"):
            out = _field_at(field, origins, dirs, to_t(u), colour)
        if n_importance > 0:
            # the coarse samples are evaluated once (with gradient unless culled); their
            # weights (detached) place the fine samples, which are evaluated and merged in
            # distance order
            with torch.no_grad(), record_function("volume: fine placement"):
                delta = torch.diff(to_t(section_edges(u, near, far)), dim=-1)
                cos = cos_of(out, dirs[:, None], to_t(u))
                alpha = neus_alpha(out["sdf"], out["s"], cos, delta)
                _, w, _ = composite(alpha, torch.zeros(*u.shape, 3, device=u.device),
                                    background)
                u_fine = sample_pdf(u, w, near, far, n_importance, generator)
            with record_function("volume: fine samples"):
                fine = _field_at(field, origins, dirs, to_t(u_fine), colour)
                u, order = torch.sort(torch.cat([u, u_fine], dim=-1), dim=-1)
                out = {k: _merge(out[k], fine[k], order) for k in out}
    t = to_t(u)
    delta = torch.diff(to_t(section_edges(u, near, far)), dim=-1)  # [R, S]
    S = t.shape[1]
    d = dirs[:, None].expand(R, S, 3)
    pts = origins[:, None] + t[..., None] * dirs[:, None]  # [R, S, 3]
    if culled:  # the gradient pass on the samples that carry weight
        with torch.no_grad(), record_function("volume: weights, colours of light samples"):
            cos = cos_of(out, d, t)
            alpha = neus_alpha(out["sdf"], out["s"], cos, delta) * hit[:, None]
            w = composite(alpha, torch.zeros_like(pts), background)[1]  # [R, S]
            keep = w >= cull
            lit = (w >= UNLIT * cull) & ~keep  # their colour without gradient
            rgb = torch.zeros_like(pts)
            if bool(lit.any()):
                rgb[lit] = field(pts[lit], d[lit])["rgb"]
            out["rgb"] = rgb
        with record_function("volume: samples with gradient"):
            live = field(pts[keep], d[keep])
            out = {k: v.index_put((keep,), live[k]) for k, v in out.items()}
    else:
        keep = torch.ones_like(u, dtype=torch.bool)
    sdf, s, rgb = out["sdf"], out["s"], out["rgb"]
    cos = cos_of(out, d, t)
    alpha = neus_alpha(sdf, s, cos, delta) * hit[:, None]
    color, weights, opacity = composite(alpha, rgb, background)
    depth = (weights * t).sum(-1)
    return {"color": color, "opacity": opacity, "depth": depth, "weights": weights,
            "points": pts, "t": t, "s": s, "sdf": sdf, "hit": hit, "grad": keep}


def _field_at(field: torch.nn.Module, origins: torch.Tensor, dirs: torch.Tensor,
              t: torch.Tensor,  # [R, S]
              colour: bool = True,  # False: the geometry only (no radiance MLP, no rgb)
              ) -> dict[str, torch.Tensor]:  # sdf, s [R, S]; normal, rgb [R, S, 3]
    R, S = t.shape
    pts = (origins[:, None] + t[..., None] * dirs[:, None]).reshape(-1, 3)
    out = (field(pts, dirs[:, None].expand(R, S, 3).reshape(-1, 3)) if colour
           else field.geometry(pts))
    keys = ("sdf", "s", "normal", "rgb") if colour else ("sdf", "s", "normal")
    return {k: out[k].reshape(R, S, *out[k].shape[1:]) for k in keys}


def _merge(a: torch.Tensor, b: torch.Tensor,  # [R, S1, ...], [R, S2, ...]
           order: torch.Tensor,  # [R, S1 + S2] sort order of the concatenated samples
           ) -> torch.Tensor:
    both = torch.cat([a, b], dim=1)
    idx = order.view(*order.shape, *([1] * (both.ndim - 2))).expand_as(both)
    return both.gather(1, idx)


@torch.no_grad()
def render_volume_image(field: torch.nn.Module,
                 origins: torch.Tensor,  # [P, 3]
                 dirs: torch.Tensor,  # [P, 3]
                 n_samples: int,
                 n_importance: int,
                 background: torch.Tensor,  # [3]
                 chunk: int = 4096,
                 grid: SpanGrid | None = None,
                 slope: str = "normal",
                 ) -> dict[str, torch.Tensor]:
    """Deterministic chunked rendering of many rays (evaluation): color [P, 3], opacity [P].
    With ``grid``, each ray is sampled on its occupied span (as in training); ``slope`` as in
    `render_volume_rays`."""
    colors, opac = [], []
    for i in range(0, origins.shape[0], chunk):
        o, d = origins[i:i + chunk], dirs[i:i + chunk]
        span = None if grid is None else grid.spans(o, d)
        out = render_volume_rays(field, o, d, n_samples, n_importance, background,
                                 generator=None, span=span, slope=slope)
        colors.append(out["color"])
        opac.append(out["opacity"])
    return {"color": torch.cat(colors), "opacity": torch.cat(opac)}
