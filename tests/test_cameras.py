"""Camera model: hand-worked pinhole rays, axis conventions, distortion, Mitsuba parity."""

from __future__ import annotations

import math

import pytest
import torch

from shells.data.cameras import (Cameras, distort, look_at, opencv_to_mitsuba, opengl_to_opencv,
                                 pinhole_cameras, subpixel_offsets, undistort)
from shells.errors import InputError

# Instant-NGP fox (../shared/data/fox/transforms.json): one shared camera, 1080x1920 portrait.
FOX = dict(fx=1375.52, fy=1374.49, cx=554.558, cy=965.268, w=1080, h=1920,
           dist=(0.0578421, -0.0805099, -0.000980296, 0.00015575))


def fox_camera(c2w: torch.Tensor | None = None, distorted: bool = True) -> Cameras:
    c2w = torch.eye(4)[None] if c2w is None else c2w[None]
    d = torch.tensor([FOX["dist"]]) if distorted else torch.zeros(1, 4)
    t = lambda v: torch.tensor([v], dtype=torch.float32)  # noqa: E731
    return Cameras(c2w=c2w, fx=t(FOX["fx"]), fy=t(FOX["fy"]), cx=t(FOX["cx"]), cy=t(FOX["cy"]),
                   width=FOX["w"], height=FOX["h"], dist=d)


def rays1(cams: Cameras, px: float, py: float, i: int = 0):
    o, d = cams.rays(torch.tensor([i]), torch.tensor([px]), torch.tensor([py]))
    return o[0], d[0]


# --------------------------------------------------------------------------------------------
# Pinhole rays worked by hand
# --------------------------------------------------------------------------------------------

def test_identity_camera_centre_and_corner_rays():
    # 5x3 image, f = 2, principal point at the image centre (2.5, 1.5) = centre of pixel (2, 1)
    cams = pinhole_cameras(torch.eye(4), fx=2.0, width=5, height=3)
    o, d = rays1(cams, 2.5, 1.5)
    assert torch.allclose(o, torch.zeros(3))
    assert torch.allclose(d, torch.tensor([0.0, 0.0, 1.0]))
    # top-left pixel (0, 0), centre (0.5, 0.5): x = (0.5 - 2.5) / 2 = -1, y = (0.5 - 1.5) / 2 =
    # -0.5, |(-1, -0.5, 1)| = 1.5 -> (-2/3, -1/3, 2/3): left and up in the image
    _, d = rays1(cams, 0.5, 0.5)
    assert torch.allclose(d, torch.tensor([-2 / 3, -1 / 3, 2 / 3]), atol=1e-6)
    # pixel_rays is row-major: index j * W + i
    o_all, d_all = cams.pixel_rays(0)
    assert o_all.shape == d_all.shape == (15, 3)
    assert torch.allclose(d_all[0], torch.tensor([-2 / 3, -1 / 3, 2 / 3]), atol=1e-6)
    assert torch.allclose(d_all[1 * 5 + 2], torch.tensor([0.0, 0.0, 1.0]))
    assert torch.allclose(d_all[2 * 5 + 4], torch.tensor([2 / 3, 1 / 3, 2 / 3]), atol=1e-6)
    assert torch.allclose(d_all.norm(dim=-1), torch.ones(15))


def test_subpixel_offsets_stratify_the_pixel():
    # spp = 4: the centres of the 2 x 2 cells, x fastest
    want = torch.tensor([[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]])
    assert torch.equal(subpixel_offsets(4), want)
    assert torch.equal(subpixel_offsets(1), torch.tensor([[0.5, 0.5]]))
    # jittered: one uniform position inside each cell, independently per pixel
    gen = torch.Generator().manual_seed(0)
    j = subpixel_offsets(9, gen, n=500)  # [500, 9, 2]
    cell = torch.floor(j * 3)
    assert torch.equal(cell, torch.floor(subpixel_offsets(9) * 3).expand(500, 9, 2))
    assert (j.std(0) > 0.05).all()  # really jittered, not the centres
    for bad in (0, 2, 8):
        with pytest.raises(InputError, match="square"):
            subpixel_offsets(bad)


def test_pixel_rays_with_spp_hit_the_sub_pixel_cell_centres():
    # 5x3 image, f = 2: a pixel's 4 rays pass through (i + 0.25 | 0.75, j + 0.25 | 0.75)
    cams = pinhole_cameras(torch.eye(4), fx=2.0, width=5, height=3)
    o, d = cams.pixel_rays(0, spp=4)
    assert d.shape == (15 * 4, 3)
    uv, _ = cams.project(o + d, torch.zeros(60, dtype=torch.long))
    pix = 1 * 5 + 2  # pixel (2, 1)
    want = torch.tensor([[2.25, 1.25], [2.75, 1.25], [2.25, 1.75], [2.75, 1.75]])
    assert torch.allclose(uv[4 * pix:4 * pix + 4], want, atol=1e-5)


