"""Data-set loaders: tiny synthetic Blender / Instant-NGP sets, bad input, and the real data."""

from __future__ import annotations

import json
import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from shells.data.datasets import detect_format, load_dataset, read_frames
from shells.errors import InputError

DATA = Path(__file__).parents[1] / ".." / "shared" / "data"
needs_data = pytest.mark.skipif(not (DATA / "lego").is_dir() or not (DATA / "fox").is_dir(),
                                reason="../shared/data (lego, fox) not present")

ANGLE = 2 * math.atan(0.5)  # camera_angle_x with tan(angle / 2) = 0.5: fx = 0.5 W / 0.5 = W


def pose(tx: float) -> list[list[float]]:
    """OpenGL camera-to-world: identity rotation, translated along x."""
    return [[1, 0, 0, tx], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]


def rgba(w: int, h: int, k: int) -> np.ndarray:
    """Image k: pixel (0, 0) is half-transparent red (255, 0, 0, 128); the rest opaque grey."""
    a = np.full((h, w, 4), 255, dtype=np.uint8)
    a[..., :3] = 10 * k + 40
    a[0, 0] = (255, 0, 0, 128)
    return a


def write_blender(root: Path, splits=(("train", 3), ("test", 2)), w: int = 4, h: int = 2,
                  extra: dict | None = None) -> Path:
    """transforms_{split}.json + RGBA PNGs, file paths without extension (like NeRF-synthetic)."""
    k = 0
    for split, n in splits:
        (root / split).mkdir(parents=True, exist_ok=True)
        frames = []
        for _ in range(n):
            iio.imwrite(root / split / f"r_{k}.png", rgba(w, h, k))
            frames.append({"file_path": f"./{split}/r_{k}", "transform_matrix": pose(k)})
            k += 1
        data = {"camera_angle_x": ANGLE, "frames": frames, **(extra or {})}
        (root / f"transforms_{split}.json").write_text(json.dumps(data))
    return root


