"""A tetrahedral cage around the outer shell, and point location in it (paper §5, Fig. 12).

The outer shell M+ contains everything visible, so a tetrahedral mesh that contains M+ can
carry the field through a deformation: move the cage's vertices, move the shells with them by
barycentric interpolation, and map every band sample back to the rest pose through the
tetrahedron that holds it (`shells.render.deformed`).

Building the cage (`build_cage`):

1. **Solidify and dilate on a voxel grid.** The cage grid (``resolution`` cells along the
   longest side of M+'s box, padded by the margin) marks the cells that hold points of M+
   (its vertices, edge midpoints and face centroids: M+ comes from marching cubes on a finer
   grid, so these are denser than the cells), thickened by one cell so that a 6-connected
   flood fill from the grid's corner cannot slip through. What the fill does not reach is the
   solid S: M+ and its interior. The distance to S (``scipy.ndimage.distance_transform_edt``,
   exact Euclidean distance between cell centres) minus ``margin`` is an SDF of S dilated by
   the margin; its zero level set (marching cubes, `shells.levelset.mesh`) is a closed,
   watertight surface at distance ~margin outside M+.
2. **Tetrahedralize** that surface with fTetWild (``pytetwild``, MPL-2.0): its output surface
   stays within ``epsilon`` (relative to the box diagonal) of the input, far less than the
   margin, so the tetrahedra still contain M+. Tetrahedra are reoriented to positive volume.
3. **Check containment**: every M+ and M- vertex is located in a tetrahedron (`TetLocator`);
   the barycentric coordinates found are the shells' embedding. A vertex in no tetrahedron is
   an error naming the fix (a larger margin). The boundary faces (faces of one tetrahedron
   only) must form a closed 2-manifold (`boundary_faces`, `is_watertight`).

Point location (`TetLocator`, Dr.Jit): a uniform grid over the tetrahedra's box lists, per
cell, the tetrahedra whose bounding box overlaps it (CSR arrays built in numpy); a query
visits its cell's list and takes the first tetrahedron whose barycentric coordinates are all
>= -``eps``. The same locator embeds the shells (rest pose) and maps band samples (deformed
pose, rebuilt each frame), so there is one implementation of "which tetrahedron holds x".
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np
import trimesh
from scipy import ndimage

from shells.errors import InputError
from shells.files import atomic_write
from shells.levelset.mesh import clean_mesh, marching_cubes

LOCATE_EPS = 1e-5  # barycentric tolerance: a point on a shared face belongs to either side
DEGENERATE = 1e-12  # |det| below this (relative to the mean) marks a collapsed tetrahedron


@dataclass
class Cage:
    vertices: np.ndarray  # [n, 3] float64 rest positions (world units)
    tets: np.ndarray  # [m, 4] int64, positive orientation
    stats: dict = field(default_factory=dict)  # JSON-ready: counts, quality, parameters, times


# --------------------------------------------------------------------------------------------
# Geometry of tetrahedral meshes
# --------------------------------------------------------------------------------------------

def tet_edges(V: np.ndarray, T: np.ndarray) -> np.ndarray:  # -> [m, 3, 3]: columns v_k - v_0
    p = V[T]
    return np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=-1)


def tet_volumes(V: np.ndarray, T: np.ndarray) -> np.ndarray:  # [m] signed volumes
    return np.linalg.det(tet_edges(V, T)) / 6.0


def orient(V: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Tetrahedra with negative volume get two vertices swapped."""
    T = np.array(T, dtype=np.int64, copy=True)
    neg = tet_volumes(V, T) < 0
    T[neg, 2], T[neg, 3] = T[neg, 3].copy(), T[neg, 2].copy()
    return T


