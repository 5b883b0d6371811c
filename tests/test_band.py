"""The torch band renderer (shells.render.band) against the Dr.Jit renderer, forward and backward.

Both renderers take the same rays, shells, sample placement and solid-end rule
(`shells.render.sampler.solid_end`); these tests pin them to each other on a trained toy field
and its extracted shells, and pin the torch renderer's gradients to finite differences.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from shells.data.datasets import load_dataset
from shells.fields.drjit_field import DrJitField
from shells.render.band import render_band_rays
from shells.render.frame import render_image, render_rays
from shells.render.sampler import band_samples
from shells.run import RunDir, load_field, load_shells, read_run
from tests.conftest import tiny_config, trained_run


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A toy field trained 40 steps on the tiny data set, its shells, a test view's rays."""
    run = trained_run(tmp_path_factory.mktemp("band"), tiny_config(train_iters=40,
                                                                   train_batch=256))
    field, cfg = load_field(run, stage="stage1")
    scene = load_shells(RunDir(run))
    test = load_dataset(read_run(RunDir(run))["data"], "test")
    o, d = test.cameras.pixel_rays(0)
    return field, cfg, scene, o, d, test.cameras.height, test.cameras.width


def test_torch_and_drjit_band_renders_agree_per_pixel(trained):
    field, cfg, scene, o, d, H, W = trained
    bg = torch.tensor(cfg.data.background)
    with torch.no_grad():
        ref = render_band_rays(field, scene, o, d, cfg.render, bg)
    every = copy.deepcopy(cfg.render)
    every.band_ert_eps = 0.0  # every sample, as the torch renderer takes them
    img, spp = render_image(DrJitField(field), o, d, H, W, every, "band", scene,
                            background=tuple(cfg.data.background))
    assert torch.equal(spp.reshape(-1).long(), ref["spp"].long())
    # same samples, formula and end rule; DrJitField vs ShellField differ by fp32 rounding
    assert (img.reshape(-1, 3) - ref["color"]).abs().max() < 1e-4
    # the test has power over the solid-end rule: rays end on M- with much light left, and
    # their last sample's colour is far from the background, so either renderer ignoring the
    # rule would move those pixels by far more than 1e-4
    _, _, _, solid = band_samples(scene, o, d, cfg.render)
    left = 1.0 - ref["opacity"]
    assert solid.sum() >= 10 and left[solid].max() > 0.05
    assert (ref["spp"] > 0).sum() > solid.sum()  # and some rays cross the band to the background


def _loss(colour: torch.Tensor, wts: torch.Tensor) -> torch.Tensor:
    return (colour * wts).sum() / wts.numel()


def _probes(field: torch.nn.Module) -> list[tuple[str, tuple[int, ...]]]:
    """Scalar parameters to differentiate: the colour output bias (every sample's colour, the
    last one of a solid ray too), the SDF output bias, and geometry / radiance weights."""
    rad_out = len(field.rad_mlp) - 1
    return ([(f"rad_mlp.{rad_out}.bias", (c,)) for c in range(3)]
            + [("geo_mlp.2.bias", (0,)), ("geo_mlp.2.bias", (1,)), ("geo_mlp.0.weight", (0, 0)),
               (f"rad_mlp.{rad_out}.weight", (1, 5))])


