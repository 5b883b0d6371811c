"""Baked shells: the band's appearance on a few nested, semi-transparent layer meshes.

A baked asset is K triangle meshes inside the band (`shells.train.bake` builds and fits them), drawn
in a fixed order, innermost first. Every vertex carries a base colour and an opacity (RGBA,
8 bits each) and three degree-1 spherical-harmonic axes per colour channel (8-bit signed, one
scale per layer). Along a ray through pixel p the renderer does what a rasteriser with a depth
buffer does when it draws each layer twice (a depth pass, then a colour pass that keeps only
the fragments at the stored depth, blended "over"):

    C = background, depth = inf
    for each layer k (innermost first):
        t_k = the layer's nearest hit (any facing), attributes interpolated barycentrically
        if t_k <= depth:  c = clamp(base + sum_j sh[:, j] d_j, 0, 1);  C = a c + (1 - a) C
        depth = min(depth, t_k)

with d the unit ray direction in the asset's (world) frame. This module is that renderer on
the CPU on Mitsuba's ray casts (`LayerScene`): in torch (`shade`, `render_baked`: the
reference, and, on float attributes with autograd, what `shells.train.bake` fits to the photos)
and as Dr.Jit kernels (`render_baked_drjit`, what `shells-render --mode baked` runs; a test
holds the two equal). The browser viewer (shells/webviewer/viewer.js) draws the same GLB with
three.js.

Files (`write_asset` / `read_asset`): RUN/baked/layers.glb (glTF 2.0 binary: one mesh per
layer, POSITION float32, COLOR_0 RGBA unsigned bytes, the SH axes as the application-specific
attributes _SHR, _SHG, _SHB: normalised signed bytes, VEC4 with w = 0) and RUN/baked/asset.json
(layer order, levels, SH scales, background, up axis, the fit's record).
"""

from __future__ import annotations

from dataclasses import dataclass, field as dc_field
from pathlib import Path
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np
import torch

from shells.device import mitsuba_variant
from shells.errors import InputError
from shells.files import atomic_write, read_json, write_json
from shells.render.raycast import make_mesh, to_point3f

FORMAT = "shells-baked-1"
SH_CHANNELS = ("_SHR", "_SHG", "_SHB")  # glTF attribute names of the red, green, blue SH axes


@dataclass
class Layer:
    """One layer mesh with its quantised appearance (what the GLB stores)."""

    level: float  # u = f / s of the level set it was cut from (0: the surface)
    V: np.ndarray  # [n, 3] float32 vertex positions, world
    F: np.ndarray  # [m, 3] uint32 triangles
    rgba: np.ndarray  # [n, 4] uint8: base colour, opacity
    sh: np.ndarray  # [n, 3, 3] int8: [vertex, channel, axis x/y/z], value = sh / 127 * sh_scale
    sh_scale: float

    def attributes(self) -> "LayerAttributes":
        return LayerAttributes(
            rgba=torch.from_numpy(self.rgba.astype(np.float32) / 255.0),
            sh=torch.from_numpy(self.sh.astype(np.float32) * (self.sh_scale / 127.0)))


@dataclass
class LayerAttributes:
    """Float per-vertex attributes of one layer: rgba [n, 4] in [0, 1], sh [n, 3, 3]."""

    rgba: torch.Tensor
    sh: torch.Tensor


@dataclass
class BakedAsset:
    layers: list[Layer]  # drawing order: innermost first
    background: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)  # the capture's up axis (world)
    meta: dict[str, Any] = dc_field(default_factory=dict)  # the fit's record


def quantise(level: float, V: np.ndarray, F: np.ndarray, rgba: torch.Tensor,
             sh: torch.Tensor) -> Layer:
    """A `Layer` of float attributes (rgba [n, 4] in [0, 1], sh [n, 3, 3]); the SH scale is the
    layer's largest |coefficient|."""
    rgba = rgba.detach().float().clamp(0, 1).cpu().numpy()
    sh = sh.detach().float().cpu().numpy()
    scale = float(np.abs(sh).max()) if sh.size else 0.0
    scale = scale if scale > 0 else 1.0
    return Layer(level=float(level), V=np.ascontiguousarray(V, np.float32),
                 F=np.ascontiguousarray(F, np.uint32),
                 rgba=np.round(rgba * 255.0).astype(np.uint8),
                 sh=np.clip(np.round(sh / scale * 127.0), -127, 127).astype(np.int8),
                 sh_scale=scale)


# ---------------------------------------------------------------------------------------------
# ray casts and the compositing rule


