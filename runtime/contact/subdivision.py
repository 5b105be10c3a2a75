r"""The contact surface: the mesh's Loop subdivision surface, on which the force is the gradient of its energy.

The law's frictionless force is k δ along the contact normal N plus the term that makes it the gradient of the
stored energy ½ k δ² (:mod:`pmask.runtime.contact.law`).  That holds exactly only where N is the normal of the
surface the proxy moves on.  On the finite-element mesh's flat triangles it is not: N is interpolated from the
vertices (so that the force turns smoothly over edges) and differs from a facet's own normal by up to the angle
between neighbouring facets, a few degrees on the default kidney; closed loops then gave back up to 1.92 % of
their stored energy (the hands issue asks ≤ 1 %), and with the facets' own normals the force jumped at every
edge.  A surface whose facets meet at vanishing angles removes the conflict: this module subdivides the contact
mesh with Loop's scheme (Loop 1987; each level splits every triangle in four and moves the vertices by Loop's
masks, whose limit is a C¹ surface, C² away from irregular vertices) and puts the vertices on the limit surface.
Each level halves the angle between neighbouring facets, so the interpolated normals and the facets' normals
agree to within a small angle and the law is the gradient of its energy to within it.  The control points are
solved for so that the limit surface passes through the mesh's vertices (:func:`_interpolating_control`): the
mesh's vertices keep their indices (the first n_s) and, away from creases (below), their positions, so a probe
pressed at a vertex presses where the finite-element mesh is.

Sharp creases (edges whose facets meet at more than ``crease_deg``, the same test as
:func:`pmask.runtime.geometry.contact_normals`) and open boundaries are kept as creases, with Loop's crease rules:
their curve is subdivided as a cubic B-spline and the surfaces on either side meet along it as before. Then the
contact surface rounds them at the scale over which the contact normals blend across them (``normal_radius``,
:func:`pmask.runtime.geometry.crease_blend`): :func:`round_creases` moves each vertex of the band along its blended
normal so that the blended normals become the surface's own, and the contact normals are the rounded surface's
(:class:`pmask.runtime.contact.ContactSurface`). A blended normal up to 50° off the facets the proxy moved on made
the force differ from the gradient of the law's energy there: out and back over the kidney's hilum lip 2 and 4 mm
deep the law dissipated 10.5 % and 30 % of the press's work, rounded 5.2 % and 7.1 %, and 0.02 % and 0.06 % once the
force's velocity and proxy terms were the energy's too (tests/test_haptics.py, :mod:`pmask.runtime.contact.output`).
Rounding by Loop's rules (no crease kept) rounds at the mesh's edge length instead, far tighter than the blend: a
probe pressed 2-4 mm deep over it is in the deep regime, and it dragged 3x and 9.5x the press's work (by hand, with
an earlier law); rounding the mesh itself at the blend's scale and subdividing it smoothly was too coarse (27.8 % at
4 mm, and the force per tick crossing the lip 3.1x the smooth slide's, 2x asked).
The mesh's vertices in the band move with it (up to 2 mm on the default kidney): the display draws the mesh where the
contact surface has them (:attr:`pmask.runtime.contact.ContactSurface.mesh_points`).

The rendered stiffness K_i and the taper λ are carried onto the subdivided surface linearly from the mesh
(:meth:`Subdivided.interpolate`: eq. 15 in the mesh triangle's barycentrics), so K at the mesh's vertices is K_i
itself and pairs of contacts pressed at vertices meet the full finite-element solve as on the mesh.  Measured on
the hands issue's grid of closed loops (two levels, tests/test_passivity_grid.py): the worst loop gives back
0.39 % of its energy and the controller takes 0.75 % (1.92 % and 2.19 % on the mesh).  Two other carryings were
tried and dropped (the haptics guide's "The contact surface"): by Loop's masks (smoother, 0.024 % on the grid,
but K at the vertices became Loop's smoothing of K_i, up to 9 % off by the support's ramp, and pairs moved 3.5 %
off the full solve) and through interpolating control values (the field overshot beside the support's ramp).
∇k of the linear field changes across a quarter of a mesh edge at every mesh edge; before the deep hold
(:mod:`pmask.runtime.contact.output`) that cost a deep oblique push beside the support 17.7 % of its force, with
the hold none of the benchmarks' deep pushes loses force.
ζ and the deformation stay on the mesh's vertices: each subdivided triangle knows the mesh triangle it lies
in (``parent``) and the barycentric
coordinates in it of its three corners (``corners``), so a point (t, b) of the subdivided surface is the point
:math:`\beta = \sum_k b_k\, \mathrm{corners}_{t,k}` of triangle ``parent[t]`` (:func:`mesh_point`).

Plain numpy (the runtime's rule): no sparse matrices.
"""
from __future__ import annotations

