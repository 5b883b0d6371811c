"""Simplified shells that still contain the fine ones: levels of detail for M+ and M- (issue 18).

Guarantee: the coarse outer shell C+ contains the fine outer shell M+, and the coarse inner
shell C- lies inside the fine inner shell M-. So the band between them only grows and nothing
the fine band holds is cut: a ray enters C+ no later than M+ and stops at C- no earlier than
at M-. Every coarse shell is checked (`verify`) before it is returned; a failed check is an
InputError, never a written file.

Construction (`make_lod`):

* **C+ = alpha wrap of M+** (CGAL's 3D alpha wrap through pymeshlab): closed, 2-manifold and
  free of self-intersections by construction, and strictly containing its input, at distance
  ``offset`` outside it. The offset is the allowance of the thinnest bands (its 5th percentile
  over M+, see below), so the wrap is tight where the band is thin; ``alpha`` (the carving
  ball) is searched so that the wrap has at most len(M+) / ratio triangles; concavities
  narrower than alpha are filled, which only widens the band there.
* **C- = a conservative voxel interior of M-, eroded by the allowance, re-meshed and
  decimated** (`voxel_interior`, `decimate`): the grid cells that M- does not touch and a
  flood fill from outside does not reach are strictly inside M-; their signed distance is
  meshed half a cell plus the local erosion inside them (marching cubes), then quadric
  decimation (weighted by the allowance: thin band, decimated last) brings it to
  len(M-) / ratio triangles. Decimation is the one step without a guarantee, so its result
  is checked; where it failed, the voxel surface is locked (its vertices' error weight
  raised) and the decimation redone at the same count, and only after a few such rounds with
  1.5x the triangles, until the check passes (the undecimated voxel surface, which passes by
  construction, is the last resort). On lego's M- one locking round takes it from 4.4x to
  10x (BENCHMARKS.md, issue 18).
* **The allowance**, tied to the local band (`band_allowance`): every fine vertex gets
  lambda = clamp(kappa * w, lo h, hi h), w the local band width there (the distance from an
  M+ vertex to the nearest M- vertex, and back), h the fine grid spacing; where M- is absent
  (thin parts) w is capped. The inner erosion below the wall of touched cells is
  max(lambda - h, 0) per cell, the outer offset the 5th percentile of lambda: thin band,
  tight; wide band, loose.

`verify` (both shells): every fine vertex inside C+ (outside C-) and every coarse vertex
outside M+ (inside M-) by ray-parity inside tests along three directions (`inside`); no
triangle of the coarse shell crosses one of the fine shell or another of its own (MeshLab's
self-intersection test on their union and on the coarse shell alone); every edge in two
faces, in opposite directions. Right-side vertices and no crossing surfaces together imply
containment: closed surfaces that do not meet lie wholly on one side of each other.

Conventions as in `shells.levelset.mesh`: world units, outward-facing triangles (volume > 0).
pymeshlab is GPL-3.0; it is imported only here, when a LOD is made.
"""

from __future__ import annotations


import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from shells.errors import InputError

Mesh = tuple[np.ndarray, np.ndarray]  # V [n, 3] float, F [m, 3] int, outward faces


@dataclass
class LodParams:
    """The allowance (lo, hi: multiples of the fine grid spacing h) and the retries."""

    kappa: float = 0.1  # allowance = kappa * local band width ...
    lo: float = 0.25  # ... clamped to [lo h, hi h]
    hi: float = 2.0
    max_retry: int = 3  # decimations with 1.5x the triangles after a failed check
    lock_rounds: int = 4  # C-: decimations at the same count, each after locking the
    # places where the last one failed (their voxel vertices' error weight x lock_weight)
    lock_weight: float = 30.0
    lock_radius: float = 3.0  # ... the voxel vertices within this many h of a failure


# --------------------------------------------------------------------------------------------
# Inside tests and ray parity (Mitsuba / Embree)
# --------------------------------------------------------------------------------------------

