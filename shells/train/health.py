"""Is a field degenerate? Checks that stage 1 and shell extraction run, so that a run that
learnt nothing says so instead of ending in blank renders.

A field is degenerate when it is solid almost everywhere in the scene box (the render can only
be the colour of that solid: the shells would enclose everything), empty everywhere while the
images hold content, or when its training PSNR stalls near that of a blank image (the
background colour everywhere) or of the data's mean colour. Stage 1 (`Stage1Health`) probes
the field every log step, writes the solid share into the log, prints one line per kind of
trouble as it appears and puts the verdict into the stage's summary; `shells-extract`
(`degenerate_grid`) refuses to extract a degenerate field.
"""

from __future__ import annotations

import math
from typing import Any

import torch

SOLID_SHARE = 0.9  # solid (f < 0) in more than this share of the probed box: degenerate
STALL_DB = 3.0  # training PSNR less than this above the better of a blank image's and the mean
# colour's ...
STALL_AFTER = 0.25  # ... once this share of the schedule has run, and
STALL_MIN_STEPS = 100  # ... at least this many steps (a shorter run is not judged by it)
SMOOTH = 3  # log records averaged for the training PSNR
FLOOR_PIXELS = 1 << 20  # pixels the floor is computed on
PROBE_POINTS = 8192  # uniform points in the box where stage 1 probes the field's sign

CAUSES = ("probable cause: a background the field cannot reproduce but by matter filling the "
          "box (training on a colour other than the images' backdrop); try --config with "
          "{\"data\": {\"background\": [R, G, B]}} set to the backdrop's colour, or check the "
          "data set's aabb and cameras")


