"""Data-set loaders: Blender / NeRF-synthetic and Instant-NGP ``transforms.json``.

Both formats store OpenGL camera-to-world matrices; they are converted once, here, to the
OpenCV convention of `shells.data.cameras`. Poses stay in the world units of the file.

Blender (``transforms_{split}.json``): ``camera_angle_x`` gives fx = fy = 0.5 W / tan(0.5 angle),
cx = W / 2, cy = H / 2; frames hold ``file_path`` (".png" may be omitted) and
``transform_matrix``. An optional top-level ``"aabb": [[x0, y0, z0], [x1, y1, z1]]`` gives the
scene box; the default is [-1.5, 1.5]^3 (NeRF-synthetic).

Instant-NGP (``transforms.json``): intrinsics ``fl_x, fl_y, cx, cy, w, h, k1, k2, p1, p2``, any of
them missing (focal from ``camera_angle_x/y``, size from the image, zeros), overridable per
frame. Instant-NGP maps a world point p to p * scale + offset (defaults 0.33 and 0.5; an
``"aabb"`` key sets them as instant-ngp does) and bounds the scene by the cube
[0.5 - aabb_scale / 2, 0.5 + aabb_scale / 2]^3 there; `Dataset.aabb` is that cube in world
units. Splits: ``transforms_{split}.json`` when it exists, otherwise every 8th frame (0, 8, ...)
of the frames whose image exists is "test", the rest "train", and "all" is every frame.
Real captures such as instant-ngp's fox list frames whose photos were left out of the
distribution: Instant-NGP frames with a missing image are skipped with a warning (and listed
in ``meta["skipped_frames"]``); in the Blender format a missing image is an error.

Pixels: 8- and 16-bit PNG (16-bit values scaled by 65535; decoded with Mitsuba's PNG reader,
as Pillow reduces 16-bit colour to 8 bits), JPEG, grey (broadcast to RGB), grey + alpha,
palette (converted to RGB / RGBA). A truncated or corrupt file, an image of another size than
the others or than the file's ``w``/``h``, an empty or duplicated frame, a focal length that is
not positive or a principal point far outside the image, or a transforms file above
`MAX_TRANSFORMS_BYTES` is a one-line InputError naming the file.

Downscaling by an integer factor f averages f x f blocks (area averaging, after compositing);
the image is cropped at the bottom/right to a multiple of f, which keeps the principal point.
"""

from __future__ import annotations

import dataclasses
import math
import os
import threading
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import imageio.v3 as iio
import numpy as np
import torch
import torch.nn.functional as F

from shells.data.cameras import Cameras, opengl_to_opencv, subpixel_offsets
from shells.errors import InputError
from shells.files import read_json

BLENDER_AABB = ((-1.5, -1.5, -1.5), (1.5, 1.5, 1.5))  # NeRF-synthetic convention
NGP_SCALE = 0.33  # instant-ngp's default world -> unit-cube scale
NGP_OFFSET = (0.5, 0.5, 0.5)  # instant-ngp's default offset
HOLDOUT_EVERY = 8  # Instant-NGP data without split files: frames 0, 8, 16, ... are "test"
MAX_TRANSFORMS_BYTES = 64 << 20  # a transforms file above this is refused before it is parsed
# (a frame takes ~0.5 KB: 64 MiB is over 100k frames; a bigger file is not a transforms file)
_MITSUBA = threading.Lock()  # 16-bit PNGs are decoded by Mitsuba, one at a time
PRINCIPAL_POINT_MARGIN = 1.0  # cx, cy may lie this many image sizes outside the image, no more
_IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
_INTRINSIC_KEYS = ("fl_x", "fl_y", "camera_angle_x", "camera_angle_y", "cx", "cy", "w", "h",
                   "k1", "k2", "p1", "p2", "k3", "k4", "is_fisheye")


