"""Simplified shells that still contain the fine ones: levels of detail for M+ and M-.

Guarantee: the coarse outer shell C+ contains the fine outer shell M+, and the coarse inner
shell C- lies inside the fine inner shell M-. So the band between them only grows and nothing
the fine band holds is cut: a ray enters C+ no later than M+ and stops at C- no earlier than
at M-. Every coarse shell is checked (`verify`) before it is returned; a failed check is an
InputError, never a written file.

Construction (`make_lod`), the same for both shells (`offset_lod`):

* **An offset of the fine shell** (`DistanceGrid`): marching cubes of the exact signed
  distance to it (libigl) on the fine grid, at 0.2 h outside M+ (C+) or 0.3 h inside M- (C-),
  h the fine grid spacing. Where the grid undersamples the shell (edges, thin parts) the
  offset can stray to the wrong side; there it is made deeper, locally, until it passes the
  check. It keeps thin parts of M- down to about 0.6 h, which rays would otherwise cross to
  the back of M+.
* **Decimated in checked stages** (`decimate_staged`): quadric decimation down to
  len(fine) / ratio triangles in halving stages. Decimation is the one step without a
  guarantee, so every stage's result is checked; where a stage failed, the faces of its
  (valid) input near the failures are kept as they were and the stage is redone, until it
  passes (a stage that never does ends the descent at the last valid mesh).
* **Snapped** (`snap`): the coarse vertices are moved 0.4 of their distance toward the fine
  shell, three times. Each time, those whose faces then fail the check go back.
* **Farther if needed**: when the descent stops above 1.2x the target, it starts again from
  an offset twice as far (more room for the decimation), up to three offsets. For C+ the
  last resort is **the alpha wrap of M+** (`wrap_outer`: CGAL's 3D alpha wrap through
  pymeshlab, closed and containing by construction, at the allowance of the thinnest bands,
  ``kappa`` x the local band width, `band_allowance`), whose filled concavities cost more
  band samples.

Why offsets: the band renderer's samples grow with the distance between the coarse and the
fine shell and with every thin part left out (an interval of width w takes
ceil((w - w_s) / delta_s) + 1 samples). A close offset keeps thin parts and adds little
width, so it costs fewer band samples than a voxel interior of M- that drops thin parts or
than the alpha wrap of M+ (`python -m bench.lod_shell_cost`; BENCHMARKS.md).

The check of every step is `shells.levelset.containment.verify` (winding numbers, no
crossing or self-intersecting faces, closed edges), with `check_side` naming where it failed.

Conventions as in `shells.levelset.mesh`: world units, outward-facing triangles (volume > 0).
pymeshlab (GPL-3.0) and libigl (MPL-2.0) are imported only here, when a LOD is made.
"""

from __future__ import annotations


import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from shells.errors import InputError
from shells.levelset.containment import (Mesh, check_side, inside, parity_check,
                                         signed_distance, verify)


@dataclass
class LodParams:
    """The offsets the coarse shells start from and the repair rounds (in fine grid cells h),
    and the allowance of the alpha-wrap fallback for C+ (lo, hi: multiples of h)."""

    kappa: float = 0.1  # alpha wrap (C+ fallback): offset = kappa * local band width ...
    lo: float = 0.25  # ... clamped to [lo h, hi h]
    hi: float = 2.0
    outer_offset: float = 0.2  # C+: the offset of M+ it starts from, in h (a closer one
    # leaves the decimation too little room: on lego it stops short of the ratio)
    inner_depth: float = 0.3  # C-: the offset of M- it starts from, in h (a shallower one
    # stops the decimation short of the ratio, a deeper one loses thin parts: BENCHMARKS.md)
    offset_tries: int = 3  # offsets tried, each offset_growth times farther than the last,
    offset_growth: float = 2.0  # while the decimation stops short of the ratio
    deepen: float = 0.25  # where an offset fails its check: this much deeper (h) ...
    deepen_rounds: int = 12  # ... for up to this many rounds
    lock_radius: float = 1.0  # decimation: after a failed check, the input faces within
    # this many h of a failure are kept as they were ...
    lock_rounds: int = 20  # ... for up to this many rounds per stage
    snap_passes: int = 3  # then the coarse vertices are moved toward the fine shell, this
    snap_frac: float = 0.4  # share of their distance beyond snap_keep h per pass, where the
    snap_keep: float = 0.05  # check still passes (`snap`)


