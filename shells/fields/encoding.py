"""Spherical-harmonics direction encoding (§4.1), tiny-cuda-nn / Dr.Jit ``dr.sh_eval`` convention.

Real SH of degree `degree` (tiny-cuda-nn counting: degree 4 = bands l = 0..3 = 16 values), in
the order of ``dr.sh_eval(d, degree - 1)`` (Sloan 2013, "Efficient Spherical Harmonic
Evaluation"): index l^2 + l + m for band l, order m. Evaluated on the unit direction itself
(no remapping to [0, 1] as tiny-cuda-nn's API expects).
"""

from __future__ import annotations

import torch

from shells.errors import InputError

MAX_DEGREE = 4


def sh_dim(degree: int) -> int:
    """Number of SH values for `degree` bands."""
    return degree * degree


def sh_encode(d: torch.Tensor,  # [N, 3] unit directions
              degree: int = 4) -> torch.Tensor:  # [N, degree^2]
    """Real spherical harmonics of bands 0..degree-1, ordered like ``dr.sh_eval``."""
    if not 1 <= degree <= MAX_DEGREE:
        raise InputError(f"sh_degree {degree}: supported degrees are 1..{MAX_DEGREE}")
    if d.ndim != 2 or d.shape[1] != 3:
        raise InputError(f"sh_encode: directions must be [N, 3], got {tuple(d.shape)}")
    x, y, z = d.unbind(1)
    out = [torch.full_like(x, 0.28209479177387814)]
    if degree > 1:
        a = -0.488602511902919978
        out += [a * y, 0.488602511902919923 * z, a * x]
    if degree > 2:
        z2 = z * z
        c1 = x * x - y * y  # cos(2 phi) sin^2(theta)
        s1 = 2.0 * x * y  # sin(2 phi) sin^2(theta)
        b = z * -1.09254843059207896
        out += [0.546274215296039478 * s1, b * y, z2 * 0.94617469575756008 - 0.315391565252520045,
                b * x, 0.546274215296039478 * c1]
    if degree > 3:
        c2 = x * c1 - y * s1  # cos(3 phi) sin^3(theta)
        s2 = x * s1 + y * c1  # sin(3 phi) sin^3(theta)
        tc = z2 * -2.28522899732232876 + 0.457045799464465774
        tb = z * 1.44530572132027735
        out += [-0.590043589926643519 * s2, tb * s1, tc * y,
                z * (z2 * 1.865881662950577 - 1.1195289977703462), tc * x, tb * c1,
                -0.590043589926643519 * c2]
    return torch.stack(out, dim=1)
