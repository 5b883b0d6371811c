"""Toy scene generators (scenes/): cameras, opacity, format, determinism, option checks.

Rays are generated here straight from the written JSON (focal from camera_angle_x, pixel centres
at +0.5, OpenGL -> OpenCV), independently of scenes/cameras.py, and also through the project's
loader (shells.data.datasets) when it exists.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from scenes import SCENES, make_scene
from scenes import dataset as ds
from scenes.cameras import look_at_gl, pixel_rays_gl, sample_poses
from scenes.content import SceneSpec, lights
from scenes.opacity import opacity, reference_opacity
from shells.errors import InputError


# --------------------------------------------------------------------------------------------
# helpers (independent reference ray generation and sphere intersection)
# --------------------------------------------------------------------------------------------

def json_rays(split_json: dict, k: int, width: int, height: int,
              ) -> tuple[np.ndarray, np.ndarray]:  # origins [H*W, 3], dirs [H*W, 3]
    """Pixel-centre rays of frame k, exactly as a Blender loader defines them."""
    fx = 0.5 * width / math.tan(0.5 * split_json["camera_angle_x"])
    c2w = np.array(split_json["frames"][k]["transform_matrix"]) @ np.diag([1, -1, -1, 1])
    j, i = np.mgrid[0:height, 0:width]
    # OpenCV camera: x right, y down, z forward.
    d_cam = np.stack([(i + 0.5 - 0.5 * width) / fx, (j + 0.5 - 0.5 * height) / fx,
                      np.ones(i.shape)], -1).reshape(-1, 3)
    d = d_cam @ c2w[:3, :3].T
    return np.broadcast_to(c2w[:3, 3], d.shape), d / np.linalg.norm(d, axis=1, keepdims=True)


def hits_sphere(o: np.ndarray, d: np.ndarray,  # [R, 3] each, d unit
                center, radius: float) -> np.ndarray:  # [R] bool
    oc = o - np.asarray(center, np.float64)
    b = np.einsum("ij,ij->i", oc, d)
    return (b * b - np.einsum("ij,ij->i", oc, oc) + radius * radius > 0) & (b < 0)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def read_split(root: Path, split: str) -> tuple[dict, np.ndarray]:  # json, RGBA [N, H, W, 4]
    meta = json.loads((root / f"transforms_{split}.json").read_text())
    images = np.stack([iio.imread(root / f"{f['file_path']}.png") for f in meta["frames"]])
    return meta, images


def area_downscale(x: np.ndarray, f: int) -> np.ndarray:  # [H, W] -> [H//f, W//f]
    h, w = x.shape[0] // f, x.shape[1] // f
    return x[:h * f, :w * f].reshape(h, f, w, f).mean((1, 3))


RES = 40


@pytest.fixture(scope="module")
def sphere_set(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("sphere")
    make_scene("sphere", root, res=RES, views=4, test_views=2, spp=4, seed=3)
    return root


@pytest.fixture(scope="module")
def fuzzy_set(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("fuzzy")
    make_scene("fuzzy-sphere", root, res=32, views=2, test_views=1, spp=4, seed=0)
    return root


@pytest.fixture(scope="module")
def core_set(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("core")
    make_scene("core-fuzz", root, res=32, views=2, test_views=1, spp=4, seed=0)
    return root


# --------------------------------------------------------------------------------------------
# cameras
# --------------------------------------------------------------------------------------------

def test_look_at_is_a_rotation_looking_at_the_target_also_at_the_poles():
    for eye in ([2.0, 1.0, 0.5], [0.0, 0.0, 3.0], [0.0, 0.0, -2.5], [1e-4, 0.0, 2.0]):
        c2w = look_at_gl(np.array(eye))
        r = c2w[:3, :3]
        assert np.allclose(r.T @ r, np.eye(3), atol=1e-12)
        assert np.isclose(np.linalg.det(r), 1.0)
        # the camera looks along -z: -z column is the unit vector from the eye to the origin
        assert np.allclose(-r[:, 2], -np.array(eye) / np.linalg.norm(eye))
        assert np.allclose(c2w[:3, 3], eye)
    # away from the poles, image-up leans towards world +z (Blender convention)
    assert look_at_gl(np.array([3.0, 0.0, 0.0]))[2, 1] == pytest.approx(1.0)


def test_sample_poses_distribution():
    poses = sample_poses(np.random.default_rng(0), 200)
    dist = np.linalg.norm(poses[:, :3, 3], axis=1)
    assert dist.min() >= 2.6 and dist.max() <= 3.0
    # uniform directions on the sphere: the mean direction is near 0 (|mean| ~ 1/sqrt(3*200))
    assert np.linalg.norm((poses[:, :3, 3] / dist[:, None]).mean(0)) < 0.15


def test_mitsuba_renders_from_the_written_camera_offcentre_sphere():
    # An off-centre sphere breaks every symmetry (a mirrored or rolled camera would move it):
    # Mitsuba's own film alpha (coverage, independent of scenes/opacity.py) must match the
    # rays built from the written OpenGL c2w, and the exact alpha must agree with it.
    center, radius = (0.3, -0.2, 0.15), 0.4
    spec = SceneSpec({"ball": {"type": "sphere", "center": list(center), "radius": radius,
                               "bsdf": {"type": "diffuse"}}, **lights()},
                     {"name": "test"}, spheres=[(center, radius)])
    scene = ds.load_colour_scene(spec, RES, 64)
    poses = sample_poses(np.random.default_rng(7), 3)
    split = {"camera_angle_x": ds.CAMERA_ANGLE_X,
             "frames": [{"transform_matrix": p.tolist()} for p in poses]}
    for k, c2w in enumerate(poses):
        film_alpha = ds._render(scene, c2w, k)[..., 3]
        o, d = json_rays(split, k, RES, RES)
        hit = hits_sphere(o, d, center, radius).reshape(RES, RES)
        assert hit.sum() > 50  # the sphere is in view
        assert iou(film_alpha > 0.5, hit) >= 0.98
        # coverage from 4x4 sub-pixel rays of the same JSON camera (a 4x finer image)
        o4, d4 = json_rays(split, k, 4 * RES, 4 * RES)
        cover = area_downscale(hits_sphere(o4, d4, center, radius).reshape(4 * RES, -1), 4)
        jj, ii = np.mgrid[0:RES, 0:RES]
        # silhouette centroids agree: a half-pixel offset would show as 0.5; the measured
        # ~0.03 is the sub-pixel sampling noise along the rim (64 and 16 samples)
        for g in (ii, jj):
            c_film = (g * film_alpha).sum() / film_alpha.sum()
            assert abs(c_film - (g * cover).sum() / cover.sum()) < 0.1
        exact = opacity(spec, c2w, ds.CAMERA_ANGLE_X, RES)
        # edge pixels only: 16 stratified (Mitsuba) vs 16 stratified (exact) sub-pixel samples
        assert np.abs(exact - film_alpha).mean() < 0.01


# --------------------------------------------------------------------------------------------
# the written data set
# --------------------------------------------------------------------------------------------

def test_sphere_dataset_format(sphere_set):
    for split, n in (("train", 4), ("test", 2)):
        meta, images = read_split(sphere_set, split)
        assert images.shape == (n, RES, RES, 4) and images.dtype == np.uint8
        assert meta["aabb"] == [[-1, -1, -1], [1, 1, 1]]
        assert meta["scene"] == {"name": "sphere", "center": [0, 0, 0], "radius": 0.5}
        assert [f["file_path"] for f in meta["frames"]] == [f"{split}/r_{k}" for k in range(n)]
        assert images[..., 3].max() == 255 and images[..., 3].min() == 0
        # transparent background: colour is zero where alpha is zero
        assert images[images[..., 3] == 0][:, :3].max() == 0
        # lit and textured: the opaque pixels carry many different colours
        opaque = images[images[..., 3] == 255][:, :3]
        assert opaque.mean() > 30 and len(np.unique(opaque, axis=0)) > 100
    train = json.loads((sphere_set / "transforms_train.json").read_text())
    test = json.loads((sphere_set / "transforms_test.json").read_text())
    eyes_train = np.array([f["transform_matrix"] for f in train["frames"]])[:, :3, 3]
    eyes_test = np.array([f["transform_matrix"] for f in test["frames"]])[:, :3, 3]
    # test views are not training views
    assert np.linalg.norm(eyes_train[:, None] - eyes_test[None], axis=-1).min() > 1e-3


@pytest.mark.parametrize("factor", [1, 2])
def test_json_cameras_hit_the_sphere_where_alpha(sphere_set, factor):
    for split in ("train", "test"):
        meta, images = read_split(sphere_set, split)
        for k in range(len(images)):
            alpha = area_downscale(images[k, ..., 3] / 255.0, factor)
            h, w = alpha.shape
            o, d = json_rays(meta, k, w, h)
            hit = hits_sphere(o, d, meta["scene"]["center"], meta["scene"]["radius"])
            assert iou(alpha.reshape(-1) > 0.5, hit) >= 0.98, (split, k)


@pytest.mark.parametrize("factor", [1, 2])
def test_loader_cameras_hit_the_sphere_where_alpha(sphere_set, factor):
    from shells.data.datasets import load_dataset

    for split in ("train", "test"):
        data = load_dataset(sphere_set, split, factor)
        n, h, w, _ = data.images.shape
        assert (h, w) == (RES // factor, RES // factor)
        for i in range(n):
            o, d = (t.double().numpy() for t in data.cameras.pixel_rays(i))
            d = d / np.linalg.norm(d, axis=1, keepdims=True)
            hit = hits_sphere(o, d, (0.0, 0.0, 0.0), 0.5)
            assert iou(data.alpha[i].numpy().reshape(-1) > 0.5, hit) >= 0.98, (split, i)


def test_same_seed_same_bytes_other_seed_other_cameras(tmp_path):
    kw = dict(res=16, views=2, test_views=1, spp=2)
    make_scene("sphere", tmp_path / "a", seed=5, **kw)
    make_scene("sphere", tmp_path / "b", seed=5, **kw)
    make_scene("sphere", tmp_path / "c", seed=6, **kw)
    files = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*")
                   if p.is_file())
    assert len(files) == 5  # 2 json + 3 png
    for f in files:
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f
    ta = json.loads((tmp_path / "a" / "transforms_train.json").read_text())
    tc = json.loads((tmp_path / "c" / "transforms_train.json").read_text())
    assert not np.allclose([f["transform_matrix"] for f in ta["frames"]],
                           [f["transform_matrix"] for f in tc["frames"]])


def test_fuzzy_alpha_is_soft_and_sphere_alpha_is_binary(fuzzy_set, sphere_set):
    def soft_fraction(root):  # soft pixels among the pixels showing any content
        a = read_split(root, "train")[1][..., 3] / 255.0
        return ((a > 0.05) & (a < 0.95)).sum() / (a > 0.05).sum()

    # sphere at res 40: only the one-pixel rim is fractional (~15 % of the disc's pixels)
    assert soft_fraction(sphere_set) < 0.25
    # the fuzzy ball: most of its pixels are partially transparent (measured ~0.6)
    assert soft_fraction(fuzzy_set) > 0.4
    a = read_split(fuzzy_set, "train")[1][..., 3]
    assert len(np.unique(a)) > 100  # a continuum of opacities, not a disc
    meta = read_split(fuzzy_set, "train")[0]
    assert meta["scene"]["name"] == "fuzzy-sphere" and meta["scene"]["radius"] == 0.6


def test_core_fuzz_core_is_opaque_and_coat_is_soft(core_set):
    meta, images = read_split(core_set, "train")
    s = meta["scene"]
    assert s["name"] == "core-fuzz" and s["core_radius"] == 0.3 and s["coat_radius"] == 0.6
    for k in range(len(images)):
        o, d = json_rays(meta, k, 32, 32)
        # pixels well inside the core's silhouette (no rim pixels)
        core = hits_sphere(o, d, s["center"], 0.9 * s["core_radius"])
        coat = hits_sphere(o, d, s["center"], s["coat_radius"]) & ~hits_sphere(
            o, d, s["center"], 1.1 * s["core_radius"])
        alpha = images[k, ..., 3].reshape(-1) / 255.0
        assert core.sum() > 20 and alpha[core].min() >= 0.99
        assert ((alpha[coat] > 0.05) & (alpha[coat] < 0.95)).mean() > 0.3
        assert alpha[~hits_sphere(o, d, s["center"], s["coat_radius"])].max() == 0.0


def test_exact_opacity_matches_mitsuba_absorber_render():
    # The exact alpha (ray marching Mitsuba's own gridvolume) against the Monte-Carlo
    # reference (absorbing medium under a unit environment, volpath), 256 spp.
    spec = ds.build("fuzzy-sphere", 0)
    c2w = sample_poses(np.random.default_rng(1), 1)[0]
    exact = opacity(spec, c2w, ds.CAMERA_ANGLE_X, 24)
    ref = reference_opacity(spec, c2w, ds.CAMERA_ANGLE_X, 24, spp=256)
    # per-pixel MC std <= sqrt(0.25 / 256) = 0.031; means over ~100 content pixels agree
    # to ~0.003, measured 0.0003
    assert abs(exact.mean() - ref.mean()) < 0.005
    assert np.abs(exact - ref).mean() < 0.01
    assert ((exact > 0.05) & (exact < 0.95)).sum() > 30


def test_to_rgba8_unpremultiplies_and_srgb_encodes():
    premult = np.array([[[0.25, 0.1, 0.0], [0.3, 0.3, 0.3]]])
    alpha = np.array([[0.5, 0.0]])
    out = ds.to_rgba8(premult, alpha)
    # straight (0.5, 0.2, 0): sRGB 0.7354 -> 187.5 -> 188; 0.4845 -> 123.6 -> 124; alpha 127.5
    # -> 128 (round half to even); alpha 0 -> colour 0
    assert out.tolist() == [[[188, 124, 0, 128], [0, 0, 0, 0]]]


# --------------------------------------------------------------------------------------------
# options
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs", [dict(res=4), dict(views=0), dict(test_views=0),
                                    dict(spp=0), dict(seed=-1), dict(res=32.5)])
def test_bad_options_raise_input_error(tmp_path, kwargs):
    with pytest.raises(InputError):
        make_scene("sphere", tmp_path / "out", **kwargs)
    assert not (tmp_path / "out").exists()  # nothing written


def test_unknown_scene_and_cli_exit_status(tmp_path, capsys):
    with pytest.raises(InputError, match="unknown scene 'cube'"):
        make_scene("cube", tmp_path / "out")
    from shells.cli import scene_main

    assert scene_main(["sphere", "--out", str(tmp_path / "x"), "--res", "4"]) == 2
    assert "--res 4" in capsys.readouterr().err
    assert set(SCENES) == {"sphere", "fuzzy-sphere", "core-fuzz", "thin-parts", "unbounded",
                           "white-tube", "off-centre"}


def test_unbounded_scene_closes_every_ray_with_its_room(tmp_path):
    """Issue 14's toy unbounded scene: opaque everywhere, the ball where the centre rays hit
    it, and beyond it a textured room far outside the cameras' sphere (not a constant colour).
    """
    from scenes.content import ROOM_RADIUS, SPHERE_RADIUS

    rec = make_scene("unbounded", tmp_path, res=32, views=3, test_views=1, spp=16)
    assert rec["scene"]["room_radius"] == ROOM_RADIUS > 3 * 3.0  # cameras sit at 2.6 .. 3
    room = []
    for k, frame in enumerate(rec["frames"]):
        img = iio.imread(tmp_path / "train" / f"r_{k}.png")
        assert (img[..., 3] == 255).all()
        o, d = (x[:, :, 0] for x in pixel_rays_gl(np.asarray(frame["transform_matrix"]),
                                                  rec["camera_angle_x"], 32, 32))
        b = np.einsum("hwc,hwc->hw", o, d)
        hit = b * b - (np.einsum("hwc,hwc->hw", o, o) - SPHERE_RADIUS ** 2) > 0
        assert hit[16, 16] and not hit[0, 0]
        room.append(img[~hit][:, :3])
    room = np.concatenate(room).astype(float)
    assert room.std(0).min() > 20  # a texture, not a flat background
    assert room.mean() > 40  # self-lit: visible without the lights


def test_cli_default_sphere_under_a_minute(tmp_path):
    from shells.cli import scene_main

    t0 = time.perf_counter()
    assert scene_main(["sphere", "--out", str(tmp_path), "--res", "64", "--views", "32"]) == 0
    assert time.perf_counter() - t0 < 60
    assert len(list((tmp_path / "train").glob("*.png"))) == 32


def test_even_training_poses_cover_every_side():
    # 32 Fibonacci directions: every direction lies within ~27 degrees of a camera (an equal-area
    # cap per camera has radius acos(1 - 2/32) = 20.4 degrees); independent draws leave gaps
    # of 37-51 degrees for the same count (seeds 0-3)
    from scenes.cameras import sample_poses

    chk = np.random.default_rng(5).normal(size=(20000, 3))
    chk /= np.linalg.norm(chk, axis=1, keepdims=True)

    def gap(poses):
        d = poses[:, :3, 3] / np.linalg.norm(poses[:, :3, 3], axis=1, keepdims=True)
        return np.degrees(np.arccos(np.clip((chk @ d.T).max(1), -1, 1))).max()

    for seed in range(3):
        even = sample_poses(np.random.default_rng(seed), 32, even=True)
        assert gap(even) < 30.0
        dist = np.linalg.norm(even[:, :3, 3], axis=1)
        assert (dist >= 2.6).all() and (dist <= 3.0).all()
    assert gap(sample_poses(np.random.default_rng(0), 32)) > 30.0


@pytest.mark.parametrize("name", ["white-tube", "off-centre"])
def test_exact_opacity_of_the_capture_scenes_matches_mitsuba(name):
    """The open tube (hit from outside and inside, zero wall thickness) and a medium off the
    origin: the exact alpha against Mitsuba's Monte-Carlo absorber render."""
    spec = ds.build(name, 0)
    for seed in (1, 2):
        c2w = sample_poses(np.random.default_rng(seed), 1)[0]
        exact = opacity(spec, c2w, ds.CAMERA_ANGLE_X, 24)
        ref = reference_opacity(spec, c2w, ds.CAMERA_ANGLE_X, 24, spp=256)
        assert exact.sum() > 20  # content in view
        assert abs(exact.mean() - ref.mean()) < 0.005
        assert np.abs(exact - ref).mean() < 0.01


