"""Full-ray NeuS volume rendering in torch (stage-1 training and its evaluation).

A ray r(t) = o + t d (unit d) is clipped to the scene box [near, far]; samples are placed by
stratified uniform sampling, then refined by inverse-CDF sampling of the coarse weights (NeuS
up-sampling). Each sample i owns the section between the mid-points to its neighbours (the first
and last sections end at near and far), so the sections tile [near, far] and the discrete NeuS
alpha of `shells.fields.neus` applies per sample with its own kernel size s(x_i).
"""

from __future__ import annotations

import torch

from shells.fields.neus import composite, neus_alpha


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
                ) -> dict[str, torch.Tensor]:
    """Render rays through the field's scene box (`field.aabb`).

    Returns color [R, 3], opacity [R], depth [R] (expected t), weights [R, S], points [R, S, 3],
    s [R, S] and hit [R]. Rays that miss the box get the background.
    """
    near, far, hit = ray_aabb(origins, dirs, field.aabb)
    t = stratified_samples(near, far, n_samples, generator)
    if n_importance > 0:
        with torch.no_grad():
            pts = origins[:, None] + t[..., None] * dirs[:, None]
            geo = field.geometry(pts.reshape(-1, 3))
            shape = t.shape
            cos = (geo["normal"].reshape(*shape, 3) * dirs[:, None]).sum(-1)
            delta = torch.diff(section_edges(t, near, far), dim=-1)
            alpha = neus_alpha(geo["sdf"].reshape(shape), geo["s"].reshape(shape), cos, delta)
            _, w, _ = composite(alpha, torch.zeros(*shape, 3, device=t.device), background)
            t_fine = sample_pdf(t, w, near, far, n_importance, generator)
            t, _ = torch.sort(torch.cat([t, t_fine], dim=-1), dim=-1)
    delta = torch.diff(section_edges(t, near, far), dim=-1)  # [R, S]
    pts = origins[:, None] + t[..., None] * dirs[:, None]  # [R, S, 3]
    R, S = t.shape
    d = dirs[:, None].expand(R, S, 3)
    out = field(pts.reshape(-1, 3), d.reshape(-1, 3))
    sdf, s = out["sdf"].reshape(R, S), out["s"].reshape(R, S)
    normal, rgb = out["normal"].reshape(R, S, 3), out["rgb"].reshape(R, S, 3)
    cos = (normal * d).sum(-1)
    alpha = neus_alpha(sdf, s, cos, delta) * hit[:, None]
    color, weights, opacity = composite(alpha, rgb, background)
    depth = (weights * t).sum(-1)
    return {"color": color, "opacity": opacity, "depth": depth, "weights": weights,
            "points": pts, "t": t, "s": s, "sdf": sdf, "hit": hit}


@torch.no_grad()
def render_volume_image(field: torch.nn.Module,
                 origins: torch.Tensor,  # [P, 3]
                 dirs: torch.Tensor,  # [P, 3]
                 n_samples: int,
                 n_importance: int,
                 background: torch.Tensor,  # [3]
                 chunk: int = 4096,
                 ) -> dict[str, torch.Tensor]:
    """Deterministic chunked rendering of many rays (evaluation): color [P, 3], opacity [P]."""
    colors, opac = [], []
    for i in range(0, origins.shape[0], chunk):
        out = render_volume_rays(field, origins[i:i + chunk], dirs[i:i + chunk], n_samples,
                                 n_importance, background, generator=None)
        colors.append(out["color"])
        opac.append(out["opacity"])
    return {"color": torch.cat(colors), "opacity": torch.cat(opac)}
