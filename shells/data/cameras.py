"""Camera model: pinhole intrinsics with OpenCV radial-tangential distortion, and ray generation.

Convention (the one place it is written down):

* ``c2w`` is a camera-to-world 4x4 matrix in the **OpenCV** convention: camera x points right,
  y points down, z points forward (the viewing direction). Translations are in world units.
* Blender / NeRF-synthetic and Instant-NGP store OpenGL matrices (x right, y up, z backward);
  loaders convert once with ``c2w_cv = c2w_gl @ diag(1, -1, -1, 1)`` (`opengl_to_opencv`).
* Pixel (i, j) is column i, row j; its centre is at (i + 0.5, j + 0.5) in continuous pixel
  coordinates, so the image spans [0, W] x [0, H]. This is Mitsuba's convention for its
  perspective sensor (film position (i + 0.5) / W, (j + 0.5) / H) and COLMAP's.
* Projection of a camera-space point (X, Y, Z), Z > 0: normalised coordinates x = X / Z,
  y = Y / Z, distorted by `distort` (k1, k2, p1, p2; OpenCV's model), then u = fx x_d + cx,
  v = fy y_d + cy. Rays invert this: pixel -> x_d -> `undistort` -> direction (x, y, 1).
* Mitsuba cameras look along +z with x *left* and y *up*: `opencv_to_mitsuba` converts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from shells.errors import InputError

_FLIP_YZ = (1.0, -1.0, -1.0, 1.0)  # OpenGL <-> OpenCV camera axes
_FLIP_XY = (-1.0, -1.0, 1.0, 1.0)  # OpenCV <-> Mitsuba camera axes


def opengl_to_opencv(c2w: Tensor) -> Tensor:  # [..., 4, 4] -> [..., 4, 4]
    """OpenGL (x right, y up, z back) camera-to-world -> OpenCV (x right, y down, z forward).

    Flipping the camera's y and z axes is its own inverse, so this also converts back.
    """
    flip = torch.tensor(_FLIP_YZ, dtype=c2w.dtype, device=c2w.device)
    return c2w * flip  # right-multiplying by a diagonal matrix scales its columns


def opencv_to_mitsuba(c2w: Tensor) -> Tensor:  # [..., 4, 4] -> [..., 4, 4]
    """OpenCV camera-to-world -> Mitsuba sensor ``to_world`` (camera x left, y up, z forward)."""
    flip = torch.tensor(_FLIP_XY, dtype=c2w.dtype, device=c2w.device)
    return c2w * flip


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> Tensor:
    """OpenCV camera-to-world [4, 4] float32 for a camera at ``eye`` [3] facing ``target`` [3].

    Image "up" (-y) is the projection of ``up`` [3] onto the image plane.
    """
    eye, target, up = (torch.as_tensor(v, dtype=torch.float64).reshape(3)
                       for v in (eye, target, up))
    z = target - eye
    if torch.linalg.norm(z) < 1e-12:
        raise InputError(f"look_at: eye {eye.tolist()} equals target; move the camera away")
    z = z / torch.linalg.norm(z)
    x = torch.linalg.cross(z, up)
    if torch.linalg.norm(x) < 1e-9 * torch.linalg.norm(up):
        raise InputError(f"look_at: up {up.tolist()} is parallel to the viewing direction; "
                         "choose another up vector")
    x = x / torch.linalg.norm(x)
    y = torch.linalg.cross(z, x)  # points "down" in the image: x, y, z is right-handed
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, y, z, eye
    return c2w.float()


# --------------------------------------------------------------------------------------------
# OpenCV radial-tangential distortion (k1, k2, p1, p2) in normalised image coordinates
# --------------------------------------------------------------------------------------------

def distort(xy: Tensor, dist: Tensor) -> Tensor:  # [..., 2], [..., 4] (broadcast) -> [..., 2]
    """Apply OpenCV's distortion to undistorted normalised coordinates (x, y) = (X/Z, Y/Z).

    r² = x² + y², radial = 1 + k1 r² + k2 r⁴,
    x_d = x radial + 2 p1 x y + p2 (r² + 2 x²),  y_d = y radial + p1 (r² + 2 y²) + 2 p2 x y.
    """
    x, y = xy[..., 0], xy[..., 1]
    k1, k2, p1, p2 = dist[..., 0], dist[..., 1], dist[..., 2], dist[..., 3]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + k2 * r2)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return torch.stack([xd, yd], dim=-1)


def _distort_jacobian(xy: Tensor, dist: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Entries d(x_d, y_d)/d(x, y) of `distort`, each [...]."""
    x, y = xy[..., 0], xy[..., 1]
    k1, k2, p1, p2 = dist[..., 0], dist[..., 1], dist[..., 2], dist[..., 3]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + k2 * r2)
    dradial = k1 + 2 * k2 * r2  # d radial / d r², and d r²/dx = 2x
    dxd_dx = radial + 2 * x * x * dradial + 2 * p1 * y + 6 * p2 * x
    dxd_dy = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
    dyd_dx = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
    dyd_dy = radial + 2 * y * y * dradial + 6 * p1 * y + 2 * p2 * x
    return dxd_dx, dxd_dy, dyd_dx, dyd_dy


