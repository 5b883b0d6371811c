"""Ray casting against the shells: ordered M+ entry/exit intervals, clipped at M- (§3.4).

One implementation, used by stage-2 training (through torch, zero-copy) and by the Dr.Jit
renderer. Conventions:

* Shell meshes are triangle arrays (V [n, 3] float32, F [m, 3] int) from marching cubes of an
  SDF that is negative inside, so the geometric normal ``si.n`` points outward and
  ``dot(d, si.n) < 0`` means the ray *enters* the shell.
* Distances ``t`` are along the original ray, in world units, with unit directions.
* A ray that starts inside M+ opens its first interval at t = 0 (its origin).
* A cast may start at a per-ray distance ``start`` instead (an unbounded field's t_near,
  `shells.render.sampler.shell_intervals`): the shells before it are not seen, an interval
  open there opens at ``start``, and distances are still measured from the origin.
* M- (inner shell) is solid: peeling stops at its first hit and an open interval is closed there.
* At most ``dp_max`` M+ hits are peeled (depth-peeling budget); an interval still open when the
  budget runs out, or when the ray leaves the scene (a non-watertight M+), is dropped.
* The next peel starts from the hit moved off its triangle, to the far side along the face
  normal, by (1 + max|p|) 1500 eps (Mitsuba's ``spawn_ray`` offset): shell sheets closer together
  than that along a ray can be skipped (irrelevant at marching-cubes spacing).

Depth peeling is one symbolic Dr.Jit loop (``@dr.syntax``); every iteration casts the rays that
are still active against a single Mitsuba scene holding both shells and scatters closed intervals
into an [R, K] buffer. A cast asks for the preliminary intersection only (distance, shape,
triangle) and gathers the triangle's normal from a table made once per mesh, which costs less
than a full intersection record (position and frame from the triangle's vertices). On the CPU
(llvm_ad_rgb) the symbolic loop and the evaluated one (one kernel per peel, like a Python loop)
run equally fast, as Embree's ray casts dominate; the symbolic loop needs no host round trip per
peel (``mode='evaluated'`` runs the same code the other way). A peel can also stop after some
hits and be resumed later for some of its rays (`ShellScene.peel`, `ShellScene.resume`, its
state in `Peel`): band rendering peels the deeper layers only for the rays still letting light
through (`shells.render.frame`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np
import torch

from shells.device import mitsuba_variant
from shells.errors import InputError


@dataclass
class Intervals:
    """M+ intervals per ray. Dr.Jit tensors; ``.torch()`` converts them without a copy."""

    enter: Any  # mi.TensorXf [R, K] entry distances (0 where unused)
    exit: Any  # mi.TensorXf [R, K] exit distances (0 where unused)
    count: Any  # TensorXi [R] number of valid intervals, in front-to-back order
    t_inner: Any  # mi.TensorXf [R] first M- hit distance, inf if none was reached

    @property
    def K(self) -> int:
        return int(self.enter.shape[1])

    @classmethod
    def from_arrays(cls, enter: Any,  # [R, K] torch/numpy/list
                    exit: Any,  # [R, K]
                    count: Any,  # [R] valid intervals per ray
                    t_inner: Any = None,  # [R], default inf
                    ) -> "Intervals":
        """Intervals given explicitly (hand-worked tests, the scene box in `full` mode)."""
        e = torch.as_tensor(enter, dtype=torch.float32)
        x = torch.as_tensor(exit, dtype=torch.float32)
        c = torch.as_tensor(count, dtype=torch.int32)
        ti = (torch.full(c.shape, float("inf")) if t_inner is None
              else torch.as_tensor(t_inner, dtype=torch.float32))
        if e.ndim != 2 or x.shape != e.shape or c.shape != e.shape[:1] or ti.shape != c.shape:
            raise InputError(f"intervals: expected enter/exit [R, K], count/t_inner [R]; got "
                             f"{tuple(e.shape)}, {tuple(x.shape)}, {tuple(c.shape)}")
        return cls(enter=mi.TensorXf(e), exit=mi.TensorXf(x), count=tensor_xi()(c),
                   t_inner=mi.TensorXf(ti))

    def rows(self, a: int, b: int) -> "Intervals":
        """The intervals of rays a..b-1."""
        n, K = b - a, self.K
        slots, rays = dr.arange(mi.UInt32, a * K, b * K), dr.arange(mi.UInt32, a, b)
        count = self.count.array
        return Intervals(enter=mi.TensorXf(dr.gather(mi.Float, self.enter.array, slots), (n, K)),
                         exit=mi.TensorXf(dr.gather(mi.Float, self.exit.array, slots), (n, K)),
                         count=tensor_xi()(dr.gather(type(count), count, rays), (n,)),
                         t_inner=mi.TensorXf(dr.gather(mi.Float, self.t_inner.array, rays), (n,)))

    def torch(self) -> dict[str, torch.Tensor]:
        """Zero-copy torch views: enter/exit [R, K] float32, count [R] int32, t_inner [R]."""
        return {"enter": self.enter.torch(), "exit": self.exit.torch(),
                "count": self.count.torch(), "t_inner": self.t_inner.torch()}


@dataclass
class Peel:
    """Where the depth peel of each ray stands (`ShellScene.peel`); Dr.Jit arrays [R]."""

    ray_o: Any  # mi.Point3f where the next cast starts
    hits: Any  # mi.UInt32 M+ hits consumed so far
    total: Any  # mi.UInt32 intervals closed so far
    inside: Any  # mi.Bool an interval is open at t_open
    t_open: Any  # mi.Float entry distance of the open interval
    t_prev: Any  # mi.Float distance of the previous M+ hit (the cast's start before the first)
    t_inner: Any  # mi.Float first M- hit, inf if none yet
    going: Any  # mi.Bool the peel has more to do (no M- hit, no miss, hits < dp_max)

    def take(self, idx: Any) -> "Peel":
        """The states of the rays ``idx`` (mi.UInt32)."""
        return Peel(**{k: dr.gather(type(v), v, idx) for k, v in vars(self).items()})


def tensor_xi() -> type:
    """The int32 tensor type of the current Mitsuba variant's backend."""
    return dr.cuda.ad.TensorXi if mi.variant().startswith("cuda") else dr.llvm.ad.TensorXi


