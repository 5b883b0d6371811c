"""Camera paths: orbit / spiral geometry by hand, interpolation through the training cameras,
nerfstudio camera_path.json, and `shells-render --path` end to end (frames + MP4)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from shells.data.camera_paths import around, camera_path, from_file, interpolate, scene_frame
from shells.data.cameras import look_at, pinhole_cameras
from shells.errors import InputError

BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def ring(n: int = 8, radius: float = 3.0, height: float = 1.0):
    """Training cameras on a circle at z = height looking at the origin, world up +z."""
    eyes = [(radius * math.cos(2 * math.pi * k / n), radius * math.sin(2 * math.pi * k / n),
             height) for k in range(n)]
    c2w = torch.stack([look_at(e, (0, 0, 0), (0, 0, 1)) for e in eyes])
    return pinhole_cameras(c2w, fx=40.0, width=32, height=24)


def test_scene_frame_and_orbit_by_hand():
    cams = ring()
    centre, up, radius, elev = scene_frame(cams, BOX)
    np.testing.assert_allclose(centre, 0.0, atol=1e-7)
    np.testing.assert_allclose(up, [0, 0, 1], atol=1e-6)
    assert radius == pytest.approx(math.sqrt(10.0), rel=1e-6)
    assert elev == pytest.approx(math.atan2(1.0, 3.0), rel=1e-6)
    orbit = around(cams, BOX, 4)
    eyes = orbit.c2w[:, :3, 3].double()
    # the first frame at the first training camera, then quarter turns at the same height
    np.testing.assert_allclose(eyes.numpy(), [[3, 0, 1], [0, 3, 1], [-3, 0, 1], [0, -3, 1]],
                               atol=1e-5)
    fwd = orbit.c2w[:, :3, 2].double()  # OpenCV z: the viewing direction, at the centre
    np.testing.assert_allclose((fwd * -eyes).sum(1) / eyes.norm(dim=1), 1.0, atol=1e-6)
    assert (orbit.c2w[:, 2, 1] < 0).all()  # image "down" (+y) points against world up
    assert orbit.width == 32 and torch.allclose(orbit.fx, torch.tensor(40.0))
    half = around(cams, BOX, 2, width=16)
    assert (half.width, half.height) == (16, 12) and torch.allclose(half.fx, torch.tensor(20.0))
    spiral = around(cams, BOX, 8, spiral=True)
    z = spiral.c2w[:, 2, 3]
    assert z.max() > 1.3 and z.min() < 0.7  # the elevation swings by +-15 degrees


def test_interpolation_passes_through_the_training_cameras():
    cams = ring(4)
    path = interpolate(cams, 7)  # 2n - 1 frames: every other frame is a training camera
    for k in range(4):
        torch.testing.assert_close(path.c2w[2 * k], cams.c2w[k], atol=1e-5, rtol=0)
    mid = path.c2w[1, :3, 3]
    torch.testing.assert_close(mid, 0.5 * (cams.c2w[0, :3, 3] + cams.c2w[1, :3, 3]))
    rot = path.c2w[1, :3, :3]
    torch.testing.assert_close(rot @ rot.T, torch.eye(3), atol=1e-5, rtol=0)  # a rotation


def test_nerfstudio_camera_path_file(tmp_path):
    c2w_gl = np.eye(4)
    c2w_gl[:3, 3] = [0.0, 0.0, 4.0]  # at +z looking down -z (OpenGL camera)
    doc = {"render_width": 40, "render_height": 30, "fps": 12,
           "camera_path": [{"camera_to_world": c2w_gl.ravel().tolist(), "fov": 60.0},
                           {"camera_to_world": c2w_gl.ravel().tolist(), "fov": 90.0}]}
    f = tmp_path / "camera_path.json"
    f.write_text(json.dumps(doc))
    cams, fps = from_file(f)
    assert fps == 12 and len(cams) == 2 and (cams.width, cams.height) == (40, 30)
    assert cams.fy[0].item() == pytest.approx(15.0 / math.tan(math.radians(30.0)), rel=1e-6)
    assert cams.fy[1].item() == pytest.approx(15.0, rel=1e-6)
    np.testing.assert_allclose(cams.c2w[0, :3, 2].numpy(), [0, 0, -1], atol=1e-7)  # OpenCV fwd
    for bad in ('{"camera_path": []}', '{"x": 1}', "not json",
                '{"camera_path": [{"camera_to_world": [1, 2]}], "render_width": 4, '
                '"render_height": 4}'):
        f.write_text(bad)
        with pytest.raises(InputError, match="camera_path.json"):
            from_file(f)
    with pytest.raises(InputError, match="no such file"):
        camera_path(str(tmp_path / "nope.json"), ring(), BOX, 4)
    with pytest.raises(InputError, match="--frames"):
        around(ring(), BOX, 0)


def test_render_a_path_to_frames_and_video(tmp_path, capsys):
    import imageio.v2 as iio2

    from shells.cli import render_main
    from tests.conftest import tiny_config, trained_run

    run = trained_run(tmp_path, tiny_config())
    out = tmp_path / "orbit"
    assert render_main([str(run), "--path", "orbit", "--frames", "5", "--width", "15",
                        "--out", str(out)]) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == ["metrics.json"] + [f"r_{i:03d}.png" for i in range(5)] + [
        f"spp_{i:03d}.png" for i in range(5)] + ["video.mp4"]
    m = json.loads((out / "metrics.json").read_text())
    assert m["path"] == "orbit" and m["fps"] == 30.0 and m["psnr"] is None and m["n_views"] == 5
    video = iio2.mimread(out / "video.mp4")
    assert len(video) == 5 and video[0].shape[:2] == (16, 16)  # 15 x 15 padded to even
    # frame k is the render of path camera k (the same pixels as rendering that camera alone),
    # and the video holds it up to H.264's loss
    import imageio.v3 as iio

    from shells.data.datasets import load_dataset
    from shells.fields.drjit_field import DrJitField
    from shells.render.frame import render_image
    from shells.render.views import to_png
    from shells.run import RunDir, load_field, load_shells, read_run

    field, cfg = load_field(run)
    data = load_dataset(read_run(RunDir(run))["data"], "train")
    cams, _ = camera_path("orbit", data.cameras, data.aabb, 5, width=15)
    o, d = cams.pixel_rays(2)
    img, _ = render_image(DrJitField(field), o, d, cams.height, cams.width, cfg.render, "band",
                          load_shells(RunDir(run)), data.aabb, tuple(cfg.data.background))
    frame = iio.imread(out / "r_002.png")
    assert np.array_equal(frame, to_png(img))
    assert np.abs(video[2][:15, :15].astype(float) - frame).mean() < 8.0
    capsys.readouterr()
    assert render_main([str(run), "--path", "orbit", "--fps", "0",
                        "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--fps" in err[0] and not (tmp_path / "x").exists()
