"""PSNR and SSIM on hand-worked images."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from shells.errors import InputError
from shells.metrics import psnr, ssim


def test_psnr_hand_worked():
    ref = np.full((8, 8, 3), 0.6)
    # MSE = 0.1^2 = 0.01 -> PSNR = -10 log10(0.01) = 20 dB
    assert psnr(np.full((8, 8, 3), 0.5), ref) == pytest.approx(20.0, abs=1e-9)
    # one channel of one pixel off by 1 in 4x4x3 = 48 values: MSE = 1/48 -> 10 log10(48) dB
    a = np.zeros((4, 4, 3)); b = a.copy(); b[1, 2, 0] = 1.0
    assert psnr(torch.tensor(a), torch.tensor(b)) == pytest.approx(10 * math.log10(48))
    assert psnr(ref, ref) == math.inf


def test_psnr_clips_to_unit_range():
    # 1.3 and 1.0 both clip to 1.0; -0.2 clips to 0: identical after clipping
    a = np.array([[[1.3, -0.2, 0.5]]]); b = np.array([[[1.0, 0.0, 0.5]]])
    assert psnr(a, b) == math.inf


def test_ssim_identical_and_degraded():
    rng = np.random.default_rng(0)
    ref = rng.uniform(size=(16, 16, 3))
    assert ssim(ref, ref) == pytest.approx(1.0)
    noisy = ref + rng.normal(scale=0.2, size=ref.shape)
    assert ssim(noisy, ref) < 0.9
    # a constant offset keeps structure: luminance term only, so SSIM stays high
    assert ssim(ref * 0.9 + 0.05, ref) > ssim(noisy, ref)


def test_bad_shapes_raise():
    with pytest.raises(InputError):
        psnr(np.zeros((4, 4, 3)), np.zeros((4, 5, 3)))
    with pytest.raises(InputError):
        ssim(np.zeros((4, 4, 3)), np.zeros((4, 4, 3)))