def write_ngp(root: Path, n: int = 10, w: int = 6, h: int = 4, **top) -> Path:
    """transforms.json + RGB PNGs (no alpha) with instant-ngp style intrinsics."""
    (root / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for k in range(n):
        iio.imwrite(root / "images" / f"{k:04d}.png", np.full((h, w, 3), 20 * k, np.uint8))
        frames.append({"file_path": f"images/{k:04d}.png", "transform_matrix": pose(k)})
    data = {"fl_x": 5.0, "fl_y": 5.5, "cx": 2.9, "cy": 2.1, "w": w, "h": h, "k1": 0.01,
            "k2": -0.02, "p1": 0.001, "p2": -0.002, "aabb_scale": 2, "frames": frames, **top}
    (root / "transforms.json").write_text(json.dumps(data))
    return root


# --------------------------------------------------------------------------------------------
# Blender format
# --------------------------------------------------------------------------------------------

def test_blender_load_composite_and_alpha(tmp_path):
    root = write_blender(tmp_path, extra={"scene": "toy", "aabb": [[-1, -2, -3], [1, 2, 3]]})
    assert detect_format(root) == "blender"
    ds = load_dataset(root, "train")
    assert ds.images.shape == (3, 2, 4, 3) and ds.alpha.shape == (3, 2, 4)
    assert ds.names == ["train/r_0.png", "train/r_1.png", "train/r_2.png"]
    assert (ds.format, ds.split, ds.background) == ("blender", "train", (1.0, 1.0, 1.0))
    # (255, 0, 0, a=128) on white: r = 1, g = b = 1 - 128/255 = 127/255 = 0.498039
    assert torch.allclose(ds.images[0, 0, 0], torch.tensor([1.0, 127 / 255, 127 / 255]))
    assert ds.alpha[0, 0, 0].item() == pytest.approx(128 / 255)
    assert ds.alpha[0, 1, 1].item() == 1.0
    assert ds.images[2, 1, 1, 0].item() == pytest.approx(60 / 255)  # opaque pixels unchanged
    # camera_angle_x with tan(angle/2) = 0.5 -> fx = fy = W = 4; principal point (2, 1)
    cams = ds.cameras
    assert (cams.width, cams.height) == (4, 2)
    assert torch.allclose(cams.fx, torch.full((3,), 4.0)) and torch.equal(cams.fx, cams.fy)
    assert torch.equal(cams.cx, torch.full((3,), 2.0)) and torch.equal(cams.cy, torch.ones(3))
    assert not cams.has_distortion
    # OpenGL -> OpenCV: columns 1 and 2 flip sign, translation kept
    assert torch.equal(cams.c2w[1], torch.tensor([[1.0, 0, 0, 1], [0, -1, 0, 0], [0, 0, -1, 4],
                                                  [0, 0, 0, 1]]))
    assert torch.equal(ds.aabb, torch.tensor([[-1.0, -2, -3], [1, 2, 3]]))
    assert ds.meta["scene"] == "toy"


def test_blender_black_background_and_straight_colour(tmp_path):
    root = write_blender(tmp_path)
    black = load_dataset(root, "test", background=(0.0, 0.0, 0.0))
    straight = load_dataset(root, "test", background=None)
    # image k = 3 is the first test image; red pixel premultiplied: (128/255, 0, 0)
    assert torch.allclose(black.images[0, 0, 0], torch.tensor([128 / 255, 0.0, 0.0]))
    assert torch.equal(straight.images[0, 0, 0], torch.tensor([1.0, 0.0, 0.0]))
    assert straight.background is None
    assert torch.equal(load_dataset(root, "train").aabb, torch.tensor([[-1.5] * 3, [1.5] * 3]))


def test_blender_splits(tmp_path):
    root = write_blender(tmp_path, splits=(("train", 3), ("val", 1), ("test", 2)))
    assert len(load_dataset(root, "test")) == 2
    assert read_frames(root, "val").names == ["val/r_3.png"]
    assert read_frames(root, "all").names == [f"{s}/r_{k}.png" for s, k in
                                              [("train", 0), ("train", 1), ("train", 2),
                                               ("val", 3), ("test", 4), ("test", 5)]]
    with pytest.raises(InputError, match=r"unknown split 'tset'.*'test'"):
        load_dataset(root, "tset")


def test_a_subset_of_views_is_those_frames_of_the_split(tmp_path):
    root = write_blender(tmp_path, splits=(("train", 4),))
    full, part = load_dataset(root, "train"), load_dataset(root, "train", views=[3, 1])
    assert part.names == [full.names[3], full.names[1]]
    assert torch.equal(part.images, full.images[[3, 1]])
    assert torch.equal(part.alpha, full.alpha[[3, 1]])
    assert torch.equal(part.cameras.c2w, full.cameras.c2w[[3, 1]])


def test_downscale_area_average(tmp_path):
    # 5x3 image, factor 2 -> 2x1 (the last column and row are cropped)
    root = write_blender(tmp_path, splits=(("train", 1),), w=5, h=3)
    full = load_dataset(root, "train")
    ds = load_dataset(root, "train", downscale=2)
    assert ds.images.shape == (1, 1, 2, 3)
    # block (0, 0): composited red pixel (1, 127/255, 127/255) and three grey 40/255 pixels
    g = 40 / 255
    assert torch.allclose(ds.images[0, 0, 0], torch.tensor([(1 + 3 * g) / 4,
                                                            (127 / 255 + 3 * g) / 4,
                                                            (127 / 255 + 3 * g) / 4]))
    assert ds.alpha[0, 0, 0].item() == pytest.approx((128 / 255 + 3) / 4)
    assert torch.allclose(ds.images[0, 0, 1], full.images[0, :2, 2:4].mean(dim=(0, 1)))
    assert ds.cameras.fx.item() == pytest.approx(2.5) and ds.cameras.cx.item() == 1.25
    # straight colour averages with alpha weights: red weighs 128/255 against three greys
    st = load_dataset(root, "train", downscale=2, background=None)
    a = 128 / 255
    assert st.images[0, 0, 0, 0].item() == pytest.approx((a + 3 * g) / (a + 3), rel=1e-6)
    with pytest.raises(InputError, match="downscale"):
        load_dataset(root, downscale=0)


def test_mixed_alpha_counts_as_opaque(tmp_path):
    root = write_blender(tmp_path, splits=(("train", 2),))
    iio.imwrite(root / "train" / "r_1.png", np.full((2, 4, 3), 200, np.uint8))  # RGB, no alpha
    ds = load_dataset(root)
    assert ds.alpha is not None and torch.equal(ds.alpha[1], torch.ones(2, 4))
    assert torch.allclose(ds.images[1], torch.full((2, 4, 3), 200 / 255))


def test_sixteen_bit_grey_png(tmp_path):
    root = write_blender(tmp_path, splits=(("train", 1),))
    iio.imwrite(root / "train" / "r_0.png", np.full((2, 4), 32768, np.uint16))
    ds = load_dataset(root)
    assert ds.alpha is None
    assert torch.allclose(ds.images[0, 1, 3], torch.full((3,), 32768 / 65535))


# --------------------------------------------------------------------------------------------
# Instant-NGP format
# --------------------------------------------------------------------------------------------

def test_ngp_intrinsics_holdout_and_aabb(tmp_path):
    root = write_ngp(tmp_path, scale=0.5, offset=[0.5, 0.5, 0.5])
    assert detect_format(root) == "ngp"
    test = load_dataset(root, "test")
    train = load_dataset(root, "train")
    assert test.names == ["images/0000.png", "images/0008.png"]  # every 8th frame, from 0
    assert len(train) == 8 and "images/0008.png" not in train.names
    assert len(load_dataset(root, "all")) == 10
    assert test.alpha is None and test.images[1, 0, 0, 0].item() == pytest.approx(160 / 255)
    c = test.cameras
    assert (c.width, c.height) == (6, 4)
    assert c.fx[0].item() == 5.0 and c.fy[0].item() == 5.5
    assert c.cx[0].item() == pytest.approx(2.9) and c.cy[0].item() == pytest.approx(2.1)
    assert torch.allclose(c.dist[0], torch.tensor([0.01, -0.02, 0.001, -0.002]))
    # unit-cube box [0.5 -+ aabb_scale/2] = [-0.5, 1.5]; world = (box - 0.5) / 0.5 = [-2, 2]
    assert torch.allclose(test.aabb, torch.tensor([[-2.0] * 3, [2.0] * 3]))
    # instant-ngp defaults scale 0.33, offset 0.5: aabb_scale 2 -> +-1 / 0.33
    root2 = write_ngp(tmp_path / "b")
    assert torch.allclose(read_frames(root2).aabb[1], torch.full((3,), 1 / 0.33))


def test_ngp_per_frame_intrinsics_and_angle_fallback(tmp_path):
    root = write_ngp(tmp_path, n=2)
    data = json.loads((root / "transforms.json").read_text())
    for key in ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "p1", "p2", "w", "h"):
        del data[key]
    data["camera_angle_x"] = ANGLE  # fx = fy = W = 6, centre (3, 2), no distortion
    data["frames"][1].update(fl_x=7.0, cy=1.0, k1=0.1)
    (root / "transforms.json").write_text(json.dumps(data))
    c = read_frames(root, "all").cameras
    assert torch.allclose(c.fx, torch.tensor([6.0, 7.0]))
    # no fl_y / camera_angle_y: square pixels, fy follows each frame's fx
    assert torch.allclose(c.fy, torch.tensor([6.0, 7.0]))
    assert torch.allclose(c.cx, torch.tensor([3.0, 3.0]))
    assert torch.allclose(c.cy, torch.tensor([2.0, 1.0]))
    assert torch.allclose(c.dist[:, 0], torch.tensor([0.0, 0.1]))