def test_posed_camera_rays_rotate_and_translate():
    # camera at (1, 2, 3) rotated 90 deg about world z: camera x -> world y, camera y -> -world x
    c2w = torch.tensor([[0.0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])
    cams = pinhole_cameras(torch.stack([torch.eye(4), c2w]), fx=2.0, width=5, height=3)
    o, d = rays1(cams, 0.5, 0.5, i=1)
    assert torch.allclose(o, torch.tensor([1.0, 2.0, 3.0]))
    # camera-space (-2/3, -1/3, 2/3) -> world (1/3, -2/3, 2/3)
    assert torch.allclose(d, torch.tensor([1 / 3, -2 / 3, 2 / 3]), atol=1e-6)


def test_opengl_to_opencv_flips_camera_y_and_z():
    # Blender camera at (0, 0, 4) with identity rotation looks down world -z, image up = +y
    c2w_gl = torch.eye(4)
    c2w_gl[2, 3] = 4.0
    c2w = opengl_to_opencv(c2w_gl)
    assert torch.equal(c2w, torch.tensor([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 4],
                                          [0, 0, 0, 1]]))
    assert torch.equal(opengl_to_opencv(c2w), c2w_gl)  # an involution
    cams = pinhole_cameras(c2w, fx=2.0, width=5, height=3)
    _, d = rays1(cams, 2.5, 1.5)
    assert torch.allclose(d, torch.tensor([0.0, 0.0, -1.0]))
    _, d_top = rays1(cams, 2.5, 0.5)  # top row of the image sees world +y
    assert d_top[1] > 0.4
    # look_at builds the same camera from eye/target/up
    assert torch.allclose(look_at((0, 0, 4), (0, 0, 0), up=(0, 1, 0)), c2w, atol=1e-7)


def test_look_at_is_orthonormal_and_faces_target():
    c2w = look_at((3.0, -2.0, 1.0), (0.5, 0.5, 0.0), up=(0, 0, 1))
    rot = c2w[:3, :3]
    assert torch.allclose(rot.T @ rot, torch.eye(3), atol=1e-6)
    assert torch.det(rot) == pytest.approx(1.0, abs=1e-6)
    fwd = torch.tensor([0.5 - 3.0, 0.5 + 2.0, -1.0])
    assert torch.allclose(rot[:, 2], fwd / fwd.norm(), atol=1e-6)
    assert rot[2, 1] < 0  # image "down" (camera y) points against world up
    with pytest.raises(InputError, match="parallel"):
        look_at((0, 0, 1), (0, 0, 0), up=(0, 0, 1))


# --------------------------------------------------------------------------------------------
# Downscaling
# --------------------------------------------------------------------------------------------

def test_downscaled_intrinsics_and_same_scene_point():
    cams = fox_camera(look_at((0.3, -4.0, 1.0), (0, 0, 0)))
    small = cams.downscaled(4)
    assert (small.width, small.height) == (270, 480)
    assert small.fx.item() == pytest.approx(1375.52 / 4)
    assert small.cx.item() == pytest.approx(554.558 / 4)
    assert torch.equal(small.dist, cams.dist)
    # a small-image pixel centre (i + 0.5) is the centre of its 4x4 block: 4 (i + 0.5) in full res
    px, py = torch.tensor([0.5, 100.5, 269.5]), torch.tensor([0.5, 300.5, 479.5])
    cam = torch.zeros(3, dtype=torch.long)
    o_s, d_s = small.rays(cam, px, py)
    o_f, d_f = cams.rays(cam, 4 * px, 4 * py)
    assert torch.allclose(o_s, o_f)
    assert torch.allclose(d_s, d_f, atol=1e-6)
    # and a world point projects to pixel coordinates scaled by exactly 1/4
    pts = o_f + 3.0 * d_f
    uv_f, _ = cams.project(pts, cam)
    uv_s, _ = small.project(pts, cam)
    assert torch.allclose(uv_s * 4, uv_f, atol=2e-2)  # float32 projection at ~1000 px
    with pytest.raises(InputError, match="downscale"):
        cams.downscaled(0)
    assert cams.downscaled(1) is cams


