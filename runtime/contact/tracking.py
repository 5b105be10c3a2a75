r"""Step 1, tracking and the proxy: where on the surface the probe is, and the proxy that follows it.

The contact point is the surface point under the probe p along the interpolated vertex normal (a Phong
projection, p = x + s N(x), continuous over edges where a closest point jumps by depth x dihedral angle),
found by walking from the proxy's triangle; a spatial grid restarts tracking in O(1).  Contact begins when
the tool sphere (radius r_tool) crosses the surface from outside.  The proxy x follows that projection along
the surface (a god-object step: across edges, never through the body) by at most ``proxy_speed`` times the
probe's motion per tick.

Functions of the contact options ``c`` (a :class:`pmask.runtime.Contacts`: its ``surface`` and options) and
of one :class:`~pmask.runtime.contact.state.ContactState`; the native core's ``core/tracking.c`` is the same
code operation for operation.
"""
from __future__ import annotations

import logging
import math

import numpy as np

from pmask.runtime.contact.linalg3 import mul3, reckoning, speed_up, tangent_part
from pmask.runtime.contact.state import FAR_FACTOR, VELOCITY_FILTER, Status, hold, release
from pmask.runtime.contact.surface import shape_at

log = logging.getLogger("pmask.runtime.haptics")


#: Newton steps at most for the Phong projection (:func:`project`; it converges in 2-4 from the flat projection)
PROJECT_STEPS = 8
#: and the residual in barycentric coordinates at which it stops (at a 3 mm edge, 3e-16 m)
PROJECT_TOL = 1e-13


def project(srf, t, px, py, pz):
    """Phong projection onto triangle t's plane: p = x + s N(x), N interpolated from the vertices (not
    normalised); returns (b0, b1, b2, s).  Newton's method on the fixed point b = g(b), g(b) the flat projection
    of p − s(b) N(b) (s(b) such that it lies in the plane), from the flat projection of p, to PROJECT_TOL.  Two
    fixed-point steps, the form before, contract by about κ δ each (depth over the radius of curvature), so
    that deep (κ δ ≈ 0.36, 4 mm into the kidney's lateral face) the projections of one probe onto two
    neighbouring triangles differed by 0.02 mm: the projection jumped by that where the walk crossed an edge,
    the proxy caught up at ``proxy_speed`` over three ticks and the force dipped (0.17 % on the subdivided
    surface; on the mesh, with the law as it was, 11 of the haptics bench's 720 deep pushes lost force, 5 with
    the projection exact), and a straight press drifted sideways (0.5 mm at 14 mm into the lateral face, where it
    now stays on its vertex).  Where N turns away from the face (N·n < 0.1) the last projection is kept; where
    Newton's Jacobian nearly vanishes (a fold of the projection near a crease) a fixed-point step is taken."""
    ox, oy, oz, ax, ay, az, bx, by, bz, nx, ny, nz = srf._tri[t]
    i0, i1, i2 = srf._idx[t]
    VN = srf._N
    n0x, n0y, n0z = VN[i0]
    n1x, n1y, n1z = VN[i1]
    n2x, n2y, n2z = VN[i2]
    m1x, m1y, m1z = n1x - n0x, n1y - n0y, n1z - n0z  # ∂N/∂b1
    m2x, m2y, m2z = n2x - n0x, n2y - n0y, n2z - n0z  # ∂N/∂b2
    e1 = nx * m1x + ny * m1y + nz * m1z
    e2 = nx * m2x + ny * m2y + nz * m2z
    dx, dy, dz = px - ox, py - oy, pz - oz
    h = nx * dx + ny * dy + nz * dz
    b1 = ax * dx + ay * dy + az * dz
    b2 = bx * dx + by * dy + bz * dz
    s = h
    for _ in range(PROJECT_STEPS):
        b0 = 1.0 - b1 - b2
        Nx = b0 * n0x + b1 * n1x + b2 * n2x
        Ny = b0 * n0y + b1 * n1y + b2 * n2y
        Nz = b0 * n0z + b1 * n1z + b2 * n2z
        hn = Nx * nx + Ny * ny + Nz * nz
        if hn < 0.1:  # normals turned away from the face: keep the last projection
            break
        s = h / hn
        qx, qy, qz = dx - s * Nx, dy - s * Ny, dz - s * Nz
        r1 = ax * qx + ay * qy + az * qz - b1  # g(b) − b
        r2 = bx * qx + by * qy + bz * qz - b2
        if abs(r1) + abs(r2) <= PROJECT_TOL:  # converged: b, and s with it
            break
        c1, c2 = s * e1 / hn, s * e2 / hn  # ∂q/∂b_k = c_k N − s m_k
        u1x, u1y, u1z = c1 * Nx - s * m1x, c1 * Ny - s * m1y, c1 * Nz - s * m1z
        u2x, u2y, u2z = c2 * Nx - s * m2x, c2 * Ny - s * m2y, c2 * Nz - s * m2z
        j11 = 1.0 - (ax * u1x + ay * u1y + az * u1z)  # I − ∂g/∂b
        j12 = -(ax * u2x + ay * u2y + az * u2z)
        j21 = -(bx * u1x + by * u1y + bz * u1z)
        j22 = 1.0 - (bx * u2x + by * u2y + bz * u2z)
        det = j11 * j22 - j12 * j21
        if det > 0.05:
            d1 = (j22 * r1 - j12 * r2) / det
            d2 = (j11 * r2 - j21 * r1) / det
        else:  # a fold: the fixed-point step
            d1, d2 = r1, r2
        b1 += d1
        b2 += d2
    return 1.0 - b1 - b2, b1, b2, s