def box_intervals(o: Any,  # mi.Point3f [R]
                  d: Any,  # mi.Vector3f [R] unit directions
                  aabb: Any,  # [2, 3] (min, max), torch/numpy/list
                  ) -> Intervals:
    """The part of each ray inside the scene box as one interval (K = 1): the `full` baseline."""
    box = torch.as_tensor(aabb, dtype=torch.float32).cpu()
    if box.shape != (2, 3):
        raise InputError(f"aabb of shape {tuple(box.shape)}: expected [2, 3] (min, max)")
    bbox = mi.BoundingBox3f(mi.ScalarPoint3f(*box[0].tolist()), mi.ScalarPoint3f(*box[1].tolist()))
    hit, mint, maxt = bbox.ray_intersect(mi.Ray3f(o, d))
    near = dr.maximum(mint, 0.0)
    hit &= maxt > near
    near, maxt = dr.select(hit, near, 0.0), dr.select(hit, maxt, 0.0)
    dr.eval(near, maxt, hit)  # one kernel; the sampler gathers from these
    n = dr.width(d)
    return Intervals(enter=mi.TensorXf(near, (n, 1)), exit=mi.TensorXf(maxt, (n, 1)),
                     count=tensor_xi()(dr.select(hit, mi.Int(1), mi.Int(0)), (n,)),
                     t_inner=mi.TensorXf(dr.full(mi.Float, dr.inf, n), (n,)))


