"""Image-space adaptive refinement (shells-render --refine L): --refine 0 is the band render bit
for bit, evaluated pixels are the band render's, interpolation stays close to it, fuzzy pixels
are always evaluated, and the command refuses what it cannot refine."""

from __future__ import annotations

import dataclasses
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
from shells.fields.drjit_field import FieldSample
from shells.metrics import psnr
from shells.render.frame import render_image
from shells.render.raycast import ShellScene
from shells.render.refine import render_refined

SHARP = (-0.45, 0.0, 0.0), 0.35  # centre, radius of the sharp sphere
FUZZY = (0.5, 0.0, 0.0), 0.3  # and of the fuzzy one


class TwoSpheres:
    """A sharp sphere (s = 0.002, thin band: one sample per interval) and a fuzzy one
    (s = 0.03, wide band: many samples), coloured by a smooth function of position."""

    def eval(self, x, d):
        x = mi.Point3f(x)
        out = []
        for (c, r), s in ((SHARP, 0.002), (FUZZY, 0.03)):
            v = x - mi.Point3f(*c)
            dist = dr.norm(v)
            out.append((dist - r, v / dr.maximum(dist, 1e-8), s))
        a = out[0][0] < out[1][0]
        sdf = dr.select(a, out[0][0], out[1][0])
        n = dr.select(a, out[0][1], out[1][1])
        s = dr.select(a, out[0][2], out[1][2])
        rgb = mi.Color3f(0.5 + 0.3 * dr.sin(3 * x.x + 0.5), 0.5 + 0.3 * dr.sin(2 * x.y + 1),
                         0.5 + 0.3 * dr.cos(2.5 * x.z))
        return FieldSample(sdf=sdf, s=s + 0 * dist, normal=n, rgb=rgb)


def _sphere(centre, r, sub=5):
    m = trimesh.creation.icosphere(subdivisions=sub, radius=r)
    return m.vertices + np.asarray(centre), m.faces


def _union(*meshes):
    V, F, off = [], [], 0
    for v, f in meshes:
        V.append(v)
        F.append(f + off)
        off += len(v)
    return np.concatenate(V), np.concatenate(F)


@pytest.fixture(scope="module")
def scene():
    mitsuba_variant()
    outer = _union(_sphere(SHARP[0], SHARP[1] + 0.004), _sphere(FUZZY[0], FUZZY[1] + 0.12))
    inner = _union(_sphere(SHARP[0], SHARP[1] - 0.004), _sphere(FUZZY[0], FUZZY[1] - 0.08))
    return ShellScene(outer, inner)


