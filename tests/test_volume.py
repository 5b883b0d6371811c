"""Full-ray torch volume rendering helpers: hand-worked numbers."""

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