DIRECTIONS = np.array([[0.5773, 0.5774, 0.5773], [-0.8017, 0.2673, 0.5345],
                       [0.2357, -0.9428, 0.2357]])  # three irrational-ish, unrelated axes


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
    and whether they alternate enter, exit, enter, ... counted from the ray's origin (an origin
    inside starts with an exit). ``scene``: a prepared `_scene(V, F)`."""
    import drjit as dr
    import mitsuba as mi

    scene = scene if scene is not None else _scene(V, F)
    n = len(o)
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(o[:, k].astype(np.float32)) for k in range(3)]),
                   mi.Vector3f(*[mi.Float(d[:, k].astype(np.float32)) for k in range(3)]))
    count = np.zeros(n, np.int64)
    first_exit = np.zeros(n, bool)
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
        first_exit[sel[first]] = e[first] < 0
        ok[sel[~first]] &= e[~first] != last[sel[~first]]  # must alternate
        last[sel] = e
        count[sel] += 1
        keep = np.flatnonzero(valid)
        idx = idx[keep]
        nxt = si.spawn_ray(ray.d)
        ray = mi.Ray3f(mi.Point3f(*[mi.Float(np.asarray(c)[keep]) for c in nxt.o]),
                       mi.Vector3f(*[mi.Float(np.asarray(c)[keep]) for c in ray.d]))
    return count, ok


def inside(V: np.ndarray, F: np.ndarray, points: np.ndarray,  # [N, 3]
           scene: Any = None) -> np.ndarray:  # [N] bool
    """Point-in-solid test of a closed mesh: odd number of crossings along a ray, decided by
    the majority of three unrelated directions (a ray grazing an edge or vertex is outvoted)."""
    scene = scene if scene is not None else _scene(V, F)
    points = np.asarray(points, np.float64)
    votes = np.zeros(len(points), np.int64)
    for d in DIRECTIONS:
        c, _ = crossings(V, F, points, np.broadcast_to(d / np.linalg.norm(d), points.shape),
                         scene=scene)
        votes += c % 2
    return votes >= 2


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
# MeshLab helpers
# --------------------------------------------------------------------------------------------

def _ms(*meshes: Mesh, quality: np.ndarray | None = None) -> Any:
    import pymeshlab as ml

    ms = ml.MeshSet()
    for k, (V, F) in enumerate(meshes):
        kw = {"v_scalar_array": np.asarray(quality, np.float64)} if (k == 0 and
                                                                     quality is not None) else {}
        ms.add_mesh(ml.Mesh(np.asarray(V, np.float64), np.asarray(F, np.int32), **kw))
    return ms


def signed_distance(points: Mesh, ref: Mesh) -> np.ndarray:  # [n] > 0 outside ref
    """Signed distance of the vertices of ``points`` to the surface ``ref`` (MeshLab: nearest
    point on ref, sign from its face normal; > 0 outside, as f)."""
    ms = _ms(points, ref)
    ms.compute_scalar_by_distance_from_another_mesh_per_vertex(measuremesh=0, refmesh=1,
                                                               signeddist=True)
    ms.set_current_mesh(0)
    return ms.current_mesh().vertex_scalar_array().copy()


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


def decimate(V: np.ndarray, F: np.ndarray, target: int,
             quality: np.ndarray | None = None) -> Mesh:
    """Quadric edge collapse to about ``target`` faces, topology kept; ``quality`` [n]: per
    vertex error amplification (collapsed last where high)."""
    ms = _ms((V, F), quality=quality)
    ms.meshing_decimation_quadric_edge_collapse(
        targetfacenum=int(target), preservetopology=True, preservenormal=True,
        optimalplacement=True, planarquadric=True, qualityweight=quality is not None,
        autoclean=True)
    m = ms.current_mesh()
    Vc, Fc = m.vertex_matrix(), m.face_matrix()
    used = np.unique(Fc)
    remap = np.full(len(Vc), -1, np.int64)
    remap[used] = np.arange(len(used))
    return Vc[used], remap[Fc].astype(np.int32)


def verify(C: Mesh, S: Mesh, side: int) -> dict:
    """The containment check of the module docstring for a coarse shell C and its fine shell S
    (``side`` +1: C must contain S; -1: C must lie inside S)."""
    return _check(C, S, side)[0]


def _check(C: Mesh, S: Mesh, side: int) -> tuple[dict, np.ndarray, np.ndarray]:
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


# --------------------------------------------------------------------------------------------
# The constructions used by `make_lod`: alpha wrap (M+) and a conservative voxel interior (M-)
# --------------------------------------------------------------------------------------------

def alpha_wrap(V: np.ndarray, F: np.ndarray, alpha: float, offset: float) -> Mesh:
    """CGAL's 3D alpha wrap through MeshLab: a closed, 2-manifold, self-intersection-free
    surface that strictly contains the input, at distance ``offset`` from it; ``alpha`` (world
    units) is the size of the ball that carves the wrap (larger: fewer triangles, concavities
    narrower than alpha filled)."""
    import pymeshlab as ml

    ms = _ms((V, F))
    ms.generate_alpha_wrap(alpha=ml.PureValue(float(alpha)), offset=ml.PureValue(float(offset)))
    m = ms.current_mesh()
    Vc, Fc = m.vertex_matrix(), m.face_matrix().astype(np.int32)
    if len(Fc) and trimesh.Trimesh(Vc, Fc, process=False).volume < 0:
        Fc = Fc[:, ::-1].copy()
    return Vc, Fc


def voxel_interior(V: np.ndarray, F: np.ndarray, origin: np.ndarray, h: float,
                   depth: np.ndarray | None = None) -> Mesh:
    """A closed surface strictly inside the closed mesh (V, F) (``depth`` [n]: extra erosion per
    vertex of it, world units), from the cells of the grid
    (``origin``, spacing ``h``) that it does not touch.

    The cells holding a point of a triangle (its vertices, edge midpoints and centroid, each
    marked in every cell whose closure holds it: for a marching-cubes mesh on this grid, whose
    triangles each lie in one cell, that is exactly the cells the surface meets) form a wall;
    a 6-connected flood fill from outside the box cannot cross it; the cells neither reached
    nor touched are strictly inside. Their signed distance (cell units, > 0 outside) is meshed
    at -0.5 - depth (per cell, from its nearest vertex: the erosion below the wall) by marching
    cubes over the cell centres, so the surface stays half a cell inside the interior cells.
    A part thinner than about two cells has no interior cells and is dropped (valid: any
    subset of M-'s interior is a valid coarse M-)."""
    from scipy import ndimage

    from shells.levelset.mesh import marching_cubes

    lo = np.floor((V.min(0) - origin) / h).astype(int) - 2
    hi = np.ceil((V.max(0) - origin) / h).astype(int) + 2
    shape = tuple(hi - lo)
    tri = V[F]
    pts = np.concatenate([V, tri.mean(1), 0.5 * (tri[:, 0] + tri[:, 1]),
                          0.5 * (tri[:, 1] + tri[:, 2]), 0.5 * (tri[:, 2] + tri[:, 0])])
    u = (pts - origin) / h - lo
    touched = np.zeros(shape, bool)
    eps = 1e-4
    for sx in (-eps, eps):
        for sy in (-eps, eps):
            for sz in (-eps, eps):
                c = np.floor(u + np.array([sx, sy, sz])).astype(int)
                c = np.clip(c, 0, np.array(shape) - 1)
                touched[c[:, 0], c[:, 1], c[:, 2]] = True
    labels, _ = ndimage.label(~touched)
    outside = labels == labels[0, 0, 0]
    interior = ~outside & ~touched
    if not interior.any():
        return np.zeros((0, 3)), np.zeros((0, 3), np.int32)
    sd = np.where(interior, -ndimage.distance_transform_edt(interior),
                  ndimage.distance_transform_edt(~interior)).astype(np.float32)
    level = np.float32(0.5)
    if depth is not None:  # per interior cell: the erosion at the nearest fine vertex, in cells
        cells = np.argwhere(interior)
        _, near = cKDTree(V).query(origin + (cells + lo + 0.5) * h)
        extra = np.zeros(shape, np.float32)
        extra[tuple(cells.T)] = depth[near] / h
        level = level + extra
    g = sd + level  # < 0 deeper than `level` cells inside the interior
    centres_box = np.stack([origin + (lo + 0.5) * h, origin + (hi - 0.5) * h])
    mesh = marching_cubes(g, centres_box)
    from shells.levelset.mesh import clean_mesh
    mesh = clean_mesh(mesh)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces, np.int32)