@dataclass
class Dataset:
    """Posed images of one split, ready for training or evaluation."""

    images: torch.Tensor  # [N, H, W, 3] float32 in [0, 1], RGBA composited on `background`
    alpha: torch.Tensor | None  # [N, H, W] float32 in [0, 1]; None when the files have no alpha
    cameras: Cameras
    aabb: torch.Tensor  # [2, 3] float32 scene box (min corner, max corner), world units
    names: list[str]  # image file paths relative to the data root
    root: Path
    format: str  # "blender" or "ngp"
    split: str
    background: tuple[float, float, float] | None  # None: straight RGB, not composited
    meta: dict = field(default_factory=dict)  # other top-level keys of the transforms file

    def __len__(self) -> int:
        return self.images.shape[0]

    def sample_pixel_rays(self, batch_rays: int, spp: int, gen: torch.Generator,
                          ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """A random batch of training pixels and their rays: ``batch_rays // spp`` pixels (flat
        indices [P] into the images, on the generator's device) with ``spp`` jittered sub-pixel
        rays each (origins, unit directions [P * spp, 3], a pixel's rays contiguous, on the
        generator's device). Training stages use this with the step's generator."""
        n_views, H, W = self.images.shape[:3]
        n = max(1, batch_rays // spp)
        idx = torch.randint(0, n_views * H * W, (n,), generator=gen, device=gen.device)
        cam, rem = idx // (H * W), idx % (H * W)
        # one ray stays at the pixel centre, drawing no random numbers (runs made before spp
        # existed are reproduced bit for bit)
        off = subpixel_offsets(spp, gen if spp > 1 else None, n, device=idx.device)  # [P, spp, 2]
        px = ((rem % W).float()[:, None] + off[..., 0]).reshape(-1)
        py = ((rem // W).float()[:, None] + off[..., 1]).reshape(-1)
        cam = cam[:, None].expand(n, spp).reshape(-1)
        o, d = self.cameras.rays(cam.cpu(), px.cpu(), py.cpu())
        return idx, o.to(idx.device), d.to(idx.device)


@dataclass
class Frames:
    """What the transforms file says about a split, before any pixels are decoded."""

    paths: list[Path]  # absolute image paths, in file order
    cameras: Cameras  # full resolution (image size read from the first image's header)
    has_alpha: bool  # the first image has an alpha channel (RGBA or grey + alpha)
    aabb: torch.Tensor  # [2, 3]
    names: list[str]
    root: Path
    format: str
    split: str
    meta: dict


# --------------------------------------------------------------------------------------------
# Format detection and transforms files
# --------------------------------------------------------------------------------------------

def detect_format(root: str | Path) -> str:
    """"ngp" when ``root/transforms.json`` exists, "blender" for ``transforms_{split}.json``."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"{root}: data directory not found; pass a folder holding "
                         "transforms.json or transforms_train.json")
    if (root / "transforms.json").is_file():
        return "ngp"
    if any(root.glob("transforms_*.json")):
        return "blender"
    raise InputError(f"{root}: no transforms.json or transforms_{{split}}.json found; "
                     "point --data at a Blender/NeRF-synthetic or Instant-NGP data set")


def _available_splits(root: Path) -> list[str]:
    return sorted(p.stem[len("transforms_"):] for p in root.glob("transforms_*.json"))


def _resolve_image(root: Path, file_path: str) -> Path:
    """Path of a frame's image; Blender files omit the extension."""
    p = Path(os.path.normpath(root / file_path))
    if p.is_file():
        return p
    if p.suffix not in _IMAGE_EXTS:
        for ext in _IMAGE_EXTS:
            q = p.with_name(p.name + ext)
            if q.is_file():
                return q
    return p  # missing: the caller decides (error or skip)


def _matrix(value: Any, src: Path, k: int, name: str) -> np.ndarray:  # -> [4, 4] float64
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        m = np.zeros(0)
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4):
        raise InputError(f"{src}: frame {k} ({name}) transform_matrix must be a 4x4 (or 3x4) "
                         f"array of numbers, got shape {m.shape}; fix the file")
    if not np.isfinite(m).all():
        raise InputError(f"{src}: frame {k} ({name}) transform_matrix has non-finite values; "
                         "fix or drop the frame")
    return m


def _focal(d: dict, w: int, h: int, src: Path) -> tuple[float, float]:
    """fx, fy from fl_x/fl_y or camera_angle_x/y; one axis falls back to the other."""
    fx = d.get("fl_x")
    fy = d.get("fl_y")
    for key in ("camera_angle_x", "camera_angle_y"):
        if d.get(key) is not None and not 0 < float(d[key]) < math.pi:
            raise InputError(f"{src}: '{key}' = {d[key]!r}: the field of view must be between 0 "
                             "and pi radians; fix the file")
    if fx is None and d.get("camera_angle_x") is not None:
        fx = 0.5 * w / math.tan(0.5 * float(d["camera_angle_x"]))
    if fy is None and d.get("camera_angle_y") is not None:
        fy = 0.5 * h / math.tan(0.5 * float(d["camera_angle_y"]))
    if fx is None and fy is None:
        raise InputError(f"{src}: no focal length; add 'fl_x' (pixels) or 'camera_angle_x' "
                         "(radians)")
    fx = fy if fx is None else fx
    fy = fx if fy is None else fy
    return float(fx), float(fy)


def _frame_intrinsics(glob: dict, frame: dict) -> dict:
    """Per-frame intrinsics override the global ones; a frame's angle overrides a global fl."""
    d = {k: glob[k] for k in _INTRINSIC_KEYS if k in glob}
    over = {k: frame[k] for k in _INTRINSIC_KEYS if k in frame}
    if "camera_angle_x" in over and "fl_x" not in over:
        d.pop("fl_x", None)
    if "camera_angle_y" in over and "fl_y" not in over:
        d.pop("fl_y", None)
    d.update(over)
    return d


def _bad_image(path: Path, exc: BaseException) -> InputError:
    """The one-line error for an image no decoder reads (truncated, corrupt, not an image)."""
    why = (str(exc).strip().splitlines() or [type(exc).__name__])[0].strip().rstrip(".")
    return InputError(f"{path}: cannot decode image ({why[:120]}); the file is truncated or "
                      "corrupt: replace it with a valid PNG or JPEG")


def _png16(path: Path) -> bool:
    """A PNG with 16 bits per sample (read from its IHDR header)."""
    with open(path, "rb") as fh:
        head = fh.read(26)
    return head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR" and head[24] == 16


def _image_shape(path: Path) -> tuple[int, int, int]:
    """(width, height, channels) from the image header."""
    try:
        shape = iio.improps(path).shape
    except Exception as exc:  # noqa: BLE001 - any decoder failure is a bad file
        raise _bad_image(path, exc)
    if len(shape) < 2 or min(shape[:2]) < 1:
        raise InputError(f"{path}: image of shape {shape}; replace it with a valid image")
    return int(shape[1]), int(shape[0]), int(shape[2]) if len(shape) > 2 else 1


def _ngp_aabb(data: dict, src: Path) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Instant-NGP's scene box in world units (see the module docstring)."""
    try:
        scale = float(data.get("scale", NGP_SCALE))
        offset = np.broadcast_to(np.asarray(data.get("offset", NGP_OFFSET), np.float64), (3,))
        aabb_scale = float(data.get("aabb_scale", 1))
    except (TypeError, ValueError) as exc:
        raise InputError(f"{src}: 'scale', 'offset' or 'aabb_scale' is malformed ({exc}); "
                         "fix the file")
    if "aabb" in data:  # instant-ngp fits this box's largest side into the unit cube
        box = _box(data["aabb"], src)
        length = max(float((box[1] - box[0]).max()), 1e-6)
        scale = 1.0 / length
        offset = 0.5 - 0.5 * (box[0] + box[1]) * scale
    if not (scale > 0 and math.isfinite(scale) and aabb_scale > 0 and np.isfinite(offset).all()):
        raise InputError(f"{src}: 'scale' and 'aabb_scale' must be positive and 'offset' finite; "
                         "fix the file")
    half = 0.5 * aabb_scale
    lo = (0.5 - half - offset) / scale
    hi = (0.5 + half - offset) / scale
    return tuple(lo.tolist()), tuple(hi.tolist())


def _box(value: Any, src: Path) -> np.ndarray:  # -> [2, 3]
    try:
        box = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        box = np.zeros(0)
    if box.shape != (2, 3) or not np.isfinite(box).all() or not (box[0] < box[1]).all():
        raise InputError(f"{src}: 'aabb' must be [[x0, y0, z0], [x1, y1, z1]] with min < max, "
                         f"got {value!r}; fix the file")
    return box


def _parse(src: Path, root: Path, skip_missing: bool) -> tuple[list, dict]:
    """Frames of one transforms file: (image path, c2w_gl [4, 4], intrinsics, src) each."""
    data = read_json(src, "transforms file", MAX_TRANSFORMS_BYTES)
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise InputError(f"{src}: expected a JSON object with a 'frames' list; fix the file")
    if not data["frames"]:
        raise InputError(f"{src}: the 'frames' list is empty; add the posed images (file_path "
                         "and transform_matrix per frame)")
    glob = {k: v for k, v in data.items() if k != "frames"}
    frames, skipped = [], []
    for k, frame in enumerate(data["frames"]):
        if not isinstance(frame, dict) or "file_path" not in frame:
            raise InputError(f"{src}: frame {k} has no 'file_path'; fix the file")
        name = str(frame["file_path"])
        if "transform_matrix" not in frame:
            raise InputError(f"{src}: frame {k} ({name}) has no 'transform_matrix'; add the "
                             "camera-to-world matrix or drop the frame")
        c2w = _matrix(frame["transform_matrix"], src, k, name)
        path = _resolve_image(root, name)
        if not path.is_file():
            if skip_missing:
                skipped.append(name)
                continue
            raise InputError(f"{path}: image file of frame {k} in {src.name} not found; add "
                             "the image or remove the frame")
        frames.append((path, c2w, _frame_intrinsics(glob, frame), src, k))
    if skipped:
        warnings.warn(f"{src}: skipped {len(skipped)} of {len(data['frames'])} frames whose image "
                      f"is missing (first: {skipped[0]})", stacklevel=3)
        glob["skipped_frames"] = skipped
    return frames, glob


def _cameras(frames: list) -> Cameras:
    """Cameras of parsed frames; the image size comes from the first image's header."""
    first = frames[0][0]
    width, height, _ = _image_shape(first)
    fx, fy, cx, cy, dist = [], [], [], [], []
    for path, _, intr, src, _ in frames:
        try:
            if "w" in intr or "h" in intr:  # the image file is the truth; the JSON must agree
                w, h = int(intr.get("w", width)), int(intr.get("h", height))
                if (w, h) != (width, height):
                    raise InputError(f"{src}: 'w', 'h' = {w}x{h} (frame {path.name}) but image "
                                     f"{first.name} is {width}x{height}; fix 'w'/'h' or the "
                                     "images")
            if intr.get("is_fisheye") or float(intr.get("k3", 0)) or float(intr.get("k4", 0)):
                raise InputError(f"{src}: fisheye / k3 / k4 distortion ({path.name}) is not "
                                 "supported; undistort the images first (e.g. with COLMAP)")
            f = _focal(intr, width, height, src)
            k = [float(intr.get(key, 0.0)) for key in ("k1", "k2", "p1", "p2")]
            c = float(intr.get("cx", width / 2)), float(intr.get("cy", height / 2))
        except (TypeError, ValueError) as exc:
            if isinstance(exc, InputError):
                raise
            raise InputError(f"{src}: intrinsics of frame {path.name} are not numbers ({exc}); "
                             "fix the file")
        if not (f[0] > 0 and f[1] > 0 and all(map(math.isfinite, [*f, *k, *c]))):
            raise InputError(f"{src}: focal lengths {f} / intrinsics of frame {path.name} must be "
                             "finite with positive focal lengths; fix the file")
        m = PRINCIPAL_POINT_MARGIN
        if not (-m * width <= c[0] <= (1 + m) * width and -m * height <= c[1] <= (1 + m) * height):
            raise InputError(f"{src}: principal point (cx, cy) = ({c[0]:g}, {c[1]:g}) of frame "
                             f"{path.name} is far outside the {width}x{height} image (pixels, "
                             "origin top-left); fix 'cx'/'cy'")
        fx.append(f[0])
        fy.append(f[1])
        cx.append(c[0])
        cy.append(c[1])
        dist.append(k)
    c2w_gl = torch.as_tensor(np.stack([fr[1] for fr in frames]), dtype=torch.float32)
    t = lambda v: torch.as_tensor(v, dtype=torch.float32)  # noqa: E731
    return Cameras(c2w=opengl_to_opencv(c2w_gl), fx=t(fx), fy=t(fy), cx=t(cx), cy=t(cy),
                   width=width, height=height, dist=t(dist))


def read_frames(root: str | Path, split: str = "train", skip_missing: bool | None = None) -> Frames:
    """Parse the transforms file(s) of ``split`` and check them; decodes no pixels.

    skip_missing: drop frames whose image file is missing (default: True for Instant-NGP data,
    False for Blender data, where a missing image is an InputError).
    """
    root = Path(os.path.normpath(root))  # names are relative to it: no ".." left inside
    fmt = detect_format(root)
    if skip_missing is None:
        skip_missing = fmt == "ngp"
    split_file = root / f"transforms_{split}.json"
    holdout = None
    if split_file.is_file():
        files = [split_file]
    elif fmt == "blender" and split == "all":
        files = [root / f"transforms_{s}.json" for s in ("train", "val", "test")
                 if (root / f"transforms_{s}.json").is_file()]
    elif fmt == "ngp" and split in ("train", "test", "all"):
        files, holdout = [root / "transforms.json"], split
    else:
        valid = _available_splits(root) + (["train", "test", "all"] if fmt == "ngp" else ["all"])
        raise InputError(f"{root}: unknown split '{split}'; valid: {sorted(set(valid))}")

    frames, meta = [], {}
    for src in files:
        fr, glob = _parse(src, root, skip_missing)
        frames += fr
        meta = {**glob, **meta}
    seen: dict[Path, tuple[Path, int]] = {}
    for path, _, _, src, k in frames:
        if path in seen:
            s0, k0 = seen[path]
            raise InputError(f"{src}: frame {k} uses image {path.name}, as frame {k0} of "
                             f"{s0.name} does; remove the duplicate frame")
        seen[path] = (src, k)
    if not frames:
        raise InputError(f"{files[0]}: no frames with an existing image; check the file paths")
    if holdout == "test":
        frames = frames[::HOLDOUT_EVERY]
    elif holdout == "train":
        frames = [f for k, f in enumerate(frames) if k % HOLDOUT_EVERY != 0]

    cameras = _cameras(frames)
    if fmt == "blender":
        aabb = _box(meta["aabb"], files[0]) if "aabb" in meta else np.asarray(BLENDER_AABB)
    else:
        aabb = np.asarray(_ngp_aabb(meta, files[0]))
    paths = [f[0] for f in frames]
    names = [p.relative_to(root).as_posix() if p.is_relative_to(root) else str(p) for p in paths]
    return Frames(paths=paths, cameras=cameras, aabb=torch.as_tensor(aabb, dtype=torch.float32),
                  names=names, root=root, format=fmt, split=split, meta=meta,
                  has_alpha=_image_shape(paths[0])[2] in (2, 4))


def says_unbounded(frames: Frames) -> bool:
    """The data set describes an unbounded capture: ``"unbounded": true`` in its transforms
    file, or Instant-NGP's ``aabb_scale`` > 1 (its convention for content beyond the unit cube:
    a room or landscape behind the object)."""
    if bool(frames.meta.get("unbounded", False)):
        return True
    try:
        return frames.format == "ngp" and float(frames.meta.get("aabb_scale", 1)) > 1
    except (TypeError, ValueError):
        return False


def region_of_interest(frames: Frames) -> tuple[tuple[float, float, float], float]:
    """Centre and radius of the ball an unbounded scene's field keeps at full resolution: the
    box of the object (Instant-NGP: its unit cube, before aabb_scale; Blender: the aabb), centre
    and half its largest side."""
    if frames.format == "ngp":
        lo, hi = (np.asarray(v) for v in _ngp_aabb({**frames.meta, "aabb_scale": 1},
                                                     frames.root / "transforms.json"))
    else:
        box = frames.aabb.double().numpy()
        lo, hi = box[0], box[1]
    c = 0.5 * (lo + hi)
    return (float(c[0]), float(c[1]), float(c[2])), float(0.5 * (hi - lo).max())


# --------------------------------------------------------------------------------------------
# Pixels
# --------------------------------------------------------------------------------------------

def _read_image(path: Path) -> tuple[torch.Tensor, torch.Tensor | None]:
    """RGB [H, W, 3] and alpha [H, W] (or None) as float32 in [0, 1]."""
    try:
        if _png16(path):  # Pillow would reduce 16-bit colour to 8 bits; Mitsuba keeps them
            with _MITSUBA:  # its lazy module set-up is not safe from several threads at once
                import mitsuba as mi

                a = np.array(mi.Bitmap(str(path)))
        else:
            a = iio.imread(path)
    except Exception as exc:  # noqa: BLE001 - any decoder failure is a bad file
        raise _bad_image(path, exc)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] not in (1, 2, 3, 4):
        raise InputError(f"{path}: unsupported image layout {a.shape}; expected RGB or RGBA")
    t = torch.from_numpy(np.ascontiguousarray(a))
    if np.issubdtype(a.dtype, np.integer):
        t = t.to(torch.float32).mul_(1.0 / float(np.iinfo(a.dtype).max))
    else:
        t = t.to(torch.float32)
    c = t.shape[2]
    rgb = t[..., :3] if c >= 3 else t[..., :1].expand(-1, -1, 3)
    alpha = t[..., c - 1] if c in (2, 4) else None
    return rgb, alpha


def area_downscale(x: torch.Tensor, f: int) -> torch.Tensor:  # [H, W, C] -> [H//f, W//f, C]
    """Mean of f x f blocks (the image cropped at the bottom/right to a multiple of f)."""
    h, w = (x.shape[0] // f) * f, (x.shape[1] // f) * f
    x = x[:h, :w].permute(2, 0, 1)[None]
    return F.avg_pool2d(x, f)[0].permute(1, 2, 0)


def _process(rgb: torch.Tensor, alpha: torch.Tensor | None, f: int,
             background: tuple[float, float, float] | None
             ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Composite (or keep straight colour), then area-downscale; returns rgb, alpha."""
    if alpha is None:
        return (area_downscale(rgb, f) if f > 1 else rgb), None
    if background is not None:
        bg = torch.tensor(background, dtype=torch.float32)
        # compositing is linear, so compositing before averaging equals averaging the composite
        rgb = torch.lerp(bg.expand_as(rgb), rgb, alpha[..., None])  # rgb a + bg (1 - a)
        if f > 1:
            rgb = area_downscale(rgb, f)
            alpha = area_downscale(alpha[..., None], f)[..., 0]
        return rgb, alpha
    if f > 1:  # straight colour: alpha-weighted average so transparent junk does not bleed in
        pre = area_downscale(torch.cat([rgb * alpha[..., None], alpha[..., None]], -1), f)
        plain = area_downscale(rgb, f)
        alpha = pre[..., 3]
        safe = alpha.clamp_min(1e-8)[..., None]
        rgb = torch.where(alpha[..., None] > 0, pre[..., :3] / safe, plain).clamp(0, 1)
    return rgb, alpha


def load_dataset(root: str | Path, split: str = "train", downscale: int = 1,
                 background: tuple[float, float, float] | None = (1.0, 1.0, 1.0),
                 skip_missing: bool | None = None, workers: int | None = None,
                 views: list[int] | None = None) -> Dataset:
    """Load one split: cameras in OpenCV axes, images float32 in [0, 1].

    downscale: integer factor f >= 1; images are area-averaged (cropped to a multiple of f) and
    intrinsics divided by f. background: RGB that RGBA images are composited onto; None keeps
    straight colour. skip_missing: see `read_frames`. workers: decoding threads. views: only
    these frames of the split (indices in file order; default all).
    """
    if isinstance(downscale, bool) or not isinstance(downscale, int) or downscale < 1:
        raise InputError(f"downscale {downscale!r}: must be an integer >= 1")
    if background is not None:
        background = tuple(float(c) for c in background)
        if len(background) != 3:
            raise InputError(f"background {background}: expected three values (R, G, B)")
    fr = read_frames(root, split, skip_missing)
    if views is not None:
        fr = dataclasses.replace(fr, paths=[fr.paths[k] for k in views], cameras=fr.cameras[views],
                                 names=[fr.names[k] for k in views])
    cams = fr.cameras.downscaled(downscale)
    n, h, w = len(fr.paths), cams.height, cams.width
    images = torch.empty(n, h, w, 3, dtype=torch.float32)
    # alpha is kept when the first image has it; others without alpha count as opaque
    alphas = torch.empty(n, h, w, dtype=torch.float32) if fr.has_alpha else None
    expect = (fr.cameras.height, fr.cameras.width)

    def work(k: int) -> None:
        rgb, alpha = _read_image(fr.paths[k])
        if tuple(rgb.shape[:2]) != expect:
            raise InputError(f"{fr.paths[k]}: image is {rgb.shape[1]}x{rgb.shape[0]} but "
                             f"{fr.names[0]} is {expect[1]}x{expect[0]}; all images of a data "
                             "set must have one size")
        images[k], a = _process(rgb, alpha, downscale, background)
        if alphas is not None:
            alphas[k] = 1.0 if a is None else a

    workers = workers or min(8, os.cpu_count() or 1)
    pool = ThreadPoolExecutor(max_workers=workers)
    try:
        list(pool.map(work, range(n)))  # list() re-raises the first worker error
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    return Dataset(images=images, alpha=alphas, cameras=cams,
                   aabb=fr.aabb, names=fr.names, root=fr.root, format=fr.format, split=split,
                   background=background, meta=fr.meta)


TRANSPARENT_SHARE = 1e-3  # an alpha channel holds transparency when at least this share of the
# pixels has alpha < 0.5; below it (alpha 255 everywhere, as in most photos of an object before
# a backdrop, or a few stray pixels) the background is baked into the colours
BACKDROP_SPREAD = 0.06  # a border pixel within this (max over RGB) of the border's median colour
BACKDROP_SHARE = 0.8  # ... for at least this share of the border pixels: a uniform backdrop


def has_transparency(alpha: torch.Tensor | None) -> bool:
    """Whether an alpha channel ([N, H, W] in [0, 1], or None) holds transparency
    (`TRANSPARENT_SHARE`): only then can a trainer recomposite its pixels on other colours."""
    if alpha is None:
        return False
    return float((alpha < 0.5).float().mean()) >= TRANSPARENT_SHARE


def backdrop_colour(images: torch.Tensor,  # [N, H, W, 3] in [0, 1]
                    ) -> tuple[float, float, float] | None:
    """The colour of a uniform backdrop baked into the images: the median of the pixels on
    the images' border when at least BACKDROP_SHARE of them lie within BACKDROP_SPREAD of it;
    None when the border is not uniform (a scene that fills the frame)."""
    border = torch.cat([images[:, 0], images[:, -1], images[:, 1:-1, 0], images[:, 1:-1, -1]],
                       1).reshape(-1, 3)
    median = border.median(0).values
    close = ((border - median).abs().amax(-1) <= BACKDROP_SPREAD).float().mean()
    if float(close) < BACKDROP_SHARE:
        return None
    return tuple(round(float(c), 4) for c in median)
