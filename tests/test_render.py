"""Dr.Jit rendering: NeuS alpha and compositing by hand, band vs full on an analytic sphere."""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import torch
import trimesh

from shells.config import RenderConfig
from shells.device import mitsuba_variant
from shells.errors import InputError
from shells.metrics import psnr
from shells.fields import neus
from shells.fields.drjit_field import DrJitField, FieldSample
from shells.fields.neus import neus_alpha
from shells.render.band import render_band_rays
from shells.render.frame import render_image, render_rays
from shells.render.shading import composite_packed
from shells.render.raycast import ShellScene

AABB = [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]


class SphereField:
    """Analytic field: SDF of a sphere, constant kernel s, colour 0.5 + 0.5 n (normal-shaded)."""

    def __init__(self, radius: float = 0.5, s: float = 0.005) -> None:
        self.radius, self.s = radius, s

    def eval(self, x, d):  # x, d: [M] 3-vectors -> sdf [M], s [M], normal [M], rgb [M]
        r = dr.norm(x)
        n = x / dr.maximum(r, 1e-8)
        return FieldSample(sdf=r - self.radius, s=dr.full(mi.Float, self.s, dr.width(r)),
                           normal=n, rgb=mi.Color3f(0.5 + 0.5 * n))


class TorchSphere(torch.nn.Module):
    """The SphereField as a torch module (the interface of ShellField: field(x, d) -> dict)."""

    def __init__(self, radius: float = 0.5, s: float = 0.005) -> None:
        super().__init__()
        self.radius, self.s = radius, s

    def forward(self, x, d):  # x, d: [N, 3]
        r = x.norm(dim=-1)
        n = x / r.clamp_min(1e-8)[:, None]
        return {"sdf": r - self.radius, "s": torch.full_like(r, self.s), "normal": n,
                "rgb": 0.5 + 0.5 * n}


WHITE = torch.ones(3)


def camera_rays(width: int, height: int, dist: float = 2.5, fov: float = 0.7):
    """Pinhole camera on the -z axis looking at the origin: origins, dirs [H * W, 3]."""
    j, i = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    f = 0.5 * width / math.tan(fov / 2)
    d = torch.stack([(i - width / 2) / f, -(j - height / 2) / f, torch.ones_like(i)], -1)
    d = torch.nn.functional.normalize(d.reshape(-1, 3), dim=-1)
    o = torch.tensor([0.0, 0.0, -dist]).expand_as(d).contiguous()
    return o, d


@pytest.fixture(scope="module")
def shells():
    mitsuba_variant()
    outer = trimesh.creation.icosphere(subdivisions=5, radius=0.6)
    inner = trimesh.creation.icosphere(subdivisions=5, radius=0.4)
    return ShellScene((outer.vertices, outer.faces), (inner.vertices, inner.faces))


def test_neus_alpha_hand_worked():
    mitsuba_variant()
    sdf = mi.Float([0.0, 0.0, 1.0])
    s = mi.Float([1.0, 1.0, 0.01])
    cos = mi.Float([-1.0, 0.5, -1.0])
    delta = mi.Float([2.0, 2.0, 0.1])
    a = neus_alpha(sdf, s, cos, delta).numpy()
    # 0: f_prev = 1, f_next = -1: (sig(1) - sig(-1)) / sig(1) = (0.731059 - 0.268941) / 0.731059
    #    = 0.632121 (= 1 - e^-1)
    # 1: facing away (cos > 0): c = 0, f_prev = f_next -> 0
    # 2: far outside (f = 1 >> s): both sigmoids = 1 -> 0
    np.testing.assert_allclose(a, [1 - math.exp(-1), 0.0, 0.0], atol=1e-6)