def _stats(x: np.ndarray) -> dict:
    x = np.asarray(x, np.float64)
    if x.size == 0:
        return {"count": 0}
    q = np.percentile(x, [5, 50, 95])
    return {"count": int(x.size), "mean": float(x.mean()), "min": float(x.min()),
            "p5": float(q[0]), "p50": float(q[1]), "p95": float(q[2]), "max": float(x.max())}




def band_allowance(V: np.ndarray,  # [n, 3] vertices of one shell
                   other: np.ndarray,  # [k, 3] vertices of the other shell (may be empty)
                   h: float, p: LodParams) -> np.ndarray:  # [n] allowance, world units
    """lambda = clamp(kappa * w, lo h, hi h), w the distance to the other shell's nearest vertex
    (the local band width; capped where the other shell is absent or farther than hi h /
    kappa)."""
    cap = p.hi * h / max(p.kappa, 1e-12)
    if len(other) == 0:
        w = np.full(len(V), cap)
    else:
        w, _ = cKDTree(other).query(V, distance_upper_bound=cap)
        w = np.minimum(w, cap)
    return np.clip(p.kappa * w, p.lo * h, p.hi * h)


def lod_outer(S: Mesh, lam: np.ndarray, ratio: float, h: float) -> tuple[Mesh, dict]:
    """C+ (module docstring): the alpha wrap of S at offset = 5th percentile of ``lam`` with the
    smallest alpha tried that gives at most len(S faces) / ratio triangles."""
    target = max(int(len(S[1]) / ratio), 8)
    offset = float(np.percentile(lam, 5))
    alpha, tries = 2.0 * h, []
    for _ in range(6):
        t0 = time.perf_counter()
        C = alpha_wrap(*S, alpha, offset)
        tries.append({"alpha": alpha, "triangles": int(len(C[1])),
                      "seconds": time.perf_counter() - t0})
        if len(C[1]) <= target:
            break
        alpha *= 1.05 * float(np.sqrt(len(C[1]) / target))  # triangles ~ 1 / alpha^2
    check = verify(C, S, +1)
    if not check["passed"]:
        raise InputError(f"outer shell LOD: the alpha wrap failed its containment check "
                         f"({check}); report this, or use a smaller --ratio")
    return C, {"method": "alpha wrap (CGAL via pymeshlab)", "offset": offset, "alpha": alpha,
               "target_triangles": target, "wraps": tries, "check": check}