@dataclass
class LayerHits:
    """Nearest hit of each ray on one layer (torch, CPU): prim [R] int64 (-1: none), uv [R, 2]
    barycentrics of vertices 1 and 2, t [R] (inf: none)."""

    prim: torch.Tensor
    uv: torch.Tensor
    t: torch.Tensor

    def take(self, idx: torch.Tensor) -> "LayerHits":
        return LayerHits(self.prim[idx], self.uv[idx], self.t[idx])


class LayerScene:
    """One Mitsuba scene per layer, for nearest-hit casts."""

    def __init__(self, meshes: list[tuple[np.ndarray, np.ndarray]], variant: str | None = None):
        self.variant = mitsuba_variant(variant)
        self.faces = [torch.from_numpy(np.asarray(F, np.int64)) for _, F in meshes]
        self.scenes = [mi.load_dict({"type": "scene", "layer": make_mesh(f"layer{k}", V, F)})
                       if len(F) else None for k, (V, F) in enumerate(meshes)]

    @classmethod
    def of(cls, asset: BakedAsset, variant: str | None = None) -> "LayerScene":
        scene = cls([(x.V, x.F) for x in asset.layers], variant)
        scene.asset = asset
        scene.attributes = [x.attributes() for x in asset.layers]
        return scene

    def flat(self) -> list[tuple[Any, Any]]:
        """Per layer, for `render_baked_drjit`: its triangles as a flat mi.UInt32 and its
        attributes as a flat mi.Float of 13 a vertex (RGBA, then SH red, green, blue x/y/z)."""
        if getattr(self, "_flat", None) is None:
            self._flat = [(mi.UInt32(F.reshape(-1).numpy().astype(np.uint32)), mi.Float(
                torch.cat([a.rgba, a.sh.reshape(len(a.sh), 9)], 1).reshape(-1).numpy()))
                for F, a in zip(self.faces, self.attributes)]
        return self._flat

    def cast(self, origins: Any, dirs: Any) -> list[LayerHits]:
        """Each layer's nearest hit of the rays ([R, 3] torch / numpy)."""
        o = to_point3f(origins, mi.Point3f)
        d = to_point3f(dirs, mi.Vector3f)
        n = dr.width(d)
        out = []
        for sc in self.scenes:
            if sc is None:
                out.append(LayerHits(torch.full((n,), -1, dtype=torch.int64),
                                     torch.zeros(n, 2), torch.full((n,), float("inf"))))
                continue
            pi = sc.ray_intersect_preliminary(mi.Ray3f(o, d), coherent=True)
            valid = pi.is_valid()
            prim = dr.select(valid, mi.Int(pi.prim_index), -1)
            t = dr.select(valid, pi.t, dr.inf)
            u, v = pi.prim_uv.x, pi.prim_uv.y
            dr.eval(prim, t, u, v)
            out.append(LayerHits(prim.torch().to(torch.int64), torch.stack(
                [u.torch(), v.torch()], 1).clone(), t.torch().clone()))
        return out


def shade(faces: list[torch.Tensor],  # per layer [m, 3] int64
          attrs: list[LayerAttributes],  # per layer, float (differentiable for fitting)
          hits: list[LayerHits],  # per layer, of the same R rays
          d: torch.Tensor,  # [R, 3] unit directions
          background: torch.Tensor,  # [3] or [R, 3]
          ) -> tuple[torch.Tensor, torch.Tensor]:  # colour [R, 3], layers drawn [R] int32
    """The compositing rule of the module docstring (differentiable in ``attrs``)."""
    R = d.shape[0]
    colour = background.to(d.dtype).expand(R, 3)
    depth = torch.full((R,), float("inf"))
    drawn = torch.zeros(R, dtype=torch.int32)
    for F, a, h in zip(faces, attrs, hits):
        hit = h.prim >= 0
        idx = torch.nonzero(hit & (h.t <= depth)).squeeze(1)
        if len(idx):
            tri = F[h.prim[idx]]  # [k, 3]
            uv = h.uv[idx]
            w = torch.cat([1.0 - uv.sum(1, keepdim=True), uv], 1)  # [k, 3]
            rgba = torch.einsum("kv,kvc->kc", w, a.rgba[tri])
            sh = torch.einsum("kv,kvcj->kcj", w, a.sh[tri])
            c = (rgba[:, :3] + torch.einsum("kcj,kj->kc", sh, d[idx])).clamp(0.0, 1.0)
            alpha = rgba[:, 3:4]
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
        return shade(scene.faces, scene.attributes, hits, d,
                     torch.tensor(background, dtype=torch.float32))