def undistort(xy: Tensor,  # [..., 2] distorted normalised coordinates
              dist: Tensor,  # [..., 4] k1, k2, p1, p2 (broadcast)
              iters: int = 10) -> Tensor:  # [..., 2]
    """Invert `distort` by Newton's method, starting from the distorted point itself.

    Converges quadratically for the mild distortion of real lenses (fox: 3 steps to 1e-12 px in
    float64); stops early once the largest step is below 0.1 sqrt(eps), after which the
    remaining error is ~step^2. float32 resolves normalised coordinates to ~6e-8, i.e. ~2e-4 px
    at a 1400 px focal length; use float64 where that matters.
    """
    dist = dist.to(xy.dtype)
    tol = 0.1 * torch.finfo(xy.dtype).eps ** 0.5
    und = xy.clone()
    for _ in range(iters):
        res = distort(und, dist) - xy
        a, b, c, d = _distort_jacobian(und, dist)
        det = a * d - b * c  # stays near 1 for realistic lenses
        step = torch.stack([d * res[..., 0] - b * res[..., 1],
                            a * res[..., 1] - c * res[..., 0]], dim=-1) / det[..., None]
        und = und - step
        if step.numel() == 0 or step.abs().max() < tol:
            break
    return und


# --------------------------------------------------------------------------------------------
# Cameras
# --------------------------------------------------------------------------------------------

