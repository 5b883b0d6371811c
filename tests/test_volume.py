"""Full-ray torch volume rendering helpers: hand-worked numbers."""

import math

import torch

from shells.render.volume import ray_aabb, sample_pdf, section_edges, stratified_samples

BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def test_ray_aabb_hand_worked():
    o = torch.tensor([[0.0, 0.0, -3.0],   # along +z through the box: enters at 2, leaves at 4
                      [0.0, 0.0, 0.0],    # starts inside: near clamps to 0, far = 1
                      [0.0, 5.0, -3.0],   # passes above the box: miss
                      [-3.0, -3.0, 0.0]])  # diagonal in xy: enters at 2*sqrt2, leaves at 4*sqrt2
    d = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0],
                      [2 ** -0.5, 2 ** -0.5, 0.0]])
    near, far, hit = ray_aabb(o, d, BOX)
    assert hit.tolist() == [True, True, False, True]
    torch.testing.assert_close(near[[0, 1, 3]], torch.tensor([2.0, 0.0, 2 * 2 ** 0.5]))
    torch.testing.assert_close(far[[0, 1, 3]], torch.tensor([4.0, 1.0, 4 * 2 ** 0.5]))


def test_stratified_and_sections():
    near, far = torch.tensor([2.0]), torch.tensor([4.0])
    t = stratified_samples(near, far, 4)  # centred: 2.25, 2.75, 3.25, 3.75
    torch.testing.assert_close(t, torch.tensor([[2.25, 2.75, 3.25, 3.75]]))
    # sections tile [near, far]: edges 2, 2.5, 3, 3.5, 4
    torch.testing.assert_close(section_edges(t, near, far),
                               torch.tensor([[2.0, 2.5, 3.0, 3.5, 4.0]]))
    g = torch.Generator().manual_seed(0)
    tj = stratified_samples(near.expand(100), far.expand(100), 4, g)
    lo = torch.tensor([2.0, 2.5, 3.0, 3.5])
    assert ((tj >= lo) & (tj < lo + 0.5)).all()  # one sample per stratum


def test_sample_pdf_concentrates_on_weight():
    near, far = torch.tensor([0.0]), torch.tensor([4.0])
    t = stratified_samples(near, far, 4)  # sections [0,1], [1,2], [2,3], [3,4]
    w = torch.tensor([[0.0, 0.0, 1.0, 0.0]])  # all weight in [2, 3]
    s = sample_pdf(t, w, near, far, 64, torch.Generator().manual_seed(1))
    # the 1e-5 floor on weights leaves ~3e-5 of the mass elsewhere: all 64 land in [2, 3]
    assert ((s >= 2.0) & (s <= 3.0)).all()
    u = sample_pdf(t, torch.ones(1, 4), near, far, 8)  # uniform pdf, centred u: (i + 0.5) / 8 * 4
    torch.testing.assert_close(u, ((torch.arange(8) + 0.5) / 2).unsqueeze(0))


# -- empty-space skipping and the one-evaluation-per-sample renderer (issue 13) ----------------

class _SphereField(torch.nn.Module):
    """f = |x - c| - r, constant kernel s, colour from the position: an exact SDF."""

    def __init__(self, r=0.4, s=0.01, c=(0.3, 0.0, 0.0)):
        super().__init__()
        self.register_buffer("aabb", BOX.clone())
        self.r, self.s = r, s
        self.c = torch.tensor(c)
        self.w = torch.nn.Parameter(torch.tensor(1.0))  # a parameter for the gradient checks

    def geometry(self, x):
        v = x - self.c.to(x)
        n = v.norm(dim=-1)
        return {"sdf": self.w * (n - self.r), "s": torch.full_like(n, self.s),
                "normal": v / n.clamp_min(1e-9)[:, None]}

    def forward(self, x, d):
        g = self.geometry(x)
        g["rgb"] = torch.sigmoid(self.w * x + d.sum(-1, keepdim=True))
        return g


