"""Containment of one closed mesh in another, and the mesh tests it rests on (shells-lod).

`verify` decides whether a coarse shell C lies wholly on one side of a fine closed shell S
(``side`` +1: C contains S; -1: C lies inside S): every vertex of S inside C (outside C) and
every vertex of C outside S (inside S) by generalised winding numbers (`inside`, libigl; exact
near the surface); no triangle of C crosses one of S or another of its own (MeshLab's
self-intersection test on their union and on C alone); every edge of C in two faces, in
opposite directions (`is_closed`). Right-side vertices and no crossing surfaces together imply
containment: closed surfaces that do not meet lie wholly on one side of each other.
`check_side` also says where it failed, which the LOD repairs use (`shells.levelset.lod`).

Also: signed distances (libigl), the enter/exit parity of random rays through a mesh
(Mitsuba / Embree: `crossings`, `parity_check`). World units, outward-facing triangles.
pymeshlab (GPL-3.0) and libigl (MPL-2.0) are imported only inside the functions.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

Mesh = tuple[np.ndarray, np.ndarray]  # V [n, 3] float, F [m, 3] int, outward faces


# --------------------------------------------------------------------------------------------
# Inside tests (libigl winding numbers) and ray parity (Mitsuba / Embree)
# --------------------------------------------------------------------------------------------

def _scene(V: np.ndarray, F: np.ndarray) -> Any:
    import mitsuba as mi

    if mi.variant() is None:
        from shells.device import mitsuba_variant
        mitsuba_variant()
    m = mi.Mesh("shell", vertex_count=len(V), face_count=len(F))
    p = mi.traverse(m)
    p["vertex_positions"] = mi.Float(np.ascontiguousarray(V, np.float32).ravel())
    p["faces"] = mi.UInt(np.ascontiguousarray(F, np.uint32).ravel())
    p.update()
    return mi.load_dict({"type": "scene", "shell": m})


def crossings(V: np.ndarray, F: np.ndarray, o: np.ndarray,  # [R, 3] origins
              d: np.ndarray,  # [R, 3] unit directions
              max_hits: int = 256, scene: Any = None
              ) -> tuple[np.ndarray, np.ndarray]:  # [R] hits, [R] bool: enter/exit alternate
    """Walk every ray through the closed mesh (V, F), hit by hit: the number of surface hits
    and whether they alternate enter, exit, enter, ... (an origin inside starts with an exit).
    ``scene``: a prepared `_scene(V, F)`."""
    import drjit as dr
    import mitsuba as mi

    scene = scene if scene is not None else _scene(V, F)
    n = len(o)
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(o[:, k].astype(np.float32)) for k in range(3)]),
                   mi.Vector3f(*[mi.Float(d[:, k].astype(np.float32)) for k in range(3)]))
    count = np.zeros(n, np.int64)
    last = np.zeros(n, np.int8)  # +1 entered last, -1 exited last, 0 nothing yet
    ok = np.ones(n, bool)
    idx = np.arange(n)
    for _ in range(max_hits):
        si = scene.ray_intersect(ray)
        valid = np.asarray(si.is_valid())
        if not valid.any():
            break
        enter = np.asarray(dr.dot(ray.d, si.n)) < 0
        sel = idx[valid]
        e = np.where(enter[valid], 1, -1).astype(np.int8)
        first = last[sel] == 0
        ok[sel[~first]] &= e[~first] != last[sel[~first]]  # must alternate
        last[sel] = e
        count[sel] += 1
        keep = np.flatnonzero(valid)
        idx = idx[keep]
        nxt = si.spawn_ray(ray.d)
        ray = mi.Ray3f(mi.Point3f(*[mi.Float(np.asarray(c)[keep]) for c in nxt.o]),
                       mi.Vector3f(*[mi.Float(np.asarray(c)[keep]) for c in ray.d]))
    return count, ok


def winding_numbers(V: np.ndarray, F: np.ndarray, points: np.ndarray,  # [N, 3]
                    exact_within: float = 0.3) -> np.ndarray:  # [N]
    """Generalised winding numbers of the closed mesh (V, F) at ``points`` (libigl): 1 inside,
    0 outside. The fast hierarchical approximation (Barill et al. 2018) everywhere, replaced
    by the exact sum of solid angles where it is within ``exact_within`` of 1/2 (points very
    near the surface, where the approximation could decide the side wrongly)."""
    import igl

    V64 = np.ascontiguousarray(V, np.float64)
    F64 = np.ascontiguousarray(F, np.int64)
    Q = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
    if len(Q) == 0 or len(F64) == 0:
        return np.zeros(len(Q))
    w = igl.fast_winding_number(V64, F64, Q)
    near = np.flatnonzero(np.abs(w - 0.5) < exact_within)
    if len(near):
        w[near] = igl.winding_number(V64, F64, np.ascontiguousarray(Q[near]))
    return w


def inside(V: np.ndarray, F: np.ndarray, points: np.ndarray  # [N, 3]
           ) -> np.ndarray:  # [N] bool
    """Point-in-solid test of a closed mesh: winding number above 1/2 (`winding_numbers`).
    Unlike ray parity it does not depend on rays missing edges and vertices, which rays from
    the grid-aligned points of marching-cubes meshes do often enough to matter."""
    return winding_numbers(V, F, points) > 0.5


def parity_check(V: np.ndarray, F: np.ndarray, n_rays: int, box: np.ndarray,
                 seed: int = 0) -> dict:
    """Random rays from outside ``box`` ([2, 3]) through it: every ray must see an even number
    of hits alternating enter / exit (closed, consistently oriented surface). Returns counts."""
    rng = np.random.default_rng(seed)
    c, r = (box[0] + box[1]) / 2, 0.5 * float(np.linalg.norm(box[1] - box[0])) + 1e-3
    u = rng.normal(size=(n_rays, 3))
    o = c + 1.5 * r * u / np.linalg.norm(u, axis=1, keepdims=True)
    target = c + rng.uniform(-0.5, 0.5, size=(n_rays, 3)) * (box[1] - box[0])
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    count, alternate = crossings(V, F, o, d)
    good = (count % 2 == 0) & alternate
    return {"rays": int(n_rays), "rays_hitting": int((count > 0).sum()),
            "parity_ok": int(good.sum()), "parity_fraction": float(good.mean())}


# --------------------------------------------------------------------------------------------
# Signed distance, self-intersections, closedness
# --------------------------------------------------------------------------------------------

def _ms(*meshes: Mesh) -> Any:
    import pymeshlab as ml

    ms = ml.MeshSet()
    for V, F in meshes:
        ms.add_mesh(ml.Mesh(np.asarray(V, np.float64), np.asarray(F, np.int32)))
    return ms


def signed_distance(points: Mesh, ref: Mesh) -> np.ndarray:  # [n] > 0 outside ref
    """Signed distance of the vertices of ``points`` to the closed surface ``ref`` (libigl:
    distance to the nearest point of ref, sign from the winding number; > 0 outside, as f)."""
    import igl

    sd, _, _, _ = igl.signed_distance(
        np.ascontiguousarray(points[0], np.float64), np.ascontiguousarray(ref[0], np.float64),
        np.ascontiguousarray(ref[1], np.int64), sign_type=igl.SIGNED_DISTANCE_TYPE_WINDING_NUMBER)
    return np.asarray(sd)


def self_intersecting_faces(V: np.ndarray, F: np.ndarray) -> np.ndarray:  # [m] bool
    """Faces that intersect another face of (V, F), not counting shared edges / vertices."""
    ms = _ms((V, F))
    ms.compute_selection_by_self_intersections_per_face()
    return ms.current_mesh().face_selection_array().astype(bool)


def is_closed(F: np.ndarray) -> bool:
    """Every edge in exactly two faces, in opposite directions (closed, oriented 2-manifold)."""
    if len(F) == 0:
        return False
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]).astype(np.int64)
    _, c = np.unique(np.sort(e, axis=1), axis=0, return_counts=True)
    _, dc = np.unique(e, axis=0, return_counts=True)
    return bool(np.all(c == 2) and np.all(dc == 1))


# --------------------------------------------------------------------------------------------
# The containment check
# --------------------------------------------------------------------------------------------

def verify(C: Mesh, S: Mesh, side: int) -> dict:
    """The containment check of the module docstring for a coarse shell C and its fine shell S
    (``side`` +1: C must contain S; -1: C must lie inside S)."""
    return check_side(C, S, side)[0]


def check_side(C: Mesh, S: Mesh, side: int) -> tuple[dict, np.ndarray, np.ndarray]:
    """`verify`'s record, and where it failed: the coarse vertices that are on the wrong side
    or on a crossing or self-intersecting face [len(C vertices)] and the fine vertices on the
    wrong side [len(S vertices)], as boolean masks."""
    t0 = time.perf_counter()
    fine_in = inside(*C, S[0])  # fine vertices inside C
    coarse_in = inside(*S, C[0])  # coarse vertices inside S
    fine_ok = fine_in if side > 0 else ~fine_in
    coarse_ok = ~coarse_in if side > 0 else coarse_in
    union_F = np.concatenate([C[1], np.asarray(S[1]) + len(C[0])])
    crossing = self_intersecting_faces(np.concatenate([C[0], S[0]]), union_F)[:len(C[1])]
    own = self_intersecting_faces(*C)
    bad = ~coarse_ok
    bad[np.asarray(C[1])[crossing | own].ravel()] = True
    out = {"fine_vertices": int(len(S[0])), "fine_vertices_ok": int(fine_ok.sum()),
           "coarse_vertices": int(len(C[0])), "coarse_vertices_ok": int(coarse_ok.sum()),
           "crossing_faces": int(crossing.sum()), "self_intersecting_faces": int(own.sum()),
           "closed": is_closed(np.asarray(C[1])), "seconds": time.perf_counter() - t0}
    out["contained"] = bool(out["fine_vertices_ok"] == out["fine_vertices"]
                            and out["coarse_vertices_ok"] == out["coarse_vertices"]
                            and out["crossing_faces"] == 0)
    out["passed"] = bool(out["contained"] and out["self_intersecting_faces"] == 0
                         and out["closed"])
    return out, bad, ~fine_ok
