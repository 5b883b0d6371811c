"""The baked asset and its files.

A baked asset is K layer meshes inside the band, drawn innermost first, and one texture atlas
that all layers share (xatlas charts, 8 bits a channel):

    base   RGBA: base colour and opacity (the glTF material's ``baseColorTexture``, so any glTF
           viewer shows the base colour)
    sh     three RGB images, one per axis x, y, z of the degree-1 spherical harmonics: the
           colour along unit direction d is clamp(base + sh_x d_x + sh_y d_y + sh_z d_z, 0, 1),
           each SH value stored as (byte - 128) / 127 * sh_scale

Files (`write_asset` / `read_asset`): RUN/baked/layers.glb, glTF 2.0 binary: one mesh per layer
(POSITION float32, TEXCOORD_0 float32 with (0, 0) the top-left corner of the atlas images,
extras: layer, level, closed), the four images as PNG inside the GLB, bilinear samplers that
clamp to the edge and make no mipmaps; the surface layer's material is opaque and the side
layers' blended (for other viewers), the SH images and their scale in the materials' extras;
and RUN/baked/asset.json (layer order, levels, SH scale, background, up axis, the fit's record).
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field as dc_field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from shells.errors import InputError
from shells.files import atomic_write, read_json, write_json

FORMAT = "shells-baked-2"
SH_AXES = "xyz"
LINEAR, CLAMP = 9729, 33071  # glTF sampler enums (GL_LINEAR, GL_CLAMP_TO_EDGE)


@dataclass
class Layer:
    """One layer mesh (the atlas holds its appearance)."""

    level: float  # u = f / s of the level set it was cut from (0: the surface)
    V: np.ndarray  # [n, 3] float32 vertex positions, world
    F: np.ndarray  # [m, 3] uint32 triangles
    uv: np.ndarray  # [n, 2] float32 atlas coordinates, (0, 0) the images' top-left corner
    closed: bool = False  # a closed, consistently wound surface (a viewer may cull back faces)


@dataclass
class Textures:
    """Float atlas textures: rgba [H, W, 4] in [0, 1]; sh [H, W, 3, 3] ([channel, axis])."""

    rgba: torch.Tensor
    sh: torch.Tensor

    def stacked(self) -> torch.Tensor:
        """[H, W, 13]: RGBA, then SH red x/y/z, green x/y/z, blue x/y/z."""
        H, W = self.rgba.shape[:2]
        return torch.cat([self.rgba, self.sh.reshape(H, W, 9)], 2)


@dataclass
class Atlas:
    """The quantised textures: base [H, W, 4] uint8; sh [3 axes, H, W, 3 channels] uint8."""

    base: np.ndarray
    sh: np.ndarray
    sh_scale: float

    @property
    def size(self) -> tuple[int, int]:  # width, height
        return int(self.base.shape[1]), int(self.base.shape[0])

    def textures(self) -> Textures:
        sh = (self.sh.astype(np.float32) - 128.0) / 127.0 * self.sh_scale  # [3, H, W, 3]
        return Textures(rgba=torch.from_numpy(self.base.astype(np.float32) / 255.0),
                        sh=torch.from_numpy(np.ascontiguousarray(sh.transpose(1, 2, 3, 0))))


@dataclass
class BakedAsset:
    layers: list[Layer]  # drawing order: innermost first
    atlas: Atlas
    background: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)  # the capture's up axis (world)
    meta: dict[str, Any] = dc_field(default_factory=dict)  # the fit's record


def quantise(tex: Textures) -> Atlas:
    """8-bit textures of float ones; the SH scale is the largest |coefficient|."""
    rgba = tex.rgba.detach().float().clamp(0, 1).cpu().numpy()
    sh = tex.sh.detach().float().cpu().numpy()  # [H, W, channel, axis]
    scale = float(np.abs(sh).max()) if sh.size else 0.0
    scale = scale if scale > 0 else 1.0
    q = np.clip(np.round(sh / scale * 127.0) + 128.0, 1, 255).astype(np.uint8)
    return Atlas(base=np.round(rgba * 255.0).astype(np.uint8),
                 sh=np.ascontiguousarray(q.transpose(3, 0, 1, 2)), sh_scale=scale)


def png(image: np.ndarray) -> bytes:
    import imageio.v3 as iio

    return iio.imwrite("<bytes>", image, extension=".png")


def write_asset(asset: BakedAsset, folder: Path) -> None:
    """layers.glb and asset.json into ``folder`` (atomic writes)."""
    import pygltflib as g

    folder.mkdir(parents=True, exist_ok=True)
    blob = bytearray()
    views, accessors, meshes, nodes = [], [], [], []

    def view(raw: bytes, target: int | None) -> int:
        while len(blob) % 4:
            blob.append(0)
        views.append(g.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(raw),
                                  target=target))
        blob.extend(raw)
        return len(views) - 1

    def add(arr: np.ndarray, ctype: int, kind: str, target: int | None,
            bounds: bool = False) -> int:
        flat = arr.reshape(len(arr), -1)
        accessors.append(g.Accessor(
            bufferView=view(np.ascontiguousarray(arr).tobytes(), target), componentType=ctype,
            count=len(arr), type=kind, min=flat.min(0).tolist() if bounds else None,
            max=flat.max(0).tolist() if bounds else None))
        return len(accessors) - 1

    atlas = asset.atlas
    images = [atlas.base] + [atlas.sh[k] for k in range(3)]
    gl_images = [g.Image(bufferView=view(png(im), None), mimeType="image/png", name=name)
                 for im, name in zip(images, ["base colour and opacity"]
                                     + [f"SH {a}" for a in SH_AXES])]
    textures = [g.Texture(source=k, sampler=0) for k in range(len(images))]
    for k, layer in enumerate(asset.layers):
        if len(layer.F) == 0:
            continue
        pos = add(layer.V.astype(np.float32), g.FLOAT, g.VEC3, g.ARRAY_BUFFER, bounds=True)
        uv = add(layer.uv.astype(np.float32), g.FLOAT, g.VEC2, g.ARRAY_BUFFER)
        ind = add(layer.F.reshape(-1).astype(np.uint32), g.UNSIGNED_INT, g.SCALAR,
                  g.ELEMENT_ARRAY_BUFFER)
        meshes.append(g.Mesh(name=f"layer{k}", primitives=[g.Primitive(
            attributes=g.Attributes(POSITION=pos, TEXCOORD_0=uv), indices=ind,
            material=0 if layer.level == 0 else 1)],
            extras={"layer": k, "level": layer.level, "closed": bool(layer.closed)}))
        nodes.append(g.Node(name=f"layer{k}", mesh=len(meshes) - 1))
    sh_extras = {"sh_textures": [1, 2, 3], "sh_scale": atlas.sh_scale,
                 "sh_rule": "colour = clamp(base + sum_k ((texel_k * 255 - 128) / 127 * "
                            "sh_scale) * d_k, 0, 1), d the unit view direction, k = x, y, z"}
    # glTF is y-up: one root node turns the capture's up axis onto +y
    root = g.Node(name="asset", children=list(range(len(nodes))),
                  matrix=up_matrix(asset.up).T.reshape(-1).tolist())
    gltf = g.GLTF2(
        asset=g.Asset(version="2.0", generator="shells-bake"),
        scene=0, scenes=[g.Scene(nodes=[len(nodes)])], nodes=nodes + [root], meshes=meshes,
        # for other glTF viewers: the base colour, the surface layer opaque and the others
        # blended by their opacity; the shells viewer adds the SH terms and its own passes
        materials=[g.Material(name=name, doubleSided=True, alphaMode=mode,
                              pbrMetallicRoughness=g.PbrMetallicRoughness(
                                  baseColorTexture=g.TextureInfo(index=0), metallicFactor=0.0,
                                  roughnessFactor=1.0),
                              extensions={"KHR_materials_unlit": {}}, extras=sh_extras)
                   for name, mode in (("surface layer", "OPAQUE"),
                                      ("side layers, blended by opacity", "BLEND"))],
        extensionsUsed=["KHR_materials_unlit"], images=gl_images, textures=textures,
        samplers=[g.Sampler(magFilter=LINEAR, minFilter=LINEAR, wrapS=CLAMP, wrapT=CLAMP)],
        accessors=accessors, bufferViews=views, buffers=[g.Buffer(byteLength=len(blob))])
    gltf.set_binary_blob(bytes(blob))
    atomic_write(folder / "layers.glb", lambda p: gltf.save_binary(str(p)))
    width, height = atlas.size
    write_json(folder / "asset.json", {
        "format": FORMAT, "glb": "layers.glb", "background": list(asset.background),
        "up": list(asset.up), "size_bytes": (folder / "layers.glb").stat().st_size,
        "atlas": {"width": width, "height": height, "sh_scale": atlas.sh_scale},
        "layers": [{"layer": k, "level": x.level, "vertices": int(len(x.V)),
                    "triangles": int(len(x.F)), "closed": bool(x.closed)}
                   for k, x in enumerate(asset.layers)],
        **asset.meta})


def read_asset(folder: Path) -> BakedAsset:
    """The asset of ``folder`` (RUN/baked), as the viewer reads it."""
    import imageio.v3 as iio
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

    def raw(view: int) -> bytes:
        v = gltf.bufferViews[view]
        return blob[v.byteOffset:v.byteOffset + v.byteLength]

    def read(i: int, dtype: Any, width: int) -> np.ndarray:
        acc = gltf.accessors[i]
        view = gltf.bufferViews[acc.bufferView]
        start = view.byteOffset + (acc.byteOffset or 0)
        return np.frombuffer(blob, dtype, acc.count * width, start).reshape(
            acc.count, width).copy()

    images = [iio.imread(io.BytesIO(raw(im.bufferView)), extension=".png")
              for im in gltf.images]
    atlas = Atlas(base=images[0], sh=np.stack(images[1:4]), sh_scale=float(
        meta["atlas"]["sh_scale"]))
    by_layer = {m.extras["layer"]: m for m in gltf.meshes}
    layers = []
    for info in meta["layers"]:
        m = by_layer.get(info["layer"])
        if m is None:
            layers.append(Layer(info["level"], np.zeros((0, 3), np.float32),
                                np.zeros((0, 3), np.uint32), np.zeros((0, 2), np.float32)))
            continue
        p = m.primitives[0]
        layers.append(Layer(level=info["level"], V=read(p.attributes.POSITION, np.float32, 3),
                            F=read(p.indices, np.uint32, 1).reshape(-1, 3),
                            uv=read(p.attributes.TEXCOORD_0, np.float32, 2),
                            closed=bool(m.extras.get("closed", False))))
    rest = {k: v for k, v in meta.items() if k not in ("format", "glb", "background", "up",
                                                       "layers", "size_bytes", "atlas")}
    return BakedAsset(layers=layers, atlas=atlas, background=tuple(meta["background"]),
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