import math

import numpy as np

from pmask.runtime.geometry import crease_edges, scatter_add, triangle_normals, unique_rows, vertex_normals

#: the largest angle between a triangle's normal and its vertices' normals (away from creases) that the
#: automatic choice of levels accepts (:func:`facet_angle`; each level halves it).  On the default kidney (the
#: hands issue's grid of closed loops, controller off) the mesh's 9.1° gave back up to 1.92 % of a loop's stored
#: energy, two levels (2.95°, the automatic choice there) 0.39 % (tests/test_passivity_grid.py's loops; one level,
#: 5.1°, 0.44 % by hand, with K carried by Loop's masks, an earlier projection and the zero-order hold's
#: correction k N Nᵀ alone, under which the mesh gave 1.78 % and two levels 0.22 %)
MAX_FACET_ANGLE = math.radians(3.5)
#: at most this many levels, and at most this many subdivided triangles (the contact surface's arrays grow 4x a
#: level)
MAX_LEVELS = 3
MAX_TRIANGLES = 400_000


class Subdivided:
    """A subdivided contact mesh: ``points`` (n_f, 3), ``triangles`` (m_f, 3), ``parent`` (m_f,) the mesh
    triangle each lies in, ``corners`` (m_f, 3, 3) the barycentrics in it of each corner (row k: corner k),
    ``levels`` the levels applied (0: the mesh itself)."""

    def __init__(self, points, triangles, parent, corners, levels):
        self.points, self.triangles, self.parent, self.corners, self.levels = points, triangles, parent, corners, levels

    def vertex_weights(self, mesh_triangles) -> tuple[np.ndarray, np.ndarray]:
        """(n_f, 3) mesh vertices and (n_f, 3) weights: each subdivided vertex's place on the mesh, so that a
        per-vertex quantity q of the mesh is :math:`\\sum_k w_k q_{v_k}` there (linear interpolation)."""
        T = np.asarray(self.triangles)
        n = len(self.points)
        t = np.empty(n, np.int64)
        k = np.empty(n, np.int64)
        t[T.ravel()] = np.repeat(np.arange(len(T)), 3)  # any triangle holding the vertex: the map is continuous
        k[T.ravel()] = np.tile(np.arange(3), len(T))
        return np.asarray(mesh_triangles)[self.parent[t]], self.corners[t, k]

    def interpolate(self, mesh_triangles, values) -> np.ndarray:
        """A per-vertex quantity of the mesh (n_s, ...) at the subdivided vertices, linearly interpolated."""
        v, w = self.vertex_weights(mesh_triangles)
        values = np.asarray(values, float)
        return np.einsum("fk,fk...->f...", w, values[v])


def facet_angle(points, triangles, crease_deg: float = 30.0) -> float:
    """The largest angle between a triangle's normal and its vertices' area-weighted normals, over the triangles
    with no vertex on a crease or boundary (there the normals are blended and the creases kept sharp)."""
    P, T = np.asarray(points, float), np.asarray(triangles, np.int64)
    if not len(T):
        return 0.0
    fn, vn = triangle_normals(P, T), vertex_normals(P, T)
    try:
        _, _, E_open = _edges(T)
    except ValueError:  # not a manifold: no subdivision, whatever the angle
        return 0.0
    crease = _creases(P, T, E_open, crease_deg)
    on = np.zeros(len(P), bool)
    on[crease.ravel()] = True
    keep = ~on[T].any(axis=1)
    if not keep.any():
        return 0.0
    cos = np.einsum("tkc,tc->tk", vn[T[keep]], fn[keep])
    return float(np.arccos(np.clip(cos.min(), -1.0, 1.0)))


def choose_levels(points, triangles, crease_deg: float = 30.0) -> int:
    """The fewest levels that bring :func:`facet_angle` within :data:`MAX_FACET_ANGLE` (each level halves it),
    at most :data:`MAX_LEVELS` and :data:`MAX_TRIANGLES` triangles."""
    angle = facet_angle(points, triangles, crease_deg)
    levels = 0
    while (angle > MAX_FACET_ANGLE and levels < MAX_LEVELS
           and 4 ** (levels + 1) * len(triangles) <= MAX_TRIANGLES):
        angle *= 0.5
        levels += 1
    return levels