def test_span_grid_spans_contain_the_surface():
    from shells.render.volume import SpanGrid

    f = _SphereField()
    grid = SpanGrid(BOX, 32, k=5.0)
    o, d = _rays(400, seed=0)
    near, far, hit = grid.spans(o, d)  # before the first update: the whole box chord
    n0, f0, h0 = ray_aabb(o, d, BOX)
    assert torch.equal(near, n0) and torch.equal(far, f0) and torch.equal(hit, h0)
    grid.update(f)
    assert 0.0 < grid.fraction < 0.25
    near, far, hit = grid.spans(o, d)
    # exact entry / exit of the sphere: both inside the span of every ray that hits it
    oc = o - f.c
    b = (oc * d).sum(-1)
    disc = b * b - ((oc * oc).sum(-1) - f.r ** 2)
    hits_sphere = disc > 0
    t0, t1 = -b - disc.clamp_min(0).sqrt(), -b + disc.clamp_min(0).sqrt()
    assert hits_sphere.sum() > 50
    assert hit[hits_sphere].all()
    assert (near[hits_sphere] <= t0[hits_sphere]).all()
    assert (far[hits_sphere] >= t1[hits_sphere]).all()
    # rays passing far from the sphere (beyond the occupied margin) get no span
    dist = (oc - b[:, None] * d).norm(dim=-1)  # closest approach to the centre
    far_away = ~hits_sphere & (dist > f.r + 5 * f.s + 4 * float(grid.cell.norm())) & h0
    assert far_away.sum() > 20
    assert not hit[far_away].any()
    # spans are never longer than the chord
    assert (near >= n0 - 1e-6).all() and (far <= f0 + 1e-6).all()
    # the same floats as the plain [R, n, 3] formulation of the probes' cells
    step = 0.5 * float(grid.cell.min())
    n = int(math.ceil(float((f0 - n0).max()) / step))
    t = n0[:, None] + step * (torch.arange(n, dtype=o.dtype) + 0.5)
    c = ((o[:, None] + t[..., None] * d[:, None] - BOX[0]) / grid.cell).floor().long()
    c = c.clamp(0, grid.N - 1)
    m = grid.occ[c[..., 0], c[..., 1], c[..., 2]] & (t < f0[:, None])
    first, last = m.float().argmax(1), n - 1 - m.flip(1).float().argmax(1)
    lo = torch.maximum(n0, n0 + step * (first + 0.5) - 2.0 * grid.h)
    hi = torch.minimum(f0, n0 + step * (last + 0.5) + 2.0 * grid.h)
    assert torch.equal(hit, m.any(1) & h0) and torch.equal(near, lo)
    assert torch.equal(far, torch.where(hit, hi, lo))


def _rays(n, seed):
    g = torch.Generator().manual_seed(seed)
    o = torch.randn(n, 3, generator=g)
    o = 3.0 * o / o.norm(dim=-1, keepdim=True)
    target = 0.8 * (torch.rand(n, 3, generator=g) * 2 - 1)
    d = target - o
    return o, d / d.norm(dim=-1, keepdim=True)


def _two_pass_reference(field, o, d, n_samples, n_importance, bg, gen):
    """The renderer before issue 13: a geometry pass without gradient places the fine samples,
    then the field is evaluated again at all samples."""
    from shells.fields.neus import composite, neus_alpha

    near, far, hit = ray_aabb(o, d, field.aabb)
    t = stratified_samples(near, far, n_samples, gen)
    with torch.no_grad():
        pts = o[:, None] + t[..., None] * d[:, None]
        geo = field.geometry(pts.reshape(-1, 3))
        cos = (geo["normal"].reshape(*t.shape, 3) * d[:, None]).sum(-1)
        delta = torch.diff(section_edges(t, near, far), dim=-1)
        alpha = neus_alpha(geo["sdf"].reshape(t.shape), geo["s"].reshape(t.shape), cos, delta)
        _, w, _ = composite(alpha, torch.zeros(*t.shape, 3), bg)
        t, _ = torch.sort(torch.cat([t, sample_pdf(t, w, near, far, n_importance, gen)], -1), -1)
    delta = torch.diff(section_edges(t, near, far), dim=-1)
    R, S = t.shape
    pts = o[:, None] + t[..., None] * d[:, None]
    dd = d[:, None].expand(R, S, 3)
    out = field(pts.reshape(-1, 3), dd.reshape(-1, 3))
    cos = (out["normal"].reshape(R, S, 3) * dd).sum(-1)
    alpha = neus_alpha(out["sdf"].reshape(R, S), out["s"].reshape(R, S), cos, delta) * hit[:, None]
    return composite(alpha, out["rgb"].reshape(R, S, 3), bg)[0]


def test_single_evaluation_matches_the_two_pass_renderer_forward_and_backward():
    from shells.render.volume import render_volume_rays

    f = _SphereField().double()
    f.c = f.c.double()
    o, d = _rays(64, seed=1)
    o, d = o.double(), d.double()
    bg = torch.ones(3, dtype=torch.float64)
    ref = _two_pass_reference(f, o, d, 16, 8, bg, torch.Generator().manual_seed(5))
    (g_ref,) = torch.autograd.grad(ref.sum(), f.w)
    out = render_volume_rays(f, o, d, 16, 8, bg, torch.Generator().manual_seed(5))
    (g_out,) = torch.autograd.grad(out["color"].sum(), f.w)
    torch.testing.assert_close(out["color"], ref, rtol=0, atol=1e-12)
    torch.testing.assert_close(g_out, g_ref, rtol=1e-10, atol=1e-12)
    assert torch.all(out["t"][:, 1:] >= out["t"][:, :-1])  # merged in distance order


