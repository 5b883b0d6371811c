"""The scene contraction of unbounded captures (issue 14): c and c^-1 are inverses, c maps
R^3 into the radius-2 ball and is the identity on the unit ball, and its Jacobian agrees with
finite differences on both sides of the unit sphere."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from shells.errors import InputError
from shells.fields.contraction import Similarity, contract, contract_jacobian, uncontract


def _points(n: int = 2000, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    u = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=1)
    r = torch.cat([torch.rand(n // 2, generator=g, dtype=torch.float64),       # inside
                   1.0 + 10 ** (4 * torch.rand(n - n // 2, generator=g, dtype=torch.float64))
                   - 1.0 + 1e-6])                                               # 1 .. 1e4
    return u * r[:, None]


def test_contraction_is_the_identity_inside_and_maps_everything_into_radius_2():
    x = _points()
    y = contract(x)
    r = torch.linalg.vector_norm(x, dim=1)
    assert torch.equal(y[r <= 1], x[r <= 1])
    assert float(torch.linalg.vector_norm(y, dim=1).max()) < 2.0
    # hand-worked: |x| = 2 -> |c| = 1.5, |x| = 4 -> 1.75, direction kept
    np.testing.assert_allclose(contract(torch.tensor([[0.0, 2.0, 0.0], [0.0, 0.0, -4.0]],
                                                     dtype=torch.float64)).numpy(),
                               [[0.0, 1.5, 0.0], [0.0, 0.0, -1.75]])


def test_contract_and_uncontract_are_inverse():
    x = _points()
    np.testing.assert_allclose(uncontract(contract(x)).numpy(), x.numpy(), rtol=1e-9)
    g = torch.Generator().manual_seed(1)
    y = torch.nn.functional.normalize(torch.randn(1000, 3, generator=g, dtype=torch.float64),
                                      dim=1) * (1.999 * torch.rand(1000, 1, generator=g,
                                                                   dtype=torch.float64))
    np.testing.assert_allclose(contract(uncontract(y)).numpy(), y.numpy(), atol=1e-12)
    with pytest.raises(ValueError, match="infinity"):
        uncontract(torch.tensor([[2.0, 0.0, 0.0]]))


def test_jacobian_matches_finite_differences_and_is_continuous_at_the_unit_sphere():
    x = _points(400, seed=2)
    x = x[torch.linalg.vector_norm(x, dim=1) < 1e3]  # FD steps stay meaningful
    h = 1e-6
    fd = torch.stack([(contract(x + h * e) - contract(x - h * e)) / (2 * h)
                      for e in torch.eye(3, dtype=torch.float64)], dim=-1)
    np.testing.assert_allclose(contract_jacobian(x).numpy(), fd.numpy(), atol=1e-7)
    # C^1 across the unit sphere: the outside formula tends to the identity
    u = torch.tensor([[0.6, 0.0, 0.8]], dtype=torch.float64)
    for r in (1.0 + 1e-9, 1.0 - 1e-9):
        np.testing.assert_allclose(contract_jacobian(u * r)[0].numpy(), np.eye(3), atol=1e-8)
    # and the inverse's Jacobian (by finite differences) is the inverse matrix
    y = contract(x)
    y = y[torch.linalg.vector_norm(y, dim=1) < 1.99]
    fdi = torch.stack([(uncontract(y + h * e) - uncontract(y - h * e)) / (2 * h)
                       for e in torch.eye(3, dtype=torch.float64)], dim=-1)
    J = contract_jacobian(uncontract(y))
    np.testing.assert_allclose((J @ fdi).numpy(), np.broadcast_to(np.eye(3), J.shape),
                               atol=1e-5)


def _ring(centre, radius, n=12, outward=False):
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    o = np.stack([np.cos(a), np.sin(a), 0.3 * np.sin(3 * a)], 1) * radius + centre
    d = (o - centre) if outward else (centre - o)
    return o, d


def test_similarity_from_inward_cameras_finds_their_focus():
    c = np.array([1.0, -2.0, 0.5])
    o, d = _ring(c, 4.0)
    s = Similarity.from_cameras(o, d)
    np.testing.assert_allclose(s.centre, c, atol=1e-9)
    assert s.radius == pytest.approx(np.median(np.linalg.norm(o - c, axis=1)))
    p = torch.from_numpy(o)
    np.testing.assert_allclose(s.to_world(s.to_unit(p)).numpy(), o, atol=1e-12)
    assert float(torch.linalg.vector_norm(s.to_unit(p), dim=1).max()) <= 1.1


def test_similarity_refuses_outward_and_parallel_cameras():
    o, d = _ring(np.zeros(3), 0.2, outward=True)  # inside the object, looking out
    with pytest.raises(InputError, match="behind most cameras"):
        Similarity.from_cameras(o, d, "transforms.json")
    o = np.random.default_rng(0).normal(size=(8, 3))
    with pytest.raises(InputError, match="parallel"):
        Similarity.from_cameras(o, np.tile([0.0, 0.0, -1.0], (8, 1)), "transforms.json")