def to_point3f(x: Any, cls: type = None) -> Any:
    """torch/numpy [R, 3] or a Dr.Jit 3-vector -> mi.Point3f (or ``cls``) of width R."""
    cls = cls or mi.Point3f
    if isinstance(x, torch.Tensor):
        if x.ndim != 2 or x.shape[1] != 3:
            raise InputError(f"ray array of shape {tuple(x.shape)}: expected [R, 3]")
        dev = "cuda" if mi.variant().startswith("cuda") else "cpu"
        x = mi.TensorXf(x.detach().to(device=dev, dtype=torch.float32).contiguous())
        return dr.unravel(cls, x.array)
    if isinstance(x, np.ndarray):
        if x.ndim != 2 or x.shape[1] != 3:
            raise InputError(f"ray array of shape {x.shape}: expected [R, 3]")
        return dr.unravel(cls, mi.Float(np.ascontiguousarray(x, dtype=np.float32).ravel()))
    return cls(x)


def make_mesh(name: str, V: np.ndarray, F: np.ndarray) -> "mi.Mesh":
    """A Mitsuba mesh from vertex [n, 3] and face [m, 3] arrays."""
    V = np.asarray(V, dtype=np.float32)
    F = np.asarray(F)
    if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3:
        raise InputError(f"mesh '{name}': expected V [n, 3] and F [m, 3], got {V.shape}, {F.shape}")
    if len(F) and (F.min() < 0 or F.max() >= len(V)):
        raise InputError(f"mesh '{name}': face indices out of range [0, {len(V)})")
    m = mi.Mesh(name, vertex_count=len(V), face_count=len(F))
    p = mi.traverse(m)
    p["vertex_positions"] = mi.Float(V.ravel())
    p["faces"] = mi.UInt(F.astype(np.uint32).ravel())
    p.update()
    return m


