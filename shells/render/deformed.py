"""Rendering a deformed asset through its tetrahedral cage (paper §5).

Given the cage at rest (vertices X, tetrahedra T) and deformed (vertices x):

* the shells move with the cage: each M+ / M- vertex keeps its barycentric coordinates in its
  rest tetrahedron (`shells.levelset.cage.build_cage` stores them), so its deformed position
  is the same combination of the deformed tetrahedron's vertices (`deformed_positions`); rays
  are cast against the deformed shells exactly as in band mode (`shells.render.frame`);
* every band sample x is mapped back to the rest pose through the deformed tetrahedron that
  holds it (`shells.levelset.cage.TetLocator`): inside tetrahedron k the map is affine,
  X = A_k x + b_k with A_k = Dm_k Ds_k^-1 (rest and deformed edge matrices), and the field is
  evaluated at X, with the view direction A_k d (normalised) for the colour;
* the NeuS opacity needs the slope of the deformed SDF along the ray: f_def(x) = f(A x + b) has
  gradient A^T grad f, so `DeformedField` reports the normal A^T n, and d . A^T n = (A d) . n
  is the rest-pose slope times the stretch |A d| of the ray: with the section length delta
  measured along the deformed ray, the opacity is that of the rest-pose section of length
  |A d| delta (exact for a rigid motion, first order for any other);
* a sample in no tetrahedron is empty (no density).

`DeformedField` has the field interface of the Dr.Jit renderer (``eval(x, d) -> FieldSample``),
so one batched evaluation per ray batch renders a deformed frame with `render_image` as is.
`CageAsset.pose` gives both for a cage pose, moving one ShellScene in place. Everything is in
the current Mitsuba variant's arrays, so the CUDA variant runs the same code (untested here:
no GPU was available).
"""

from __future__ import annotations

from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np

from shells.errors import InputError
from shells.fields.drjit_field import FieldSample
from shells.levelset.cage import TetLocator, tet_edges
from shells.render.raycast import ShellScene

EMPTY_SDF = 1e6  # SDF reported outside every tetrahedron: no density


def _vec(cls: type, a: np.ndarray) -> Any:
    a = np.ascontiguousarray(a, dtype=np.float32)
    return cls(*[mi.Float(a[:, i].copy()) for i in range(3)])


class DeformedField:
    """The rest-pose Dr.Jit field ``field`` seen through the cage deformation X -> x."""

    def __init__(self, field: Any, rest: np.ndarray, tets: np.ndarray,
                 deformed: np.ndarray, cells_per_tet: float = 1.0,
                 rest_edges: np.ndarray | None = None,  # tet_edges(rest, tets), if known
                 ) -> None:
        rest = np.asarray(rest, np.float64)
        deformed = np.asarray(deformed, np.float64)
        if deformed.shape != rest.shape:
            raise InputError(f"deformed cage of shape {deformed.shape}: the rest cage has "
                             f"{rest.shape}")
        self.field = field
        self.locator = TetLocator(deformed, tets, cells_per_tet)
        Dm = tet_edges(rest, tets) if rest_edges is None else rest_edges
        A = Dm @ self.locator.inverse_edges  # Dm Ds^-1 (0 if collapsed)
        b = rest[tets[:, 0]] - np.einsum("mij,mj->mi", A, deformed[tets[:, 0]])
        self.rows = [_vec(mi.Vector3f, A[:, r, :]) for r in range(3)]
        self.offset = _vec(mi.Vector3f, b)

    def to_rest(self, x: Any, d: Any) -> tuple[Any, Any, Any, list]:
        """(found Bool, rest position X, rest direction A d (not normalised), rows of A)."""
        tet, _ = self.locator.locate(x)
        found = tet >= 0
        t = mi.UInt32(dr.maximum(tet, 0))
        rows = [dr.gather(mi.Vector3f, r, t, found) for r in self.rows]
        b = dr.gather(mi.Vector3f, self.offset, t, found)
        X = mi.Point3f(dr.dot(rows[0], x), dr.dot(rows[1], x), dr.dot(rows[2], x)) + b
        Ad = mi.Vector3f(dr.dot(rows[0], d), dr.dot(rows[1], d), dr.dot(rows[2], d))
        return found, X, Ad, rows

    def eval(self, x: Any, d: Any) -> FieldSample:
        found, X, Ad, rows = self.to_rest(mi.Point3f(x), mi.Vector3f(d))
        dn = Ad * dr.rcp(dr.maximum(dr.norm(Ad), 1e-12))
        f = self.field.eval(X, dn)
        n = f.normal
        pulled = rows[0] * n.x + rows[1] * n.y + rows[2] * n.z  # A^T n
        return FieldSample(sdf=dr.select(found, f.sdf, EMPTY_SDF), s=f.s,
                           normal=dr.select(found, pulled, 0.0), rgb=f.rgb)


def deformed_positions(tet: np.ndarray, w: np.ndarray, tets: np.ndarray,
                       deformed: np.ndarray) -> np.ndarray:
    """Positions [k, 3] of points embedded as (tetrahedron [k], weights [k, 4])."""
    return np.einsum("kj,kjc->kc", w, deformed[tets[tet]])


class CageAsset:
    """A field, its shells and its cage: `pose` gives the field and the shells of a deformed
    cage, ready for `shells.render.frame.render_image` in band mode. One ShellScene is built
    at rest and moved in place for every pose (`ShellScene.move`)."""

    def __init__(self, field: Any, rest: np.ndarray, tets: np.ndarray,
                 embedding: dict[str, np.ndarray], outer_faces: np.ndarray,
                 inner_faces: np.ndarray, variant: str | None = None,
                 cells_per_tet: float = 1.0) -> None:
        self.field, self.rest, self.tets = field, np.asarray(rest, np.float64), tets
        self.embedding, self.cells_per_tet = embedding, cells_per_tet
        self.rest_edges = tet_edges(self.rest, tets)  # the same for every pose
        self.has_inner = len(inner_faces) > 0
        outer, inner = self._shells(self.rest)
        self.scene = ShellScene((outer, outer_faces),
                                (inner, inner_faces) if self.has_inner else None, variant)

    def _shells(self, cage: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        e = self.embedding
        outer = deformed_positions(e["outer_tet"], e["outer_w"], self.tets, cage)
        inner = (deformed_positions(e["inner_tet"], e["inner_w"], self.tets, cage)
                 if self.has_inner else None)
        return outer, inner

    def pose(self, deformed: np.ndarray) -> tuple[DeformedField, ShellScene]:
        deformed = np.asarray(deformed, np.float64)
        if deformed.shape != self.rest.shape:
            raise InputError(f"cage pose of shape {deformed.shape}: this cage has "
                             f"{self.rest.shape} vertices")
        self.scene.move(*self._shells(deformed))
        return (DeformedField(self.field, self.rest, self.tets, deformed, self.cells_per_tet,
                              self.rest_edges), self.scene)