def subdivide(points, triangles, levels: int, crease_deg: float = 30.0) -> Subdivided:
    """Loop subdivision ``levels`` times, creases and boundaries kept, vertices on the limit surface.

    Raises ValueError on an edge shared by more than two triangles (not a manifold: the caller keeps the mesh)."""
    P = np.asarray(points, float)
    T = np.asarray(triangles, np.int64)
    m = len(T)
    parent = np.arange(m)
    corners = np.broadcast_to(np.eye(3), (m, 3, 3)).copy()
    if levels <= 0 or not m:
        return Subdivided(P.copy(), T.copy(), parent, corners, 0)
    E, _, E_open = _edges(T)
    crease = _creases(P, T, E_open, crease_deg)
    fixed = _corners(P, crease, crease_deg)
    X = _interpolating_control(P, E, crease, fixed)
    for _ in range(levels):
        X, T, crease, parent, corners = _split(X, T, crease, parent, corners, fixed)
        fixed = np.r_[fixed, np.zeros(len(X) - len(fixed), bool)]
    X = _limit(X, T, crease, fixed)
    return Subdivided(np.ascontiguousarray(X), T, parent, corners, int(levels))


def _corners(P, crease, crease_deg):
    """Vertices kept where they are: three or more crease edges, or two that turn by more than crease_deg (a
    corner of a crease curve, such as a box's or a flat patch's boundary)."""
    n = len(P)
    nc = _valence(n, crease)
    fixed = nc >= 3
    two = np.flatnonzero(nc == 2)
    if len(two):
        other = np.full((n, 2), -1)
        fill = np.zeros(n, np.int64)
        for a, b in ((crease[:, 0], crease[:, 1]), (crease[:, 1], crease[:, 0])):
            for v, w in zip(a.tolist(), b.tolist()):
                if nc[v] == 2:
                    other[v, fill[v]] = w
                    fill[v] += 1
        d1 = P[other[two, 0]] - P[two]
        d2 = P[two] - P[other[two, 1]]
        cos = np.einsum("ij,ij->i", d1, d2) / (np.linalg.norm(d1, axis=1) * np.linalg.norm(d2, axis=1))
        fixed[two[cos < math.cos(math.radians(crease_deg))]] = True
    return fixed


def _interpolating_control(P0, E, crease, fixed, rtol: float = 1e-13, iterations: int = 500):
    """Control points Q whose limit surface passes through the mesh's vertices: M Q = P0, M Loop's limit mask (a
    vertex's limit position depends on its own level's ring only, and is the same at every level).  Loop's
    surface of the mesh itself lies inside a convex mesh by about twice its sagitta (0.08 mm at the median vertex
    of the default kidney; on a 4 mm-edged 20 mm ball 0.2 mm, which a display that meets the tool shows as a gap);
    through the vertices it meets the finite-element mesh where its ζ and K live, and bulges between them as a
    smooth surface through them does.  Richardson iteration: M's eigenvalues lie in (0, 1] (smooth vertices of
    valence 6: [1/4, 1]), so the residual falls by at least 3/4 a sweep (measured: ~40 sweeps to 1e-13)."""
    scale = float(np.abs(P0).max()) or 1.0
    is_crease = _crease_flags(E, crease)
    Q = P0.copy()
    for _ in range(iterations):
        r = P0 - _smooth_or_crease(Q, E, is_crease, fixed, _limit_smooth, _limit_crease)
        Q += r
        if np.abs(r).max() <= rtol * scale:
            return Q
    raise ValueError("the interpolating control points did not converge")


def mesh_point(parent, corners, t, b0, b1, b2):
    """(mesh triangle, β0, β1, β2): the point (t, b) of the subdivided surface on the mesh (plain Python, per
    tick; ``corners`` as flat rows of 9).  The native core's ``pm__mesh_point`` is the same operation for
    operation."""
    c = corners[t]
    return (parent[t], b0 * c[0] + b1 * c[3] + b2 * c[6], b0 * c[1] + b1 * c[4] + b2 * c[7],
            b0 * c[2] + b1 * c[5] + b2 * c[8])