def locate(c, t, px, py, pz, retry=True):
    """Walk from triangle t to the one holding the projection of p; return (t, b0, b1, b2, s).

    Two triangles that send the walk to each other hold p's projection on their shared edge (the gap of a
    convex edge) unless the projection map folds there (normals blended near a crease): then the spatial
    grid's nearest triangle restarts the walk, once."""
    srf = c.surface
    prev = -1
    nbs = srf._nb
    for _ in range(c.max_walk):
        b0, b1, b2, s = project(srf, t, px, py, pz)
        if b0 >= 0.0 and b1 >= 0.0 and b2 >= 0.0:
            return t, b0, b1, b2, s
        k = 0 if (b0 <= b1 and b0 <= b2) else (1 if b1 <= b2 else 2)
        nb = nbs[t][k]
        if nb < 0 or nb == prev:
            if retry:
                near = srf.grid.nearest((px, py, pz))
                if near != t and near != prev:
                    return locate(c, near, px, py, pz, retry=False)
            break  # a ridge or an open edge: clamp onto t (already projected)
        prev, t = t, nb
    else:
        b0, b1, b2, s = project(srf, t, px, py, pz)  # walk budget spent: clamp where it ended
    b0, b1, b2 = max(b0, 0.0), max(b1, 0.0), max(b2, 0.0)
    tot = b0 + b1 + b2
    return t, b0 / tot, b1 / tot, b2 / tot, s


def point(srf, t, b0, b1, b2):
    """The surface point at barycentric b of triangle t."""
    i0, i1, i2 = srf._idx[t]
    P = srf._P
    a, b, c = P[i0], P[i1], P[i2]
    return (b0 * a[0] + b1 * b[0] + b2 * c[0], b0 * a[1] + b1 * b[1] + b2 * c[1],
            b0 * a[2] + b1 * b[2] + b2 * c[2])


def normal(srf, t, b0, b1, b2):
    """Unit interpolated (shaded) normal at barycentric b of triangle t."""
    i0, i1, i2 = srf._idx[t]
    VN = srf._N
    a, b, c = VN[i0], VN[i1], VN[i2]
    x = b0 * a[0] + b1 * b[0] + b2 * c[0]
    y = b0 * a[1] + b1 * b[1] + b2 * c[1]
    z = b0 * a[2] + b1 * b[2] + b2 * c[2]
    r = math.sqrt(x * x + y * y + z * z)
    return x / r, y / r, z / r