def lod_inner(S: Mesh, lam: np.ndarray, ratio: float, origin: np.ndarray, h: float,
              p: LodParams) -> tuple[Mesh, dict]:
    """C- (module docstring): the voxel interior of S eroded by max(lam - h, 0), decimated to
    len(S faces) / ratio triangles. After a failed check the places where it failed are locked
    (the error weight of the voxel vertices within ``lock_radius`` h of a failing vertex, coarse
    or fine, times ``lock_weight``) and the decimation is redone at the same count, up to
    ``lock_rounds`` times; then with 1.5x the triangles, up to ``max_retry`` times."""
    target = max(int(len(S[1]) / ratio), 8)
    t0 = time.perf_counter()
    voxel = voxel_interior(*S, origin, h, depth=np.maximum(lam - h, 0.0))
    info: dict[str, Any] = {"method": "voxel interior + quadric decimation",
                            "voxel_triangles": int(len(voxel[1])), "target_triangles": target,
                            "voxel_s": time.perf_counter() - t0, "decimations": []}
    if len(voxel[1]) == 0:
        info["check"] = {"passed": True, "empty": True}
        return voxel, info
    _, near = cKDTree(S[0]).query(voxel[0])
    quality = (p.hi * h / lam[near]) ** 2
    voxel_tree = cKDTree(voxel[0])
    for _ in range(p.max_retry + 1):
        if target >= len(voxel[1]):
            break
        weight = quality.copy()
        for _ in range(p.lock_rounds + 1):
            t0 = time.perf_counter()
            C = decimate(*voxel, target, weight)
            check, bad_coarse, bad_fine = _check(C, S, -1)
            info["decimations"].append({"target": target, "triangles": int(len(C[1])),
                                        "passed": check["passed"],
                                        "failing_vertices": int(bad_coarse.sum()
                                                                + bad_fine.sum()),
                                        "seconds": time.perf_counter() - t0})
            if check["passed"]:
                info["check"] = check
                return C, info
            where = np.concatenate([C[0][bad_coarse], S[0][bad_fine]])
            near_failure = voxel_tree.query_ball_point(where, p.lock_radius * h)
            locked = np.unique(np.concatenate([np.asarray(i, np.int64) for i in near_failure]
                                              + [np.zeros(0, np.int64)]))
            weight[locked] *= p.lock_weight
        target = int(target * 1.5)
    check = verify(voxel, S, -1)
    if not check["passed"]:
        raise InputError(f"inner shell LOD: the voxel interior failed its containment check "
                         f"({check}); M- may hold a cavity: re-extract the shells")
    info["check"] = check
    return voxel, info


