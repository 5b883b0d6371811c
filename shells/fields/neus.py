"""NeuS density with a spatially varying kernel (§3.1-3.2, Eq. 2-3), as pure functions.

Conventions: SDF f > 0 outside, f < 0 inside; kernel size s > 0 in world units (larger s = wider,
fuzzier kernel); Phi_s(f) = sigmoid(f / s); cos = d . grad f, negative when a ray enters.

`neus_alpha` is written once for both backends: it accepts torch tensors (training) and Dr.Jit
arrays (inference, ``shells.fields.drjit_field``) and uses the matching math functions.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def phi(f: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """Phi_s(f) = sigmoid(f / s): the logistic CDF of the kernel, 0 deep inside, 1 far outside."""
    return torch.sigmoid(f / s)


def density(f: torch.Tensor, s: torch.Tensor, cos: torch.Tensor) -> torch.Tensor:
    """Eq. 3: sigma = max(-(dPhi/dtau) / Phi, 0) with dPhi/dtau = Phi (1 - Phi) cos / s.

    Simplified: sigma = max(-cos, 0) (1 - Phi_s(f)) / s = relu(-cos) sigmoid(-f / s) / s,
    which is finite for any f. All arguments broadcast; returns sigma in 1 / world units.
    """
    return F.relu(-cos) * torch.sigmoid(-f / s) / s


class _TorchOps:
    relu = staticmethod(F.relu)
    logsigmoid = staticmethod(F.logsigmoid)
    exp = staticmethod(torch.exp)

    @staticmethod
    def clip(x, lo, hi):
        return torch.clamp(x, lo, hi)


class _DrJitOps:
    @staticmethod
    def relu(x):
        import drjit as dr
        return dr.maximum(x, 0)

    @staticmethod
    def logsigmoid(x):
        # log sigmoid(x) = min(x, 0) - log(1 + exp(-|x|)), finite for every x
        import drjit as dr
        return dr.minimum(x, 0) - dr.log(1 + dr.exp(-dr.abs(x)))

    @staticmethod
    def exp(x):
        import drjit as dr
        return dr.exp(x)

    @staticmethod
    def clip(x, lo, hi):
        import drjit as dr
        return dr.clip(x, lo, hi)


def may_have_density(f: torch.Tensor, s: torch.Tensor, h: float, k: float) -> torch.Tensor:
    """The occupancy rule of every occupancy grid: a cell whose centre (or any tested point) has
    |f| < h + k s may hold density (h: half the cell diagonal). For an SDF (|grad f| <= 1)
    the test at one point bounds |f| >= k s over the whole cell otherwise, and a layer with
    |f| >= k s holds an opacity <= e^-k (the NeuS transmittance across f in [-k s, k s] falls
    by Phi_s(-k s) / Phi_s(k s) ~ e^-k). Torch tensors, any shape."""
    return f.abs() < h + k * s


def half_cell_diagonal(box: torch.Tensor,  # [2, 3] (min, max)
                       resolution: int) -> float:
    """Half the diagonal of one cell of a ``resolution``^3 grid over ``box``: the h of
    `may_have_density`."""
    return 0.5 * float((box[1] - box[0]).norm()) / resolution


def _ops(x):
    return _TorchOps if isinstance(x, torch.Tensor) else _DrJitOps


def neus_alpha(sdf, s, cos, delta):
    """Discrete NeuS opacity of a section of length delta centred on a sample; all [R, S].

    f_prev = sdf - c delta / 2 and f_next = sdf + c delta / 2 with c = -relu(-cos) (only the
    entering part of the slope, as NeuS at the end of its cos annealing), s = s(x) at the sample:

        alpha = clip((Phi_s(f_prev) - Phi_s(f_next)) / Phi_s(f_prev), 0, 1)
              = clip(1 - exp(log sigmoid(f_next / s) - log sigmoid(f_prev / s)), 0, 1).

    The log-sigmoid form needs no epsilon: it stays exact when both Phi underflow (deep inside,
    small s) and when both round to 1 (far outside). Works on torch tensors and Dr.Jit arrays.
    """
    o = _ops(sdf)
    half = -o.relu(-cos) * delta * 0.5
    log_ratio = o.logsigmoid((sdf + half) / s) - o.logsigmoid((sdf - half) / s)
    return o.clip(1.0 - o.exp(log_ratio), 0.0, 1.0)


def composite(alpha: torch.Tensor,  # [R, S]
              rgb: torch.Tensor,  # [R, S, 3]
              background: torch.Tensor,  # [3] or [R, 3]
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Eq. 2: T_i = prod_{j<i} (1 - alpha_j), w_i = T_i alpha_i; color = sum_i w_i c_i + (1 - O) bg.

    Returns (color [R, 3], weights [R, S], opacity O = sum_i w_i [R]).
    """
    trans = torch.cumprod(
        torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha[:, :-1]], dim=1), dim=1)
    weights = trans * alpha
    opacity = weights.sum(dim=1)
    color = (weights.unsqueeze(-1) * rgb).sum(dim=1) + (1.0 - opacity).unsqueeze(-1) * background
    return color, weights, opacity