def test_downscale_floor_size():
    cams = pinhole_cameras(torch.eye(4), fx=10.0, width=801, height=799)
    small = cams.downscaled(2)
    assert (small.width, small.height) == (400, 399)  # floor; the odd column/row is cropped
    assert small.cx.item() == pytest.approx(801 / 4)  # principal point unaffected by the crop


# --------------------------------------------------------------------------------------------
# Distortion
# --------------------------------------------------------------------------------------------

def test_distort_hand_worked():
    # radial k1 = 0.1: (1, 0) has r^2 = 1 -> (1.1, 0)
    d = torch.tensor([0.1, 0.0, 0.0, 0.0])
    assert torch.allclose(distort(torch.tensor([1.0, 0.0]), d), torch.tensor([1.1, 0.0]))
    # tangential p1 = 0.01 at (0.5, 0.5): r^2 = 0.5, x_d = 0.5 + 2 p1 x y = 0.505,
    # y_d = 0.5 + p1 (r^2 + 2 y^2) = 0.51
    d = torch.tensor([0.0, 0.0, 0.01, 0.0])
    assert torch.allclose(distort(torch.tensor([0.5, 0.5]), d), torch.tensor([0.505, 0.51]))
    # p2 = 0.01 mirrors it: x_d = 0.5 + p2 (r^2 + 2 x^2) = 0.51, y_d = 0.5 + 2 p2 x y = 0.505
    d = torch.tensor([0.0, 0.0, 0.0, 0.01])
    assert torch.allclose(distort(torch.tensor([0.5, 0.5]), d), torch.tensor([0.51, 0.505]))
    # k2 = -0.1 at (0, 0.5): r^4 = 1/16 -> y_d = 0.5 (1 - 0.1 / 16) = 0.496875
    d = torch.tensor([0.0, -0.1, 0.0, 0.0])
    assert torch.allclose(distort(torch.tensor([0.0, 0.5]), d), torch.tensor([0.0, 0.496875]))


def test_distort_jacobian_matches_autograd():
    from shells.data.cameras import _distort_jacobian

    torch.manual_seed(0)
    xy = torch.rand(16, 2, dtype=torch.float64) * 1.6 - 0.8
    dist = torch.tensor([0.2, -0.3, 0.01, -0.02], dtype=torch.float64)
    xy.requires_grad_(True)
    out = distort(xy, dist)  # points are independent: d(sum of x_d)/d(x, y) is row 0 of each J
    row0 = torch.autograd.grad(out[:, 0].sum(), xy, retain_graph=True)[0]  # [16, 2]
    row1 = torch.autograd.grad(out[:, 1].sum(), xy)[0]
    a, b, c, d = _distort_jacobian(xy.detach(), dist)
    assert torch.allclose(torch.stack([a, b], -1), row0, atol=1e-12)
    assert torch.allclose(torch.stack([c, d], -1), row1, atol=1e-12)


def test_undistort_inverts_distort_over_fox_image():
    # a 9-pixel grid over the whole 1080x1920 fox image, edges and corners included (float64).
    # 120 x 214 < 32768 points keeps torch single-threaded: on 2 busy cores its thread pool
    # made this test 100x slower.
    u = torch.linspace(0, FOX["w"], 120, dtype=torch.float64)
    v = torch.linspace(0, FOX["h"], 214, dtype=torch.float64)
    uu, vv = torch.meshgrid(u, v, indexing="ij")
    xy_d = torch.stack([(uu - FOX["cx"]) / FOX["fx"], (vv - FOX["cy"]) / FOX["fy"]], -1)
    dist = torch.tensor(FOX["dist"], dtype=torch.float64)
    xy_u = undistort(xy_d, dist)
    back = distort(xy_u, dist)
    err_px = ((back - xy_d) * torch.tensor([FOX["fx"], FOX["fy"]], dtype=torch.float64)).abs()
    assert err_px.max() < 1e-4
    # Newton converges quadratically: 3 steps already reach 1e-6 px (a wrong Jacobian would not)
    err3 = (distort(undistort(xy_d, dist, iters=3), dist) - xy_d).abs().max() * FOX["fx"]
    assert err3 < 1e-6
    assert (xy_u - xy_d).abs().max() > 1e-3  # the lens really distorts at the corners
    # and the other way round: undistort(distort(p)) = p
    assert torch.allclose(undistort(distort(xy_u, dist), dist), xy_u, atol=1e-10)
    # float32 (what `Cameras.rays` uses) resolves ~6e-8 normalised units, ~1e-4 px
    xy_32 = undistort(xy_d.float(), dist.float()).double()
    assert ((xy_32 - xy_u).abs() * FOX["fx"]).max() < 1e-3