@dataclass
class Cameras:
    """N cameras sharing one image size. All tensors float32 on one device."""

    c2w: Tensor  # [N, 4, 4] camera-to-world, OpenCV axes, world units
    fx: Tensor  # [N] focal length in pixels
    fy: Tensor  # [N]
    cx: Tensor  # [N] principal point in pixels (pixel centres at i + 0.5)
    cy: Tensor  # [N]
    width: int
    height: int
    dist: Tensor  # [N, 4] k1, k2, p1, p2 (OpenCV radial-tangential); zeros = pinhole

    def __post_init__(self) -> None:
        n = self.c2w.shape[0]
        assert self.c2w.shape == (n, 4, 4), self.c2w.shape
        for name in ("fx", "fy", "cx", "cy"):
            assert getattr(self, name).shape == (n,), (name, getattr(self, name).shape)
        assert self.dist.shape == (n, 4), self.dist.shape

    def __len__(self) -> int:
        return self.c2w.shape[0]

    def __getitem__(self, idx) -> "Cameras":
        """Subset of the cameras (int, slice, index tensor or list); keeps the batch axis."""
        if isinstance(idx, int):
            idx = slice(idx, idx + 1) if idx != -1 else slice(-1, None)
        return replace(self, c2w=self.c2w[idx], fx=self.fx[idx], fy=self.fy[idx],
                       cx=self.cx[idx], cy=self.cy[idx], dist=self.dist[idx])

    def to(self, device: torch.device | str) -> "Cameras":
        return replace(self, c2w=self.c2w.to(device), fx=self.fx.to(device), fy=self.fy.to(device),
                       cx=self.cx.to(device), cy=self.cy.to(device), dist=self.dist.to(device))

    @property
    def device(self) -> torch.device:
        return self.c2w.device

    @property
    def has_distortion(self) -> bool:
        return bool((self.dist != 0).any())

    def downscaled(self, factor: int) -> "Cameras":
        """Cameras for images shrunk by an integer ``factor`` (area averaging, floor size).

        Output pixel i covers input pixels [f i, f i + f), so continuous pixel coordinates
        scale by exactly 1/f: fx, fy, cx, cy all divide by f. Distortion acts on normalised
        coordinates and is unchanged. Input rows/columns beyond ``(W // f) * f`` are cropped
        away, which does not move the principal point.
        """
        if not isinstance(factor, int) or factor < 1:
            raise InputError(f"downscale factor {factor!r}: must be an integer >= 1")
        if factor == 1:
            return self
        if self.width // factor < 1 or self.height // factor < 1:
            raise InputError(f"downscale factor {factor}: larger than the image "
                             f"({self.width}x{self.height}); use a smaller factor")
        return replace(self, fx=self.fx / factor, fy=self.fy / factor, cx=self.cx / factor,
                       cy=self.cy / factor, width=self.width // factor,
                       height=self.height // factor)

    def resized(self, width: int | None, height: int | None) -> "Cameras":
        """Cameras at another resolution: intrinsics scaled per axis (aspect kept if one is
        None; both None: unchanged)."""
        if width is None and height is None:
            return self
        if width is None:
            width = max(1, round(self.width * height / self.height))
        if height is None:
            height = max(1, round(self.height * width / self.width))
        if width < 1 or height < 1:
            raise InputError(f"--width {width} --height {height}: must be positive")
        sx, sy = width / self.width, height / self.height
        return replace(self, fx=self.fx * sx, cx=self.cx * sx, fy=self.fy * sy,
                       cy=self.cy * sy, width=int(width), height=int(height))

    def intrinsics(self) -> Tensor:  # -> [N, 3, 3]
        """Pinhole matrices K (distortion not included)."""
        K = torch.zeros(len(self), 3, 3, dtype=self.fx.dtype, device=self.device)
        K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2] = self.fx, self.fy, self.cx, self.cy
        K[:, 2, 2] = 1
        return K

    def camera_directions(self, cam: Tensor, px: Tensor, py: Tensor) -> Tensor:
        """Camera-space directions (x, y, 1) through pixel coordinates, undistorted.

        cam [R] long, px/py [R] -> [R, 3] (not normalised; z = 1). float32: the undistortion
        is accurate to ~2e-4 px (see `undistort`).
        """
        xd = (px - self.cx[cam]) / self.fx[cam]
        yd = (py - self.cy[cam]) / self.fy[cam]
        xy = torch.stack([xd, yd], dim=-1)  # [R, 2]
        if self.has_distortion:
            xy = undistort(xy, self.dist[cam])
        return torch.cat([xy, torch.ones_like(xd)[:, None]], dim=-1)

    def rays(self, cam: Tensor, px: Tensor, py: Tensor) -> tuple[Tensor, Tensor]:
        """World-space rays through continuous pixel coordinates.

        cam [R] long camera indices; px, py [R] float pixel coordinates (centre of pixel i is
        i + 0.5) -> origins [R, 3], unit directions [R, 3].
        """
        d_cam = self.camera_directions(cam, px, py)  # [R, 3]
        rot = self.c2w[cam, :3, :3]  # [R, 3, 3]
        d = torch.einsum("rij,rj->ri", rot, d_cam)
        d = d / torch.linalg.norm(d, dim=-1, keepdim=True)
        o = self.c2w[cam, :3, 3]
        return o, d

    def pixel_grid(self, rows: tuple[int, int] | None = None) -> tuple[Tensor, Tensor]:
        """Pixel-centre coordinates px, py of every pixel (of image rows [y0, y1) when ``rows``
        is given), row-major: [H*W] (or [(y1 - y0) * W]) each."""
        y0, y1 = rows if rows is not None else (0, self.height)
        j, i = torch.meshgrid(torch.arange(y0, y1, device=self.device),
                              torch.arange(self.width, device=self.device), indexing="ij")
        return i.reshape(-1).float() + 0.5, j.reshape(-1).float() + 0.5

    def pixel_rays(self, i: int, spp: int = 1,
                   rows: tuple[int, int] | None = None) -> tuple[Tensor, Tensor]:
        """Rays of all pixels of camera ``i`` (of rows [y0, y1) only: a tile of a large frame),
        row-major: [H*W*spp, 3] each.

        ``spp`` = 1: through the pixel centres; otherwise through the centres of a k x k grid
        of sub-pixel cells (spp = k^2, `subpixel_offsets`), a pixel's rays contiguous.
        """
        px, py = self.pixel_grid(rows)
        off = subpixel_offsets(spp, device=px.device)  # [spp, 2]
        px = (px[:, None] - 0.5 + off[:, 0]).reshape(-1)
        py = (py[:, None] - 0.5 + off[:, 1]).reshape(-1)
        cam = torch.full_like(px, i, dtype=torch.long)
        return self.rays(cam, px, py)

    def project(self, points: Tensor, cam: Tensor) -> tuple[Tensor, Tensor]:
        """World points -> distorted pixel coordinates and camera-space depth.

        points [R, 3], cam [R] long -> pixels [R, 2], depth z [R] (negative behind the camera).
        The inverse of `rays` up to the point's position along the ray.
        """
        w2c = torch.linalg.inv(self.c2w[cam])  # [R, 4, 4]
        p = torch.einsum("rij,rj->ri", w2c[:, :3, :3], points) + w2c[:, :3, 3]
        z = p[:, 2]
        xy = distort(p[:, :2] / z[:, None], self.dist[cam])
        u = self.fx[cam] * xy[:, 0] + self.cx[cam]
        v = self.fy[cam] * xy[:, 1] + self.cy[cam]
        return torch.stack([u, v], dim=-1), z