def test_composite_hand_worked():
    mitsuba_variant()
    alpha = mi.Float([0.5, 0.5, 1.0, 0.2])
    rgb = mi.Color3f([1.0, 0.0, 0.0, 0.3], [0.0, 1.0, 0.0, 0.3], [0.0, 0.0, 1.0, 0.3])
    start, count = mi.UInt32([0, 3, 4]), mi.UInt32([3, 1, 0])
    colour, opacity = composite_packed(alpha, rgb, start, count, mi.Color3f(1.0, 1.0, 1.0))
    # ray 0: T = [1, 0.5, 0.25] -> weights [0.5, 0.25, 0.25], T_end = 0: (0.5, 0.25, 0.25)
    # ray 1: weight 0.2 on 0.3 grey + 0.8 white = 0.86; ray 2: no samples -> background
    np.testing.assert_allclose(np.asarray(colour).T, [[0.5, 0.25, 0.25], [0.86] * 3, [1.0] * 3],
                               atol=1e-6)
    np.testing.assert_allclose(opacity.numpy(), [1.0, 0.2, 0.0], atol=1e-6)


def test_composite_matches_torch_reference():
    """Packed Dr.Jit compositing vs the padded torch reference (shells.fields.neus.composite)."""
    mitsuba_variant()
    g = torch.Generator().manual_seed(0)
    R, S = 50, 7
    counts = torch.randint(0, S + 1, (R,), generator=g)
    mask = torch.arange(S)[None] < counts[:, None]
    alpha = torch.rand(R, S, generator=g) * mask  # padded slots: alpha 0 = no effect
    rgb = torch.rand(R, S, 3, generator=g)
    bg = torch.tensor([0.2, 0.4, 0.6])
    want, _, want_opacity = neus.composite(alpha, rgb, bg)
    start = torch.cumsum(counts, 0) - counts
    colour, opacity = composite_packed(mi.Float(alpha[mask].numpy()),
                                mi.Color3f(*[mi.Float(rgb[mask][:, c].numpy()) for c in range(3)]),
                                mi.UInt32(start.numpy().astype(np.uint32)),
                                mi.UInt32(counts.numpy().astype(np.uint32)), mi.Color3f(*bg.tolist()))
    # float32, <= 7 products and sums in a different order: agreement to ~1e-6
    np.testing.assert_allclose(np.asarray(colour).T, want.numpy(), atol=2e-6)
    np.testing.assert_allclose(opacity.numpy(), want_opacity.numpy(), atol=2e-6)


def test_packed_drjit_band_render_matches_padded_torch_reference(shells):
    o, d = camera_rays(24, 24)
    cfg = RenderConfig(band_ert_eps=0.0)  # every sample, as the torch renderer takes them
    ref = render_band_rays(TorchSphere(), shells, o, d, cfg, WHITE)
    want, want_spp = ref["color"], ref["spp"]
    colour, spp = render_rays(SphereField(), o, d, cfg, "band", scene=shells)
    got = torch.from_numpy(np.asarray(colour).T.copy())
    assert torch.equal(torch.from_numpy(spp.numpy().astype(np.int64)), want_spp)
    # same samples and formula, float32 sums in a different order: measured 4e-7
    assert (got - want).abs().max() < 5e-6


def test_trained_field_twin_band_render_matches_torch(shells):
    """The real field (geometric init: a sphere of radius 0.5, inside the 0.4-0.6 band) through
    DrJitField + packed Dr.Jit compositing vs ShellField + padded torch compositing."""
    from shells.presets import toy_config
    from shells.fields.network import ShellField

    torch.manual_seed(0)
    field = ShellField(toy_config().field, torch.tensor(AABB)).eval()

    o, d = camera_rays(16, 16)
    cfg = RenderConfig(band_ert_eps=0.0)
    with torch.no_grad():
        ref = render_band_rays(field, shells, o, d, cfg, WHITE)
    want, want_spp = ref["color"], ref["spp"]
    colour, spp = render_rays(DrJitField(field), o, d, cfg, "band", scene=shells)
    got = torch.from_numpy(np.asarray(colour).T.copy())
    assert torch.equal(torch.from_numpy(spp.numpy().astype(np.int64)), want_spp)
    assert (want_spp > 0).any() and (want < 0.99).any()  # the surface is visible
    # DrJitField vs ShellField: fp32 rounding in grid and MLPs (grid features may differ by up
    # to 5e-5, DESIGN.md); measured 3e-7 on the colour here
    assert (got - want).abs().max() < 1e-4