def move_proxy(c, st, tx, ty, tz, limit):
    """Slide the proxy along the surface towards the point (tx, ty, tz), by a path of length at most
    ``limit`` (a god-object step): in each triangle towards the target's flat projection on its plane,
    across an edge into the neighbour when the straight path leaves the triangle."""
    surf = c.surface
    t, (b0, b1, b2) = st.tri, st.b
    remaining = limit
    for _ in range(c.max_walk):
        ox, oy, oz, ax, ay, az, bx, by, bz, _, _, _ = surf._tri[t]
        dx, dy, dz = tx - ox, ty - oy, tz - oz
        q1 = ax * dx + ay * dy + az * dz  # the target's flat projection on t's plane, barycentric
        q2 = bx * dx + by * dy + bz * dz
        d0, d1, d2 = (1.0 - q1 - q2) - b0, q1 - b1, q2 - b2
        i0, i1, i2 = surf._idx[t]
        P = surf._P
        v0, v1, v2 = P[i0], P[i1], P[i2]
        ex = d0 * v0[0] + d1 * v1[0] + d2 * v2[0]
        ey = d0 * v0[1] + d1 * v1[1] + d2 * v2[1]
        ez = d0 * v0[2] + d1 * v1[2] + d2 * v2[2]
        dist = math.sqrt(ex * ex + ey * ey + ez * ez)
        if dist <= 0.0 or remaining <= 0.0:
            break
        a = min(1.0, remaining / dist)  # how far along towards the target this step may go
        exit_k, exit_a = -1, a
        for k, (bk, dk) in enumerate(((b0, d0), (b1, d1), (b2, d2))):
            if dk < 0.0 and bk + exit_a * dk < 0.0:
                exit_a, exit_k = -bk / dk, k
        b0, b1, b2 = b0 + exit_a * d0, b1 + exit_a * d1, b2 + exit_a * d2
        remaining -= exit_a * dist
        if exit_k < 0:
            break
        nb = surf._nb[t][exit_k]
        if nb < 0:
            break  # an open edge: stay on it
        bs = [b0, b1, b2]
        bs[exit_k] = 0.0
        w = {surf._idx[t][k]: bs[k] for k in range(3)}
        t = nb
        b0, b1, b2 = (w.get(v, 0.0) for v in surf._idx[t])
    b0, b1, b2 = max(b0, 0.0), max(b1, 0.0), max(b2, 0.0)
    tot = b0 + b1 + b2
    st.tri, st.b = t, (b0 / tot, b1 / tot, b2 / tot)


#: what is never a coordinate, although float() converts it: text ("000" is 0.0) and truth values
NOT_COORDINATES = (str, bytes, bytearray, bool, np.bool_)


def coordinate(v) -> float:
    """One coordinate of a probe sample: a real number, not text or a truth value (TypeError otherwise)."""
    if isinstance(v, NOT_COORDINATES):
        raise TypeError(f"not a coordinate: {type(v).__name__}")
    return float(v)


def prepare(c, st, sample):
    """Step 1 of one contact: check the sample, track the probe, start or keep the contact.  Returns the probe
    as a tuple and whether the contact is active (in contact this tick)."""
    try:
        if isinstance(sample, (str, bytes, bytearray)):  # iterable, but text is not a point
            raise TypeError("text is not a probe sample")
        px, py, pz = (coordinate(v) for v in sample)
    except Exception:  # not three numbers (None, text, a bool, an object whose __float__ raises, 10**400)
        hold(c, st, Status.BAD_SAMPLE)
        return None, False
    if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)):
        hold(c, st, Status.BAD_SAMPLE)
        return None, False
    last = st.last
    if last is not None:
        dx, dy, dz = abs(px - last[0]), abs(py - last[1]), abs(pz - last[2])
        mj = c.max_jump  # the per-axis test first: no overflow for absurd samples
        if dx > mj or dy > mj or dz > mj or dx * dx + dy * dy + dz * dz > mj * mj:
            st.bad += 1
            if st.bad <= c.reset_after:
                hold(c, st, Status.JUMP)
                return None, False
            st.reset()  # tracking restarts here: the jump is not a motion
            last = None
    st.bad = 0
    s = c.surface
    lo, hi = s.lo, s.hi
    gx = max(lo[0] - px, px - hi[0], 0.0)
    gy = max(lo[1] - py, py - hi[1], 0.0)
    gz = max(lo[2] - pz, pz - hi[2], 0.0)
    st.move = (px - last[0], py - last[1], pz - last[2]) if last is not None else (0.0, 0.0, 0.0)
    a, v = VELOCITY_FILTER, st.vel
    st.vel = (v[0] + a * (st.move[0] - v[0]), v[1] + a * (st.move[1] - v[1]), v[2] + a * (st.move[2] - v[2]))
    st.last = (px, py, pz)
    st.target = None
    far = FAR_FACTOR * s.diag  # per axis first: no overflow for absurd samples
    if gx > far or gy > far or gz > far or gx * gx + gy * gy + gz * gz > far * far:
        if not c._far_warned:
            log.warning("probe at (%.4g, %.4g, %.4g) is more than %g model sizes from the model (size %.3g): "
                        "are the probe and the model in the same length unit?", px, py, pz, FAR_FACTOR, s.diag)
            c._far_warned = True
        st.tri, st.in_contact, st.above = -1, False, False
        release(st, Status.FAR_OUTSIDE)
        return None, False
    m = c._margin
    if gx > m or gy > m or gz > m:
        st.tri, st.in_contact, st.above = -1, False, False
        release(st)
        return None, False
    r = c.tool_radius
    if st.tri < 0:  # (re)start tracking
        t = s.grid.nearest((px, py, pz))
        t, b0, b1, b2, h = locate(c, t, px, py, pz)
        st.tri, st.b = t, (b0, b1, b2)
        st.above = h >= r  # starting inside the body is not a contact
        release(st)
        return None, False
    mx, my, mz = st.move
    if not st.in_contact and mx * mx + my * my + mz * mz > s.mean_edge * s.mean_edge:
        # a jump out of contact (a mouse dragged across the view, a device's reset): the walk starts from the
        # grid's nearest triangle, not from where the probe was; walking from the body's far side it found a
        # projection there, read the probe as deep inside and began a contact on the wrong side
        st.tri = s.grid.nearest((px, py, pz))
    t, b0, b1, b2, h = locate(c, st.tri, px, py, pz)
    if not st.in_contact:
        st.tri, st.b = t, (b0, b1, b2)
        if h >= r or not st.above:
            st.above = st.above or h >= r
            release(st)
            return None, False
        st.in_contact, st.sliding = True, False  # crossed the surface: the proxy is born at the projection
        st.anchor, st.slip = None, 0.0
        st.body_force = (0.0, 0.0, 0.0)
        return (px, py, pz), True
    st.target = (t, b0, b1, b2)  # the contact ends where the penetration at the proxy reaches zero
    return (px, py, pz), True


