"""Finite-element simulation of the cage: stable neo-Hookean elasticity on its tetrahedra,
gravity, a pinned region and a ground plane, explicit time stepping (numpy, vectorised).

Per tetrahedron with rest edge matrix Dm = [X1 - X0, X2 - X0, X3 - X0], rest volume W and
deformation gradient F = Ds Dm^-1, the energy density is the stable neo-Hookean one
(Smith, de Goes and Kim 2018, in its simplest form)

    Psi(F) = mu / 2 (tr F^T F - 3) - mu (J - 1) + lambda / 2 (J - 1)^2,   J = det F,

which is zero with zero stress at rest and stays finite under inversion (no log J). Its first
Piola-Kirchhoff stress is P = mu F + (lambda (J - 1) - mu) dJ/dF, dJ/dF = cof F, and the
elastic forces on the vertices are H = -W P Dm^-T (columns: vertices 1..3), vertex 0 the
negative sum (`elastic_forces`, checked against finite differences of `elastic_energy`).

Masses are lumped (a quarter of each tetrahedron's mass to each vertex). Time stepping is
symplectic Euler with a step below the explicit stability limit (`stable_dt`), mass-
proportional damping, pinned vertices held at their rest positions, and a ground plane
{x . up = ground}: a vertex below it is put back on it, its velocity into the plane removed
and its tangential velocity reduced by the friction factor.

Units: the world units of the scene (metres, if the capture's scale is metric) and seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from shells.errors import InputError
from shells.progress import tqdm


@dataclass
class Material:
    young: float = 3e4  # Young's modulus, Pa (soft rubber-like: visible wobble at 1 m)
    poisson: float = 0.3
    density: float = 1000.0  # kg / m^3
    damping: float = 2.0  # mass-proportional damping rate, 1 / s

    @property
    def lame(self) -> tuple[float, float]:
        E, nu = self.young, self.poisson
        if not (E > 0 and -1.0 < nu < 0.5):
            raise InputError(f"material E={E}, nu={nu}: need E > 0 and -1 < nu < 0.5")
        return E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))


class Elastic:
    """Rest-state quantities of a tetrahedral mesh and its elastic energy and forces."""

    def __init__(self, X: np.ndarray, T: np.ndarray, material: Material) -> None:
        self.X = np.asarray(X, np.float64)
        self.T = np.asarray(T, np.int64)
        Dm = self._edges(self.X)
        det = np.linalg.det(Dm)
        if np.any(det <= 0):
            raise InputError(f"{int((det <= 0).sum())} cage tetrahedra have non-positive rest "
                             "volume; rebuild the cage (shells-cage)")
        self.Bm = np.linalg.inv(Dm)
        self.W = det / 6.0
        self.mu, self.lam = material.lame
        self.material = material
        mass = np.zeros(len(self.X))
        np.add.at(mass, self.T.reshape(-1), np.repeat(material.density * self.W / 4.0, 4))
        self.mass = mass

    def _edges(self, x: np.ndarray) -> np.ndarray:
        p = x[self.T]
        return np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=-1)

    def gradient(self, x: np.ndarray) -> np.ndarray:  # [m, 3, 3] F
        return self._edges(x) @ self.Bm

    def elastic_energy(self, x: np.ndarray) -> float:
        F = self.gradient(x)
        J = np.linalg.det(F)
        psi = (0.5 * self.mu * ((F ** 2).sum((1, 2)) - 3.0) - self.mu * (J - 1.0)
               + 0.5 * self.lam * (J - 1.0) ** 2)
        return float((self.W * psi).sum())

    def elastic_forces(self, x: np.ndarray) -> np.ndarray:  # [n, 3] = -dE/dx
        F = self.gradient(x)
        J = np.linalg.det(F)
        f0, f1, f2 = F[:, :, 0], F[:, :, 1], F[:, :, 2]
        cof = np.stack([np.cross(f1, f2), np.cross(f2, f0), np.cross(f0, f1)], axis=-1)
        P = self.mu * F + (self.lam * (J - 1.0) - self.mu)[:, None, None] * cof
        H = -self.W[:, None, None] * P @ np.transpose(self.Bm, (0, 2, 1))
        out = np.zeros_like(x)
        for k in range(3):
            np.add.at(out, self.T[:, k + 1], H[:, :, k])
        np.add.at(out, self.T[:, 0], -H.sum(axis=2))
        return out

    def stable_dt(self, safety: float = 0.4) -> float:
        """A step below the explicit limit: safety * (shortest edge) / (p-wave speed)."""
        p = self.X[self.T]
        edges = [np.linalg.norm(p[:, a] - p[:, b], axis=1)
                 for a, b in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))]
        h = float(np.min(edges))
        c = math.sqrt((self.lam + 2 * self.mu) / self.material.density)
        return safety * h / c


@dataclass
class Scenario:
    gravity: float = 9.81  # m / s^2, along -up
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    ground: float | None = None  # height of the ground plane along up; None: no ground
    friction: float = 0.5  # share of tangential velocity removed on contact per step
    pinned: np.ndarray | None = None  # [n] bool: vertices held at their rest positions
    lift: float = 0.0  # initial offset along up (the asset starts above its rest place)


def simulate(X: np.ndarray, T: np.ndarray, frames: int, fps: float, material: Material,
             scenario: Scenario, progress: bool = True) -> tuple[np.ndarray, dict]:
    """Cage positions [frames, n, 3] at t = k / fps (frame 0 = the initial state), and a
    summary (time step, sub-steps per frame, kinetic energy at the end)."""
    if frames < 1 or not fps > 0:
        raise InputError(f"frames={frames}, fps={fps}: need at least 1 frame and fps > 0")
    el = Elastic(X, T, material)
    up = np.asarray(scenario.up, np.float64)
    up /= np.linalg.norm(up)
    pinned = (np.zeros(len(X), bool) if scenario.pinned is None
              else np.asarray(scenario.pinned, bool))
    x = el.X + scenario.lift * up
    x[pinned] = el.X[pinned]
    v = np.zeros_like(x)
    g = -scenario.gravity * up
    sub = max(1, math.ceil((1.0 / fps) / el.stable_dt()))
    dt = (1.0 / fps) / sub
    decay = math.exp(-material.damping * dt)
    out = np.empty((frames, *x.shape))
    out[0] = x
    for k in tqdm(range(1, frames), desc="simulate", unit="frame", disable=not progress):
        for _ in range(sub):
            a = el.elastic_forces(x) / el.mass[:, None] + g
            v = (v + dt * a) * decay
            v[pinned] = 0.0
            x = x + dt * v
            if scenario.ground is not None:
                h = x @ up
                below = h < scenario.ground
                if np.any(below):
                    x[below] += (scenario.ground - h[below])[:, None] * up
                    vn = v[below] @ up
                    vt = v[below] - vn[:, None] * up
                    v[below] = (1.0 - scenario.friction) * vt + np.maximum(vn, 0.0)[:, None] * up
        if not np.all(np.isfinite(x)):
            raise InputError(f"the simulation diverged at frame {k}; use a softer or more "
                             "damped material, or a finer cage")
        out[k] = x
    kinetic = 0.5 * float((el.mass * (v ** 2).sum(1)).sum())
    return out, {"dt": dt, "substeps_per_frame": sub, "kinetic_energy_end": kinetic,
                 "mass": float(el.mass.sum()), "young": material.young,
                 "poisson": material.poisson, "density": material.density,
                 "damping": material.damping, "gravity": scenario.gravity,
                 "ground": scenario.ground, "pinned_vertices": int(pinned.sum()),
                 "lift": scenario.lift}


def drop(X: np.ndarray, T: np.ndarray, frames: int, fps: float, up=(0.0, 0.0, 1.0),
         material: Material | None = None, progress: bool = True) -> tuple[np.ndarray, dict]:
    """The asset dropped from 40 % of its height onto a ground plane at its rest base."""
    up_v = np.asarray(up, np.float64) / np.linalg.norm(up)
    h = X @ up_v
    sc = Scenario(up=tuple(up_v), ground=float(h.min()), lift=0.4 * float(h.max() - h.min()))
    return simulate(X, T, frames, fps, material or Material(), sc, progress)


def hang(X: np.ndarray, T: np.ndarray, frames: int, fps: float, up=(0.0, 0.0, 1.0),
         material: Material | None = None, progress: bool = True) -> tuple[np.ndarray, dict]:
    """The asset held by its top 10 % (pinned) and sagging under gravity."""
    up_v = np.asarray(up, np.float64) / np.linalg.norm(up)
    h = X @ up_v
    pinned = h >= h.max() - 0.1 * (h.max() - h.min())
    sc = Scenario(up=tuple(up_v), pinned=pinned)
    return simulate(X, T, frames, fps, material or Material(young=1e5), sc, progress)


SIMULATED = {"drop": drop, "hang": hang}
