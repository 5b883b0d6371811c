"""Differentiable narrow-band rendering in torch: the reference for the Dr.Jit renderer and the
renderer of stage-2 training (§3.4-3.5).

The rays are cast against the fixed shells and sampled by the renderer's own code
(`shells.render.sampler.band_samples`: Procedure 3, padded layout, no gradient); the torch field
is evaluated at the valid samples only, their NeuS alpha (`shells.fields.neus.neus_alpha`, the
formula of every renderer) is composited front to back (`shells.fields.neus.composite`), and a
ray that reached M- ends on its last sample's colour (`shells.render.sampler.solid_end`, the
rule `shells.render.frame` applies too). Gradients flow to the field's parameters through the
sample values; sample positions depend on the shells only.

Works on any torch device and dtype: the samples come from the Mitsuba variant's device (CUDA
with cuda_ad_rgb, the CPU with llvm_ad_rgb) and take the dtype of the rays, so the same call
runs in float64 for gradient checks.
"""

from __future__ import annotations

import torch

from shells.config import RenderConfig
from shells.fields.neus import composite, neus_alpha
from shells.render.raycast import ShellScene
from shells.render.sampler import band_samples, field_warp


def render_band_rays(field: torch.nn.Module,  # ShellField: field(x, d) -> sdf, s, normal, rgb
                     scene: ShellScene,
                     origins: torch.Tensor,  # [R, 3]
                     dirs: torch.Tensor,  # [R, 3] unit
                     cfg: RenderConfig,
                     background: torch.Tensor,  # [3]
                     extra: torch.Tensor | None = None,  # [A, 3] world points
                     ) -> dict[str, torch.Tensor]:
    """color [R, 3], opacity [R] (of the band samples) and spp [R] (samples per ray); with
    ``extra``, also the field's ``extra_sdf`` and ``extra_s`` [A] at those points, evaluated
    in the samples' batch: one hash-grid lookup, so one gradient scatter into the table
    (a second call would make a second, into its own zeroed table-sized buffer)."""
    t, delta, mask, solid = band_samples(scene, origins, dirs, cfg,  # [R, S] x 3, [R]
                                         field_warp(field))
    dev, dtype = origins.device, origins.dtype
    # own copies (the Dr.Jit buffers are reused), on the rays' device and in their dtype
    t, delta = t.to(dev, dtype, copy=True), delta.to(dev, dtype, copy=True)
    mask, solid = mask.to(dev, copy=True), solid.to(dev, copy=True)
    R, S = t.shape
    pts = origins[:, None] + t[..., None] * dirs[:, None]  # [R, S, 3]
    d = dirs[:, None].expand(R, S, 3)
    sdf = torch.zeros(R, S, device=dev, dtype=dtype)
    s = torch.ones(R, S, device=dev, dtype=dtype)
    cos = torch.zeros(R, S, device=dev, dtype=dtype)
    rgb = torch.zeros(R, S, 3, device=dev, dtype=dtype)
    res = {}
    if mask.any() or extra is not None:
        x, dx = pts[mask], d[mask]
        n = len(x)
        if extra is not None:  # any direction: their colour is not used
            x = torch.cat([x, extra.to(dev, dtype)])
            dx = torch.cat([dx, dx.new_tensor([0.0, 0.0, 1.0]).expand(len(extra), 3)])
        out = field(x, dx)
        if extra is not None:
            res = {"extra_sdf": out["sdf"][n:], "extra_s": out["s"][n:]}
        sdf = sdf.masked_scatter(mask, out["sdf"][:n])
        s = s.masked_scatter(mask, out["s"][:n])
        cos = cos.masked_scatter(mask, (out["normal"][:n] * d[mask]).sum(-1))
        rgb = rgb.masked_scatter(mask[..., None].expand(R, S, 3), out["rgb"][:n])
    alpha = neus_alpha(sdf, s, cos, delta) * mask
    # the solid-end rule: a solid ray's remaining transmittance ends on its last sample
    last = rgb[torch.arange(R, device=dev), (mask.sum(-1) - 1).clamp_min(0)]  # [R, 3]
    end = torch.where(solid[:, None], last, background.to(dev, dtype).expand(R, 3))
    color, _, opacity = composite(alpha, rgb, end)
    return {"color": color, "opacity": opacity, "spp": mask.sum(-1), **res}