def render_baked_drjit(scene: LayerScene, origins: Any, dirs: Any,
                       background: tuple[float, float, float]) -> tuple[Any, Any]:
    """`render_baked` as Dr.Jit kernels, the cast, the attribute gathers and the blending of a
    layer traced together (no torch round trip): mi.Color3f and layers drawn (mi.UInt32)."""
    o = to_point3f(origins, mi.Point3f)
    d = dr.normalize(to_point3f(dirs, mi.Vector3f))
    ray = mi.Ray3f(o, d)
    colour = mi.Color3f(*background)
    depth = dr.full(mi.Float, dr.inf, dr.width(d))
    drawn = dr.zeros(mi.UInt32, dr.width(d))
    for sc, flat in zip(scene.scenes, scene.flat()):
        if sc is None:
            continue
        F, A = flat  # F: 3 indices a triangle; A: 13 floats a vertex (RGBA, SH r, g, b x/y/z)
        pi = sc.ray_intersect_preliminary(ray, coherent=True)
        hit = pi.is_valid()
        draw = hit & (pi.t <= depth)
        prim = mi.UInt32(pi.prim_index)
        w = (1.0 - pi.prim_uv.x - pi.prim_uv.y, pi.prim_uv.x, pi.prim_uv.y)
        vi = [dr.gather(mi.UInt32, F, prim * 3 + j, draw) * 13 for j in range(3)]

        def attr(c: int) -> Any:
            return sum(w[j] * dr.gather(mi.Float, A, vi[j] + c, draw) for j in range(3))

        a = attr(3)
        rgb = [dr.clip(attr(c) + attr(4 + 3 * c) * d.x + attr(5 + 3 * c) * d.y
                       + attr(6 + 3 * c) * d.z, 0.0, 1.0) for c in range(3)]
        colour = dr.select(draw, a * mi.Color3f(*rgb) + (1.0 - a) * colour, colour)
        drawn += dr.select(draw, 1, 0)
        depth = dr.select(hit, dr.minimum(depth, pi.t), depth)
    dr.eval(colour, drawn)
    return colour, drawn


# ---------------------------------------------------------------------------------------------
# files


def write_asset(asset: BakedAsset, folder: Path) -> None:
    """layers.glb and asset.json into ``folder`` (atomic writes)."""
    import pygltflib as g

    folder.mkdir(parents=True, exist_ok=True)
    blob = bytearray()
    views, accessors, meshes, nodes = [], [], [], []

    def add(arr: np.ndarray, ctype: int, kind: str, target: int | None,
            normalized: bool = False, bounds: bool = False) -> int:
        while len(blob) % 4:
            blob.append(0)
        raw = np.ascontiguousarray(arr).tobytes()
        views.append(g.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(raw),
                                  target=target))
        blob.extend(raw)
        flat = arr.reshape(len(arr), -1)
        accessors.append(g.Accessor(
            bufferView=len(views) - 1, componentType=ctype, count=len(arr), type=kind,
            normalized=normalized or None,
            min=flat.min(0).tolist() if bounds else None,
            max=flat.max(0).tolist() if bounds else None))
        return len(accessors) - 1

    for k, layer in enumerate(asset.layers):
        if len(layer.F) == 0:
            continue
        pos = add(layer.V.astype(np.float32), g.FLOAT, g.VEC3, g.ARRAY_BUFFER, bounds=True)
        col = add(layer.rgba, g.UNSIGNED_BYTE, g.VEC4, g.ARRAY_BUFFER, normalized=True)
        sh4 = np.zeros((len(layer.V), 3, 4), np.int8)
        sh4[:, :, :3] = layer.sh
        shs = [add(np.ascontiguousarray(sh4[:, c]), g.BYTE, g.VEC4, g.ARRAY_BUFFER,
                   normalized=True) for c in range(3)]
        ind = add(layer.F.reshape(-1).astype(np.uint32), g.UNSIGNED_INT, g.SCALAR,
                  g.ELEMENT_ARRAY_BUFFER)
        attributes = g.Attributes(POSITION=pos, COLOR_0=col)
        for name, acc in zip(SH_CHANNELS, shs):
            setattr(attributes, name, acc)
        meshes.append(g.Mesh(name=f"layer{k}", primitives=[g.Primitive(
            attributes=attributes, indices=ind, material=0 if layer.level == 0 else 1)],
            extras={"layer": k, "level": layer.level, "sh_scale": layer.sh_scale}))
        nodes.append(g.Node(name=f"layer{k}", mesh=len(meshes) - 1))
    # glTF is y-up: one root node turns the capture's up axis onto +y
    root = g.Node(name="asset", children=list(range(len(nodes))),
                  matrix=up_matrix(asset.up).T.reshape(-1).tolist())
    gltf = g.GLTF2(
        asset=g.Asset(version="2.0", generator="shells-bake"),
        scene=0, scenes=[g.Scene(nodes=[len(nodes)])], nodes=nodes + [root], meshes=meshes,
        # for other glTF viewers: the surface layer opaque, the others blended by their
        # opacity (COLOR_0's alpha); the shells viewer draws all with its own shader
        materials=[g.Material(name=name, doubleSided=True, alphaMode=mode,
                              pbrMetallicRoughness=g.PbrMetallicRoughness(
                                  baseColorFactor=[1, 1, 1, 1], metallicFactor=0.0,
                                  roughnessFactor=1.0),
                              extensions={"KHR_materials_unlit": {}})
                   for name, mode in (("surface layer: vertex colours", "OPAQUE"),
                                      ("side layers: vertex colours and opacity", "BLEND"))],
        extensionsUsed=["KHR_materials_unlit"],
        accessors=accessors, bufferViews=views, buffers=[g.Buffer(byteLength=len(blob))])
    gltf.set_binary_blob(bytes(blob))
    atomic_write(folder / "layers.glb", lambda p: gltf.save_binary(str(p)))
    write_json(folder / "asset.json", {
        "format": FORMAT, "glb": "layers.glb", "background": list(asset.background),
        "up": list(asset.up), "size_bytes": (folder / "layers.glb").stat().st_size,
        "layers": [{"layer": k, "level": x.level, "sh_scale": x.sh_scale,
                    "vertices": int(len(x.V)), "triangles": int(len(x.F))}
                   for k, x in enumerate(asset.layers)],
        **asset.meta})


