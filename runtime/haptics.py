"""Haptic contact: a probe point, a proxy on the surface, and the force f = K(x) ū at 1 kHz.

God-object / proxy style (Zilles & Salisbury; Ruspini's friction cone) with
force shading (Morgenbesser & Srinivasan): the surface point x "under" the
probe is found along the interpolated vertex normal N(x) = Σ b_k n_k rather
than the flat triangle normal (a Phong projection: probe = x + s N(x)), which,
unlike the closest point on a polyhedron, moves continuously when the probe
slides over an edge — a closest-point proxy jumps by about depth x dihedral
angle at every convex edge, which a user feels.  While out of contact this
point is tracked by walking from triangle to neighbouring triangle; when the
probe crosses the surface (s < 0) the proxy is born there, and afterwards it
slides only as far as the friction cone demands (``friction`` = 0: it stays
the projection of the probe).  The displacement constraint is
ū = probe − proxy, the force on the body f = K(x) ū (eq. 15), and −f is
rendered to the user.

Every step does a bounded amount of work (at most ``max_walk`` triangle steps),
so its cost does not grow with the mesh; a brute-force search over all
triangles runs only when tracking (re)starts.  The hot path is plain Python
floats: for 3-vectors it is several times faster than numpy calls.

``step`` never raises on a sample.  Every result carries a :class:`Status`:
a NaN/inf or malformed sample, or an implausible jump, returns the last good
force decaying geometrically and leaves the state alone; a probe over a
triangle outside the precomputed contact region gets no force.
"""
from __future__ import annotations

import logging
import math
from enum import IntEnum

import numpy as np

from pmask.errors import InputError
from pmask.runtime.geometry import triangle_neighbours, triangle_normals, vertex_normals

log = logging.getLogger(__name__)


class Status(IntEnum):
    NO_CONTACT = 0      #: probe outside the body (or not tracked): zero force
    CONTACT = 1         #: in contact: force = −K(x) ū
    BAD_SAMPLE = 2      #: NaN/inf or malformed probe sample: last good force, decaying
    JUMP = 3            #: probe moved implausibly far in one step: last good force, decaying
    OUTSIDE_REGION = 4  #: over a triangle without precomputed stiffness: zero force