def quality(V: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Mean-ratio-like quality 6 sqrt(2) V / l_rms^3 per tetrahedron: 1 for a regular one,
    -> 0 for slivers (negative when inverted)."""
    p = V[T]
    pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    l2 = np.stack([((p[:, a] - p[:, b]) ** 2).sum(1) for a, b in pairs], 1).mean(1)
    return 6.0 * np.sqrt(2.0) * tet_volumes(V, T) / np.maximum(l2, 1e-300) ** 1.5


def boundary_faces(T: np.ndarray) -> np.ndarray:
    """Faces that belong to exactly one tetrahedron, oriented outward: [k, 3]."""
    T = np.asarray(T, dtype=np.int64)
    # faces opposite vertex 0..3, wound so that the normal points away from that vertex
    local = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
    faces = T[:, local].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inv.reshape(-1)] == 1]


def is_watertight(faces: np.ndarray) -> bool:
    """Every edge of the triangle set is shared by exactly two triangles, in opposite
    directions (closed, consistently oriented 2-manifold)."""
    if len(faces) == 0:
        return False
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    und = np.sort(e, axis=1)
    _, counts = np.unique(und, axis=0, return_counts=True)
    if not np.all(counts == 2):
        return False
    _, dcounts = np.unique(e, axis=0, return_counts=True)  # each directed edge exactly once
    return bool(np.all(dcounts == 1))


# --------------------------------------------------------------------------------------------
# Point location
# --------------------------------------------------------------------------------------------

class TetLocator:
    """Which tetrahedron holds each query point, and its barycentric coordinates (Dr.Jit).

    Built from vertex positions (any pose) and the tetrahedra; `locate` takes an
    ``mi.Point3f`` of width M and returns (tet ``mi.Int`` [M], -1 outside every tetrahedron;
    barycentric ``mi.Vector3f`` [M] for vertices 1..3, vertex 0 gets 1 - sum). Collapsed
    tetrahedra (|det| ~ 0, e.g. flattened by a simulation) are never returned.
    """

    def __init__(self, V: np.ndarray, T: np.ndarray, cells_per_tet: float = 1.0) -> None:
        if mi.variant() is None:
            from shells.device import mitsuba_variant
            mitsuba_variant()
        V = np.asarray(V, dtype=np.float64)
        T = np.asarray(T, dtype=np.int64)
        if V.ndim != 2 or V.shape[1] != 3 or T.ndim != 2 or T.shape[1] != 4 or len(T) == 0:
            raise InputError(f"cage: expected vertices [n, 3] and tetrahedra [m, 4], got "
                             f"{V.shape}, {T.shape}")
        if not np.all(np.isfinite(V)):
            raise InputError("cage: vertex positions contain NaN/inf (a diverged deformation?)")
        self.n_tets = len(T)
        D = tet_edges(V, T)
        det = np.linalg.det(D)
        ok = np.abs(det) > DEGENERATE * max(float(np.abs(det).mean()), 1e-300)
        Dinv = np.zeros_like(D)
        Dinv[ok] = np.linalg.inv(D[ok])
        self.valid = ok
        self.inverse_edges = Dinv  # [m, 3, 3] Ds^-1 (0 for collapsed tetrahedra)
        p = V[T]
        lo, hi = p.min(1), p.max(1)  # [m, 3] tetrahedron boxes
        self.lo = lo.min(0)
        span = np.maximum(hi.max(0) - self.lo, 1e-12)
        cell = (np.prod(span) * cells_per_tet / max(int(ok.sum()), 1)) ** (1.0 / 3.0)
        self.res = np.clip(np.ceil(span / cell), 1, 512).astype(np.int64)
        self.cell = span / self.res
        start, members = _csr(lo[ok], hi[ok], self.lo, self.cell, self.res)
        members = np.flatnonzero(ok)[members]  # back to tetrahedron ids
        self.mean_candidates = float(len(members) / max(len(start) - 1, 1))

        self.start = mi.UInt32(start.astype(np.uint32))
        self.members = mi.UInt32(members.astype(np.uint32))
        self.v0 = _vec(mi.Point3f, p[:, 0])
        self.rows = [_vec(mi.Vector3f, Dinv[:, r, :]) for r in range(3)]

    def locate(self, x: Any) -> tuple[Any, Any]:
        rel = [(x[a] - float(self.lo[a])) / float(self.cell[a]) for a in range(3)]
        inside_box = mi.Bool(True)
        idx = []
        for a in range(3):
            inside_box &= (rel[a] >= 0.0) & (rel[a] <= float(self.res[a]))
            idx.append(dr.clip(mi.Int(dr.floor(rel[a])), 0, int(self.res[a]) - 1))
        c = mi.UInt32((idx[2] * int(self.res[1]) + idx[1]) * int(self.res[0]) + idx[0])
        begin = dr.gather(mi.UInt32, self.start, c, inside_box)
        end = dr.gather(mi.UInt32, self.start, c + 1, inside_box)
        return _search(mi.Point3f(x), begin, end, self.members, self.v0, *self.rows,
                       LOCATE_EPS)

    def locate_numpy(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`locate` for a numpy [N, 3] array: tet [N] int (-1 outside), weights [N, 4]."""
        tet, b = self.locate(_vec(mi.Point3f, np.asarray(pts, dtype=np.float64)))
        t = np.asarray(tet.numpy(), dtype=np.int64)
        b = np.stack([np.asarray(b[a].numpy(), np.float64) for a in range(3)], 1)
        w = np.concatenate([1.0 - b.sum(1, keepdims=True), b], axis=1)
        w[t < 0] = 0.0
        return t, w


def _vec(cls: type, a: np.ndarray) -> Any:
    a = np.ascontiguousarray(a, dtype=np.float32)
    return cls(*[mi.Float(a[:, i].copy()) for i in range(3)])


def _csr(lo: np.ndarray, hi: np.ndarray, origin: np.ndarray, cell: np.ndarray,
         res: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cell -> overlapping boxes, as (start [C + 1], members [P]) with C = prod(res)."""
    a = np.clip(np.floor((lo - origin) / cell).astype(np.int64), 0, res - 1)
    b = np.clip(np.floor((hi - origin) / cell).astype(np.int64), 0, res - 1)
    ext = b - a + 1
    cells, owners = [], []
    ids = np.arange(len(lo))
    # one pass per offset inside the largest box extent (a few dozen), each over all boxes
    for dz in range(int(ext[:, 2].max())):
        for dy in range(int(ext[:, 1].max())):
            for dx in range(int(ext[:, 0].max())):
                m = (ext[:, 0] > dx) & (ext[:, 1] > dy) & (ext[:, 2] > dz)
                am = a[m]
                cells.append(((am[:, 2] + dz) * res[1] + am[:, 1] + dy) * res[0] + am[:, 0] + dx)
                owners.append(ids[m])
    cells = np.concatenate(cells)
    owners = np.concatenate(owners)
    order = np.argsort(cells)
    start = np.zeros(int(res.prod()) + 1, np.int64)
    np.cumsum(np.bincount(cells, minlength=int(res.prod())), out=start[1:])
    return start, owners[order]


@dr.syntax
def _search(x: Any, begin: Any, end: Any, members: Any, v0: Any, r0: Any, r1: Any, r2: Any,
            eps: float) -> tuple[Any, Any]:
    """First tetrahedron of members[begin:end] holding x: (tet Int, -1 if none; bary)."""
    tet = dr.full(mi.Int, -1, dr.width(begin))
    bary = dr.zeros(mi.Vector3f, dr.width(begin))
    i = mi.UInt32(begin)
    while dr.hint((i < end) & (tet < 0), max_iterations=-1, label="cage_locate"):
        t = dr.gather(mi.UInt32, members, i)
        p = x - dr.gather(mi.Point3f, v0, t)
        b = mi.Vector3f(dr.dot(dr.gather(mi.Vector3f, r0, t), p),
                        dr.dot(dr.gather(mi.Vector3f, r1, t), p),
                        dr.dot(dr.gather(mi.Vector3f, r2, t), p))
        b0 = 1.0 - b.x - b.y - b.z
        if dr.minimum(dr.minimum(b0, b.x), dr.minimum(b.y, b.z)) >= -eps:
            tet = mi.Int(t)
            bary = b
        i += 1
    return tet, bary


# --------------------------------------------------------------------------------------------
# Building the cage
# --------------------------------------------------------------------------------------------

def dilated_surface(V: np.ndarray, F: np.ndarray, margin: float,
                    resolution: int) -> tuple[trimesh.Trimesh, float]:
    """The surface at distance ~``margin`` outside the solid bounded by (V, F), closed and
    watertight (step 1 of the module docstring); also returns the cage-grid cell size."""
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    lo, hi = V.min(0), V.max(0)
    h = float((hi - lo).max()) / resolution
    pad = margin + 3 * h
    origin = lo - pad
    shape = np.ceil((hi - lo + 2 * pad) / h).astype(np.int64) + 1
    pts = np.concatenate([V, V[F].mean(1), 0.5 * (V[F[:, 0]] + V[F[:, 1]]),
                          0.5 * (V[F[:, 1]] + V[F[:, 2]]), 0.5 * (V[F[:, 2]] + V[F[:, 0]])])
    ijk = np.clip(np.round((pts - origin) / h).astype(np.int64), 0, shape - 1)
    surf = np.zeros(tuple(shape), bool)
    surf[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    surf = ndimage.binary_dilation(surf, ndimage.generate_binary_structure(3, 3))
    labels, _ = ndimage.label(~surf)  # 6-connected free space
    outside = labels == labels[0, 0, 0]
    dist = ndimage.distance_transform_edt(outside) * h  # 0 on the solid (and its shell)
    # the shell layer added above reaches ~1.5 h beyond M+; count the margin from M+ itself
    f = dist - max(margin - 1.5 * h, 0.5 * h)
    box = np.stack([origin, origin + (shape - 1) * h])
    mesh = clean_mesh(marching_cubes(f.astype(np.float32), box))
    return mesh, h


def build_cage(outer: tuple[np.ndarray, np.ndarray],  # M+ (V, F)
               inner: tuple[np.ndarray, np.ndarray] | None = None,  # M- (V, F), may be empty
               margin: float | None = None,  # world units; default 2.5 cage cells
               resolution: int = 48,  # cage-grid cells along M+'s longest side
               edge_length: float = 0.06,  # fTetWild target edge, share of the box diagonal
               epsilon: float = 1e-3,  # fTetWild envelope, share of the box diagonal
               threads: int = 0,  # fTetWild threads, 0 = all cores
               ) -> tuple[Cage, dict[str, Any]]:
    """The cage of the module docstring, and the shells' embedding
    {'outer_tet', 'outer_w', 'inner_tet', 'inner_w'} (tetrahedron [n], weights [n, 4])."""
    import pytetwild

    Vo, Fo = (np.asarray(a) for a in outer)
    if len(Fo) == 0:
        raise InputError("outer shell is empty: no cage to build; re-run shells-extract")
    if resolution < 8:
        raise InputError(f"--resolution {resolution}: use at least 8 cells (e.g. 48)")
    if not 0 < edge_length <= 1:
        raise InputError(f"--edge-length {edge_length}: a share of the box diagonal in (0, 1]")
    t0 = time.perf_counter()
    h0 = float((Vo.max(0) - Vo.min(0)).max()) / resolution
    margin = 2.5 * h0 if margin is None else float(margin)
    if margin <= 0:
        raise InputError(f"--margin {margin}: must be > 0 world units")
    surface, h = dilated_surface(Vo, Fo, margin, resolution)
    t1 = time.perf_counter()
    here = os.getcwd()
    with tempfile.TemporaryDirectory(prefix="shells-tetwild-") as scratch:
        os.chdir(scratch)  # fTetWild writes a debug file (__tracked_surface.stl) into the cwd
        try:
            Vt, Tt = pytetwild.tetrahedralize(np.asarray(surface.vertices, np.float64),
                                              np.asarray(surface.faces, np.int32),
                                              edge_length_fac=edge_length, epsilon=epsilon,
                                              num_threads=threads, quiet=True)
        finally:
            os.chdir(here)
    t2 = time.perf_counter()
    Vt = np.asarray(Vt, np.float64)
    Tt = orient(Vt, np.asarray(Tt, np.int64))
    used = np.unique(Tt)
    if len(used) < len(Vt):  # drop vertices no tetrahedron uses
        remap = np.full(len(Vt), -1, np.int64)
        remap[used] = np.arange(len(used))
        Vt, Tt = Vt[used], remap[Tt]
    locator = TetLocator(Vt, Tt)
    emb = {}
    for name, mesh in (("outer", (Vo, Fo)), ("inner", inner)):
        Vm = np.zeros((0, 3)) if mesh is None else np.asarray(mesh[0], np.float64)
        tet, w = locator.locate_numpy(Vm) if len(Vm) else (np.zeros(0, np.int64),
                                                           np.zeros((0, 4)))
        missing = int((tet < 0).sum())
        if missing:
            raise InputError(f"cage: {missing} of {len(Vm)} {name}-shell vertices lie in no "
                             f"tetrahedron; build it again with a larger --margin (now "
                             f"{margin:.4g})")
        emb[f"{name}_tet"], emb[f"{name}_w"] = tet, w
    bf = boundary_faces(Tt)
    q = quality(Vt, Tt)
    stats = {
        "vertices": int(len(Vt)), "tetrahedra": int(len(Tt)),
        "boundary_faces": int(len(bf)), "watertight": is_watertight(bf),
        "volume": float(tet_volumes(Vt, Tt).sum()),
        "quality": {"min": float(q.min()), "p01": float(np.percentile(q, 1)),
                    "median": float(np.median(q)), "mean": float(q.mean())},
        "contains_outer_vertices": int(len(Vo)),
        "contains_inner_vertices": int(len(emb["inner_tet"])),
        "locator_candidates_per_cell": locator.mean_candidates,
        "params": {"margin": margin, "resolution": int(resolution), "cell": h,
                   "edge_length": edge_length, "epsilon": epsilon},
        "dilated_surface_triangles": int(len(surface.faces)),
        "timings_s": {"dilate": t1 - t0, "tetwild": t2 - t1,
                      "embed": time.perf_counter() - t2},
    }
    if not stats["watertight"]:
        raise InputError("cage: the tetrahedral mesh's boundary is not closed (fTetWild "
                         "output); try another --edge-length or --resolution")
    return Cage(Vt, Tt, stats), emb


# --------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------

def write_cage(folder: Path, cage: Cage, embedding: dict[str, Any],
               extra: dict[str, Any] | None = None) -> None:
    """folder/cage.npz (vertices, tets, shell embedding: what the code reads),
    folder/cage.vtu (the tetrahedra for ParaView and other tools), folder/cage.json (stats)."""
    folder.mkdir(parents=True, exist_ok=True)

    def npz(p: Path) -> None:
        with open(p, "wb") as fh:
            np.savez(fh, vertices=cage.vertices, tets=cage.tets, **embedding)

    atomic_write(folder / "cage.npz", npz)
    atomic_write(folder / "cage.vtu", lambda p: p.write_text(vtu_text(cage.vertices,
                                                                       cage.tets)))
    stats = {**cage.stats, **(extra or {})}
    atomic_write(folder / "cage.json", lambda p: p.write_text(json.dumps(stats, indent=2)))


def vtu_text(V: np.ndarray, T: np.ndarray) -> str:
    """A VTK XML UnstructuredGrid (ASCII) of tetrahedra (VTK cell type 10)."""
    pts = "\n".join(" ".join(f"{c:.9g}" for c in v) for v in V)
    con = "\n".join(" ".join(str(int(i)) for i in t) for t in T)
    off = " ".join(str(4 * (k + 1)) for k in range(len(T)))
    typ = " ".join("10" for _ in range(len(T)))
    return ('<?xml version="1.0"?>\n<VTKFile type="UnstructuredGrid" version="0.1" '
            'byte_order="LittleEndian">\n<UnstructuredGrid>\n'
            f'<Piece NumberOfPoints="{len(V)}" NumberOfCells="{len(T)}">\n'
            f'<Points>\n<DataArray type="Float64" NumberOfComponents="3" format="ascii">\n'
            f'{pts}\n</DataArray>\n</Points>\n<Cells>\n'
            f'<DataArray type="Int64" Name="connectivity" format="ascii">\n{con}\n</DataArray>\n'
            f'<DataArray type="Int64" Name="offsets" format="ascii">\n{off}\n</DataArray>\n'
            f'<DataArray type="UInt8" Name="types" format="ascii">\n{typ}\n</DataArray>\n'
            '</Cells>\n</Piece>\n</UnstructuredGrid>\n</VTKFile>\n')


def read_cage(path: Path) -> tuple[Cage, dict[str, np.ndarray]]:
    """folder/cage.npz -> (Cage, embedding)."""
    if not path.is_file():
        raise InputError(f"{path}: no cage; run shells-cage first")
    try:
        with np.load(path) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:
        raise InputError(f"{path}: not a readable cage ({type(exc).__name__}); run shells-cage "
                         "again")
    need = ("vertices", "tets", "outer_tet", "outer_w", "inner_tet", "inner_w")
    if any(k not in data for k in need):
        raise InputError(f"{path}: not a cage file (missing {[k for k in need if k not in data]}"
                         "); run shells-cage again")
    cage = Cage(data.pop("vertices").astype(np.float64), data.pop("tets").astype(np.int64))
    return cage, data