class ShellScene:
    """One Mitsuba scene holding the outer shell M+ and (optionally) the inner shell M-."""

    def __init__(self, outer: tuple[np.ndarray, np.ndarray],  # (V [n, 3], F [m, 3]) of M+
                 inner: tuple[np.ndarray, np.ndarray] | None = None,  # M-, None/empty = none
                 variant: str | None = None) -> None:
        self.variant = mitsuba_variant(variant)
        if outer is None or len(outer[1]) == 0:
            raise InputError("outer shell is empty: nothing to render; re-run shells-extract "
                             "with a field that has a surface")
        self.outer = make_mesh("outer", *outer)
        shapes = {"type": "scene", "outer": self.outer}
        self.has_inner = inner is not None and len(inner[1]) > 0
        if self.has_inner:
            self.inner = make_mesh("inner", *inner)
            shapes["inner"] = self.inner
        self.scene = mi.load_dict(shapes)
        self._outer_ptr = mi.ShapePtr(self.outer)
        self._set_normals()

    def _set_normals(self) -> None:
        """The unit face normals of each shell, which the peel gathers at its hits."""
        self._normals_outer = face_normals(self.outer)
        self._normals_inner = face_normals(self.inner) if self.has_inner else None

    def move(self, outer: np.ndarray,  # [n, 3] new M+ vertex positions, same faces
             inner: np.ndarray | None = None,  # [k, 3] new M- vertex positions
             ) -> None:
        """New vertex positions for the same triangles (a deformation): the meshes are
        updated in place and the scene's acceleration structure is rebuilt once, about 3x
        faster than building a new scene."""
        params = mi.traverse(self.scene)
        pairs = [(self.outer, outer)] + ([(self.inner, inner)] if self.has_inner else [])
        for mesh, V in pairs:
            V = np.asarray(V, dtype=np.float32)
            if V.shape != (mesh.vertex_count(), 3):
                raise InputError(f"mesh '{mesh.id()}': {V.shape} new positions for "
                                 f"{mesh.vertex_count()} vertices")
            params[f"{mesh.id()}.vertex_positions"] = mi.Float(V.ravel())
        params.update()
        self._set_normals()

    def first_hit(self, origins: Any, dirs: Any, start: Any = None) -> tuple[Any, Any]:
        """Distance (inf: no hit) and unit geometric normal of each ray's first hit on either
        shell: mi.Float [R], mi.Vector3f [R]; with ``start`` (mi.Float [R]) the first hit past
        that distance (the distance still from the origin)."""
        o = to_point3f(origins, mi.Point3f)
        d = to_point3f(dirs, mi.Vector3f)
        o0 = o if start is None else o + start * d
        si = self.scene.ray_intersect(mi.Ray3f(o0, d), mi.RayFlags.Minimal, False)
        valid = si.is_valid()
        t = dr.select(valid, si.t if start is None else si.t + start, dr.inf)
        n = dr.select(valid, si.n, 0.0)
        dr.eval(t, n)
        return t, n

    def intervals(self, origins: Any,  # [R, 3] torch/numpy, or mi.Point3f
                  dirs: Any,  # [R, 3] unit directions, torch/numpy, or mi.Vector3f
                  dp_max: int,  # at most this many M+ hits are peeled per ray
                  mode: str = "symbolic",  # Dr.Jit loop mode: 'symbolic' or 'evaluated'
                  start: Any = None,  # mi.Float [R]: each ray's cast starts at this distance
                  ) -> Intervals:
        """Ordered M+ entry/exit intervals per ray, K = ceil(dp_max / 2) slots; with
        ``start``, of the rays' parts beyond it (module docstring).

        Both loop modes give identical results (timings in the module docstring).
        """
        return self.peel(origins, dirs, dp_max, dp_max, mode, start)[0]

    def peel(self, origins: Any, dirs: Any,  # as `intervals`
             dp_max: int,  # the rays' budget of M+ hits
             hits: int,  # M+ hits peeled by this call (at most dp_max)
             mode: str = "symbolic", start: Any = None) -> tuple[Intervals, "Peel"]:
        """The intervals closed within the first ``hits`` M+ hits of each ray, and where each
        peel stands (`Peel`): `resume` takes the rays it still has going on from there, so a
        renderer peels the deeper layers only for the rays that still let light through."""
        _check_hits(hits, dp_max)
        o = to_point3f(origins, mi.Point3f)
        d = to_point3f(dirs, mi.Vector3f)
        n = dr.width(d)
        o0, t0 = (o, mi.Float(0.0)) if start is None else (o + start * d, mi.Float(start))
        state = Peel(ray_o=mi.Point3f(o0), hits=dr.zeros(mi.UInt32, n),
                     total=dr.zeros(mi.UInt32, n), inside=dr.full(mi.Bool, False, n),
                     t_open=dr.zeros(mi.Float, n), t_prev=dr.zeros(mi.Float, n) + t0,
                     t_inner=dr.full(mi.Float, dr.inf, n), going=dr.full(mi.Bool, True, n))
        return self._resume(o, d, state, dp_max, hits, mode)

    def resume(self, origins: Any, dirs: Any,  # the rays of ``state``, as `intervals`
               state: "Peel", dp_max: int,
               hits: int | None = None,  # peel on to this many M+ hits (None: dp_max)
               mode: str = "symbolic") -> tuple[Intervals, "Peel"]:
        """Go on peeling from ``state`` (`peel`): the intervals closed from there on, in
        slots counted from 0, and the new state. A peel resumed to dp_max closes the same
        intervals, with the same distances, as one `intervals` call."""
        hits = dp_max if hits is None else hits
        _check_hits(hits, dp_max)
        return self._resume(to_point3f(origins, mi.Point3f), to_point3f(dirs, mi.Vector3f),
                            state, dp_max, hits, mode)

    def _resume(self, o: Any, d: Any, state: "Peel", dp_max: int, hits: int, mode: str
                ) -> tuple[Intervals, "Peel"]:
        n = dr.width(d)
        K = (dp_max + 1) // 2  # a ray starting inside M+ closes an interval on its first hit
        enter = dr.zeros(mi.Float, n * K)
        exit_ = dr.zeros(mi.Float, n * K)
        normals = (self._normals_outer,
                   self._normals_inner if self.has_inner else self._normals_outer)
        count, state = _peel(self.scene, self._outer_ptr, normals, o, d, enter, exit_,
                             K, dp_max, hits, mode, state)
        dr.eval(enter, exit_, count, *vars(state).values())
        iv = Intervals(enter=mi.TensorXf(enter, (n, K)), exit=mi.TensorXf(exit_, (n, K)),
                       count=tensor_xi()(mi.Int(count), (n,)),
                       t_inner=mi.TensorXf(state.t_inner, (n,)))
        return iv, state