class HapticContact:
    """Proxy-based point contact against a :class:`pmask.runtime.stiffness.SurfaceStiffness`.

    friction : Coulomb coefficient of the proxy's friction cone (0: frictionless sliding).
    decay : factor per step applied to the last good force during bad samples.
    max_jump : largest plausible probe move per step [model units]; default 5 mean edge lengths.
    reset_after : after this many consecutive implausible samples, tracking restarts from scratch.
    """

    def __init__(self, stiffness, *, friction: float = 0.0, decay: float = 0.9, max_jump: float | None = None,
                 max_walk: int = 24, reset_after: int = 50):
        if not (friction >= 0 and math.isfinite(friction)):
            raise InputError(f"friction must be a finite number >= 0, got {friction!r}")
        if not 0 <= decay < 1:
            raise InputError(f"decay must lie in [0, 1), got {decay!r}")
        self.stiffness = stiffness
        P = stiffness.points
        T = stiffness.triangles
        v0, e1, e2 = P[T[:, 0]], P[T[:, 1]] - P[T[:, 0]], P[T[:, 2]] - P[T[:, 0]]
        n = triangle_normals(P, T)
        inv = np.linalg.inv(np.stack([e1, e2, n], axis=2))  # rows: dual vectors of e1, e2, n
        self._R = inv  # (T, 3, 3) for the vectorised search
        self._v0 = v0
        self._V = P[T]  # (T, 3, 3)
        self._tri = [tuple(row) for row in np.concatenate([v0, inv[:, 0], inv[:, 1], n], axis=1).tolist()]
        self._nb = [tuple(r) for r in triangle_neighbours(T).tolist()]
        self._vert = [tuple(r) for r in P[T].reshape(len(T), 9).tolist()]
        self._vn = [tuple(r) for r in vertex_normals(P, T)[T].reshape(len(T), 9).tolist()]
        self._table = [tuple(r) for r in stiffness.table.reshape(len(T), 27).tolist()]
        self._touchable = stiffness.touchable.tolist()
        edge = float(np.mean(np.linalg.norm(e1, axis=1)))
        self.max_jump = 5.0 * edge if max_jump is None else float(max_jump)
        lo, hi = P.min(axis=0) - 2 * self.max_jump, P.max(axis=0) + 2 * self.max_jump
        self._lo, self._hi = tuple(lo.tolist()), tuple(hi.tolist())
        self.friction = float(friction)
        self.decay = float(decay)
        self.max_walk = int(max_walk)
        self.reset_after = int(reset_after)
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget all contact state (the next sample starts tracking afresh)."""
        self.triangle = -1         # tracked / proxy triangle, -1 when not tracking
        self.bary = (1.0, 0.0, 0.0)
        self.in_contact = False
        self._above = False        # the probe was seen outside the body since tracking began
        self._last_probe = None
        self._bad = 0
        self.u_bar = (0.0, 0.0, 0.0)
        self.force = (0.0, 0.0, 0.0)     # force rendered to the user (−f)
        self.body_force = (0.0, 0.0, 0.0)  # force on the body (f = K ū)
        self._good_force = (0.0, 0.0, 0.0)
        self.status = Status.NO_CONTACT

    def _hold(self, status: Status):
        d = self.decay
        g = self._good_force
        self._good_force = (g[0] * d, g[1] * d, g[2] * d)
        self.force = self._good_force
        self.status = status
        return self.force, status

    def _none(self, status: Status = Status.NO_CONTACT):
        self.force = self._good_force = self.body_force = (0.0, 0.0, 0.0)
        self.u_bar = (0.0, 0.0, 0.0)
        self.status = status
        return self.force, status

    # ------------------------------------------------------------------ geometry
    def _project(self, t: int, px: float, py: float, pz: float):
        """Phong projection onto triangle t's plane: p = x + s N(x); returns (b0, b1, b2, s).

        Two fixed-point steps from the flat projection (each contracts by about
        depth x normal variation / edge length, ~0.05 at haptic depths).
        """
        ox, oy, oz, ax, ay, az, bx, by, bz, nx, ny, nz = self._tri[t]
        n0x, n0y, n0z, n1x, n1y, n1z, n2x, n2y, n2z = self._vn[t]
        dx, dy, dz = px - ox, py - oy, pz - oz
        h = nx * dx + ny * dy + nz * dz
        b1 = ax * dx + ay * dy + az * dz
        b2 = bx * dx + by * dy + bz * dz
        s = h
        for _ in range(2):
            b0 = 1.0 - b1 - b2
            Nx = b0 * n0x + b1 * n1x + b2 * n2x
            Ny = b0 * n0y + b1 * n1y + b2 * n2y
            Nz = b0 * n0z + b1 * n1z + b2 * n2z
            hn = Nx * nx + Ny * ny + Nz * nz
            if hn < 0.1:  # normals turned away from the face: keep the flat projection
                break
            s = h / hn
            qx, qy, qz = dx - s * Nx, dy - s * Ny, dz - s * Nz
            b1 = ax * qx + ay * qy + az * qz
            b2 = bx * qx + by * qy + bz * qz
        return 1.0 - b1 - b2, b1, b2, s

    def _locate(self, t: int, px: float, py: float, pz: float):
        """Walk from triangle t to the one holding the projection of p; return (t, b0, b1, b2, s)."""
        prev = -1
        nbs = self._nb
        for _ in range(self.max_walk):
            b0, b1, b2, s = self._project(t, px, py, pz)
            if b0 >= 0.0 and b1 >= 0.0 and b2 >= 0.0:
                return t, b0, b1, b2, s
            k = 0 if (b0 <= b1 and b0 <= b2) else (1 if b1 <= b2 else 2)
            nb = nbs[t][k]
            if nb < 0 or nb == prev:
                break  # a ridge or an open edge: clamp onto t (already projected)
            prev, t = t, nb
        else:
            b0, b1, b2, s = self._project(t, px, py, pz)  # walk budget spent: clamp where it ended
        b0, b1, b2 = max(b0, 0.0), max(b1, 0.0), max(b2, 0.0)
        tot = b0 + b1 + b2
        return t, b0 / tot, b1 / tot, b2 / tot, s

    def _search(self, p) -> int:
        """Nearest triangle by brute force (only when tracking starts): clamped projections."""
        d = np.asarray(p) - self._v0
        b12 = np.einsum("tij,tj->ti", self._R[:, :2, :], d)
        b = np.column_stack([1 - b12.sum(axis=1), b12])
        b = np.clip(b, 0, None)
        b /= b.sum(axis=1, keepdims=True)
        q = np.einsum("tk,tkj->tj", b, self._V)
        return int(np.argmin(np.sum((q - p) ** 2, axis=1)))

    def _point(self, t: int, b0: float, b1: float, b2: float):
        v = self._vert[t]
        return (b0 * v[0] + b1 * v[3] + b2 * v[6], b0 * v[1] + b1 * v[4] + b2 * v[7],
                b0 * v[2] + b1 * v[5] + b2 * v[8])

    def _normal(self, t: int, b0: float, b1: float, b2: float):
        """Unit interpolated (shaded) normal at barycentric b of triangle t."""
        n = self._vn[t]
        x = b0 * n[0] + b1 * n[3] + b2 * n[6]
        y = b0 * n[1] + b1 * n[4] + b2 * n[7]
        z = b0 * n[2] + b1 * n[5] + b2 * n[8]
        r = math.sqrt(x * x + y * y + z * z)
        return x / r, y / r, z / r

    # ------------------------------------------------------------------ the loop
    def step(self, probe):
        """Advance one haptic tick with a new probe position; return (force on user, Status)."""
        try:
            px, py, pz = (float(c) for c in probe)
        except (TypeError, ValueError):
            return self._hold(Status.BAD_SAMPLE)
        if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)):
            return self._hold(Status.BAD_SAMPLE)
        last = self._last_probe
        if last is not None:
            dx, dy, dz = abs(px - last[0]), abs(py - last[1]), abs(pz - last[2])
            mj = self.max_jump  # the per-axis test first: no overflow for absurd samples
            if dx > mj or dy > mj or dz > mj or dx * dx + dy * dy + dz * dz > mj * mj:
                self._bad += 1
                if self._bad <= self.reset_after:
                    return self._hold(Status.JUMP)
                self.reset()
        self._bad = 0
        self._last_probe = (px, py, pz)
        lo, hi = self._lo, self._hi
        if not (lo[0] <= px <= hi[0] and lo[1] <= py <= hi[1] and lo[2] <= pz <= hi[2]):
            self.triangle, self.in_contact, self._above = -1, False, False
            return self._none()
        if self.triangle < 0:  # (re)start tracking
            t = self._search((px, py, pz))
            t, b0, b1, b2, h = self._locate(t, px, py, pz)
            self.triangle, self.bary = t, (b0, b1, b2)
            self._above = h >= 0.0  # starting inside the body is not a contact
            return self._none()
        if not self.in_contact:
            t, b0, b1, b2, h = self._locate(self.triangle, px, py, pz)
            self.triangle, self.bary = t, (b0, b1, b2)
            if h >= 0.0 or not self._above:
                self._above = self._above or h >= 0.0
                return self._none()
            self.in_contact = True  # crossed the surface: the proxy is born at the projection
        else:
            t = self.triangle
            b0, b1, b2 = self.bary
            cx, cy, cz = self._point(t, b0, b1, b2)
            nx, ny, nz = self._normal(t, b0, b1, b2)
            ux, uy, uz = px - cx, py - cy, pz - cz
            un = ux * nx + uy * ny + uz * nz
            if un >= 0.0:  # the probe left the body: contact ends
                self.in_contact = False
                self._above = True
                t, b0, b1, b2, _ = self._locate(t, px, py, pz)
                self.triangle, self.bary = t, (b0, b1, b2)
                return self._none()
            tx, ty, tz = ux - un * nx, uy - un * ny, uz - un * nz
            ut = math.sqrt(tx * tx + ty * ty + tz * tz)
            limit = -self.friction * un
            if ut <= limit:  # inside the friction cone: the proxy sticks, ū as computed
                return self._render(t, b0, b1, b2, ux, uy, uz)
            s = 1.0 - limit / ut  # slide the proxy to the edge of the friction cone
            t, b0, b1, b2, _ = self._locate(t, cx + s * tx, cy + s * ty, cz + s * tz)
            self.triangle, self.bary = t, (b0, b1, b2)
        t = self.triangle
        b0, b1, b2 = self.bary
        cx, cy, cz = self._point(t, b0, b1, b2)
        return self._render(t, b0, b1, b2, px - cx, py - cy, pz - cz)

    def _render(self, t: int, b0: float, b1: float, b2: float, ux: float, uy: float, uz: float):
        """f = K(x) ū at the proxy (eq. 15); −f to the user."""
        if not self._touchable[t]:
            return self._none(Status.OUTSIDE_REGION)
        k = self._table[t]
        K = [b0 * k[i] + b1 * k[9 + i] + b2 * k[18 + i] for i in range(9)]  # eq. 15
        fx = K[0] * ux + K[1] * uy + K[2] * uz
        fy = K[3] * ux + K[4] * uy + K[5] * uz
        fz = K[6] * ux + K[7] * uy + K[8] * uz
        self.u_bar = (ux, uy, uz)
        self.body_force = (fx, fy, fz)
        self.force = self._good_force = (-fx, -fy, -fz)
        self.status = Status.CONTACT
        return self.force, Status.CONTACT
