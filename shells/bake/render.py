"""The compositing rule of a baked asset on Mitsuba's ray casts.

Along a ray through pixel p the renderer does what a rasteriser with a depth buffer does when
it draws each layer twice (a depth pass, then a colour pass that keeps only the fragments at
the stored depth, blended "over"):

    C = background, depth = inf
    for each layer k (innermost first):
        t_k = the layer's nearest hit (any facing); its atlas coordinate interpolated
              barycentrically, the textures sampled bilinearly there (clamped to the edge)
        if t_k <= depth:  c = clamp(base + sh_x d_x + sh_y d_y + sh_z d_z, 0, 1)
                          C = a c + (1 - a) C
        depth = min(depth, t_k)

with d the unit ray direction in the asset's (world) frame. `shade` is that rule in torch (the
reference, and, on float textures with autograd, what `shells.bake.fit` fits to the photos);
`render_baked_drjit` is the same as Dr.Jit kernels (what ``shells-render --mode baked`` runs; a
test holds the two equal). The browser viewer (shells/webviewer/viewer.js) draws the same GLB
with three.js.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np
import torch

from shells.bake.format import BakedAsset, Textures
from shells.device import mitsuba_variant
from shells.render.raycast import make_mesh, to_point3f


@dataclass
class LayerHits:
    """Nearest hit of each ray on one layer (torch, CPU): t [R] (inf: none) and the hit's atlas
    coordinate tc [R, 2] (0 where none)."""

    t: torch.Tensor
    tc: torch.Tensor

    def take(self, idx: torch.Tensor) -> "LayerHits":
        return LayerHits(self.t[idx], self.tc[idx])


def sample(tex: torch.Tensor,  # [C, H, W]
           tc: torch.Tensor,  # [k, 2] atlas coordinates, (0, 0) the top-left corner
           ) -> torch.Tensor:  # [k, C]
    """Bilinear texture look-ups as a GPU samples a texture with LINEAR filtering and
    CLAMP_TO_EDGE: texel (i, j)'s centre at ((i + 0.5) / W, (j + 0.5) / H); differentiable."""
    grid = (2.0 * tc - 1.0).reshape(1, 1, -1, 2).to(tex.dtype)
    out = torch.nn.functional.grid_sample(tex[None], grid, mode="bilinear",
                                          padding_mode="border", align_corners=False)
    return out[0, :, 0].T


class LayerScene:
    """One Mitsuba scene per layer, for nearest-hit casts, with the layers' atlas coordinates."""

    def __init__(self, meshes: list[tuple[np.ndarray, np.ndarray, np.ndarray]],  # V, F, uv
                 variant: str | None = None):
        self.variant = mitsuba_variant(variant)
        self.faces = [torch.from_numpy(np.asarray(F, np.int64)) for _, F, _ in meshes]
        self.uv = [torch.from_numpy(np.asarray(uv, np.float32)) for _, _, uv in meshes]
        self.scenes = [mi.load_dict({"type": "scene", "layer": make_mesh(f"layer{k}", V, F)})
                       if len(F) else None for k, (V, F, _) in enumerate(meshes)]
        self.asset: BakedAsset | None = None
        self.textures: Textures | None = None
        self._drjit: Any = None

    @classmethod
    def of(cls, asset: BakedAsset, variant: str | None = None) -> "LayerScene":
        scene = cls([(x.V, x.F, x.uv) for x in asset.layers], variant)
        scene.asset = asset
        scene.textures = asset.atlas.textures()
        return scene

    def render(self, origins: Any, dirs: Any, background: tuple[float, float, float]
               ) -> tuple[Any, Any]:
        """`render_baked_drjit` of this scene's asset (``shells-render --mode baked``)."""
        return render_baked_drjit(self, origins, dirs, background)

    def cast(self, origins: Any, dirs: Any) -> list[LayerHits]:
        """Each layer's nearest hit of the rays ([R, 3] torch / numpy)."""
        o = to_point3f(origins, mi.Point3f)
        d = to_point3f(dirs, mi.Vector3f)
        n = dr.width(d)
        out = []
        for sc, F, uv in zip(self.scenes, self.faces, self.uv):
            if sc is None:
                out.append(LayerHits(torch.full((n,), float("inf")), torch.zeros(n, 2)))
                continue
            pi = sc.ray_intersect_preliminary(mi.Ray3f(o, d), coherent=True)
            valid = pi.is_valid()
            prim = dr.select(valid, mi.Int(pi.prim_index), -1)
            t = dr.select(valid, pi.t, dr.inf)
            dr.eval(prim, t, pi.prim_uv)
            prim = prim.torch().to(torch.int64)
            b = torch.stack([pi.prim_uv.x.torch(), pi.prim_uv.y.torch()], 1)
            hit = prim >= 0
            tri = F[prim.clamp(min=0)]  # [R, 3]
            w = torch.cat([1.0 - b.sum(1, keepdim=True), b], 1)
            tc = torch.einsum("rv,rvc->rc", w, uv[tri]) * hit[:, None]
            out.append(LayerHits(t.torch().clone(), tc))
        return out


