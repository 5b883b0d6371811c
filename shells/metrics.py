"""Image quality metrics: PSNR and SSIM (LPIPS is not included: no local weights).

Protocol (written into every metrics.json as ``protocol``): images are float RGB [H, W, 3] with
sRGB-encoded values as stored in the files (no gamma change), both clipped to [0, 1]; RGBA
references are composited over the render's background colour by the data set loader before
they reach these functions. PSNR = 10 log10(1 / MSE) over all pixels and channels. SSIM is
scikit-image's ``structural_similarity`` with ``channel_axis=-1, data_range=1.0`` and its
defaults (7x7 uniform window, K1 = 0.01, K2 = 0.03), averaged over channels. Scores of a split
are the mean of the per-image scores.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from skimage.metrics import structural_similarity

from shells.errors import InputError

PROTOCOL = ("sRGB-encoded values as stored, clipped to [0,1]; PSNR over all pixels and "
            "channels; SSIM: skimage structural_similarity(channel_axis=-1, data_range=1, "
            "7x7 uniform window); per-image scores averaged over the split")


def _pair(img, ref) -> tuple[np.ndarray, np.ndarray]:  # [H, W, 3] each -> float64, clipped
    a = img.detach().cpu().numpy() if isinstance(img, torch.Tensor) else np.asarray(img)
    b = ref.detach().cpu().numpy() if isinstance(ref, torch.Tensor) else np.asarray(ref)
    if a.shape != b.shape or a.ndim != 3:
        raise InputError(f"image shapes {a.shape} and {b.shape}: expected two equal [H, W, C]")
    return (np.clip(a.astype(np.float64), 0.0, 1.0), np.clip(b.astype(np.float64), 0.0, 1.0))


def psnr(img, ref) -> float:  # [H, W, 3] each; inf for identical images
    """Peak signal-to-noise ratio in dB for peak value 1."""
    a, b = _pair(img, ref)
    mse = float(np.mean((a - b) ** 2))
    return math.inf if mse == 0.0 else -10.0 * math.log10(mse)


def ssim(img, ref) -> float:  # [H, W, 3] each
    """Structural similarity (see the module docstring for the protocol)."""
    a, b = _pair(img, ref)
    if min(a.shape[:2]) < 7:
        raise InputError(f"image of {a.shape[1]}x{a.shape[0]} pixels: SSIM needs at least 7x7")
    return float(structural_similarity(a, b, channel_axis=-1, data_range=1.0))