def subpixel_offsets(spp: int, generator: torch.Generator | None = None, n: int | None = None,
                     device: torch.device | str = "cpu") -> Tensor:
    """Positions inside a pixel (in [0, 1)^2, x then y) of its ``spp`` = k^2 rays: one per
    cell of a k x k grid, at the cell centre, or uniformly jittered within the cell when a
    ``generator`` is given. -> [spp, 2], or [n, spp, 2] (independent jitter per pixel) with ``n``.

    Averaging the rays of a pixel is the box filter the toy scenes' references are rendered
    with (`scenes/dataset.py`), so a field trained this way need not blur its edges to match
    anti-aliased pixels. spp = 1 is the pixel centre.
    """
    k = math.isqrt(spp)
    if spp < 1 or k * k != spp:
        raise InputError(f"{spp} rays per pixel: must be a square number (1, 4, 9, 16, ...)")
    j, i = torch.meshgrid(torch.arange(k, device=device), torch.arange(k, device=device),
                          indexing="ij")
    cell = torch.stack([i.reshape(-1), j.reshape(-1)], dim=-1).float()  # [spp, 2]
    shape = (spp, 2) if n is None else (n, spp, 2)
    if generator is None:
        jitter = torch.full(shape, 0.5, device=device)
    else:
        jitter = torch.rand(shape, generator=generator, device=device)
    return (cell + jitter) / k


def pinhole_cameras(c2w: Tensor, fx: float, width: int, height: int, fy: float | None = None,
                    cx: float | None = None, cy: float | None = None) -> Cameras:
    """Cameras sharing one undistorted pinhole model; cx, cy default to the image centre.

    c2w [N, 4, 4] OpenCV. A convenience for toy scenes and tests.
    """
    c2w = torch.as_tensor(c2w, dtype=torch.float32)
    if c2w.ndim == 2:
        c2w = c2w[None]
    n = c2w.shape[0]
    full = lambda v: torch.full((n,), float(v), dtype=torch.float32)  # noqa: E731
    return Cameras(c2w=c2w, fx=full(fx), fy=full(fx if fy is None else fy),
                   cx=full(width / 2 if cx is None else cx),
                   cy=full(height / 2 if cy is None else cy), width=int(width),
                   height=int(height), dist=torch.zeros(n, 4, dtype=torch.float32))
