"""Marching cubes of a gridded SDF, mesh cleanup and PLY I/O for the shells.

Conventions: f > 0 outside; meshes are in world coordinates with outward-facing triangles
(counter-clockwise seen from outside, so the enclosed volume is positive). A cavity's surface
faces into the cavity (away from the solid), as it should.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import trimesh
from skimage import measure
from trimesh.exchange.ply import export_ply, load_ply as _trimesh_load_ply

from shells.errors import InputError
from shells.files import atomic_write
from shells.levelset.grid import check_aabb


def empty_mesh() -> trimesh.Trimesh:
    return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), process=False)


def marching_cubes(f: np.ndarray,  # [X, Y, Z] SDF samples at the grid points, f > 0 outside
                   aabb) -> trimesh.Trimesh:
    """Zero level set of ``f`` in world coordinates, closed at the box boundary.

    The grid is padded by one layer of large positive values so that a surface cut by the box
    is capped on the box face (the mesh stays watertight; the cap is clipped onto the face).
    Exact zeros are nudged outside so no vertex sits on a grid point (which would create
    duplicate, degenerate vertices). Returns an empty mesh when f has no negative sample.
    """
    f = np.asarray(f, dtype=np.float32)
    box = check_aabb(aabb)
    spacing = (box[1] - box[0]) / (np.asarray(f.shape) - 1)
    if not np.any(f < 0):
        return empty_mesh()
    big = float(max(np.abs(f).max(), 1.0)) * 4.0
    padded = np.pad(np.where(f == 0, np.float32(1e-7 * spacing.min()), f), 1,
                    constant_values=big)
    verts, faces, _, _ = measure.marching_cubes(padded, level=0.0, spacing=tuple(spacing),
                                                allow_degenerate=False)
    # caps lie a sliver (|f| / big of a voxel) outside the box: put them on the box face
    verts = np.clip(verts + (box[0] - spacing), box[0], box[1])
    mesh = trimesh.Trimesh(verts, faces, process=False)
    if mesh.volume < 0:  # keep outward orientation whatever skimage's winding convention is
        mesh.invert()
    return mesh


def clean_mesh(mesh: trimesh.Trimesh, min_component_fraction: float = 0.0,
               roi: tuple[tuple[float, float, float], float] | None = None) -> trimesh.Trimesh:
    """Merge duplicate vertices, drop components with fewer than ``min_component_fraction`` of
    all faces; keep the outward orientation (volume > 0).

    ``roi`` (centre, radius): count only the faces in that ball for the fraction (an unbounded
    scene's shells: the far background and the grid box's closure would otherwise outnumber
    the object, and its small parts would be dropped as specks).

    Near-zero-area faces are kept: skimage already drops exactly degenerate ones, and the
    slivers that remain (e.g. where a surface meets the capped box face) are needed for the
    mesh to stay watertight.
    """
    if len(mesh.faces) == 0:
        return empty_mesh()
    mesh = mesh.copy()
    mesh.merge_vertices()
    mesh.remove_unreferenced_vertices()
    if min_component_fraction > 0 and len(mesh.faces) > 0:
        labels = trimesh.graph.connected_component_labels(mesh.face_adjacency,
                                                          node_count=len(mesh.faces))
        counts = np.bincount(labels)
        total = len(mesh.faces)
        if roi is not None:
            near = np.linalg.norm(mesh.triangles_center - np.asarray(roi[0]), axis=1) <= roi[1]
            total = max(int(near.sum()), 1)
        keep = counts[labels] >= min_component_fraction * total
        if not np.all(keep):
            mesh.update_faces(keep)
            mesh.remove_unreferenced_vertices()
    if len(mesh.faces) and mesh.volume < 0:
        mesh.invert()
    return mesh


def write_ply(path: str | Path, mesh: trimesh.Trimesh) -> None:
    """Atomically write a binary little-endian PLY (float32 xyz, int32 faces); empty is valid."""
    data = export_ply(mesh, encoding="binary", include_attributes=False)
    atomic_write(path, lambda p: p.write_bytes(data))


def load_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray]:  # V [n, 3] f32, F [m, 3] i32
    """Read a triangle PLY; an empty file (0 vertices, 0 faces) gives empty arrays."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: mesh not found; run shells-extract first")
    try:
        data = _trimesh_load_ply(io.BytesIO(path.read_bytes()))
    except Exception as exc:  # trimesh raises assorted types on malformed files
        raise InputError(f"{path}: not a readable PLY mesh ({exc}); re-run shells-extract")
    verts = np.asarray(data.get("vertices", np.zeros((0, 3))), dtype=np.float32).reshape(-1, 3)
    faces = np.asarray(data.get("faces", np.zeros((0, 3))), dtype=np.int32).reshape(-1, 3)
    if faces.size and (faces.min() < 0 or faces.max() >= len(verts)):
        raise InputError(f"{path}: face indices out of range; re-run shells-extract")
    return verts, faces
