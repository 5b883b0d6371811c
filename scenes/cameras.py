"""Camera placement for the toy scenes and the OpenGL <-> Mitsuba camera-frame conversion.

Conventions (owned here, written once):
- World: z is up (Blender). The scene box is [-1, 1]^3 with content around the origin.
- Written poses are Blender/OpenGL camera-to-world 4x4 matrices: columns are the camera's
  right (+x, image right), up (+y, image up), back (+z, the camera looks along -z) and eye.
- Mitsuba's ``perspective`` sensor looks along its local +z with local +x pointing to the image
  *left* and +y up (checked by rendering a marker at world +x: it appears on the image's right
  for a camera whose local x is world -x). Hence ``to_world = c2w_gl @ diag(-1, 1, -1, 1)``.
- Pixel (i, j) has its centre at (i + 0.5, j + 0.5); fx = 0.5 W / tan(0.5 camera_angle_x);
  the principal point is the image centre (Mitsuba's sensor satisfies all three).
"""

from __future__ import annotations

import numpy as np

# Mitsuba's camera frame expressed in the OpenGL camera frame (and its own inverse).
GL_TO_MITSUBA = np.diag([-1.0, 1.0, -1.0, 1.0])


def look_at_gl(eye: np.ndarray,  # [3]
               target: np.ndarray | None = None,  # [3], default the origin
               ) -> np.ndarray:  # [4, 4] OpenGL c2w
    """OpenGL camera-to-world matrix of a camera at ``eye`` looking at ``target``.

    Up is world +z, except within ~2.6 degrees of the poles, where world +y is used instead
    (the cross product with +z would be ill-conditioned there).
    """
    eye = np.asarray(eye, np.float64)
    target = np.zeros(3) if target is None else np.asarray(target, np.float64)
    forward = target - eye
    forward /= np.linalg.norm(forward)
    up = np.array([0.0, 0.0, 1.0])
    if abs(forward @ up) > 0.999:
        up = np.array([0.0, 1.0, 0.0])
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, -forward, eye
    return c2w


def sample_poses(rng: np.random.Generator, n: int, radius: tuple[float, float] = (2.6, 3.0),
                 even: bool = False) -> np.ndarray:  # [n, 4, 4] OpenGL c2w
    """``n`` cameras looking at the origin from directions uniform on the sphere, at distances
    uniform in ``radius`` (content within radius ~0.6 of the origin stays in view).

    ``even``: directions on a randomly rotated Fibonacci sphere instead of independent draws, so
    a few training views still see every side of the content (independent draws leave gaps).
    """
    if even and n:
        k = np.arange(n) + 0.5
        z = 1.0 - 2.0 * k / n
        phi = np.pi * (3.0 - np.sqrt(5.0)) * k
        r = np.sqrt(1.0 - z * z)
        dirs = np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))  # a random orthogonal matrix
        dirs = dirs @ q.T
    else:
        dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    dist = rng.uniform(radius[0], radius[1], size=(n, 1))
    return np.stack([look_at_gl(e) for e in dirs * dist]) if n else np.zeros((0, 4, 4))


def gl_to_mitsuba(c2w_gl: np.ndarray,  # [4, 4]
                  ) -> np.ndarray:  # [4, 4] Mitsuba sensor to_world
    """Mitsuba ``perspective`` sensor ``to_world`` for an OpenGL camera-to-world matrix."""
    return np.asarray(c2w_gl, np.float64) @ GL_TO_MITSUBA


def pixel_rays_gl(c2w_gl: np.ndarray,  # [4, 4]
                  camera_angle_x: float, width: int, height: int,
                  offsets: np.ndarray | None = None,  # [K, 2] in-pixel offsets, default centre
                  ) -> tuple[np.ndarray, np.ndarray]:  # origins [H, W, K, 3], dirs [H, W, K, 3]
    """World-space rays through points of each pixel, for the written camera convention.

    The reference ray generator of this module (used to compute exact opacities); unit dirs.
    """
    offsets = np.array([[0.5, 0.5]]) if offsets is None else np.asarray(offsets, np.float64)
    focal = 0.5 * width / np.tan(0.5 * camera_angle_x)
    j, i = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")  # [H, W]
    u = i[..., None] + offsets[:, 0]  # [H, W, K]
    v = j[..., None] + offsets[:, 1]
    # OpenGL camera: x right, y up, looking along -z; image rows grow downwards.
    d_cam = np.stack([(u - 0.5 * width) / focal, -(v - 0.5 * height) / focal,
                      -np.ones_like(u)], -1)
    dirs = d_cam @ c2w_gl[:3, :3].T
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    origins = np.broadcast_to(c2w_gl[:3, 3], dirs.shape).copy()
    return origins, dirs