# ----------------------------------------------------------------------------------------------- the scheme
def _edges(T):
    """(unique edges (e, 2) sorted, edge of each triangle side (m, 3): side k joins corners k and k+1, the open
    edges (b, 2)).  Raises ValueError on an edge of more than two triangles."""
    sides = np.sort(np.stack([T, np.roll(T, -1, axis=1)], axis=2).reshape(-1, 2), axis=1)
    E, inv, count = unique_rows(sides, return_inverse=True, return_counts=True)
    if np.any(count > 2):
        raise ValueError("an edge is shared by more than two triangles")
    return E, inv.reshape(-1, 3), E[count == 1]


def _creases(P, T, E_open, crease_deg):
    """The edges kept as creases: the open ones and those whose facets meet at more than crease_deg (the test
    the contact normals blend by, :func:`pmask.runtime.geometry.crease_edges`)."""
    sharp = np.vstack([E_open, crease_edges(P, T, crease_deg)])
    return unique_rows(sharp) if len(sharp) else sharp


def _valence(n, E):
    return np.bincount(np.asarray(E, np.int64).ravel(), minlength=n)


def _neighbour_sum(n, E, P):
    return scatter_add(np.concatenate([E[:, 0], E[:, 1]]), np.concatenate([P[E[:, 1]], P[E[:, 0]]]), n)


def _beta(val):
    v = np.maximum(val, 1).astype(float)
    return (0.625 - (0.375 + 0.25 * np.cos(2 * np.pi / v)) ** 2) / v


def _crease_flags(E, crease):
    """Whether each unique edge is a crease."""
    if not len(crease):
        return np.zeros(len(E), bool)
    w = int(max(E.max(), crease.max())) + 1
    return np.isin(E[:, 0] * w + E[:, 1], crease[:, 0] * w + crease[:, 1])


def _split(P, T, crease, parent, corners, fixed):
    """One level: every triangle into four (corners' barycentrics halved along its edges), new vertices on the
    edges by Loop's odd mask (3/8, 3/8, 1/8, 1/8; a crease's midpoint), old ones by the even mask."""
    n = len(P)
    E, side, _ = _edges(T)
    is_crease = _crease_flags(E, crease)
    # the vertex opposite each side, gathered per edge (two for an interior edge)
    opp = np.roll(T, -2, axis=1).ravel()
    opp_sum = scatter_add(side, P[opp], len(E))
    odd = np.where(is_crease[:, None], 0.5 * (P[E[:, 0]] + P[E[:, 1]]),
                   0.375 * (P[E[:, 0]] + P[E[:, 1]]) + 0.125 * opp_sum)
    even = _smooth_or_crease(P, E, is_crease, fixed, _even_smooth, _even_crease)
    new_P = np.vstack([even, odd])
    a, b, c = T.T
    x, y, z = n + side[:, 0], n + side[:, 1], n + side[:, 2]  # midpoints of ab, bc, ca
    new_T = np.concatenate([np.c_[a, x, z], np.c_[x, b, y], np.c_[z, y, c], np.c_[x, y, z]])
    ce = E[is_crease]
    mid = n + np.flatnonzero(is_crease)
    new_crease = np.sort(np.concatenate([np.c_[ce[:, 0], mid], np.c_[mid, ce[:, 1]]]), axis=1)
    Ma, Mb, Mc = corners[:, 0], corners[:, 1], corners[:, 2]
    Mx, My, Mz = 0.5 * (Ma + Mb), 0.5 * (Mb + Mc), 0.5 * (Mc + Ma)
    new_corners = np.concatenate([np.stack(q, axis=1) for q in ((Ma, Mx, Mz), (Mx, Mb, My), (Mz, My, Mc),
                                                                 (Mx, My, Mz))])
    return new_P, new_T, new_crease, np.tile(parent, 4), new_corners


def _even_smooth(P, val, nsum):
    beta = _beta(val)
    return (1.0 - val * beta)[:, None] * P + beta[:, None] * nsum


def _even_crease(P, csum):
    return 0.75 * P + 0.125 * csum


def _limit_smooth(P, val, nsum):
    beta = _beta(val)
    chi = 1.0 / (3.0 / (8.0 * np.maximum(beta, 1e-300)) + val)
    return (1.0 - val * chi)[:, None] * P + chi[:, None] * nsum


def _limit_crease(P, csum):
    return (2.0 / 3.0) * P + (1.0 / 6.0) * csum