def test_culled_gradient_pass_keeps_the_render_and_drops_only_light_samples():
    """``cull``: the samples under the weight threshold keep their values without gradient,
    and those under UNLIT * cull their geometry only. The render is the unculled one less
    exactly the colour those last samples carry; the gradient loses only what the light
    samples carry."""
    from shells.render.volume import UNLIT, render_volume_rays

    f = _SphereField().double()
    f.c = f.c.double()
    o, d = _rays(64, seed=1)
    o, d = o.double(), d.double()
    bg = torch.ones(3, dtype=torch.float64)
    ref = render_volume_rays(f, o, d, 16, 8, bg, torch.Generator().manual_seed(5))
    (g_ref,) = torch.autograd.grad(ref["color"].sum(), f.w)
    calls, geo_calls = [], []
    f.register_forward_hook(lambda m, args, out: calls.append(len(args[0])))
    geometry = f.geometry
    f.geometry = lambda x: geo_calls.append(len(x)) or geometry(x)
    out = render_volume_rays(f, o, d, 16, 8, bg, torch.Generator().manual_seed(5), cull=1e-4)
    (g_out,) = torch.autograd.grad(out["color"].sum(), f.w)
    w = ref["weights"].detach()
    kept, unlit = w >= 1e-4, w < UNLIT * 1e-4
    lit = ~kept & ~unlit
    for k in ("opacity", "weights", "sdf", "s"):
        torch.testing.assert_close(out[k], ref[k], rtol=0, atol=1e-12)
    # the colour of the unlit samples is all that is missing: at most 24 * 1e-6 per channel
    rgb = torch.sigmoid(f.w * ref["points"] + d.sum(-1)[:, None, None])  # _SphereField's
    missing = (w[..., None] * rgb)[unlit].sum(0)
    short = (ref["color"] - out["color"]).detach()
    torch.testing.assert_close(short.sum(0), missing.detach(), rtol=0, atol=1e-12)
    assert float(short.min()) >= -1e-12 and float(short.max()) <= 24 * UNLIT * 1e-4
    assert int(unlit.sum()) > 0.5 * w.numel()  # most samples: empty or occluded space
    # coarse and fine geometry without gradient, colours of the lit samples without gradient,
    # then one pass on the kept samples: a sharp sphere keeps under a quarter of them
    assert geo_calls[:2] == [64 * 16, 64 * 8]
    assert calls == [int(lit.sum()), int(kept.sum())] and 0 < calls[1] < 0.25 * 64 * 24
    # the gradient is the reference's with the light samples' field values detached and the
    # unlit samples' colours zero
    light = {tuple(p) for p in ref["points"][~kept].tolist()}
    dark = {tuple(p) for p in ref["points"][unlit].tolist()}

    class Detached(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.inner, self.aabb = f, f.aabb

        def forward(self, x, dd):
            g = self.inner(x, dd)
            m = torch.tensor([tuple(p) in light for p in x.tolist()])
            g = {k: torch.where(m.view(-1, *[1] * (v.ndim - 1)), v.detach(), v)
                 for k, v in g.items()}
            g["rgb"] = torch.where(torch.tensor([tuple(p) in dark for p in x.tolist()])[:, None],
                                   torch.zeros_like(g["rgb"]), g["rgb"])
            return g

    part = render_volume_rays(Detached(), o, d, 16, 8, bg, torch.Generator().manual_seed(5))
    (g_part,) = torch.autograd.grad(part["color"].sum(), f.w)
    torch.testing.assert_close(g_out, g_part, rtol=1e-10, atol=1e-12)
    assert float(g_out - g_ref) != 0.0  # culling did drop samples' gradient
    # a threshold of 0 keeps every sample: the gradient of the reference
    out0 = render_volume_rays(f, o, d, 16, 8, bg, torch.Generator().manual_seed(5), cull=0.0)
    (g0,) = torch.autograd.grad(out0["color"].sum(), f.w)
    torch.testing.assert_close(g0, g_ref, rtol=0, atol=0)
    # without gradient (evaluation) the threshold changes nothing
    with torch.no_grad():
        ev = render_volume_rays(f, o, d, 16, 8, bg, None, cull=1e-4)
    torch.testing.assert_close(ev["color"], render_volume_rays(f, o, d, 16, 8, bg)["color"].detach(),
                               rtol=0, atol=0)


def test_culled_gradient_pass_on_a_hash_grid_field():
    """The same on a hash-grid field after a few steps toward a sharp sphere: every parameter's
    gradient within 1 % of the unculled one (relative norm), with samples culled."""
    from shells.presets import toy_config
    from shells.fields.network import ShellField
    from shells.render.volume import render_volume_rays

    torch.manual_seed(0)
    field = ShellField(toy_config().field, BOX.clone())
    o, d = _rays(256, seed=2)
    bg = torch.ones(3)
    sphere = _SphereField(r=0.5, c=(0.0, 0.0, 0.0))
    opt = torch.optim.Adam(field.parameters(), lr=1e-2)
    for _ in range(30):  # fit the SDF and a small kernel, so that weights concentrate
        x = torch.rand(4096, 3) * 2 - 1
        geo = field.geometry(x)
        loss = ((geo["sdf"] - sphere.geometry(x)["sdf"]) ** 2).mean() + geo["s"].mean()
        opt.zero_grad()
        loss.backward()
        opt.step()

    def grads(cull):
        field.zero_grad()
        out = render_volume_rays(field, o, d, 32, 16, bg, torch.Generator().manual_seed(3),
                                 cull=cull)
        out["color"].square().sum().backward()
        return out, torch.cat([p.grad.reshape(-1) for p in field.parameters()
                               if p.grad is not None])

    ref, g_ref = grads(0.0)
    out, g = grads(1e-4)
    torch.testing.assert_close(out["color"], ref["color"], rtol=0, atol=1e-5)
    kept = float((ref["weights"].detach() >= 1e-4).float().mean())
    assert kept < 0.6, f"only {1 - kept:.0%} of the samples culled"
    assert float((g - g_ref).norm()) <= 0.01 * float(g_ref.norm())


# -- the opacity's slope from the ray's own samples (``train.slope`` "ray") -------------------

def test_ray_slope_hand_worked():
    from shells.render.volume import ray_slope

    t = torch.tensor([[0.0, 1.0, 3.0, 4.0], [2.0, 2.0, 2.0, 2.0]])
    f = torch.tensor([[1.0, 0.0, -4.0, -4.5], [0.3, 0.3, 0.3, 0.3]])
    # one-sided at the ends, central inside: -1, (-4 - 1) / 3, (-4.5 - 0) / 3, -0.5;
    # coinciding samples (a ray that misses its span) get slope 0
    torch.testing.assert_close(ray_slope(f, t), torch.tensor([[-1.0, -5.0 / 3.0, -1.5, -0.5],
                                                              [0.0, 0.0, 0.0, 0.0]]))


class _WrongNormals(_SphereField):
    """The exact sphere with predicted normals turned inside out: d . n says "leaving" where a
    ray enters, so with ``slope`` "normal" rays pass the crossing and are absorbed deeper
    inside, where the normal flips back (the failure on fox, BENCHMARKS.md)."""

    def geometry(self, x):
        g = super().geometry(x)
        g["normal"] = -g["normal"]
        return g


def test_ray_slope_matches_the_normal_on_an_exact_sdf_and_ignores_wrong_normals():
    from shells.render.volume import render_volume_rays

    o, d = _rays(200, seed=4)
    bg = torch.ones(3)
    with torch.no_grad():
        f = _SphereField(s=0.02)
        ref = render_volume_rays(f, o, d, 128, 64, bg)
        ray = render_volume_rays(f, o, d, 128, 64, bg, slope="ray")
        # an exact SDF: d . n = df/dt, so the two agree up to the sampling's differences
        assert float((ray["color"] - ref["color"]).abs().max()) < 0.02
        assert float((ray["opacity"] - ref["opacity"]).abs().max()) < 0.02
        wrong = _WrongNormals(s=0.02)
        bad = render_volume_rays(wrong, o, d, 128, 64, bg)
        good = render_volume_rays(wrong, o, d, 128, 64, bg, slope="ray")
    # with the slope along the ray the wrong normals change nothing...
    torch.testing.assert_close(good["color"], ray["color"], rtol=0, atol=0)
    # ...while the predicted-normal opacity puts the weight deep inside the solid
    deep = lambda out: float((out["weights"] * (out["sdf"] < -0.1)).sum())  # noqa: E731
    assert deep(ray) < 0.01 * float(ray["weights"].sum())  # grazing rays: 0.4 %
    assert deep(bad) > 0.5 * float(bad["weights"].sum())
    import pytest
    with pytest.raises(ValueError):
        render_volume_rays(f, o, d, 8, 0, bg, slope="gradient")