def _check_hits(hits: int, dp_max: int) -> None:
    if not 1 <= hits <= dp_max:
        raise InputError(f"dp_max={dp_max}, hits={hits}: need 1 <= hits <= dp_max")


def face_normals(mesh: "mi.Mesh") -> Any:
    """Unit geometric normal of each triangle of a Mitsuba mesh, as Mitsuba orients it: (p1 -
    p0) x (p2 - p0); flat (mi.Float [3 faces], x y z of each), for `dr.gather`."""
    p = mi.traverse(mesh)
    V = dr.unravel(mi.Point3f, p["vertex_positions"])
    F = dr.unravel(mi.Vector3u, p["faces"])
    a, b, c = (dr.gather(mi.Point3f, V, F[i]) for i in range(3))
    n = dr.ravel(dr.normalize(dr.cross(b - a, c - a)))
    dr.eval(n)
    return n


@dr.syntax
def _peel(scene: "mi.Scene", outer_ptr: Any, normals: tuple[Any, Any], o: Any, d: Any,
          enter: Any, exit_: Any, K: int, dp_max: int, limit: int, mode: str, state: Peel
          ) -> tuple[Any, Peel]:
    """Depth-peel the scene on from ``state`` until ``limit`` M+ hits; scatter the intervals
    it closes (distances from o) into enter/exit [R * K] in place, from slot 0. Returns the
    count of those intervals and the new state. ``normals``: the face normals of M+ and of
    M-."""
    n = dr.width(d)
    row = dr.arange(mi.UInt32, n) * K
    ray_o, hits, total, inside = state.ray_o, state.hits, state.total, state.inside
    t_open, t_prev, t_inner, going = state.t_open, state.t_prev, state.t_inner, state.going
    count = dr.zeros(mi.UInt32, n)  # intervals closed by this call
    # opaque: one kernel for every step of a peel resumed in steps
    limit = dr.opaque(mi.UInt32, limit)
    active = going & (hits < limit)
    while dr.hint(active, mode=mode, max_iterations=-1, label="shell_peel"):
        pi = scene.ray_intersect_preliminary(mi.Ray3f(ray_o, d), False)
        valid = pi.is_valid()
        is_outer = valid & (pi.shape == outer_ptr)
        is_inner = valid & ~is_outer
        normal = dr.select(is_outer, dr.gather(mi.Vector3f, normals[0], pi.prim_index, is_outer),
                           dr.gather(mi.Vector3f, normals[1], pi.prim_index, is_inner))
        p = dr.fma(d, pi.t, ray_o)
        t = dr.dot(p - o, d)
        cos = dr.dot(d, normal)
        entering = cos < 0

        # An exit while not inside means the ray started inside M+ (or a missed entry):
        # the interval then starts at the previous hit, the origin for the first one.
        start = dr.select(inside, t_open, t_prev)
        # M- lies inside M+: hitting it first also means the ray started inside M+.
        close = (is_outer & ~entering) | (is_inner & (inside | (hits == 0)))
        close &= total < K
        dr.scatter(enter, start, row + count, active=close)
        dr.scatter(exit_, t, row + count, active=close)
        count = dr.select(close, count + 1, count)
        total = dr.select(close, total + 1, total)

        t_inner = dr.select(is_inner, t, t_inner)
        t_open = dr.select(is_outer & entering & ~inside, t, t_open)  # a double entry keeps the first
        inside = is_outer & entering
        hits = dr.select(is_outer, hits + 1, hits)
        t_prev = dr.select(is_outer, t, t_prev)
        going = is_outer & (hits < dp_max)
        active = going & (hits < limit)
        offset = (1.0 + dr.max(dr.abs(p))) * (1500.0 * dr.epsilon(mi.Float))
        ray_o = dr.fma(normal, dr.select(cos >= 0, offset, -offset), p)
    return count, Peel(ray_o=ray_o, hits=hits, total=total, inside=inside, t_open=t_open,
                       t_prev=t_prev, t_inner=t_inner, going=going)