def make_lod(outer: Mesh, inner: Mesh | None, ratio: float, origin: np.ndarray, h: float,
             p: LodParams | None = None, parity_rays: int = 100_000,
             box: np.ndarray | None = None) -> tuple[Mesh, Mesh, dict]:
    """Coarse (C+, C-) of the fine shells (M+, M-) on the grid (``origin``, spacing ``h``) they
    were extracted on, about ``ratio`` times fewer triangles each; with the statistics
    (triangles, offsets used, checks, ray parity of ``parity_rays`` random rays through
    ``box``)."""
    p = p or LodParams()
    if not ratio > 1:
        raise InputError(f"--ratio {ratio}: must be > 1 (fine triangles per coarse triangle)")
    Vo, Fo = np.asarray(outer[0], np.float64), np.asarray(outer[1], np.int64)
    has_inner = inner is not None and len(inner[1]) > 0
    Vi = np.asarray(inner[0], np.float64) if has_inner else np.zeros((0, 3))
    Fi = np.asarray(inner[1], np.int64) if has_inner else np.zeros((0, 3), np.int64)
    box = np.asarray(box if box is not None else np.stack([Vo.min(0), Vo.max(0)]), np.float64)
    stats: dict[str, Any] = {"ratio": ratio, "params": dict(vars(p)), "grid_spacing": h}
    t0 = time.perf_counter()
    lam_o = band_allowance(Vo, Vi, h, p)
    Co, info_o = lod_outer((Vo, Fo), lam_o, ratio, h)
    stats["timings_s"] = {"outer": time.perf_counter() - t0}
    if has_inner:
        t0 = time.perf_counter()
        lam_i = band_allowance(Vi, Vo, h, p)
        Ci, info_i = lod_inner((Vi, Fi), lam_i, ratio, origin, h, p)
        stats["timings_s"]["inner"] = time.perf_counter() - t0
    else:
        Ci, info_i = (np.zeros((0, 3)), np.zeros((0, 3), np.int32)), {"method": "none (no M-)"}
    for name, C, S, info, side in (("outer", Co, (Vo, Fo), info_o, +1),
                                   ("inner", Ci, (Vi, Fi), info_i, -1)):
        if len(S[1]) and len(C[1]):
            d = side * signed_distance(C, S)  # > 0: on the allowed side of S
            info["offset_coarse_vertices"] = _stats(d)
            info["offset_coarse_vertices_over_h"] = _stats(d / h)
        info.update({"triangles": int(len(C[1])), "vertices": int(len(C[0])),
                     "fine_triangles": int(len(S[1])), "fine_vertices": int(len(S[0])),
                     "reduction": float(len(S[1]) / max(len(C[1]), 1))})
        if len(C[1]):
            t0 = time.perf_counter()
            info["parity"] = parity_check(C[0], C[1], parity_rays, box)
            info["parity"]["seconds"] = time.perf_counter() - t0
        stats[name] = info
    return ((np.asarray(Co[0], np.float32), np.asarray(Co[1], np.int32)),
            (np.asarray(Ci[0], np.float32), np.asarray(Ci[1], np.int32)), stats)