class Phases:
    """A progress bar over the named phases of a LOD construction (tqdm, on stderr); a
    disabled one costs nothing. `start` ends the running phase and names the next; `add`
    grows the count (a retry, the fallback)."""

    def __init__(self, total: int = 0, enabled: bool = False) -> None:
        from shells.progress import tqdm
        self.bar = tqdm(total=total, desc="shells-lod", unit="phase", leave=False,
                        disable=not enabled)
        self.running = False

    def start(self, label: str) -> None:
        if self.running:
            self.bar.update(1)
        self.running = True
        self.bar.set_postfix_str(label)

    def add(self, n: int) -> None:
        self.bar.total += n
        self.bar.refresh()

    def close(self) -> None:
        if self.running:
            self.bar.update(1)
        self.bar.close()


def decimate(V: np.ndarray, F: np.ndarray, target: int,
             keep: np.ndarray | None = None) -> Mesh:
    """Quadric edge collapse to about ``target`` faces, topology kept; ``keep`` [m] bool: faces
    left as they are (with their vertices; MeshLab's decimation of the selected faces only)."""
    import pymeshlab as ml

    ms = ml.MeshSet()
    kw = {} if keep is None else {"f_scalar_array": (~keep).astype(np.float64)}
    ms.add_mesh(ml.Mesh(np.asarray(V, np.float64), np.asarray(F, np.int32), **kw))
    if keep is not None:
        ms.compute_selection_by_condition_per_face(condselect="fq > 0.5")
    ms.meshing_decimation_quadric_edge_collapse(
        targetfacenum=int(target), preservetopology=True, preservenormal=True,
        optimalplacement=True, planarquadric=True, autoclean=True, selected=keep is not None)
    m = ms.current_mesh()
    Vc, Fc = m.vertex_matrix(), m.face_matrix()
    used = np.unique(Fc)
    remap = np.full(len(Vc), -1, np.int64)
    remap[used] = np.arange(len(used))
    return Vc[used], remap[Fc].astype(np.int32)


# --------------------------------------------------------------------------------------------
# The constructions used by `make_lod`: offsets (both shells), staged decimation, snap, and
# the alpha wrap (C+ fallback)
# --------------------------------------------------------------------------------------------

def alpha_wrap(V: np.ndarray, F: np.ndarray, alpha: float, offset: float) -> Mesh:
    """CGAL's 3D alpha wrap through MeshLab: a closed, 2-manifold, self-intersection-free
    surface that strictly contains the input, at distance ``offset`` from it; ``alpha`` (world
    units) is the size of the ball that carves the wrap (larger: fewer triangles, concavities
    narrower than alpha filled)."""
    import pymeshlab as ml

    ms = ml.MeshSet()
    ms.add_mesh(ml.Mesh(np.asarray(V, np.float64), np.asarray(F, np.int32)))
    ms.generate_alpha_wrap(alpha=ml.PureValue(float(alpha)), offset=ml.PureValue(float(offset)))
    m = ms.current_mesh()
    Vc, Fc = m.vertex_matrix(), m.face_matrix().astype(np.int32)
    if len(Fc) and trimesh.Trimesh(Vc, Fc, process=False).volume < 0:
        Fc = Fc[:, ::-1].copy()
    return Vc, Fc


def _triangles_meet_cells(tri: np.ndarray,  # [n, 3, 3] triangles, in cell units
                          cells: np.ndarray,  # [n, 3] int: one cell (its lower corner) each
                          grow: float) -> np.ndarray:  # [n] bool
    """Exact overlap of each triangle with its unit cell grown by ``grow`` on every side: the
    separating-axis test of Akenine-Moller (2001) on the cell's three axes, the triangle's
    normal and the nine cross products of the axes with its edges."""
    e = 0.5 + grow
    v = tri - (cells + 0.5)[:, None, :]
    f = v[:, [1, 2, 0]] - v  # [n, 3 edges, 3]
    meet = (v.min(1) <= e).all(1) & (v.max(1) >= -e).all(1)
    n = np.cross(f[:, 0], f[:, 1])
    meet &= np.abs(np.einsum("ij,ij->i", n, v[:, 0])) <= e * np.abs(n).sum(1)
    for k in range(3):
        for j in range(3):
            axis = np.cross(np.eye(3)[k], f[:, j])  # [n, 3]
            proj = np.einsum("nij,nj->ni", v, axis)
            r = e * np.abs(axis).sum(1)
            meet &= (proj.min(1) <= r) & (proj.max(1) >= -r)
    return meet