def test_backdrop_bakes_the_background_in_with_an_opaque_alpha(tmp_path):
    """--backdrop: the same views as the transparent data set, composited on the colour in
    the stored (sRGB) values, alpha 255 everywhere; --distance moves the cameras."""
    a = make_scene("white-tube", tmp_path / "a", res=16, views=2, test_views=1, spp=4)
    b = make_scene("white-tube", tmp_path / "b", res=16, views=2, test_views=1, spp=4,
                   backdrop=(0.2, 0.4, 1.0))
    assert a["frames"] == b["frames"]
    ta = iio.imread(tmp_path / "a" / "train" / "r_0.png").astype(np.float64)
    tb = iio.imread(tmp_path / "b" / "train" / "r_0.png").astype(np.float64)
    assert (tb[..., 3] == 255).all() and (ta[..., 3] == 0).any()
    al = ta[..., 3:] / 255.0
    want = np.round(ta[..., :3] * al + np.array([0.2, 0.4, 1.0]) * 255.0 * (1 - al))
    assert np.array_equal(tb[..., :3], want)
    far = make_scene("white-tube", tmp_path / "c", res=16, views=3, test_views=1, spp=4,
                     distance=5.0)
    d = [np.linalg.norm(np.asarray(f["transform_matrix"])[:3, 3]) for f in far["frames"]]
    assert min(d) >= 0.95 * 5.0 - 1e-9 and max(d) <= 1.05 * 5.0 + 1e-9
    with pytest.raises(InputError, match="--backdrop"):
        make_scene("sphere", tmp_path / "x", res=16, backdrop=(2.0, 0.0, 0.0))
    with pytest.raises(InputError, match="--distance"):
        make_scene("sphere", tmp_path / "y", res=16, distance=1.0)
