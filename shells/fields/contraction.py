"""Scene contraction for unbounded captures (paper §4.7, after Mip-NeRF 360 and BakedSDF).

A world point p is first mapped by a similarity, x = (p - centre) / radius, that takes the
region of interest into the unit ball (`Similarity`), then contracted:

    c(x) = x                          |x| <= 1
    c(x) = (2 - 1/|x|) x / |x|        |x| > 1

which maps all of R^3 into the open ball of radius 2, so a hash grid over the cube [-2, 2]^3
holds the whole scene: the unit ball at full resolution, the far background with resolution
falling as 1/|x|^2 along a ray (evenly spaced in disparity). The inverse, for |y| < 2:

    c^-1(y) = y                       |y| <= 1
    c^-1(y) = y / (|y| (2 - |y|))     1 < |y| < 2

The Jacobian outside the unit ball, with r = |x| and u = x / r, is

    J = (2 - 1/r) / r (I - u u^T) + 1 / r^2 u u^T

(tangential stretch (2 - 1/r) / r, radial derivative 1 / r^2); it is the identity on the unit
sphere, so c is C^1. These functions are torch (training, the level-set grid's points) and are
also applied to numpy arrays through ``torch.from_numpy`` by their callers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from shells.errors import InputError

_EPS = 1e-12


def contract(x: torch.Tensor) -> torch.Tensor:
    """c(x) for points [..., 3] in the similarity's frame; |c(x)| < 2."""
    r = torch.linalg.vector_norm(x, dim=-1, keepdim=True)
    far = r > 1.0
    scale = torch.where(far, (2.0 - 1.0 / r.clamp_min(1.0)) / r.clamp_min(1.0), 1.0)
    return x * scale


def uncontract(y: torch.Tensor) -> torch.Tensor:
    """c^-1(y) for points [..., 3] with |y| < 2 (the radius-2 sphere is infinitely far)."""
    r = torch.linalg.vector_norm(y, dim=-1, keepdim=True)
    if bool((r >= 2.0).any()):
        raise ValueError("uncontract: a point at |y| >= 2 has no preimage (it is at infinity)")
    far = r > 1.0
    rr = r.clamp_min(1.0)
    return y * torch.where(far, 1.0 / (rr * (2.0 - rr)), 1.0)


def contract_jacobian(x: torch.Tensor) -> torch.Tensor:
    """dc/dx [..., 3, 3] at points [..., 3] (the identity inside the unit ball)."""
    r = torch.linalg.vector_norm(x, dim=-1, keepdim=True)[..., None]  # [..., 1, 1]
    u = x[..., :, None] / r.clamp_min(_EPS)
    uu = u @ u.transpose(-1, -2)
    eye = torch.eye(3, dtype=x.dtype, device=x.device).expand_as(uu)
    rr = r.clamp_min(1.0)
    far = (2.0 - 1.0 / rr) / rr * (eye - uu) + uu / rr ** 2
    return torch.where(r > 1.0, far, eye)


@dataclass(frozen=True)
class Similarity:
    """x = (p - centre) / radius: the region of interest of a capture into the unit ball."""

    centre: tuple[float, float, float]
    radius: float

    def to_unit(self, p: torch.Tensor) -> torch.Tensor:
        return (p - p.new_tensor(self.centre)) / self.radius

    def to_world(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.radius + x.new_tensor(self.centre)

    @staticmethod
    def from_cameras(origins: np.ndarray, forward: np.ndarray, what: str = "the cameras"
                     ) -> "Similarity":
        """The point nearest to every camera's optical axis (least squares) as the centre, and
        the cameras' median distance from it as the radius: an inward-facing capture's object
        sits well inside the unit ball, the cameras on its sphere, the room beyond it.

        ``origins`` [N, 3] camera centres, ``forward`` [N, 3] viewing directions. An InputError
        names ``what`` when there is no such point: the axes (nearly) parallel, or the point
        behind most of the cameras (they look outwards, e.g. from inside the object)."""
        o = np.asarray(origins, np.float64).reshape(-1, 3)
        d = np.asarray(forward, np.float64).reshape(-1, 3)
        if len(o) < 2:
            raise InputError(f"{what}: need at least 2 cameras to find the region they look at")
        d = d / np.linalg.norm(d, axis=1, keepdims=True).clip(_EPS)
        P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # projectors off each axis
        A, b = P.sum(0), (P @ o[:, :, None]).sum(0)[:, 0]
        w = np.linalg.eigvalsh(A)
        if w[0] < 1e-3 * w[-1]:
            raise InputError(f"{what}: the optical axes are (nearly) parallel, so they meet "
                             "nowhere; an unbounded scene needs cameras that look at a common "
                             "region (or give the data set's scale/offset)")
        c = np.linalg.solve(A, b)
        depth = np.einsum("ij,ij->i", c[None] - o, d)
        if np.mean(depth > 0) < 0.5:
            raise InputError(f"{what}: the point the optical axes meet lies behind most "
                             "cameras (they look outwards, e.g. from inside the object); an "
                             "unbounded scene needs cameras that look at a common region")
        radius = float(np.median(np.linalg.norm(o - c[None], axis=1)))
        return Similarity((float(c[0]), float(c[1]), float(c[2])), radius)