def test_band_and_full_agree_on_analytic_sphere(shells):
    cfg = RenderConfig()  # w_s = delta_s = 0.01, n_max = 16, full_samples = 256
    o, d = camera_rays(64, 64)
    band, spp_band = render_image(SphereField(), o, d, 64, 64, cfg, "band", scene=shells)
    full, spp_full = render_image(SphereField(), o, d, 64, 64, cfg, "full", aabb=AABB)
    assert band.shape == (64, 64, 3) and spp_band.shape == (64, 64)
    # measured 50 dB: only silhouette pixels differ (different sample positions there)
    assert psnr(band, full) > 35.0
    covered = spp_band > 0
    assert spp_full.float().mean() == 256.0  # every ray of this camera crosses the box
    # band: <= 16 samples per covered pixel (the 0.2-wide band, N_max = 16); measured ~5.7 mean
    assert spp_band.max() <= 16 and spp_band.float().mean() < 256.0 / 20
    # pixels whose rays miss the outer shell show the white background exactly
    assert torch.equal(band[~covered], torch.ones_like(band[~covered]))
    # centre pixel sees the sphere's front at n ~ (0, 0, -1): colour ~ (0.5, 0.5, 0)
    np.testing.assert_allclose(band[32, 32].numpy(), [0.5, 0.5, 0.0], atol=0.03)


def test_band_early_termination_differs_by_no_more_than_the_light_left(shells):
    # Band mode's early ray termination (`render.band_ert_eps`, rounds of `band_chunk`
    # samples) against every sample of Procedure 3: a pixel moves by no more than the
    # transmittance at which its ray stopped, and the rays through the opaque sphere stop
    # early: the centre ray has 16 samples 0.0125 apart in the 0.2 of band, the surface after
    # 8 of them; past it each section keeps e^(-0.0125 / s) = 8 % of the light, so T < 1e-4
    # about 4 samples later.
    o, d = camera_rays(32, 32)
    img, spp = render_image(SphereField(), o, d, 32, 32, RenderConfig(band_ert_eps=0.0),
                            "band", scene=shells)
    for eps in (1e-4, 0.05):
        for chunk in (1, 3):
            cfg = RenderConfig(band_ert_eps=eps, band_chunk=chunk)
            img2, spp2 = render_image(SphereField(), o, d, 32, 32, cfg, "band", scene=shells)
            assert (img2 - img).abs().max() <= eps + 1e-6
            assert (spp2 <= spp).all()
            assert spp[16, 16].item() == 16 and spp2[16, 16].item() < 16
    covered = spp > 0
    assert spp2[covered].float().mean() < 0.75 * spp[covered].float().mean()


def test_band_peeled_on_demand_renders_what_one_peel_renders(monkeypatch):
    # `render.band_peel_step`: every ray peels its first 2 M+ hits, and only the rays still
    # letting light through once those are shaded peel on, 2 hits at a time. M+ is a shell
    # around the opaque sphere and a second one behind it (z = 1.2; the field is empty
    # there). The rays through the sphere stop in their first interval and never cast against
    # the one behind; the rays past its rim resume. Each pixel moves by no more than the light
    # left where its ray stopped, and the resumed rays are a small share of the covered ones.
    mitsuba_variant()
    front, back = trimesh.creation.icosphere(5, 0.6), trimesh.creation.icosphere(4, 0.3)
    back.apply_translation((0.0, 0.0, 1.2))
    both = trimesh.util.concatenate([front, back])
    scene = ShellScene((both.vertices, both.faces))
    o, d = camera_rays(32, 32, fov=0.9)
    resumed = []
    resume = ShellScene.resume

    def counting(self, o, d, state, dp_max, hits=None, mode="symbolic"):
        resumed.append(dr.width(d))
        return resume(self, o, d, state, dp_max, hits, mode)

    monkeypatch.setattr(ShellScene, "resume", counting)
    for eps in (1e-4, 0.05):
        for chunk in (1, 3):
            cfg = RenderConfig(band_ert_eps=eps, band_chunk=chunk)
            img, spp = render_image(SphereField(), o, d, 32, 32, cfg, "band", scene=scene)
            assert resumed == []
            cfg.band_peel_step = 2
            img2, spp2 = render_image(SphereField(), o, d, 32, 32, cfg, "band", scene=scene)
            assert (img2 - img).abs().max() <= eps + 1e-6
            assert torch.equal(spp2 > 0, spp > 0)
            assert abs(int(spp2.sum()) - int(spp.sum())) <= 0.02 * int(spp.sum())
            covered = int((spp > 0).sum())
            # steps of 2 hits up to dp_max 8: at most 3 resumptions, each of fewer rays
            assert 1 <= len(resumed) <= 3 and resumed == sorted(resumed, reverse=True)
            assert 0 < resumed[0] < 0.5 * covered, (resumed, covered)
            resumed.clear()
    assert torch.equal(img2[0, 0], torch.ones(3))  # a ray missing both shells