def test_torch_band_gradients_match_finite_differences(trained):
    """float64: autograd of the torch band renderer == central differences of the same function;
    float32: == central differences of the Dr.Jit renderer (the forward the images come from)."""
    field32, cfg, scene, o, d, H, W = trained
    keep = torch.arange(0, H * W, 3)  # a third of the pixels: band, solid and empty rays
    o, d = o[keep], d[keep]
    field = copy.deepcopy(field32).double()
    o64, d64 = o.double(), d.double()
    bg = torch.tensor(cfg.data.background, dtype=torch.float64)
    wts = torch.rand(len(o), 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    params = dict(field.named_parameters())
    for p in params.values():
        p.grad = None
    _loss(render_band_rays(field, scene, o64, d64, cfg.render, bg)["color"], wts).backward()

    def loss64() -> float:
        with torch.no_grad():
            return float(_loss(render_band_rays(field, scene, o64, d64, cfg.render, bg)["color"],
                               wts))

    def loss_drjit(f32: torch.nn.Module) -> float:
        colour, _ = render_rays(DrJitField(f32), o, d, cfg.render, "band", scene,
                                background=tuple(cfg.data.background))
        return float(_loss(torch.from_numpy(np.asarray(colour).T.copy()).double(), wts))

    h64, h32 = 1e-6, 1e-3
    for name, idx in _probes(field):
        g = float(params[name].grad[idx])
        with torch.no_grad():
            p = params[name]
            p[idx] += h64
            up = loss64()
            p[idx] -= 2 * h64
            down = loss64()
            p[idx] += h64
        fd = (up - down) / (2 * h64)
        assert fd == pytest.approx(g, rel=1e-5, abs=1e-10), name
        # the Dr.Jit renderer, float32, a larger step: agreement to 1 % of the gradient
        f32 = copy.deepcopy(field32)
        p32 = dict(f32.named_parameters())[name]
        with torch.no_grad():
            p32[idx] += h32
            up = loss_drjit(f32)
            p32[idx] -= 2 * h32
            down = loss_drjit(f32)
        fd32 = (up - down) / (2 * h32)
        assert fd32 == pytest.approx(g, rel=1e-2, abs=1e-7), name


def test_solid_end_carries_gradient_to_the_last_sample(trained):
    """Hand-worked: d colour / d rgb_last of a solid ray = w_last + (1 - opacity), the colour's
    own weight plus the light the ray still carries when it is absorbed at M-."""
    field, cfg, scene, o, d, H, W = trained
    _, _, mask, solid = band_samples(scene, o, d, cfg.render)
    r = int(torch.nonzero(solid)[0])
    n = int(mask[r].sum())

    class Wrapped(torch.nn.Module):  # the trained field with a colour offset on every sample
        def __init__(self):
            super().__init__()
            self.offset = None

        def forward(self, x, dd):
            out = field(x, dd)
            self.offset = torch.zeros_like(out["rgb"], requires_grad=True)
            out["rgb"] = out["rgb"] + self.offset
            return out

    w = Wrapped()
    out = render_band_rays(w, scene, o[r:r + 1], d[r:r + 1], cfg.render,
                           torch.tensor(cfg.data.background))
    out["color"][0, 0].backward()
    g = w.offset.grad[:, 0]  # [n] d red / d red_i of the ray's samples
    assert g.shape == (n,)
    with torch.no_grad():
        res = render_band_rays(field, scene, o[r:r + 1], d[r:r + 1], cfg.render,
                               torch.tensor(cfg.data.background))
    left = 1.0 - float(res["opacity"][0])
    assert left > 1e-3  # the end term is visible in this ray
    # weights w_i = T_i alpha_i sum to the opacity; the last sample also takes the rest
    assert float(g.sum()) == pytest.approx(1.0, abs=1e-5)
    assert float(g[-1]) >= left - 1e-6


def test_extra_points_in_the_samples_batch_change_nothing_else(trained):
    """Points evaluated in the band's batch (`extra`, the stage-2 anchor's): the colour is the
    same as without them, their f and s are the field's own, and the gradient of a loss on
    both is the sum of the gradients of the two parts taken apart (float64)."""
    field32, cfg, scene, o, d, H, W = trained
    field = copy.deepcopy(field32).double()
    o, d = o[::2].double(), d[::2].double()
    bg = torch.tensor(cfg.data.background, dtype=torch.float64)
    x = (torch.rand(500, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
         * 2 - 1)
    wts = torch.rand(len(o), 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    def grads(loss: torch.Tensor) -> list[torch.Tensor]:
        return [g if g is not None else torch.zeros_like(p) for p, g in
                zip(field.parameters(), torch.autograd.grad(loss, list(field.parameters()),
                                                            allow_unused=True))]

    both = render_band_rays(field, scene, o, d, cfg.render, bg, extra=x)
    alone = render_band_rays(field, scene, o, d, cfg.render, bg)
    geo = field.geometry(x)
    assert torch.allclose(both["color"], alone["color"], atol=1e-12)
    assert torch.allclose(both["extra_sdf"], geo["sdf"], atol=1e-12)
    assert torch.allclose(both["extra_s"], geo["s"], atol=1e-12)
    g_both = grads(_loss(both["color"], wts) + both["extra_sdf"].sum() + both["extra_s"].sum())
    g_parts = [a + b for a, b in zip(grads(_loss(alone["color"], wts)),
                                     grads(geo["sdf"].sum() + geo["s"].sum()))]
    assert all(torch.allclose(a, b, atol=1e-10) for a, b in zip(g_both, g_parts))
    assert any(b.abs().sum() > 0 for b in grads(field.geometry(x)["sdf"].sum()))  # they count