def test_ngp_explicit_split_file_and_missing_images(tmp_path):
    root = write_ngp(tmp_path)
    (root / "images" / "0003.png").unlink()
    with pytest.warns(UserWarning, match="skipped 1 of 10"):
        fr = read_frames(root, "all")
    assert len(fr.names) == 9 and fr.meta["skipped_frames"] == ["images/0003.png"]
    with pytest.warns(UserWarning):
        assert read_frames(root, "test").names == ["images/0000.png", "images/0009.png"]
    with pytest.raises(InputError, match="0003.png"):
        read_frames(root, "all", skip_missing=False)
    data = json.loads((root / "transforms.json").read_text())
    data["frames"] = data["frames"][5:7]
    (root / "transforms_val.json").write_text(json.dumps(data))
    assert read_frames(root, "val").names == ["images/0005.png", "images/0006.png"]


# --------------------------------------------------------------------------------------------
# Bad input: one-line InputError naming the offending file
# --------------------------------------------------------------------------------------------

def _edit(path: Path, fn) -> None:
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


def test_missing_directory_and_transforms(tmp_path):
    with pytest.raises(InputError, match="nowhere: data directory not found"):
        load_dataset(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="empty: no transforms.json"):
        load_dataset(tmp_path / "empty")
    root = write_blender(tmp_path / "b", splits=(("train", 1),))
    with pytest.raises(InputError, match="unknown split 'test'"):
        load_dataset(root, "test")