def follow(c, st) -> None:
    """The proxy's move this tick: towards this tick's projection, at most ``proxy_speed`` ‖Δp‖.

    Deeper than half the radius of curvature the projection nears the surface's focal point and runs off
    sideways; the proxy then moves by dead reckoning instead, by (I − δ_f S)⁻¹ P Δp (P = I − N Nᵀ at the
    proxy, S the shape operator on the tangent plane, δ_f = R / 2), the factor the law's tangential term
    uses (:func:`pmask.runtime.contact.linalg3.tracking_depth`): a straight press keeps its contact point.
    From 0.4 R to R/2 the move blends from the one into the other (:func:`~pmask.runtime.contact.linalg3.reckoning`:
    weight w of the dead reckoning, 1 − w of following's move, towards the projection by at most proxy_speed
    ‖Δp‖ along the chord), so that the proxy does not hop where the depth hovers about R/2.
    So it does past δ_lin (status DEEP) when this tick's projection lies more than a mean edge from the proxy:
    deep in the body the projection can land on another part of the surface (10 mm below the kidney's side,
    beside the support, it jumped 5 mm onto the hilum's wall), and the proxy sliding there tilted the normal
    until the penetration, and with it ‖F‖, fell by 8-10 % while the push went deeper."""
    if st.target is None:
        return
    srf = c.surface
    here = there = None  # the proxy's point and the projection's, each evaluated once a tick
    if st.depth > 0.0:
        t, (b0, b1, b2) = st.tri, st.b
        Nx, Ny, Nz = normal(srf, t, b0, b1, b2)
        St = tangent_part(Nx, Ny, Nz, shape_at(srf, t, b0, b1, b2))
        d, w = reckoning(St, st.depth)
        if st.status == Status.DEEP:
            here, there = point(srf, t, b0, b1, b2), point(srf, *st.target)
            ex, ey, ez = there[0] - here[0], there[1] - here[1], there[2] - here[2]
            if ex * ex + ey * ey + ez * ez > srf.mean_edge * srf.mean_edge:  # jumped
                w = 1.0
        if w > 0.0:
            mx, my, mz = st.move
            mn = Nx * mx + Ny * my + Nz * mz
            vx, vy, vz = mul3(speed_up(St, d), mx - mn * Nx, my - mn * Ny, mz - mn * Nz)
            x, y, z = here if here is not None else point(srf, t, b0, b1, b2)
            if w < 1.0:  # and the rest towards the projection, as far as following would go (the chord)
                tx, ty, tz = there if there is not None else point(srf, *st.target)
                gx, gy, gz = tx - x, ty - y, tz - z
                g = math.sqrt(gx * gx + gy * gy + gz * gz)
                lim = c.proxy_speed * norm(st.move)
                f = (1.0 - w) * (lim / g if g > lim else 1.0)
                vx, vy, vz = w * vx + f * gx, w * vy + f * gy, w * vz + f * gz
            move_proxy(c, st, x + vx, y + vy, z + vz, math.sqrt(vx * vx + vy * vy + vz * vz))
            return
    move_proxy(c, st, *(there if there is not None else point(srf, *st.target)), c.proxy_speed * norm(st.move))


def norm(v):
    return math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
