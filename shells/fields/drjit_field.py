"""Dr.Jit inference twin of `ShellField`, for rendering (Mitsuba ray casting + field evaluation).

Same function as the torch model, evaluated with ``dr.nn.HashGridEncoding`` (which takes the
torch grid's flat parameter vector as is; the layout is defined in ``shells.fields.hashgrid``),
``dr.nn.Sequential`` MLPs packed for inference and evaluated on ``nn.CoopVec``, and
``dr.sh_eval``. Inputs are arrays of the current Mitsuba variant (``mi.Point3f``/``mi.Vector3f``;
``shells.device.mitsuba_variant()`` is called if none is set). The NeuS opacity for Dr.Jit arrays
is ``shells.fields.neus.neus_alpha`` itself (it dispatches on the array type).

Weights are copied at construction: rebuild the twin after further training.

An unbounded field (``field.similarity``) is evaluated as `ShellField` evaluates it: at
z = W(x) (the contraction), with the solid far sphere min(f_net, radius (far_radius - |y|)),
the world slope normal J^T n as ``normal`` (for cos = d . normal) and the unit field-space
normal into the radiance MLP. `eval_geometry_field` takes field-space points (the occupancy
grid of an unbounded scene lives there).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr
import torch
from torch import nn

from shells.fields.network import NORMAL_EPS, ShellField


@dataclass
class FieldSample:
    """Field values at a batch of points (a Dr.Jit PyTree)."""

    sdf: Any  # Float, world units, > 0 outside
    s: Any  # Float, kernel size, world units
    normal: Any  # Array3f, predicted unit normal (unbounded: the world slope normal J^T n)
    rgb: Any  # Array3f in (0, 1); None from eval_geometry


def contract_point(x, centre: tuple[float, float, float], radius: float):
    """W(x) = centre + radius c((x - centre) / radius) for Dr.Jit 3-vectors (x itself inside
    the ball), with u = (x - centre) / radius and |u|: the contraction of
    `shells.fields.contraction`, for the twin and the occupancy march of an unbounded field."""
    c = type(x)(*centre)
    u = (x - c) / radius
    r = dr.norm(u)
    z = dr.select(r > 1.0, dr.fma(u * ((2.0 - dr.rcp(r)) * dr.rcp(r)), radius, c), x)
    return z, u, r


def _sigmoid(x):
    return dr.rcp(1.0 + dr.exp(-x))


class DrJitField:
    """Evaluate a trained `ShellField` in Dr.Jit; weights are copied once, at construction."""

    def __init__(self, field: ShellField) -> None:
        import mitsuba as mi

        if mi.variant() is None:
            from shells.device import mitsuba_variant
            mitsuba_variant()
        self.Float, self.TensorXf, self.Array3f = mi.Float, mi.TensorXf, mi.Vector3f
        cfg, grid = field.cfg, field.grid
        self.sh_order = cfg.sh_degree - 1  # dr.sh_eval counts from 0
        self.geo_dim = cfg.geo_feature_dim
        aabb = field.aabb.detach().cpu().float()
        self.centre = [float(v) for v in 0.5 * (aabb[0] + aabb[1])]
        self.inv_half = [float(v) for v in 2.0 / (aabb[1] - aabb[0])]
        self.log_kmin, self.log_krange = field.log_kmin, field.log_krange
        self.kernel_z0 = field.kernel_z0
        self.similarity = field.similarity  # None: bounded (field space = world)
        self._ball = (None if field.similarity is None else
                      (field.similarity.centre, float(field.similarity.radius)))
        self.far_radius = float(field.cfg.far_radius)
        self.near_radius = float(field.cfg.near_radius)
        self.dome_logit = float(field.dome_logit)
        self.aabb = aabb  # field-space box [2, 3]

        self.encoding = dr.nn.HashGridEncoding(
            self.Float, 3, n_levels=grid.n_levels, n_features_per_level=grid.n_features,
            hashmap_size=grid.hashmap_size, base_resolution=grid.base_resolution,
            per_level_scale=grid.per_level_scale)
        self.encoding.set_params(self.Float(grid.params.detach().float().cpu().contiguous()))
        self.geo_mlp = self._convert(field.geo_mlp, field.geo_in)
        self.rad_mlp = self._convert(field.rad_mlp, field.rad_in)

    def _convert(self, seq: nn.Sequential, n_in: int):
        """torch Linear/ReLU stack -> packed dr.nn.Sequential with the same weights."""
        layers = []
        for m in seq:
            if isinstance(m, nn.Linear):
                layers.append(dr.nn.Linear(m.in_features, m.out_features, bias=True))
            elif isinstance(m, nn.ReLU):
                layers.append(dr.nn.ReLU())
            else:
                raise TypeError(f"DrJitField: no Dr.Jit counterpart for {type(m).__name__}")
        net = dr.nn.Sequential(*layers).alloc(self.TensorXf, n_in)
        for i, m in enumerate(seq):
            if isinstance(m, nn.Linear):
                net[f"layers.{i}.weights"] = self.TensorXf(m.weight.detach().float().cpu())
                net[f"layers.{i}.bias"] = self.TensorXf(m.bias.detach().float().cpu())
        return dr.nn.pack(net, layout="inference")

    def _raw(self, z):  # Array3f field space -> (xn [3 Floats], raw [2+G+3 Floats], on)
        """``on``: where the far solid is the surface (None for a bounded field)."""
        xn = [(z[i] - self.centre[i]) * self.inv_half[i] for i in range(3)]
        p01 = [dr.clip(v * 0.5 + 0.5, 0.0, 1.0) for v in xn]
        feats = list(self.encoding(p01))
        raw = list(self.geo_mlp(dr.nn.CoopVec(*xn, *feats)))
        if self.similarity is None:
            return xn, raw, None
        dome = self._dome(z)  # the solid far background (ShellField._geo_raw)
        on = dome < raw[0]
        raw[0] = dr.select(on, dome, raw[0])
        raw[1] = dr.select(on, self.dome_logit, raw[1])
        return xn, raw, on

    def _unit(self, p):  # Array3f -> (p - centre) / radius
        c, r = self.similarity.centre, self.similarity.radius
        return self.Array3f(*[(p[i] - c[i]) / r for i in range(3)])

    def _dome(self, z):
        return self.similarity.radius * (self.far_radius - dr.norm(self._unit(z)))

    def _kernel(self, z):
        return dr.exp(self.log_kmin + self.log_krange * _sigmoid(z + self.kernel_z0))

    def eval_geometry_field(self, z) -> FieldSample:
        """sdf and s at field-space points (the world for a bounded field)."""
        _, raw, _ = self._raw(z)
        return FieldSample(sdf=raw[0], s=self._kernel(raw[1]), normal=None, rgb=None)

    def eval_geometry(self, x) -> FieldSample:
        """sdf and s only (no normal, no colour) at world points."""
        z = x if self.similarity is None else contract_point(x, *self._ball)[0]
        return self.eval_geometry_field(z)

    def eval(self, x, d) -> FieldSample:
        """x: Point3f world positions, d: Vector3f unit view directions (same width or 1)."""
        if self.similarity is None:
            z = x
        else:
            z, u, r = contract_point(x, *self._ball)
        xn, raw, on = self._raw(z)
        G = self.geo_dim
        feat = raw[2:2 + G]
        n = self.Array3f(*raw[2 + G:])
        n = n * dr.rcp(dr.maximum(dr.norm(n), NORMAL_EPS))
        slope = n
        if self.similarity is not None:
            y = self._unit(z)
            n = dr.select(on, -y * dr.rcp(dr.maximum(dr.norm(y), 1e-12)), n)
            rr = dr.maximum(r, 1.0)
            uh = u * dr.rcp(rr)
            a = (2.0 - dr.rcp(rr)) * dr.rcp(rr)
            b = dr.rcp(rr * rr)
            slope = dr.select(r > 1.0, a * n + (b - a) * dr.dot(uh, n) * uh, n)
        sh = dr.sh_eval(self.Array3f(d), self.sh_order)
        out = list(self.rad_mlp(dr.nn.CoopVec(*sh, *feat, n.x, n.y, n.z, *xn)))
        rgb = self.Array3f(*[_sigmoid(v) for v in out])
        return FieldSample(sdf=raw[0], s=self._kernel(raw[1]), normal=slope, rgb=rgb)

    def eval_torch(self, x: torch.Tensor, d: torch.Tensor | None = None
                   ) -> dict[str, torch.Tensor]:
        """Convenience for tests and tools: torch [N, 3] in, torch tensors out (via Dr.Jit)."""
        def to_dr(t):
            t = t.detach().float().contiguous()
            return self.Array3f(*[self.Float(t[:, i].contiguous()) for i in range(3)])

        def col(v):
            return v.torch().clone()

        def vec(v):
            return torch.stack([col(v[i]) for i in range(3)], dim=1)

        if d is None:
            r = self.eval_geometry(to_dr(x))
            return dict(sdf=col(r.sdf), s=col(r.s))
        r = self.eval(to_dr(x), to_dr(d))
        return dict(sdf=col(r.sdf), s=col(r.s), normal=vec(r.normal), rgb=vec(r.rgb))