def test_malformed_json(tmp_path):
    root = write_blender(tmp_path)
    (root / "transforms_train.json").write_text('{"frames": [')
    with pytest.raises(InputError, match=r"transforms_train.json: malformed JSON"):
        load_dataset(root)
    (root / "transforms_train.json").write_text('{"camera_angle_x": 1}')
    with pytest.raises(InputError, match=r"transforms_train.json: expected .*'frames'"):
        load_dataset(root)


def test_frame_without_pose_or_bad_pose(tmp_path):
    root = write_blender(tmp_path)
    src = root / "transforms_train.json"
    _edit(src, lambda d: d["frames"][1].pop("transform_matrix"))
    with pytest.raises(InputError, match=r"transforms_train.json: frame 1 .*no 'transform_matrix'"):
        load_dataset(root)
    src.write_text(src.read_text().replace('"frames": [', '"frames": [{"file_path": "./train/r_0",'
                                           ' "transform_matrix": [[NaN, 0, 0, 0], [0, 1, 0, 0],'
                                           ' [0, 0, 1, 0], [0, 0, 0, 1]]}, '))
    with pytest.raises(InputError, match=r"transforms_train.json: frame 0 .*non-finite"):
        load_dataset(root)
    _edit(src, lambda d: d["frames"].__setitem__(0, {"file_path": "./train/r_0",
                                                     "transform_matrix": [[1, 0], [0, 1]]}))
    with pytest.raises(InputError, match=r"transforms_train.json: frame 0 .*4x4"):
        load_dataset(root)


def test_missing_image_and_size_mismatch(tmp_path):
    root = write_blender(tmp_path)
    (root / "train" / "r_1.png").unlink()
    with pytest.raises(InputError, match=r"train/r_1: image file of frame 1"):
        load_dataset(root)
    iio.imwrite(root / "train" / "r_1.png", rgba(5, 2, 1))
    with pytest.raises(InputError, match=r"r_1.png: image is 5x2 but train/r_0.png is 4x2"):
        load_dataset(root)
    root = write_ngp(tmp_path / "ngp")
    _edit(root / "transforms.json", lambda d: d.update(w=7))  # the images are 6 wide
    with pytest.raises(InputError, match=r"transforms.json: 'w', 'h' = 7x4 .* 0001.png is 6x4"):
        load_dataset(root)
    _edit(root / "transforms.json", lambda d: d.update(w=6, k3=0.1))
    with pytest.raises(InputError, match="transforms.json: fisheye / k3"):
        load_dataset(root)


def test_missing_focal_and_bad_aabb(tmp_path):
    root = write_blender(tmp_path, splits=(("train", 1),))
    _edit(root / "transforms_train.json", lambda d: d.pop("camera_angle_x"))
    with pytest.raises(InputError, match="transforms_train.json: no focal length"):
        load_dataset(root)
    _edit(root / "transforms_train.json", lambda d: d.update(camera_angle_x=1.0,
                                                             aabb=[[1, 1, 1], [0, 2, 2]]))
    with pytest.raises(InputError, match=r"transforms_train.json: 'aabb'"):
        load_dataset(root)
    _edit(root / "transforms_train.json", lambda d: (d.pop("aabb"), d.update(fl_x="abc")))
    with pytest.raises(InputError, match=r"transforms_train.json: intrinsics .* not numbers"):
        load_dataset(root)
    _edit(root / "transforms_train.json", lambda d: d.update(fl_x=-3.0))
    with pytest.raises(InputError, match=r"transforms_train.json: focal lengths"):
        load_dataset(root)
    ngp = write_ngp(tmp_path / "ngp", scale=-1.0)
    with pytest.raises(InputError, match=r"transforms.json: 'scale'"):
        load_dataset(ngp)