def test_ray_reprojects_to_its_pixel_with_distortion():
    cams = fox_camera(look_at((0.3, -4.0, 1.0), (0, 0, 0)))
    px = torch.tensor([0.5, 1079.5, 0.5, 1079.5, 540.0])
    py = torch.tensor([0.5, 0.5, 1919.5, 1919.5, 960.0])
    cam = torch.zeros(5, dtype=torch.long)
    o, d = cams.rays(cam, px, py)
    uv, z = cams.project(o + 2.5 * d, cam)
    # float32 world points at distance ~4 carry ~5e-7 relative error -> ~1e-3 px
    assert torch.allclose(uv, torch.stack([px, py], -1), atol=5e-3)
    assert (z > 0).all()


def test_distortion_changes_corner_rays_not_principal_ray():
    dcam, pcam = fox_camera(distorted=True), fox_camera(distorted=False)
    _, d0 = rays1(dcam, FOX["cx"], FOX["cy"])
    _, p0 = rays1(pcam, FOX["cx"], FOX["cy"])
    assert torch.allclose(d0, p0) and torch.allclose(d0, torch.tensor([0.0, 0.0, 1.0]))
    _, dc = rays1(dcam, 0.5, 0.5)
    _, pc = rays1(pcam, 0.5, 0.5)
    angle = torch.acos(torch.dot(dc, pc).clamp(max=1.0)).item()
    # the corner sits at r ~ 0.8 in normalised units, where k1 r^2 + k2 r^4 ~ 0.004 (~2.5 px)
    assert angle * FOX["fx"] > 1.0
    # hand-worked: k1 = 0.1 maps undistorted (1, 0) to distorted (1.1, 0); the pixel at
    # x_d = 1.1 therefore looks along (1, 0, 1) / sqrt(2)
    cams = Cameras(c2w=torch.eye(4)[None], fx=torch.tensor([100.0]), fy=torch.tensor([100.0]),
                   cx=torch.tensor([50.0]), cy=torch.tensor([50.0]), width=200, height=100,
                   dist=torch.tensor([[0.1, 0.0, 0.0, 0.0]]))
    _, d = rays1(cams, 50.0 + 110.0, 50.0)
    assert torch.allclose(d, torch.tensor([1.0, 0.0, 1.0]) / math.sqrt(2), atol=1e-6)


def test_subset_and_device():
    cams = pinhole_cameras(torch.eye(4)[None].repeat(3, 1, 1), fx=2.0, width=5, height=3)
    assert len(cams) == 3 and len(cams[1]) == 1 and len(cams[torch.tensor([0, 2])]) == 2
    assert cams.to("cpu").device.type == "cpu"
    K = cams.intrinsics()
    assert K.shape == (3, 3, 3) and K[0, 0, 2] == 2.5 and K[0, 1, 1] == 2.0


# --------------------------------------------------------------------------------------------
# Parity with Mitsuba's perspective sensor (the toy scenes are rendered with it)
# --------------------------------------------------------------------------------------------

def test_pixel_rays_match_mitsuba_perspective_sensor():
    import mitsuba as mi

    from shells.device import mitsuba_variant

    mitsuba_variant("llvm_ad_rgb")
    W, H, fov_x = 6, 4, 50.0
    c2w = look_at((0.5, -3.0, 1.2), (0.1, 0.2, 0.0), up=(0, 0, 1))
    fx = 0.5 * W / math.tan(math.radians(fov_x) / 2)
    cams = pinhole_cameras(c2w, fx=fx, width=W, height=H)
    sensor = mi.load_dict({
        # Mitsuba starts rays on the near plane: make it tiny so that origins compare too
        "type": "perspective", "fov": fov_x, "fov_axis": "x", "near_clip": 1e-6,
        "to_world": mi.ScalarTransform4f(opencv_to_mitsuba(c2w).double().tolist()),
        "film": {"type": "hdrfilm", "width": W, "height": H, "rfilter": {"type": "box"}},
    })
    o, d = cams.pixel_rays(0)
    j, i = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    pos = mi.Point2f(((i.reshape(-1) + 0.5) / W).tolist(), ((j.reshape(-1) + 0.5) / H).tolist())
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
    d_mi = torch.tensor([list(ray.d.x), list(ray.d.y), list(ray.d.z)]).T
    o_mi = torch.tensor([list(ray.o.x), list(ray.o.y), list(ray.o.z)]).T
    assert torch.allclose(d, d_mi, atol=1e-5)
    assert torch.allclose(o, o_mi, atol=1e-5)