def test_band_batches_shade_their_samples_in_groups_within_the_budget(shells, monkeypatch):
    # A band batch holds its rays, not their worst-case samples; samples beyond the budget are
    # placed and shaded in consecutive groups of rays. With a budget of 100 samples the 32 x 32
    # frame (measured: about 5 samples per covered pixel, 2600 in all) takes dozens of groups,
    # every one within the budget unless a single ray has more, and gives the one-batch image
    # and counts bit for bit; so do the refinement's extras (opacity, normal).
    import shells.render.frame as frame
    from shells.render.frame import ray_groups, render_intervals
    from shells.render.raycast import to_point3f

    # 3 + 0 + 4 = 7 fits; 5 + 9 does not; 9 > 7 alone; then 1
    assert ray_groups(mi.UInt32([3, 0, 4, 5, 9, 1]), 7) == [(0, 3), (3, 4), (4, 5), (5, 6)]
    assert ray_groups(mi.UInt32([1, 1, 1, 1]), 100) == [(0, 4)]
    o, d = camera_rays(32, 32)
    cfg = RenderConfig()
    whole, spp = render_image(SphereField(), o, d, 32, 32, cfg, "band", scene=shells)
    iv = shells.intervals(o, d, cfg.dp_max)
    O, D = to_point3f(o), to_point3f(d, mi.Vector3f)
    ref = render_intervals(SphereField(), O, D, iv, cfg, extras=True)
    seen = []
    place = frame.place_packed

    def counting(iv, cfg, **kw):
        samples = place(iv, cfg, **kw)
        seen.append(int(dr.sum(samples.count)[0]))
        return samples

    monkeypatch.setattr(frame, "place_packed", counting)
    monkeypatch.setattr(frame, "sample_budget", lambda cfg: 100)
    grouped, spp2 = render_image(SphereField(), o, d, 32, 32, cfg, "band", scene=shells)
    assert len(seen) > 20 and max(seen) <= 100 and sum(seen) == int(spp.sum()) > 2000
    assert torch.equal(grouped, whole) and torch.equal(spp2, spp)
    got = render_intervals(SphereField(), O, D, iv, cfg, extras=True)
    for a, b in zip(got, ref):
        assert np.array_equal(np.asarray(a), np.asarray(b))
    assert float(dr.max(got[2])[0]) == 1.0  # opaque rays: the extras are not all zero


def test_spp_averages_the_sub_pixel_rays(shells):
    # cfg.spp = 4: a pixel's colour is the mean of its 4 rays and its sample count their sum,
    # exactly as four separate one-ray renders of the same rays
    from shells.data.cameras import pinhole_cameras

    # OpenCV camera at z = -2 looking at the sphere (radius 0.5: ~5 px of the 16 px image)
    c2w = torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -2.0], [0, 0, 0, 1]])
    cams = pinhole_cameras(c2w, fx=20.0, width=16, height=16)
    o, d = cams.pixel_rays(0, spp=4)  # [16 * 16 * 4, 3]
    cfg = RenderConfig(spp=4)
    img, spp = render_image(SphereField(), o, d, 16, 16, cfg, "band", scene=shells)
    one = RenderConfig()
    parts = [render_image(SphereField(), o[k::4], d[k::4], 16, 16, one, "band", scene=shells)
             for k in range(4)]
    want = torch.stack([p[0] for p in parts]).mean(0)
    assert torch.allclose(img, want, atol=1e-6)
    assert torch.equal(spp, sum(p[1] for p in parts))
    edge = (want < 0.99).any(-1) & (want > 0.01).any(-1)
    assert edge.any()  # some pixels are partly covered: the average matters there
    with pytest.raises(InputError):
        render_image(SphereField(), o[:256], d[:256], 16, 16, cfg, "band", scene=shells)