def test_errors_are_one_line(tmp_path):
    root = write_blender(tmp_path)
    (root / "transforms_train.json").write_text("{\n\n oops")
    with pytest.raises(InputError) as info:
        load_dataset(root)
    assert "\n" not in str(info.value)


# --------------------------------------------------------------------------------------------
# Real data (../shared/data)
# --------------------------------------------------------------------------------------------

@pytest.mark.data
@needs_data
def test_lego_splits_and_intrinsics():
    train = read_frames(DATA / "lego", "train")
    test = read_frames(DATA / "lego", "test")
    assert (len(train.names), len(test.names)) == (87, 13)
    assert test.names[:2] == ["train/r_0.png", "train/r_8.png"]
    c = train.cameras
    assert (c.width, c.height) == (800, 800)
    angle = json.loads((DATA / "lego" / "transforms_train.json").read_text())["camera_angle_x"]
    assert c.fx[0].item() == pytest.approx(0.5 * 800 / math.tan(0.5 * angle))  # 1111.111
    assert c.cx[0].item() == 400.0 and not c.has_distortion
    assert torch.equal(train.aabb, torch.tensor([[-1.5] * 3, [1.5] * 3]))


@pytest.mark.data
@needs_data
def test_lego_downscale_8():
    ds = load_dataset(DATA / "lego", "test", downscale=8)
    assert ds.images.shape == (13, 100, 100, 3) and ds.alpha.shape == (13, 100, 100)
    assert ds.cameras.fx[0].item() == pytest.approx(1111.111 / 8, rel=1e-6)
    # reference: composite r_0 on white in numpy, then average 8x8 blocks
    a = iio.imread(DATA / "lego" / "train" / "r_0.png").astype(np.float64) / 255
    comp = a[..., :3] * a[..., 3:] + (1 - a[..., 3:])
    ref = comp.reshape(100, 8, 100, 8, 3).mean(axis=(1, 3))
    assert np.abs(ds.images[0].numpy() - ref).max() < 1e-5  # float32 accumulation
    assert (ds.alpha[0] > 0.99).float().mean() > 0.05  # the model is opaque ...
    assert (ds.alpha[0] < 0.01).float().mean() > 0.3  # ... on a transparent background


@pytest.mark.data
@needs_data
def test_fox_holdout_intrinsics_and_distortion():
    data = json.loads((DATA / "fox" / "transforms.json").read_text())
    with pytest.warns(UserWarning, match="skipped"):  # the JSON lists 67 frames, 50 images ship
        train = read_frames(DATA / "fox", "train")
    with pytest.warns(UserWarning):
        test = read_frames(DATA / "fox", "test")
    assert (len(train.names), len(test.names)) == (43, 7)
    assert not set(train.names) & set(test.names)
    c = test.cameras
    shape = iio.improps(DATA / "fox" / test.names[0]).shape
    assert (c.width, c.height) == (1080, 1920) == (shape[1], shape[0]) == (data["w"], data["h"])
    for name, value in [("fx", "fl_x"), ("fy", "fl_y"), ("cx", "cx"), ("cy", "cy")]:
        assert torch.allclose(getattr(c, name), torch.tensor(float(data[value])))
    assert torch.allclose(c.dist, torch.tensor([[data[k] for k in ("k1", "k2", "p1", "p2")]]))
    assert c.has_distortion
    frame = next(f for f in data["frames"] if f["file_path"] == test.names[0])
    gl = torch.tensor(frame["transform_matrix"], dtype=torch.float32)
    assert torch.allclose(c.c2w[0][:, 0], gl[:, 0])
    assert torch.allclose(c.c2w[0][:, 1:3], -gl[:, 1:3])  # OpenGL -> OpenCV
    # aabb_scale 4 with instant-ngp's default scale 0.33: +-2 / 0.33 world units
    assert torch.allclose(test.aabb, torch.tensor([[-2 / 0.33] * 3, [2 / 0.33] * 3]))


@pytest.mark.data
@needs_data
def test_fox_test_split_downscaled():
    with pytest.warns(UserWarning, match="skipped 17 of 67"):
        ds = load_dataset(DATA / "fox", "test", downscale=8)
    assert ds.images.shape == (7, 240, 135, 3) and ds.alpha is None
    assert 0.1 < ds.images.mean().item() < 0.9