def _rays(width: int, dist: float = 2.6, fov: float = 0.8):
    j, i = torch.meshgrid(torch.arange(width) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    f = 0.5 * width / math.tan(fov / 2)
    d = torch.stack([(i - width / 2) / f, -(j - width / 2) / f, torch.ones_like(i)], -1)
    d = torch.nn.functional.normalize(d.reshape(-1, 3), dim=-1)
    return torch.tensor([0.0, 0.1, -dist]).expand_as(d).contiguous(), d


CFG = RenderConfig(w_s=0.02, delta_s=0.01, refine_colour=0.05)


def test_refine_zero_is_the_band_render(scene):
    o, d = _rays(64)
    band, spp = render_image(TwoSpheres(), o, d, 64, 64, CFG, "band", scene)
    img, spp2, evaluated, covered = render_refined(TwoSpheres(), o, d, 64, 64, CFG, scene)
    assert torch.equal(img, band) and torch.equal(spp2, spp)
    assert torch.equal(evaluated, spp > 0) and torch.equal(covered, spp > 0)


@pytest.mark.parametrize("levels", [1, 3])
def test_evaluated_pixels_are_the_band_render_and_the_rest_is_close(scene, levels):
    W = 96
    o, d = _rays(W)
    band, spp = render_image(TwoSpheres(), o, d, W, W, CFG, "band", scene)
    cfg = dataclasses.replace(CFG, refine_levels=levels)
    img, spp_r, evaluated, covered = render_refined(TwoSpheres(), o, d, W, W, cfg, scene)
    assert torch.equal(covered, spp > 0)
    assert torch.equal(img[evaluated], band[evaluated])  # bit for bit
    assert torch.equal(spp_r[evaluated], spp[evaluated]) and int(spp_r[~evaluated].sum()) == 0
    share = evaluated.sum().item() / covered.sum().item()
    assert share < 0.8, share  # the sharp sphere is mostly interpolated
    # the mean of the parents on a smooth colour: measured 80 / 70 dB (the first parent's
    # colour instead of the mean gives 56 / 51)
    assert psnr(img, band) >= 60.0
    assert torch.equal(img[~covered], band[~covered])  # background is background


def test_fuzzy_pixels_are_always_evaluated(scene):
    W = 96
    o, d = _rays(W)
    iv = scene.intervals(o, d, CFG.dp_max).torch()
    width = (iv["exit"] - iv["enter"]).clamp_min(0)
    valid = torch.arange(width.shape[1])[None] < iv["count"][:, None].long()
    n = torch.ceil((width - CFG.w_s).clamp_min(0) / CFG.delta_s) + 1
    fuzzy = ((n > 1) & valid).any(1).reshape(W, W)
    assert fuzzy.sum() > 200  # the fuzzy sphere's pixels
    cfg = dataclasses.replace(CFG, refine_levels=2)
    _, _, evaluated, _ = render_refined(TwoSpheres(), o, d, W, W, cfg, scene)
    assert evaluated[fuzzy].all()
    # with a looser fuzziness threshold some of them may be interpolated
    loose = dataclasses.replace(cfg, refine_fuzzy_samples=64, refine_colour=1.0,
                                refine_clear=1.0, refine_field_normal=2.0)
    _, _, evaluated, _ = render_refined(TwoSpheres(), o, d, W, W, loose, scene)
    assert not evaluated[fuzzy].all()


def test_little_to_gain_falls_back_to_the_whole_band_render(scene):
    o, d = _rays(64)
    band, spp = render_image(TwoSpheres(), o, d, 64, 64, CFG, "band", scene)
    cfg = dataclasses.replace(CFG, refine_levels=2, refine_min_share=1.0)
    img, _, evaluated, covered = render_refined(TwoSpheres(), o, d, 64, 64, cfg, scene)
    assert torch.equal(img, band) and torch.equal(evaluated, covered)


def test_refine_refuses_supersampling_and_other_modes(tmp_path):
    with pytest.raises(InputError, match="spp"):
        cfg = RenderConfig(refine_levels=2, spp=4)
        render_refined(None, torch.zeros(16, 3), torch.zeros(16, 3), 2, 2, cfg, None)
    from shells.config import Config
    with pytest.raises(InputError, match="refine_levels"):
        Config().update({"render": {"refine_levels": 9}}, "test")

    from tests.conftest import tiny_config, trained_run
    from shells.pipeline import render_run

    run = trained_run(tmp_path, tiny_config())
    with pytest.raises(InputError, match="--refine 2: refinement is for band mode"):
        render_run(run, mode="full", refine=2, progress=False)
    a = render_run(run, progress=False, out=tmp_path / "band")
    b = render_run(run, progress=False, out=tmp_path / "r0", refine=0)
    c = render_run(run, progress=False, out=tmp_path / "r2", refine=2)
    assert a["psnr"] == b["psnr"] and c["render_config"]["refine_levels"] == 2
    assert 0 < c["evaluated_fraction_of_covered"] <= 1.0
    import imageio.v3 as iio
    assert np.array_equal(iio.imread(tmp_path / "band" / "r_000.png"),
                          iio.imread(tmp_path / "r0" / "r_000.png"))


def _features():
    """Cast features and parent values of one new pixel (index 0) and four parents (1..4)
    under which every test of `_agree` passes."""
    n = torch.tensor([[0.0, 0.0, -1.0]]).repeat(5, 1)
    cast = {"count": torch.ones(5, dtype=torch.int32), "solid": torch.ones(5, dtype=torch.bool),
            "single": torch.ones(5, dtype=torch.bool), "n_hit": n.clone(),
            "t_hit": torch.full((5,), 2.0), "cos": torch.ones(5)}
    colour = torch.full((5, 3), 0.5)
    opacity = torch.ones(5)
    nfield = n.clone()
    return cast, colour, opacity, nfield


@pytest.mark.parametrize("veto", ["count", "solid", "single_pixel", "single_parent", "normal",
                                  "depth", "grazing", "colour", "opacity", "field_normal"])
def test_each_agreement_test_can_veto_the_interpolation(veto):
    from shells.render.refine import _agree

    cfg = RenderConfig()
    idx, par = torch.tensor([0]), torch.tensor([[1, 2, 3, 4]])
    cast, colour, opacity, nfield = _features()
    assert _agree(cast, idx, par, colour, opacity, nfield, cfg).item()
    tilt = torch.tensor([0.0, math.sin(0.5), -math.cos(0.5)])  # 29 degrees off
    if veto == "count":
        cast["count"][2] = 2
    elif veto == "solid":
        cast["solid"][3] = False
    elif veto == "single_pixel":
        cast["single"][0] = False
    elif veto == "single_parent":
        cast["single"][4] = False
    elif veto == "normal":
        cast["n_hit"][1] = tilt
    elif veto == "depth":
        cast["t_hit"][0] = 2.1
    elif veto == "grazing":
        cast["cos"][0] = 0.1
    elif veto == "colour":
        colour[2, 1] = 0.6
    elif veto == "opacity":
        opacity[1] = 0.9
    elif veto == "field_normal":
        nfield[3] = tilt
    assert not _agree(cast, idx, par, colour, opacity, nfield, cfg).item()
    if veto in ("opacity", "field_normal"):  # clear parents pass both, when allowed
        opacity[:] = 0.0
        clear = dataclasses.replace(cfg, refine_clear=0.01)
        assert _agree(cast, idx, par, colour, opacity, nfield, clear).item()