def test_band_render_respects_background(shells):
    o = torch.tensor([[0.0, 0.0, -2.5], [0.0, 0.9, -2.5]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    colour, count = render_rays(SphereField(), o, d, RenderConfig(), "band", scene=shells,
                                background=(0.0, 0.0, 0.0))
    # ray 1 misses M+ (offset 0.9 > 0.6): zero samples, black background
    assert count.numpy().tolist()[1] == 0
    np.testing.assert_allclose(np.asarray(colour)[:, 1], [0.0, 0.0, 0.0])
    assert np.asarray(colour)[2, 0] < 0.05  # blue of a -z facing normal: 0.5 + 0.5 * -1 = 0


def test_bad_mode_raises(shells):
    o, d = camera_rays(4, 4)
    with pytest.raises(InputError):
        render_rays(SphereField(), o, d, RenderConfig(), "dense", scene=shells)
    with pytest.raises(InputError):
        render_rays(SphereField(), o, d, RenderConfig(), "band", scene=None)


# ---------------------------------------------------------------------------------------------
# shells-render: views of a split -> PNGs + metrics (toy field), and the run-level errors
# ---------------------------------------------------------------------------------------------

def test_render_views_writes_images_and_metrics(shells, tmp_path, tiny_blender):
    from shells.data.datasets import load_dataset
    from shells.render.views import render_views

    data = load_dataset(tiny_blender, "test")  # 2 views, 16x16, cameras 3 units from the origin
    cfg = RenderConfig()
    out = tmp_path / "out"
    out.mkdir()
    m = render_views(SphereField(), data.cameras, data.images, cfg, "band", shells, data.aabb,
                     out, progress=False)
    assert sorted(p.name for p in out.iterdir()) == [
        "r_000.png", "r_001.png", "spp_000.png", "spp_001.png"]
    assert (m["width"], m["height"], m["n_views"]) == (16, 16, 2)
    assert 0 < m["samples_per_pixel"] < m["samples_per_covered_pixel"] <= 16
    assert m["ms_per_frame"] > 0 and isinstance(m["psnr"], float) and len(m["psnr_per_view"]) == 2
    # a resized render: intrinsics scale with the image, so the sphere covers the same fraction
    half = data.cameras.resized(8, None)
    assert (half.width, half.height) == (8, 8)
    assert torch.allclose(half.fx, data.cameras.fx / 2) and torch.allclose(half.cx, data.cameras.cx / 2)
    m8 = render_views(SphereField(), half, None, cfg, "band", shells, data.aabb, out,
                      progress=False)
    assert m8["psnr"] is None and m8["ssim"] is None
    assert m8["covered_fraction"] == pytest.approx(m["covered_fraction"], abs=0.1)


def test_heatmap_ends():
    from shells.render.views import heatmap

    h = heatmap(torch.tensor([[0, 8, 16]]), 16.0)
    assert h.shape == (1, 3, 3) and h.dtype == np.uint8
    assert h[0, 0].tolist() == [0, 0, 0] and h[0, 2].tolist() == [255, 255, 160]


def test_render_run_errors_write_nothing(tmp_path):
    from shells.files import write_json
    from shells.pipeline import render_run

    run = tmp_path / "run"
    run.mkdir()
    with pytest.raises(InputError, match="run.json"):
        render_run(run)
    write_json(run / "run.json", {"data": str(tmp_path / "data"), "downscale": 1})
    with pytest.raises(InputError, match="shells-train"):
        render_run(run)
    (run / "checkpoint.pt").write_bytes(b"")
    with pytest.raises(InputError, match="shells-extract"):
        render_run(run, mode="band")
    with pytest.raises(InputError, match="--mode"):
        render_run(run, mode="dense")
    assert sorted(p.name for p in run.iterdir()) == ["checkpoint.pt", "run.json"]


def test_render_run_end_to_end(tmp_path, tiny_blender):
    """A run directory as the pipeline leaves it (untrained field: geometric-init sphere r = 0.5,
    shells at 0.6 / 0.4) -> images, heatmaps and metrics.json; full mode at a reduced size."""
    import json

    from shells.presets import toy_config
    from shells.files import write_json
    from shells.fields.network import ShellField
    from shells.train.optim import make_optimizer
    from shells.pipeline import render_run
    from shells.run import save_checkpoint
    from shells.train.stage1 import build_field

    run = tmp_path / "run"
    cfg = toy_config()
    cfg.render.full_samples = 32  # keep the full-mode part of this test fast
    torch.manual_seed(0)
    field = build_field(cfg, torch.tensor(AABB), torch.device("cpu"))
    assert isinstance(field, ShellField)
    save_checkpoint(run / "checkpoint.pt", field, make_optimizer(field, 1e-2, 1e-3), 0, cfg)
    write_json(run / "run.json", {"data": str(tiny_blender), "downscale": 1})
    (run / "shells").mkdir()
    trimesh.creation.icosphere(subdivisions=3, radius=0.6).export(run / "shells" / "outer.ply")
    trimesh.creation.icosphere(subdivisions=3, radius=0.4).export(run / "shells" / "inner.ply")
    health = {"ok": False, "kinds": ["solid"], "warnings": ["..."]}
    write_json(run / "train_summary.json", {"health": health})  # stage 1's verdict

    m = render_run(run, progress=False)
    out = run / "render-band"
    names = sorted(p.name for p in out.iterdir())
    assert names == ["metrics.json", "r_000.png", "r_001.png", "spp_000.png", "spp_001.png"]
    saved = json.loads((out / "metrics.json").read_text())
    assert saved == json.loads(json.dumps(m))
    for key in ("psnr", "ssim", "samples_per_pixel", "samples_per_covered_pixel", "ms_per_frame",
                "width", "height", "mode", "device", "variant", "background", "split",
                "n_views", "protocol"):
        assert key in saved, key
    assert (saved["width"], saved["height"], saved["mode"]) == (16, 16, "band")
    assert saved["stage1_health"] == health  # carried into every render's metrics
    # nerfstudio ns-eval's names, top level and under "results" (its layout)
    for key in ("psnr", "ssim", "fps", "num_rays_per_sec"):
        assert saved[key] == saved["results"][key] and saved[f"{key}_std"] is not None, key
    assert saved["psnr_std"] == pytest.approx(float(np.std(saved["psnr_per_view"])))
    assert saved["num_rays_per_sec"] == pytest.approx(256 * saved["fps"], rel=1e-6)
    assert 0 < saved["samples_per_pixel"] <= 16 and saved["psnr"] > 0

    mf = render_run(run, mode="full", width=8, out=tmp_path / "full8", progress=False)
    assert (mf["width"], mf["height"], mf["psnr"]) == (8, 8, None)
    assert mf["samples_per_pixel"] == 32.0  # every ray of these cameras crosses the box
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())  # no temp leftovers


def test_ray_reaching_the_inner_shell_is_absorbed_there():
    # a very thin band (+-0.01) around a sphere with a wide kernel (s = 0.05): the band holds
    # only 1 - sigmoid(-0.2) / sigmoid(0.2) = 0.33 of the opacity (NeuS alpha of one section
    # from f = +0.01 to -0.01). M- bounds the solid interior, so the rest of the light ends on
    # the last sample's colour, not on the background: the axis ray shows the sphere's front
    # colour (0.5, 0.5, 0), not a mix with the white background (blue ~0.67 if it leaked).
    mitsuba_variant()
    outer = trimesh.creation.icosphere(subdivisions=5, radius=0.51)
    inner = trimesh.creation.icosphere(subdivisions=5, radius=0.49)
    scene = ShellScene((outer.vertices, outer.faces), (inner.vertices, inner.faces))
    o = torch.tensor([[0.0, 0.0, -2.5], [0.0, 0.505, -2.5]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    colour, count = render_rays(SphereField(s=0.05), o, d, RenderConfig(), "band", scene=scene)
    c = np.asarray(colour)  # [3, R]
    assert count.numpy().tolist()[0] >= 1
    np.testing.assert_allclose(c[:, 0], [0.5, 0.5, 0.0], atol=0.02)
    # the grazing ray crosses the band without reaching M-: it does see the background
    assert c[2, 1] > 0.5