def _smooth_or_crease(P, E, is_crease, fixed, smooth, crease_rule):
    """Each vertex by the smooth mask, by the crease mask on a crease curve (two crease edges), or kept (a corner:
    :func:`_corners`)."""
    n = len(P)
    val = _valence(n, E)
    ce = E[is_crease]
    nc = _valence(n, ce)
    out = smooth(P, val, _neighbour_sum(n, E, P))
    on = nc == 2
    out[on] = crease_rule(P, _neighbour_sum(n, ce, P))[on]
    out[fixed] = P[fixed]
    return out


def _limit(P, T, crease, fixed):
    E, _, _ = _edges(T)
    return _smooth_or_crease(P, E, _crease_flags(E, crease), fixed, _limit_smooth, _limit_crease)


#: :func:`round_creases` stops when the normal equations' residual has fallen by this much
ROUND_RTOL = 1e-10
#: and its Tikhonov weight on the heights, relative to the mean diagonal of the normal equations: it only pins
#: what the normals leave free (a flat face's uniform shift, when no vertex with h = 0 holds it)
ROUND_REGULARISATION = 1e-8


def round_creases(points, triangles, normals, free, iterations: int = 5000) -> np.ndarray:
    r"""Heights h (n_f,) along the unit ``normals`` N that make them the surface's own normals: x = points + h N
    with, over every edge (i, j) of every triangle t that has a ``free`` vertex,

    .. math::  \min_h \sum_t \sum_{(i,j) \in t} \big(n_t \cdot (x_j - x_i)\big)^2, \qquad h = 0 \text{ off free}

    (n_t the normalised mean of t's corners' N; a surface whose edges are all perpendicular to the normals has
    them as its normals).  The heights move vertices along N only, so the triangles keep their shape in the
    tangent plane; at a crease, where N is blended over ``normal_radius``, the surface is rounded at that scale.
    Preconditioned (Jacobi) conjugate gradients on the normal equations, plain numpy."""
    P, T, N = np.asarray(points, float), np.asarray(triangles, np.int64), np.asarray(normals, float)
    free = np.asarray(free, bool)
    m = int(free.sum())
    h = np.zeros(len(P))
    if not m:
        return h
    Tu = T[free[T].any(axis=1)]
    nt = N[Tu].sum(axis=1)
    nt /= np.linalg.norm(nt, axis=1, keepdims=True)
    I, J = Tu.T.ravel(), Tu[:, [1, 2, 0]].T.ravel()  # each triangle's three edges
    n3 = np.tile(nt, (3, 1))
    b = np.einsum("ij,ij->i", n3, P[J] - P[I])  # the residuals at h = 0
    ci, cj = np.einsum("ij,ij->i", n3, N[I]), np.einsum("ij,ij->i", n3, N[J])
    col = np.full(len(P), m)  # free vertex -> its unknown; m: a fixed vertex (h = 0)
    col[free] = np.arange(m)
    fi, fj = col[I], col[J]
    oi, oj = fi < m, fj < m
    diag = np.bincount(fj[oj], cj[oj] ** 2, minlength=m) + np.bincount(fi[oi], ci[oi] ** 2, minlength=m)
    eps = ROUND_REGULARISATION * float(diag.mean())
    diag = diag + eps

    def normal_matrix(x):  # (AᵀA + ε) x, A the residuals' derivative in the free heights
        xp = np.r_[x, 0.0]  # (a fixed vertex's column m reads 0)
        r = cj * xp[fj] - ci * xp[fi]
        return np.bincount(fj[oj], (cj * r)[oj], minlength=m) - np.bincount(fi[oi], (ci * r)[oi], minlength=m) + eps * x

    rhs = np.bincount(fi[oi], (ci * b)[oi], minlength=m) - np.bincount(fj[oj], (cj * b)[oj], minlength=m)  # −Aᵀb
    x, r = np.zeros(m), rhs.copy()
    z = r / diag
    p, rz = z.copy(), float(r @ z)
    stop = ROUND_RTOL * float(np.linalg.norm(rhs))
    for _ in range(iterations):
        if float(np.linalg.norm(r)) <= stop:
            break
        Ap = normal_matrix(p)
        a = rz / float(p @ Ap)
        x += a * p
        r -= a * Ap
        z = r / diag
        rz, rz0 = float(r @ z), rz
        p = z + (rz / rz0) * p
    else:
        raise ValueError("rounding the creases did not converge")
    h[free] = x
    return h