def shade(tex: torch.Tensor,  # [13, H, W]: `Textures.stacked` channels first (differentiable)
          hits: list[LayerHits],  # per layer, of the same R rays
          d: torch.Tensor,  # [R, 3] unit directions
          background: torch.Tensor,  # [3] or [R, 3]
          ) -> tuple[torch.Tensor, torch.Tensor]:  # colour [R, 3], layers drawn [R] int32
    """The compositing rule of the module docstring."""
    R = d.shape[0]
    colour = background.to(d.dtype).expand(R, 3)
    depth = torch.full((R,), float("inf"))
    drawn = torch.zeros(R, dtype=torch.int32)
    for h in hits:
        hit = torch.isfinite(h.t)
        idx = torch.nonzero(hit & (h.t <= depth)).squeeze(1)
        if len(idx):
            v = sample(tex, h.tc[idx])  # [k, 13]
            sh = v[:, 4:].reshape(-1, 3, 3)  # [k, channel, axis]
            c = (v[:, :3] + torch.einsum("kcj,kj->kc", sh, d[idx])).clamp(0.0, 1.0)
            alpha = v[:, 3:4]
            colour = colour.index_put((idx,), alpha * c + (1.0 - alpha) * colour[idx])
            drawn[idx] += 1
        depth = torch.where(hit, torch.minimum(depth, h.t), depth)
    return colour, drawn


def render_baked(scene: LayerScene, origins: torch.Tensor, dirs: torch.Tensor,
                 background: tuple[float, float, float]) -> tuple[torch.Tensor, torch.Tensor]:
    """Colour [R, 3] and layers drawn [R] of rays through the baked asset of ``scene``: the
    reference in torch (`shade`, the rule the fit differentiates)."""
    hits = scene.cast(origins, dirs)
    d = torch.as_tensor(dirs, dtype=torch.float32)
    with torch.no_grad():
        return shade(scene.textures.stacked().permute(2, 0, 1), hits, d,
                     torch.tensor(background, dtype=torch.float32))


def render_baked_drjit(scene: LayerScene, origins: Any, dirs: Any,
                       background: tuple[float, float, float]) -> tuple[Any, Any]:
    """`render_baked` as Dr.Jit kernels, the cast, the atlas look-up and the blending of a
    layer traced together (no torch round trip): mi.Color3f and layers drawn (mi.UInt32)."""
    if scene._drjit is None:  # the faces, atlas coordinates and one 13-channel texture
        flat = [(mi.UInt32(F.reshape(-1).numpy().astype(np.uint32)),
                 mi.Float(uv.reshape(-1).numpy())) for F, uv in zip(scene.faces, scene.uv)]
        tex = mi.Texture2f(mi.TensorXf(scene.textures.stacked().numpy()), use_accel=False,
                           filter_mode=dr.FilterMode.Linear, wrap_mode=dr.WrapMode.Clamp)
        scene._drjit = (flat, tex)
    flat, tex = scene._drjit
    o = to_point3f(origins, mi.Point3f)
    d = dr.normalize(to_point3f(dirs, mi.Vector3f))
    ray = mi.Ray3f(o, d)
    colour = mi.Color3f(*background)
    depth = dr.full(mi.Float, dr.inf, dr.width(d))
    drawn = dr.zeros(mi.UInt32, dr.width(d))
    for sc, (F, UV) in zip(scene.scenes, flat):
        if sc is None:
            continue
        pi = sc.ray_intersect_preliminary(ray, coherent=True)
        hit = pi.is_valid()
        draw = hit & (pi.t <= depth)
        prim = mi.UInt32(pi.prim_index)
        w = (1.0 - pi.prim_uv.x - pi.prim_uv.y, pi.prim_uv.x, pi.prim_uv.y)
        vi = [dr.gather(mi.UInt32, F, prim * 3 + j, draw) * 2 for j in range(3)]
        tc = mi.Point2f(sum(w[j] * dr.gather(mi.Float, UV, vi[j], draw) for j in range(3)),
                        sum(w[j] * dr.gather(mi.Float, UV, vi[j] + 1, draw) for j in range(3)))
        v = tex.eval(tc, draw)
        a = v[3]
        rgb = [dr.clip(v[c] + v[4 + 3 * c] * d.x + v[5 + 3 * c] * d.y + v[6 + 3 * c] * d.z,
                       0.0, 1.0) for c in range(3)]
        colour = dr.select(draw, a * mi.Color3f(*rgb) + (1.0 - a) * colour, colour)
        drawn += dr.select(draw, 1, 0)
        depth = dr.select(hit, dr.minimum(depth, pi.t), depth)
    dr.eval(colour, drawn)
    return colour, drawn
