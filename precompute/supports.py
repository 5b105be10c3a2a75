"""Supports defined by area: the selector's boundary made a chain of surface edges.

A support chosen by vertex membership fixes the surface triangles whose three corners the selector
matches, so its area depends on where the mesh's vertices happen to fall: on one ellipsoid the fixed
cap was 0.75-0.96 of the intended area across meshes, and that alone kept P2 stiffness sequences from
converging.  :func:`conform` removes the dependence.  Every surface edge that the selector's boundary
crosses has one end moved along the edge onto the boundary (the crossing is found by bisection on the
selector itself, so every selector form works, ``|`` unions included).  Afterwards every surface
triangle lies wholly inside the support or wholly outside it, and the fixed triangles cover exactly the
selected part of the piecewise-linear surface: the fixed area is the surface integral ∫_Λu dΓ of the
geometry up to the surface's own O(h²) discretisation, the same on every mesh.  The Dirichlet
condition is then imposed on whole facets (all their nodes, P2 edge nodes included), and the vertex
areas a_i = ∫ φ_i dΓ (paper eq. 5) of the free vertices come from the free facets alone.

The nearer end of each crossing edge is moved (at most half the edge); the farther end only where the
nearer one would deform a tetrahedron around it too much (below :data:`KEEP_VOLUME` of its volume), and
neither where both would: such edges are counted in the report (``unresolved``) and keep vertex
membership.  A vertex is moved along a surface edge, so it stays on the discrete surface, and the volume
enclosed changes only by the curvature between the edge and the surface (second order in h).

``group:`` selectors are left alone: a physical group is already a set of whole facets of the geometry.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from pmask.precompute import selectors
from pmask.precompute.meshing import signed_volumes
from pmask.runtime.geometry import edges

#: a move is refused when a tetrahedron around the vertex would keep less than this share of its volume
KEEP_VOLUME = 0.2
#: bisection steps along an edge: 2^-48 of its length, below round-off of the coordinates' last digits
BISECTION_STEPS = 48
#: name of the group (bool over the volume points) of vertices moved onto the support's boundary
RIM = "support_rim"


def conformable(selector: str) -> bool:
    """Whether ``selector`` describes geometry (half-spaces, boxes, balls) that the mesh can be fitted to."""
    parts = [p.strip() for p in selector.split("|")]
    return not any(p.startswith("group:") or p == "all" for p in parts)


def crossings(selector: str, points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Parameter t ∈ (0, 1) where the segment from ``points[a]`` (matched by ``selector``) to ``points[b]``
    (not matched) leaves the selected set, by bisection on the selector (``points`` in the selector's units)."""
    lo, hi = np.zeros(len(a)), np.ones(len(a))
    pa, d = points[a], points[b] - points[a]
    for _ in range(BISECTION_STEPS):
        mid = 0.5 * (lo + hi)
        inside = selectors.select(selector, pa + mid[:, None] * d)
        lo, hi = np.where(inside, mid, lo), np.where(inside, hi, mid)
    return 0.5 * (lo + hi)


def fixed_facets(fixed: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Surface triangles whose three corners are fixed: the facets the support holds."""
    return np.all(fixed[triangles], axis=1)


def conform(points: np.ndarray, tets: np.ndarray, selector: str, scale: float = 1.0):
    """Move surface vertices so the boundary of ``selector`` runs along surface edges.

    ``points`` in metres, ``selector`` in input units (``points / scale``).  Returns ``(points, rim,
    report)``: the moved copy of the points, a bool over the points marking those on the boundary
    (fixed, whatever the selector says of their position after rounding), and a dict with the number
    of moved vertices, the largest move relative to its edge, the unresolved edges and the change of the
    enclosed volume (the moves cut the chords of a curved rim: second order in h).
    """
    from pmask.precompute.surface import boundary_surface

    vertices, triangles = boundary_surface(points, tets)
    sp_ = points[vertices] / scale
    inside = selectors.select(selector, sp_)
    e = edges(triangles)
    crossing = inside[e[:, 0]] != inside[e[:, 1]]
    e = e[crossing]
    a = np.where(inside[e[:, 0]], e[:, 0], e[:, 1])  # the end inside the support
    b = np.where(inside[e[:, 0]], e[:, 1], e[:, 0])
    t = crossings(selector, sp_, a, b)
    new = np.array(points, float, copy=True)
    rim = np.zeros(len(points), bool)
    report = {"crossing_edges": int(len(e)), "moved": 0, "largest_move_per_edge": 0.0, "unresolved": 0,
              "volume_change": 0.0}
    if len(e) == 0:
        return new, rim, report
    n_pts = len(points)
    incidence = sp.csr_matrix((np.ones(tets.size), (tets.ravel(), np.repeat(np.arange(len(tets)), 4))),
                              shape=(n_pts, len(tets)))
    vol0 = signed_volumes(points, tets)
    on_rim = np.zeros(len(vertices), bool)
    for k in np.argsort(np.minimum(t, 1 - t), kind="stable"):
        if on_rim[a[k]] or on_rim[b[k]]:  # an end already lies on the boundary: the edge no longer crosses it
            continue
        target = (sp_[a[k]] + t[k] * (sp_[b[k]] - sp_[a[k]])) * scale
        for v, frac in sorted(((a[k], t[k]), (b[k], 1 - t[k])), key=lambda c: c[1]):
            gv = vertices[v]
            around = incidence.indices[incidence.indptr[gv]:incidence.indptr[gv + 1]]
            old = new[gv].copy()
            new[gv] = target
            if np.all(signed_volumes(new, tets[around]) >= KEEP_VOLUME * vol0[around]):
                on_rim[v] = True
                report["moved"] += 1
                report["largest_move_per_edge"] = max(report["largest_move_per_edge"], float(frac))
                break
            new[gv] = old
        else:
            report["unresolved"] += 1
    rim[vertices[on_rim]] = True
    # the moves cut the chords of curved rims: the enclosed volume changes by their sag (stored with the remesh's)
    report["volume_change"] = float(signed_volumes(new, tets).sum() / vol0.sum() - 1.0)
    return new, rim, report