def psnr_floor(pixels: torch.Tensor,  # [N, 3] training pixels
               background: torch.Tensor,  # [3] the colour the renders show where empty
               ) -> float:
    """The PSNR of a render that learnt nothing: the better of a blank image (the background
    everywhere) and the data's mean colour everywhere (over at most FLOOR_PIXELS pixels, an
    even stride)."""
    pixels = pixels[::max(1, len(pixels) // FLOOR_PIXELS)]
    blank = float(((pixels - background) ** 2).mean())
    flat = float(((pixels - pixels.mean(0)) ** 2).mean())
    return -10.0 * math.log10(max(min(blank, flat), 1e-10))


def probe_points(aabb: torch.Tensor,  # [2, 3] the field-space box
                 n: int = PROBE_POINTS, seed: int = 0,
                 ) -> torch.Tensor:  # [n, 3]
    """Fixed uniform points in the box (the same at every probe)."""
    gen = torch.Generator().manual_seed(seed)
    u = torch.rand(n, 3, generator=gen).to(aabb.device)
    return aabb[0] + (aabb[1] - aabb[0]) * u


def solid_share(sdf: torch.Tensor) -> float:
    """Share of the values below zero (the solid)."""
    return float((sdf < 0).float().mean()) if sdf.numel() else 0.0


class Stage1Health:
    """Stage 1's running verdict: `update` after each probe returns the new warnings (each kind
    once), `summary` the record for the stage's summary and metrics.json."""

    def __init__(self, floor_db: float, iters: int, start: int = 0):
        self.floor_db, self.iters = floor_db, iters
        self.check_from = max(start, int(STALL_AFTER * iters), STALL_MIN_STEPS)
        self.psnrs: list[float] = []
        self.solid: float | None = None
        self.warnings: dict[str, str] = {}

    def update(self, step: int, psnr: float, solid: float) -> list[str]:
        self.psnrs = (self.psnrs + [psnr])[-SMOOTH:]
        self.solid = solid
        new = []

        def warn(kind: str, text: str) -> None:
            if kind not in self.warnings:
                self.warnings[kind] = text
                new.append(text)

        if solid > SOLID_SHARE:
            warn("solid", f"stage 1, step {step}: the field is solid in {solid:.0%} of the scene "
                          f"box, a degenerate field (the shells would cover everything); "
                          f"{CAUSES}")
        if step >= self.check_from:
            mean = sum(self.psnrs) / len(self.psnrs)
            if mean < self.floor_db + STALL_DB:
                kind = "empty" if solid == 0.0 else "stalled"
                what = "is empty and its" if kind == "empty" else "has not learnt the content:"
                warn(kind, f"stage 1, step {step}: the field {what} training PSNR {mean:.1f} dB "
                           f"is within {STALL_DB:g} dB of a render that learnt nothing "
                           f"({self.floor_db:.1f} dB); {CAUSES}")
        return new

    def summary(self) -> dict[str, Any]:
        mean = sum(self.psnrs) / len(self.psnrs) if self.psnrs else None
        return {"ok": not self.warnings, "warnings": list(self.warnings.values()),
                "kinds": list(self.warnings), "solid_share": self.solid,
                "psnr_train": mean, "psnr_floor": self.floor_db}


def degenerate_grid(sdf: torch.Tensor) -> str | None:
    """Why a grid of SDF samples over the box is degenerate (solid in more than SOLID_SHARE
    of it, or nowhere), or None."""
    share = solid_share(sdf)
    if share > SOLID_SHARE:
        return f"the field is solid in {share:.0%} of the scene box"
    if share == 0.0:
        return "the field is empty (f > 0 everywhere in the scene box)"
    return None


BAND_CHECK_PIXELS = 4096  # training pixels of stage 2's band check
BAND_CHECK_DB = 0.3  # the band further than this under full ray: a warning


@torch.no_grad()
def band_check(field: torch.nn.Module, scene: Any, data: Any,
               pixels: torch.Tensor,  # [N, 3] training pixels on the run's background
               rc: Any,  # RenderConfig: the band's sampling; full_samples
               background: torch.Tensor,  # [3]
               n: int = BAND_CHECK_PIXELS, seed: int = 0) -> dict[str, Any]:
    """How far the band is from full ray, on ``n`` training pixels drawn with ``seed`` (the same
    pixels for both): the band as stage 2 renders it (`render_band_rays`) and the torch full-ray
    renderer over the whole ray (``render.full_samples`` stratified samples plus half as many
    placed by importance, so that a sharp field's crossings are resolved), each scored against
    the pixels. Returns both PSNRs, their difference (band - full ray), the band's samples per
    pixel, and a warning when the band is more than BAND_CHECK_DB under full ray (None
    otherwise): a cheap check of the shells that needs no full-ray render of the test views."""
    from shells.metrics import psnr
    from shells.render.band import render_band_rays
    from shells.render.volume import render_volume_rays

    gen = torch.Generator(device=pixels.device).manual_seed(seed)
    idx, o, d = data.sample_pixel_rays(n, 1, gen)
    target = pixels[idx].clamp(0, 1)
    band = render_band_rays(field, scene, o, d, rc, background)
    full = render_volume_rays(field, o, d, rc.full_samples, rc.full_samples // 2, background,
                              gen)
    band_db = psnr(band["color"][None], target[None])  # [1, n, 3]: one strip of pixels
    full_db = psnr(full["color"][None], target[None])
    spp = float(band["spp"].float().mean())
    gap = band_db - full_db
    warning = None
    if gap < -BAND_CHECK_DB:
        warning = (f"stage 2: the band renders {-gap:.2f} dB under full ray on {len(idx)} "
                   f"training pixels ({band_db:.2f} against {full_db:.2f} dB at {spp:.2f} "
                   f"samples/px): the shells miss weight the field has; wider shells "
                   f"(shell.dilate_zeta, shell.beta_d) or a denser band (render.w_s, "
                   f"render.delta_s) may close it")
    return {"pixels": len(idx), "band_psnr": band_db, "full_psnr": full_db, "gap_db": gap,
            "band_spp": spp, "full_samples": rc.full_samples + rc.full_samples // 2,
            "warning": warning}