def read_asset(folder: Path) -> BakedAsset:
    """The asset of ``folder`` (RUN/baked), as the viewer reads it."""
    import pygltflib as g

    folder = Path(folder)
    meta = read_json(folder / "asset.json", "baked asset")
    if meta.get("format") != FORMAT:
        raise InputError(f"{folder / 'asset.json'}: not a baked asset of this version "
                         f"(format {meta.get('format')!r}); run shells-bake again")
    path = folder / meta["glb"]
    try:
        gltf = g.GLTF2().load_binary(str(path))
        blob = gltf.binary_blob()
    except Exception as exc:  # pygltflib raises assorted types on a broken file
        raise InputError(f"{path}: not a readable GLB ({exc}); run shells-bake again")

    def read(i: int, dtype: Any, width: int) -> np.ndarray:
        acc = gltf.accessors[i]
        view = gltf.bufferViews[acc.bufferView]
        start = view.byteOffset + (acc.byteOffset or 0)
        n = acc.count * width
        return np.frombuffer(blob, dtype, n, start).reshape(acc.count, width).copy()

    by_layer = {m.extras["layer"]: m for m in gltf.meshes}
    layers = []
    for info in meta["layers"]:
        m = by_layer.get(info["layer"])
        if m is None:
            layers.append(Layer(info["level"], np.zeros((0, 3), np.float32),
                                np.zeros((0, 3), np.uint32), np.zeros((0, 4), np.uint8),
                                np.zeros((0, 3, 3), np.int8), info["sh_scale"]))
            continue
        p = m.primitives[0]
        a = p.attributes
        sh = np.stack([read(getattr(a, c), np.int8, 4)[:, :3] for c in SH_CHANNELS], 1)
        layers.append(Layer(level=info["level"], V=read(a.POSITION, np.float32, 3),
                            F=read(p.indices, np.uint32, 1).reshape(-1, 3),
                            rgba=read(a.COLOR_0, np.uint8, 4), sh=sh,
                            sh_scale=float(m.extras["sh_scale"])))
    rest = {k: v for k, v in meta.items() if k not in ("format", "glb", "background", "up",
                                                       "layers", "size_bytes")}
    return BakedAsset(layers=layers, background=tuple(meta["background"]),
                      up=tuple(meta["up"]), meta=rest)


def up_matrix(up: tuple[float, float, float]) -> np.ndarray:  # [4, 4]
    """The GLB root node's matrix: a rotation taking the unit vector ``up`` onto +y (glTF is
    y-up), by Rodrigues' formula."""
    u = np.asarray(up, np.float64)
    u = u / np.linalg.norm(u)
    y = np.array([0.0, 1.0, 0.0])
    v, c = np.cross(u, y), float(u @ y)
    M = np.eye(4)
    if c < -1 + 1e-9:  # upside down: half a turn about x
        M[:3, :3] = np.diag([1.0, -1.0, -1.0])
        return M
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    M[:3, :3] = np.eye(3) + vx + vx @ vx / (1.0 + c)
    return M
