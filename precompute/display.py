r"""The display surface: the organ as scanned, carried by the simulation surface (the scans issue's item 6).

Haptics needs a few thousand surface vertices; a user wants to see the organ at the scan's resolution.  The
user's own surface (the ``--surface`` file as given, or a label image's smoothed surface) is kept in the
artifact, up to :data:`MAX_TRIANGLES`, each of its vertices x_d embedded in the simulation surface by its
closest point c_d on triangle t_d with barycentric weights b_d and the lift ℓ_d = x_d − c_d:

.. math::  x_d' = x_d + \sum_{k} b_{d,k}\, u_{T[t_d, k]} - w_d\, \ell_d

u the simulation surface's displacement (eq. 16) and w_d ∈ [0, 1] a weight that is 1 at a contact and falls
to 0 over the mask radius (:func:`pmask.runtime.display.deform`): where the tool presses, the display surface
lies on the deformed simulation surface and so meets the tool; elsewhere it keeps its own detail.  An
embedding is *folded* where a display triangle's image on the simulation surface faces the other way (a scan
detail finer than the simulation mesh folds over itself when projected); the count is recorded and warned
about.
"""
from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)

#: the largest display surface kept (triangles); a larger one is left out with a warning
MAX_TRIANGLES = 2_000_000


def embed(points: np.ndarray, triangles: np.ndarray, sim_points: np.ndarray, sim_triangles: np.ndarray,
          candidates: int = 16) -> dict:
    """The embedding of a display surface (points, triangles) in the simulation surface: for each display
    vertex its simulation triangle, barycentric weights of its closest point there, and the lift vector; the
    number of folded display triangles and the largest lift."""
    from scipy.spatial import cKDTree
    from trimesh.triangles import closest_point, points_to_barycentric

    points = np.asarray(points, float)
    sim_points = np.asarray(sim_points, float)
    sim_triangles = np.asarray(sim_triangles, np.int64)
    k = min(candidates, len(sim_triangles))
    _, idx = cKDTree(sim_points[sim_triangles].mean(axis=1)).query(points, k=k)
    idx = np.asarray(idx).reshape(len(points), k)
    tri = np.empty(len(points), np.int64)
    foot = np.empty((len(points), 3))
    for s0 in range(0, len(points), 20_000):  # bounded memory: 20,000 x k point-triangle pairs at a time
        s1 = min(s0 + 20_000, len(points))
        q = np.repeat(points[s0:s1], k, axis=0)
        c = closest_point(sim_points[sim_triangles[idx[s0:s1].ravel()]], q).reshape(s1 - s0, k, 3)
        best = np.argmin(np.linalg.norm(c - points[s0:s1, None], axis=2), axis=1)
        rows = np.arange(s1 - s0)
        tri[s0:s1] = idx[s0:s1][rows, best]
        foot[s0:s1] = c[rows, best]
    bary = points_to_barycentric(sim_points[sim_triangles[tri]], foot)
    bary = np.clip(bary, 0.0, 1.0)
    bary /= bary.sum(axis=1, keepdims=True)
    foot = np.einsum("dk,dkc->dc", bary, sim_points[sim_triangles[tri]])
    lift = points - foot
    # folded: the image of a display triangle on the simulation surface faces the other way
    t = np.asarray(triangles, np.int64)
    n_disp = np.cross(points[t[:, 1]] - points[t[:, 0]], points[t[:, 2]] - points[t[:, 0]])
    n_img = np.cross(foot[t[:, 1]] - foot[t[:, 0]], foot[t[:, 2]] - foot[t[:, 0]])
    big = np.linalg.norm(n_img, axis=1) > 1e-12 * np.linalg.norm(n_disp, axis=1).max()
    folded = int(np.sum(big & (np.einsum("ij,ij->i", n_disp, n_img) < 0)))
    return {"vertices": sim_triangles[tri], "bary": bary, "lift": lift, "folded": folded,
            "max_lift": float(np.linalg.norm(lift, axis=1).max()) if len(lift) else 0.0}


def display_surface(points: np.ndarray, triangles: np.ndarray, sim_points: np.ndarray, sim_triangles: np.ndarray,
                    name) -> dict | None:
    """The display datasets for the artifact (points, triangles and the embedding), or None with a warning
    when the surface is larger than :data:`MAX_TRIANGLES`.  Duplicate vertices are merged and degenerate
    triangles dropped (an STL repeats every vertex)."""
    if len(triangles) > MAX_TRIANGLES:
        log.warning("%s: the display surface has %d triangles, more than the %d kept; the artifact shows the "
                    "simulation surface instead", name, len(triangles), MAX_TRIANGLES)
        return None
    pts, inverse = np.unique(np.asarray(points, float), axis=0, return_inverse=True)
    tris = inverse.ravel()[np.asarray(triangles, np.int64)]
    tris = tris[(tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 0] != tris[:, 2])]
    used = np.unique(tris)
    remap = np.full(len(pts), -1)
    remap[used] = np.arange(len(used))
    pts, tris = pts[used], remap[tris]
    e = embed(pts, tris, sim_points, sim_triangles)
    if e["folded"]:
        log.warning("%s: %d of %d display triangles fold when carried by the simulation surface (detail finer than "
                    "its edges): they may show creased under a press; a smaller --edge-length carries them",
                    name, e["folded"], len(tris))
    return {"points": pts, "triangles": tris, **e}
