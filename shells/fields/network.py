"""The SDF field with a spatially varying kernel (§4.1): hash grid + geometry MLP + radiance MLP.

    x (world) -> x_n = (x - centre) / half_extent in [-1, 1]^3 -> p = clamp((x_n + 1) / 2, 0, 1)
    geometry MLP  [x_n (3), Psi(p) (L F)] -> H -> [f (1), z_s (1), feat (G), n_raw (3)]
    kernel        s = exp(log s_min + (log s_max - log s_min) sigmoid(z_s + z0))
    radiance MLP  [SH(d) (deg^2), feat (G), n (3), x_n (3)] -> H -> H -> 3, sigmoid

f is in world units (> 0 outside); n = n_raw / |n_raw| is the *predicted* normal (trained
towards grad f / |grad f| by the normal loss).

Unbounded captures (``cfg.unbounded``, paper §4.7): the field lives in *field space*, the
contracted copy of the world z = W(x) = centre + radius c((x - centre) / radius)
(`shells.fields.contraction`), over the box centre +- 2 radius; W is the identity inside the
ball of interest, so f and s keep world units there. Beyond ``cfg.far_radius`` (contracted,
in radius units) everything is solid: f = min(f_net, radius (far_radius - |y|)) with
y = (z - centre) / radius, the far background that closes every ray. f is an SDF of z (the
Eikonal term acts in field space); along a world ray its slope is d . J^T grad_z f, so
`geometry` reports the *slope normal* J^T n (J = dW/dx, symmetric; |J^T n| <= 1) as
``normal``, which every renderer's cos = d . normal then gets right, and the unit field-space
normal as ``n_unit`` (what the radiance MLP sees). For a bounded field the two are the same and
field space is the world. Activations are ReLU: ``dr.nn`` has ReLU but no
softplus, and the Dr.Jit twin must evaluate the same function. The soft clamp keeps s in
(s_min, s_max) with non-zero gradient everywhere; z0 makes s = init_kernel when z_s = 0.

Geometric initialisation: hidden unit k computes ReLU(u_k . (x - centre)) for u_k on a Fibonacci
sphere (first-layer weights u_k * half_extent on x_n, zero on the hash features, zero bias), and
the SDF row averages them with weight 4 / H, because the mean of max(u . v, 0) over unit u is
|v| / 4. So f(x) = |x - centre| - init_radius to within 1.6 % of |x - centre| for H = 64
(0.4 % for H = 128), in world units, for any box aspect ratio. The kernel row is zero.
Checkpoint = ``state_dict()``.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from shells.config import FieldConfig
from shells.errors import InputError
from shells.fields.contraction import Similarity, contract
from shells.fields.encoding import sh_dim, sh_encode
from shells.fields.hashgrid import HashGrid, per_level_scale

NORMAL_EPS = 1e-12  # n = n_raw / max(|n_raw|, eps)
DOME_KERNEL = 0.002  # kernel size on the far sphere of an unbounded field, in radius units


def fibonacci_sphere(n: int) -> torch.Tensor:  # [n, 3] unit vectors, near-uniform
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = torch.sqrt(1.0 - z * z)
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=1)


class ShellField(nn.Module):
    """Hash-grid SDF field f(x), kernel s(x) and view-dependent colour c(x, d)."""

    def __init__(self, cfg: FieldConfig, aabb: torch.Tensor  # [2, 3] (min, max), world units
                 ) -> None:
        super().__init__()
        aabb = torch.as_tensor(aabb).detach().cpu().float()  # move the module with .to(device)
        if aabb.shape != (2, 3) or not bool((aabb[1] > aabb[0]).all()):
            raise InputError(f"ShellField: aabb must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] "
                             f"with max > min, got {aabb.tolist()}")
        self.cfg = cfg
        self.similarity = (Similarity(tuple(float(c) for c in cfg.centre), float(cfg.radius))
                           if cfg.unbounded else None)
        if self.similarity is not None:
            # field space: the contracted ball of radius 2 around the centre, whatever was given
            c, r = torch.tensor(cfg.centre, dtype=torch.float32), 2.0 * float(cfg.radius)
            aabb = torch.stack([c - r, c + r])
        self.register_buffer("aabb", aabb.clone())
        L, Fl = cfg.n_levels, cfg.n_features_per_level
        self.grid = HashGrid(L, Fl, 2 ** cfg.log2_hashmap_size, cfg.base_resolution,
                             per_level_scale(L, cfg.base_resolution, cfg.max_resolution))
        G = cfg.geo_feature_dim
        self.geo_in, self.geo_out = 3 + L * Fl, 2 + G + 3
        # ReLUs in place: the out-of-place clamp took a share of a training step
        self.geo_mlp = nn.Sequential(nn.Linear(self.geo_in, cfg.geo_hidden),
                                     nn.ReLU(inplace=True),
                                     nn.Linear(cfg.geo_hidden, self.geo_out))
        self.rad_in = sh_dim(cfg.sh_degree) + G + 3 + 3
        layers, width = [], self.rad_in
        for _ in range(cfg.rad_layers):
            layers += [nn.Linear(width, cfg.rad_hidden), nn.ReLU(inplace=True)]
            width = cfg.rad_hidden
        self.rad_mlp = nn.Sequential(*layers, nn.Linear(width, 3))
        self.log_kmin = math.log(cfg.min_kernel)
        self.log_krange = math.log(cfg.max_kernel) - self.log_kmin
        t = (math.log(cfg.init_kernel) - self.log_kmin) / self.log_krange
        self.kernel_z0 = math.log(t / (1.0 - t))  # logit: sigmoid(z0) = t
        self.geometric_init()
        # where the far sphere is the surface its kernel is sharp, DOME_KERNEL radii: a ray
        # that reaches it is absorbed well before its samples end (shells.render.warp)
        t = (math.log(min(max(DOME_KERNEL * cfg.radius, 1.01 * cfg.min_kernel),
                          0.99 * cfg.max_kernel)) - self.log_kmin) / self.log_krange
        self.dome_logit = math.log(t / (1.0 - t)) - self.kernel_z0
        # coarse-to-fine training (Neuralangelo): hash levels >= active_levels read as zero;
        # None = all levels (inference always uses all)
        self.active_levels: int | None = None
        if cfg.global_kernel:
            # the kernel row of the last layer stays zero: s depends on its bias only, one
            # learned scalar (the Dr.Jit twin evaluates the same layer unchanged)
            mask = torch.ones_like(self.geo_mlp[2].weight)
            mask[1] = 0.0
            self.geo_mlp[2].weight.register_hook(lambda g: g * mask.to(g))

    # -- initialisation ------------------------------------------------------------------------
    @torch.no_grad()
    def geometric_init(self) -> None:
        """SDF = |x - centre| - init_radius (to ~1.6 % for H = 64), s = init_kernel."""
        H = self.cfg.geo_hidden
        first, last = self.geo_mlp[0], self.geo_mlp[2]
        half = 0.5 * (self.aabb[1] - self.aabb[0])
        first.weight.zero_()
        first.weight[:, :3] = (fibonacci_sphere(H) * half.double()).float()
        first.bias.zero_()
        last.weight[:2].zero_()
        last.weight[0] = 4.0 / H
        last.bias[0] = -self.cfg.init_radius
        last.bias[1] = 0.0
        if self.cfg.unbounded:
            # the predicted normal starts as grad f of that sphere: the mean of u max(u . v, 0)
            # over unit u is v / 6, so these rows give n_raw ~ (x - centre), radial
            G = self.cfg.geo_feature_dim
            last.weight[2 + G:] = (fibonacci_sphere(H).T * (6.0 / H)).float()
            last.bias[2 + G:] = 0.0

    # -- evaluation ----------------------------------------------------------------------------
    def normalize(self, x: torch.Tensor  # [N, 3] field space
                  ) -> torch.Tensor:  # [N, 3] box-normalised, [-1, 1]^3 inside the box
        centre = 0.5 * (self.aabb[0] + self.aabb[1])
        inv_half = 2.0 / (self.aabb[1] - self.aabb[0])
        return (x - centre) * inv_half

    def kernel_from_logit(self, z: torch.Tensor) -> torch.Tensor:
        """s = exp(log s_min + (log s_max - log s_min) sigmoid(z + z0)): a soft clamp."""
        return torch.exp(self.log_kmin + self.log_krange * torch.sigmoid(z + self.kernel_z0))

    def _geo_raw(self, z: torch.Tensor,  # [N, 3] field space (the world for bounded fields)
                 far: bool = True,  # False: the network alone, without the far solid
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """x_n [N, 3], raw outputs [N, 2+G+3], and where the far solid is the surface [N]
        (None when it is not applied)."""
        if z.ndim != 2 or z.shape[1] != 3:
            raise InputError(f"ShellField: points must be [N, 3], got {tuple(z.shape)}")
        xn = self.normalize(z)
        feats = self.grid(torch.clamp(xn * 0.5 + 0.5, 0.0, 1.0))
        L, Fl = self.cfg.n_levels, self.cfg.n_features_per_level
        if self.active_levels is not None and self.active_levels < L:
            mask = (torch.arange(L * Fl, device=z.device) < self.active_levels * Fl)
            feats = feats * mask.to(feats.dtype)
        raw = self.geo_mlp(torch.cat([xn, feats], dim=1))
        if self.similarity is None or not far:
            return xn, raw, None
        dome = self._dome(z)  # the solid far background: min(f_net, dome)
        on = dome < raw[:, 0]
        f = torch.where(on, dome, raw[:, 0])
        k = torch.where(on, torch.full_like(dome, self.dome_logit), raw[:, 1])
        return xn, torch.cat([f[:, None], k[:, None], raw[:, 2:]], dim=1), on

    def _dome(self, z: torch.Tensor) -> torch.Tensor:  # [N, 3] field space -> [N]
        """radius (far_radius - |y|), y = (z - centre) / radius: > 0 inside the far sphere."""
        y = self.similarity.to_unit(z)
        return self.similarity.radius * (self.cfg.far_radius - torch.linalg.vector_norm(y, dim=-1))

    @property
    def far_radius(self) -> float:
        return float(self.cfg.far_radius)

    @property
    def near_radius(self) -> float:  # where rays start (shells.render.warp.ray_span)
        return float(self.cfg.near_radius)

    def _contract(self, x: torch.Tensor  # [N, 3] world, unbounded field
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """z = W(x) [N, 3] (x itself inside the ball), u = (x - centre) / radius, |u| [N, 1]."""
        u = self.similarity.to_unit(x)
        r = torch.linalg.vector_norm(u, dim=-1, keepdim=True)
        return torch.where(r > 1.0, self.similarity.to_world(contract(u)), x), u, r

    def to_field(self, x: torch.Tensor) -> torch.Tensor:  # [N, 3] world -> field space
        """W(x) = centre + radius c((x - centre) / radius); the identity for bounded fields."""
        return x if self.similarity is None else self._contract(x)[0]

    def geometry_field(self, z: torch.Tensor,  # [N, 3] field space
                       far: bool = True,  # False: the network alone (the regularisers)
                       ) -> dict[str, torch.Tensor]:
        """sdf [N], s [N], feat [N, G], normal [N, 3] (unit, field space), xn [N, 3]."""
        xn, raw, on = self._geo_raw(z, far)
        G = self.cfg.geo_feature_dim
        normal = F.normalize(raw[:, 2 + G:], dim=1, eps=NORMAL_EPS)
        if on is not None:  # the far sphere's normal where it is the surface
            y = self.similarity.to_unit(z)
            inward = -y / torch.linalg.vector_norm(y, dim=-1, keepdim=True).clamp_min(1e-12)
            normal = torch.where(on[:, None], inward, normal)
        return dict(sdf=raw[:, 0], s=self.kernel_from_logit(raw[:, 1]), feat=raw[:, 2:2 + G],
                    normal=normal, xn=xn)

    def geometry(self, x: torch.Tensor  # [N, 3] world
                 ) -> dict[str, torch.Tensor]:
        """`geometry_field` at W(x), with ``normal`` the world slope normal J^T n and
        ``n_unit`` the unit field-space normal (the same tensor for a bounded field)."""
        if self.similarity is None:
            geo = self.geometry_field(x)
            geo["n_unit"] = geo["normal"]
            return geo
        z, u, r = self._contract(x)
        geo = self.geometry_field(z)
        n = geo["normal"]
        geo["n_unit"] = n
        far = r > 1.0
        rr = r.clamp_min(1.0)
        uh = u / rr
        a = (2.0 - 1.0 / rr) / rr  # tangential stretch of the contraction
        b = 1.0 / rr ** 2  # its radial derivative
        jn = a * n + (b - a) * (uh * n).sum(-1, keepdim=True) * uh  # J^T n, J symmetric
        geo["normal"] = torch.where(far, jn, n)
        return geo

    def radiance(self, d: torch.Tensor,  # [N, 3] unit view directions
                 geo: dict[str, torch.Tensor]) -> torch.Tensor:  # [N, 3] in (0, 1)
        sh = sh_encode(d, self.cfg.sh_degree)
        h = torch.cat([sh, geo["feat"], geo.get("n_unit", geo["normal"]), geo["xn"]], dim=1)
        return torch.sigmoid(self.rad_mlp(h))

    def forward(self, x: torch.Tensor,  # [N, 3] world
                d: torch.Tensor,  # [N, 3] unit view directions
                ) -> dict[str, torch.Tensor]:
        """geometry(x) plus rgb [N, 3]."""
        geo = self.geometry(x)
        geo["rgb"] = self.radiance(d, geo)
        return geo

    def sdf(self, z: torch.Tensor,  # [N, 3] field space
            far: bool = True) -> torch.Tensor:  # [N]
        return self._geo_raw(z, far)[1][:, 0]

    def kernel(self, z: torch.Tensor,  # [N, 3] field space
               far: bool = True) -> torch.Tensor:  # s [N]
        """s(z); ``far`` False: the network's own kernel, also where the far solid's sharp
        constant one applies (the smoothness prior is on the learned kernel field only)."""
        return self.kernel_from_logit(self._geo_raw(z, far)[1][:, 1])

    def sdf_gradient_fd(self, x: torch.Tensor,  # [N, 3] field space
                        eps: float, far: bool = True) -> torch.Tensor:  # [N, 3]
        """grad_z f by central differences (f(x + eps e_i) - f(x - eps e_i)) / (2 eps), one
        batched call; ``far`` False: of the network alone."""
        f = self.sdf(_fd_points(x, eps), far).view(-1, 6)
        return (f[:, :3] - f[:, 3:]) / (2.0 * eps)

    def regulariser_probe(self, z: torch.Tensor,  # [N, 3] field space
                          eps: float,
                          z_extra: torch.Tensor,  # [M, 3] field space
                          ) -> dict[str, torch.Tensor]:
        """The network alone (no far solid) at z, at z +- eps e_i and at z_extra, in one
        batched evaluation: one hash-grid lookup, hence one gradient scatter into the table
        where three separate calls would make three, each into a zeroed table-sized buffer,
        then summed (BENCHMARKS.md). Returns ``grad`` [N, 3] (= `sdf_gradient_fd` (z, eps, far=
        False)), ``normal`` [N, 3] and ``s`` [N] (= `geometry_field` (z, far=False)) and
        ``s_extra`` [M] (= `kernel` (z_extra, far=False))."""
        N = z.shape[0]
        raw = self._geo_raw(torch.cat([_fd_points(z, eps), z, z_extra]), far=False)[1]
        f = raw[:6 * N, 0].view(N, 6)
        centre, G = raw[6 * N:7 * N], self.cfg.geo_feature_dim
        return dict(grad=(f[:, :3] - f[:, 3:]) / (2.0 * eps),
                    normal=F.normalize(centre[:, 2 + G:], dim=1, eps=NORMAL_EPS),
                    s=self.kernel_from_logit(centre[:, 1]),
                    s_extra=self.kernel_from_logit(raw[7 * N:, 1]))


def _fd_points(x: torch.Tensor, eps: float) -> torch.Tensor:  # [N, 3] -> [6 N, 3]
    """x + eps e_0, x + eps e_1, x + eps e_2, x - eps e_0, ... for each point in turn: the
    central-difference neighbours of `ShellField.sdf_gradient_fd`."""
    offs = torch.eye(3, dtype=x.dtype, device=x.device) * eps  # [3, 3]
    return torch.cat([x[:, None, :] + offs, x[:, None, :] - offs], dim=1).reshape(-1, 3)