def touched_cells(V: np.ndarray, F: np.ndarray, origin: np.ndarray, cell: float,
                  lo: np.ndarray, shape: tuple[int, int, int], grow: float = 1e-3,
                  chunk: int = 100_000) -> np.ndarray:  # bool [shape]
    """The cells (spacing ``cell``, cell ``lo`` at index 0) that some triangle of (V, F) meets,
    each cell grown by ``grow`` cells on every side: a conservative rasterisation (every cell
    the surface meets is marked, exactly, whatever the size of the triangles)."""
    touched = np.zeros(shape, bool)
    top = np.array(shape) - 1
    for s in range(0, len(F), chunk):
        tri = (np.asarray(V, np.float64)[F[s:s + chunk]] - origin) / cell - lo
        first = np.floor(tri.min(1) - grow).astype(np.int64)
        count = np.floor(tri.max(1) + grow).astype(np.int64) - first + 1
        for off in np.ndindex(*count.max(0)):
            sel = np.flatnonzero((np.array(off) < count).all(1))
            c = first[sel] + np.array(off)
            c = np.clip(c[_triangles_meet_cells(tri[sel], c, grow)], 0, top)
            touched[c[:, 0], c[:, 1], c[:, 2]] = True
    return touched


def solid_groups(free: np.ndarray,  # bool grid: cells or nodes that do not meet S
                 V: np.ndarray, F: np.ndarray, position: Any  # index [k, 3] -> world [k, 3]
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The 6-connected groups of ``free`` (labels, 0 where not free) and, per label, whether
    the group lies inside the closed mesh (V, F): a connected set that does not meet the
    surface lies wholly on one side of it, so one winding number (at its first element)
    decides."""
    from scipy import ndimage

    labels, n = ndimage.label(free)
    reps = np.zeros((n, 3), np.int64)  # each group's first element in C order, found in its
    for k, box in enumerate(ndimage.find_objects(labels)):  # bounding box: no grid-sized
        mine = labels[box] == k + 1  # index array (1 GB of int64 at 512^3)
        at = np.unravel_index(int(np.argmax(mine)), mine.shape)
        reps[k] = [sl.start + j for sl, j in zip(box, at)]
    return labels, np.concatenate([[False], inside(V, F, position(reps))])


class DistanceGrid:
    """The exact signed distance to a closed mesh S (libigl) at the nodes of the grid
    (``origin``, spacing h) within three cells of the cells S meets (`touched_cells`), and
    the side of S of every other node (`solid_groups`: so a cavity of S is outside, however
    it is reached). Built once per shell; `offset` meshes it at any distance up to 2.5 h."""

    def __init__(self, S: Mesh, origin: np.ndarray, h: float):
        import igl
        from scipy import ndimage

        self.V, self.F = np.asarray(S[0], np.float64), np.asarray(S[1], np.int64)
        self.h, self.cap = h, 2.5 * h  # the band of exact distances reaches 3 h: no farther
        pad = 6  # the band reaches 4 cells past S's extent, its nodes 5: one node spare
        self.lo = np.floor((self.V.min(0) - origin) / h).astype(int) - pad
        hi = np.ceil((self.V.max(0) - origin) / h).astype(int) + pad
        cshape = tuple(int(x) for x in hi - self.lo)
        near = ndimage.binary_dilation(touched_cells(self.V, self.F, origin, h, self.lo, cshape),
                                       iterations=3)
        band = np.zeros(tuple(c + 1 for c in cshape), bool)  # the nodes of those cells
        for off in np.ndindex(2, 2, 2):
            band[off[0]:off[0] + cshape[0], off[1]:off[1] + cshape[1],
                 off[2]:off[2] + cshape[2]] |= near
        self.nodes = np.argwhere(band)
        self.P = origin + (self.nodes + self.lo) * h
        self.sd, _, _, _ = igl.signed_distance(self.P, self.V, self.F,
                                               sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)
        labels, solid = solid_groups(~band, self.V, self.F,
                                     lambda idx: origin + (idx + self.lo) * h)
        self.g = np.where(solid[labels], -3.0 * h, 3.0 * h)  # beyond the band: far from S
        self.box = np.stack([origin + self.lo * h, origin + hi * h])
        self.tree = cKDTree(self.P)

    def offset(self, depth: float, side: int = -1, deepen: float = 0.25, rounds: int = 12
               ) -> tuple[Mesh, dict]:
        """A closed surface at ``depth`` (world units) inside (``side`` -1) or outside (+1) S,
        checked (`check_side`) to lie wholly on that side of it: marching cubes of
        sd - side * depth. It can stray to the wrong side where the grid undersamples S
        (edges, thin parts); there the offset is made ``deepen`` (h) deeper, at the nodes
        within 2 h of each failure, and the surface re-meshed, for up to ``rounds`` rounds
        (parts that get too thin vanish, which keeps the surface valid). Returns the surface
        and a record of the rounds."""
        from shells.levelset.mesh import clean_mesh, marching_cubes

        h, V = self.h, self.V
        if not 0 <= depth <= self.cap:
            raise ValueError(f"DistanceGrid.offset: depth {depth / h:.3g} h outside [0, 2.5] h")
        d = np.full(len(self.P), float(depth))
        g = self.g.copy()
        info: dict[str, Any] = {"depth": float(depth), "band_nodes": int(len(self.P)),
                                "rounds": []}
        for _ in range(rounds + 1):
            g[tuple(self.nodes.T)] = self.sd - side * d
            m = clean_mesh(marching_cubes(g.astype(np.float32), self.box))
            C = (np.asarray(m.vertices), np.asarray(m.faces, np.int32))
            if len(C[1]) == 0:
                info["check"] = {"passed": True, "empty": True}
                return C, info
            check, bad_c, bad_f = check_side(C, (V, self.F), side)
            info["rounds"].append({"triangles": int(len(C[1])), "passed": check["passed"],
                                   "failing_vertices": int(bad_c.sum() + bad_f.sum())})
            if check["passed"]:
                info["check"] = check
                return C, info
            where = np.concatenate([C[0][bad_c], V[bad_f]])
            k = np.unique(np.concatenate([np.asarray(i, np.int64)
                                          for i in self.tree.query_ball_point(where, 2.0 * h)]
                                         + [np.zeros(0, np.int64)]))
            d[k] = np.minimum(d[k] + deepen * h, self.cap)
        raise InputError(f"shell LOD: the offset surface failed its containment check after "
                         f"{rounds} deeper rounds ({check}); re-extract the shells or report "
                         "this")


def decimate_staged(C: Mesh, S: Mesh, side: int, target: int, h: float, p: "LodParams"
                    ) -> tuple[Mesh, dict]:
    """Decimate C, which passes `check_side` against S (``side``), towards ``target`` faces in
    halving stages, every stage's result passing the check too: after a failed check the faces
    of the stage's input within ``p.lock_radius`` h of a failure are kept as they were and the
    stage redone with its count less the kept faces, up to ``p.lock_rounds`` times. A stage
    that still fails ends the descent at the last valid mesh (fewer than ``ratio`` fewer
    triangles, said in the record)."""
    stages, t = [], len(C[1]) // 2
    while t > target:
        stages.append(t)
        t //= 2
    stages.append(target)
    info: dict[str, Any] = {"stages": []}
    for T in stages:
        if T >= len(C[1]):
            continue
        keep = np.zeros(len(C[1]), bool)
        centres = cKDTree(np.asarray(C[0])[np.asarray(C[1])].mean(1))
        for r in range(p.lock_rounds + 1):
            t0 = time.perf_counter()
            Cn = decimate(*C, max(T - int(keep.sum()), T // 4), keep if keep.any() else None)
            check, bad_c, bad_f = check_side(Cn, S, side)
            rec = {"target": T, "round": r, "triangles": int(len(Cn[1])),
                   "kept": int(keep.sum()), "passed": check["passed"],
                   "failing_vertices": int(bad_c.sum() + bad_f.sum()),
                   "seconds": time.perf_counter() - t0}
            info["stages"].append(rec)
            if check["passed"]:
                break
            where = np.concatenate([Cn[0][bad_c], np.asarray(S[0])[bad_f]])
            hit = centres.query_ball_point(where, p.lock_radius * h)
            keep[np.unique(np.concatenate([np.asarray(i, np.int64) for i in hit]
                                          + [np.zeros(0, np.int64)]))] = True
        else:
            info["stopped_at"] = T
            break
        C, info["check"] = Cn, check
    return C, info


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


def snap(C: Mesh, S: Mesh, side: int, h: float, p: LodParams) -> tuple[Mesh, dict]:
    """Move the vertices of C, which passes `check_side` against S (``side``), toward S: each by
    ``p.snap_frac`` of its distance beyond ``p.snap_keep`` h, toward its nearest point of S
    (libigl), ``p.snap_passes`` times. In each pass, the vertices of coarse faces that then
    fail the check, and the coarse vertices within 2 h of fine vertices it names, go back to
    where they were (with their neighbours), until the check passes (at worst all go back)."""
    import igl

    V, F = np.asarray(C[0], np.float64), np.asarray(C[1], np.int64)
    SV, SF = np.asarray(S[0], np.float64), np.asarray(S[1], np.int64)
    info: dict[str, Any] = {"passes": []}
    for _ in range(p.snap_passes):
        sd, _, near, _ = igl.signed_distance(V, SV, SF,
                                             sign_type=igl.SIGNED_DISTANCE_TYPE_WINDING_NUMBER)
        dist = side * sd  # > 0: on the allowed side
        step = np.clip(p.snap_frac * (dist - p.snap_keep * h), 0.0, None) / np.maximum(dist,
                                                                                      1e-12)
        moved = V + (near - V) * step[:, None]
        back = np.zeros(len(V), bool)
        for r in range(10):
            W = np.where(back[:, None], V, moved)
            check, bad_c, bad_f = check_side((W, F), S, side)
            if check["passed"]:
                break
            bad = bad_c.copy()
            if bad_f.any():
                for i in cKDTree(W).query_ball_point(SV[bad_f], 2.0 * h):
                    bad[np.asarray(i, np.int64)] = True
            back[np.unique(F[bad[F].any(1)])] = True
        else:  # still failing: every vertex goes back
            back[:] = True
            W, check = V, check_side((V, F), S, side)[0]
        info["passes"].append({"moved": int((~back & (step > 0)).sum()), "rounds": r + 1})
        V = W
    info["check"] = check if p.snap_passes else None
    return (V, np.asarray(C[1], np.int32)), info


def offset_lod(S: Mesh, side: int, ratio: float, origin: np.ndarray, h: float,
               distance: float, p: LodParams, phases: Phases | None = None
               ) -> tuple[Mesh, dict]:
    """The offset of S at ``distance`` h on ``side`` (`DistanceGrid`), decimated to
    len(S faces) / ratio triangles (`decimate_staged`); where the checked descent stops above
    1.2x that count, again from an offset ``p.offset_growth`` times farther (more room for the
    decimation), up to ``p.offset_tries`` offsets. Returns the last try and every try's
    record. ``phases``: the progress bar (4 phases, 3 more per further try)."""
    ph = phases or Phases()
    name = "outer" if side > 0 else "inner"
    target = max(int(len(S[1]) / ratio), 8)
    info: dict[str, Any] = {"method": "offset (exact signed distance) + staged decimation",
                            "target_triangles": target, "tries": []}
    t0 = time.perf_counter()
    ph.start(f"{name}: signed distance")
    grid = DistanceGrid(S, origin, h)  # once: the tries differ only in the distance
    info["distance_grid_s"] = time.perf_counter() - t0
    for k in range(p.offset_tries):
        t0 = time.perf_counter()
        d = distance * p.offset_growth ** k
        if k:
            ph.add(3)
        ph.start(f"{name}: offset {d:g} h")
        C, off = grid.offset(d * h, side, p.deepen, p.deepen_rounds)
        rec: dict[str, Any] = {"distance_h": d, "offset": off,
                               "offset_triangles": int(len(C[1]))}
        info["check"] = off["check"]
        if len(C[1]):
            ph.start(f"{name}: decimate {len(C[1])} -> {target}")
            C, rec["decimation"] = decimate_staged(C, S, side, target, h, p)
            ph.start(f"{name}: snap")
            C, rec["snap"] = snap(C, S, side, h, p)
            info["check"] = rec["snap"]["check"] or rec["decimation"].get("check", off["check"])
        rec["triangles"], rec["seconds"] = int(len(C[1])), time.perf_counter() - t0
        info["tries"].append(rec)
        info["distance_h"] = d
        if len(C[1]) <= 1.2 * target:
            break
    return C, info


def lod_outer(S: Mesh, lam: np.ndarray, ratio: float, origin: np.ndarray, h: float,
              p: LodParams, phases: Phases | None = None) -> tuple[Mesh, dict]:
    """C+ (module docstring): `offset_lod` of S outward from ``p.outer_offset`` h; if no try
    gets within 1.2x the triangle target, the alpha wrap of S instead (`wrap_outer`)."""
    ph = phases or Phases()
    C, info = offset_lod(S, +1, ratio, origin, h, p.outer_offset, p, ph)
    if len(C[1]) <= 1.2 * info["target_triangles"]:
        return C, info
    ph.add(1)
    ph.start("outer: alpha wrap")
    C, wrap = wrap_outer(S, lam, ratio, h)
    wrap["offset_attempt"] = info
    return C, wrap


def wrap_outer(S: Mesh, lam: np.ndarray, ratio: float, h: float) -> tuple[Mesh, dict]:
    """The alpha wrap of S at offset = 5th percentile of ``lam`` with the smallest alpha tried
    that gives at most len(S faces) / ratio triangles (closed and containing by construction,
    but its filled concavities cost band samples: BENCHMARKS.md)."""
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


def lod_inner(S: Mesh, ratio: float, origin: np.ndarray, h: float, p: LodParams,
              phases: Phases | None = None) -> tuple[Mesh, dict]:
    """C- (module docstring): `offset_lod` of S inward from ``p.inner_depth`` h."""
    return offset_lod(S, -1, ratio, origin, h, p.inner_depth, p, phases)


def make_lod(outer: Mesh, inner: Mesh | None, ratio: float, origin: np.ndarray, h: float,
             p: LodParams | None = None, parity_rays: int = 100_000,
             box: np.ndarray | None = None, progress: bool = False
             ) -> tuple[Mesh, Mesh, dict]:
    """Coarse (C+, C-) of the fine shells (M+, M-) on the grid (``origin``, spacing ``h``) they
    were extracted on, about ``ratio`` times fewer triangles each; with the statistics
    (triangles, offsets used, checks, ray parity of ``parity_rays`` random rays through
    ``box``). ``progress``: a bar over the phases (`Phases`)."""
    p = p or LodParams()
    if not ratio > 1:
        raise InputError(f"--ratio {ratio}: must be > 1 (fine triangles per coarse triangle)")
    Vo, Fo = np.asarray(outer[0], np.float64), np.asarray(outer[1], np.int64)
    has_inner = inner is not None and len(inner[1]) > 0
    Vi = np.asarray(inner[0], np.float64) if has_inner else np.zeros((0, 3))
    Fi = np.asarray(inner[1], np.int64) if has_inner else np.zeros((0, 3), np.int64)
    box = np.asarray(box if box is not None else np.stack([Vo.min(0), Vo.max(0)]), np.float64)
    stats: dict[str, Any] = {"ratio": ratio, "params": dict(vars(p)), "grid_spacing": h}
    ph = Phases(5 + 5 * has_inner, progress)  # per shell: 4 of offset_lod and the parity
    try:
        Co, Ci, stats = _make_lod(Vo, Fo, Vi, Fi, has_inner, ratio, origin, h, p,
                                  parity_rays, box, stats, ph)
    finally:
        ph.close()
    return Co, Ci, stats


def _make_lod(Vo, Fo, Vi, Fi, has_inner: bool, ratio: float, origin: np.ndarray, h: float,
              p: LodParams, parity_rays: int, box: np.ndarray, stats: dict, ph: Phases
              ) -> tuple[Mesh, Mesh, dict]:
    t0 = time.perf_counter()
    lam_o = band_allowance(Vo, Vi, h, p)
    Co, info_o = lod_outer((Vo, Fo), lam_o, ratio, origin, h, p, ph)
    stats["timings_s"] = {"outer": time.perf_counter() - t0}
    if has_inner:
        t0 = time.perf_counter()
        Ci, info_i = lod_inner((Vi, Fi), ratio, origin, h, p, ph)
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
            ph.start(f"{name}: ray parity")
            info["parity"] = parity_check(C[0], C[1], parity_rays, box)
            info["parity"]["seconds"] = time.perf_counter() - t0
        stats[name] = info
    return ((np.asarray(Co[0], np.float32), np.asarray(Co[1], np.int32)),
            (np.asarray(Ci[0], np.float32), np.asarray(Ci[1], np.int32)), stats)
