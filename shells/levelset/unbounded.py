"""Shells of an unbounded field, taken from field space back to the world (paper §4.7).

An unbounded field (`shells.fields.network.ShellField`, ``cfg.unbounded``) is an SDF of the
contracted point z = W(x) = centre + radius c((x - centre) / radius), so its shells are
extracted on the grid over the field-space box, as for a bounded field, and only then taken to
the world vertex by vertex with W^-1. Ray casting, band sampling, stage 2 and rendering then
run in world space, unchanged.

Containment. A mapped triangle is straight in the world, while the image of the field-space
triangle is curved, so between its vertices the world mesh is not exactly W^-1 of the
extracted one. Everything the shells must keep in (M+) or out (M-) lies at least part of a grid
cell away from them (the dilation / erosion moves each front by kernel multiples, and marching
cubes places vertices on cell edges), so the mapped mesh keeps containment when it stays
within a small share of a cell of the extracted one. `to_world` measures this for every edge:
the world chord's midpoint taken back to field space, against the field-space midpoint of the
edge (the largest deviation of a short chord is at its middle), in units of the grid spacing
h. While it is above ``tol`` (default 0.1 h) on any edge, every triangle is split into four
in field space (midpoints in field space, which W^-1 takes to points on the curved image) and
the check is repeated: the deviation falls 4x per split. On the test scenes and the fox at
256^3 no split was needed (BENCHMARKS.md). Vertices beyond the contracted radius ``clamp``
(1.99, 100 radii away; only the inner shell's part in the solid far sphere gets there, and
points at radius 2 are infinitely far) are pulled in radially to it: they stay inside the far
solid, so M- stays inside the solid. Edges with both ends in the far solid (beyond the far
radius) are not checked: their chords stay in it.
"""

from __future__ import annotations

import numpy as np
import torch
import trimesh

from shells.fields.contraction import Similarity, contract, uncontract

CLAMP = 1.99  # contracted radius (radius units) the vertices are kept within
TOL = 0.1  # largest chord deviation allowed, in grid spacings (field space)
MAX_SPLITS = 3


def _clamped(z: np.ndarray, sim: Similarity, clamp: float) -> tuple[np.ndarray, int]:
    """Field-space points pulled in radially to the contracted radius ``clamp``."""
    c = np.asarray(sim.centre)
    y = (z - c) / sim.radius
    r = np.linalg.norm(y, axis=1, keepdims=True)
    over = r[:, 0] > clamp
    y = np.where(over[:, None], y * (clamp / np.maximum(r, 1e-12)), y)
    return y * sim.radius + c, int(over.sum())


def _to_world(z: np.ndarray, sim: Similarity) -> np.ndarray:  # field space, |y| < 2
    y = (z - np.asarray(sim.centre)) / sim.radius
    x = uncontract(torch.from_numpy(y.astype(np.float64))).numpy()
    return x * sim.radius + np.asarray(sim.centre)


def _to_field(x: np.ndarray, sim: Similarity) -> np.ndarray:
    u = (x - np.asarray(sim.centre)) / sim.radius
    return contract(torch.from_numpy(u)).numpy() * sim.radius + np.asarray(sim.centre)


def chord_deviation(mesh: trimesh.Trimesh, world: np.ndarray, sim: Similarity,
                    far: float | None = None) -> np.ndarray:
    """Per unique edge: |W(chord midpoint) - field-space midpoint| (field-space units); 0 for
    edges with both ends beyond the contracted radius ``far`` (inside the far solid, where a
    chord stays: it dips by r (1 - cos(angle / 2)), a millionth of r for a grid cell)."""
    e = mesh.edges_unique
    if len(e) == 0:
        return np.zeros(0)
    zm = 0.5 * (mesh.vertices[e[:, 0]] + mesh.vertices[e[:, 1]])
    wm = 0.5 * (world[e[:, 0]] + world[e[:, 1]])
    dev = np.linalg.norm(_to_field(wm, sim) - zm, axis=1)
    if far is not None:
        y = np.linalg.norm((np.asarray(mesh.vertices) - np.asarray(sim.centre)) / sim.radius,
                           axis=1)
        dev[(y[e[:, 0]] > far) & (y[e[:, 1]] > far)] = 0.0
    return dev


def to_world(mesh: trimesh.Trimesh,  # field-space shell (vertices z)
             sim: Similarity, spacing: float,  # the grid spacing h (field space)
             tol: float = TOL, clamp: float = CLAMP, max_splits: int = MAX_SPLITS,
             far: float | None = None,  # the field's far radius: edges beyond are not checked
             ) -> tuple[trimesh.Trimesh, dict]:
    """The world mesh W^-1(mesh) with chords within ``tol`` h of the field-space mesh (see the
    module), and its report: splits made, largest deviation (in h), clamped vertices."""
    if len(mesh.faces) == 0:
        return mesh.copy(), {"splits": 0, "max_chord_deviation_h": 0.0, "clamped_vertices": 0}
    m = trimesh.Trimesh(np.asarray(mesh.vertices, np.float64), mesh.faces, process=False)
    splits = 0
    while True:
        z, clamped = _clamped(np.asarray(m.vertices), sim, clamp)
        m = trimesh.Trimesh(z, m.faces, process=False)
        world = _to_world(z, sim)
        dev = float(chord_deviation(m, world, sim, far).max()) / spacing
        if dev <= tol or splits >= max_splits:
            break
        v, f = trimesh.remesh.subdivide(m.vertices, m.faces)
        m = trimesh.Trimesh(v, f, process=False)
        splits += 1
    out = trimesh.Trimesh(world.astype(np.float64), m.faces, process=False)
    return out, {"splits": splits, "max_chord_deviation_h": dev, "clamped_vertices": clamped,
                 "within_tolerance": bool(dev <= tol), "tolerance_h": tol}
