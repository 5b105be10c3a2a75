"""Surface geometry on triangle meshes: vertex areas, normals, adjacency.

Plain numpy; shared by the runtime and (imported from here) by the precompute,
so that each concept has one home.
"""
from __future__ import annotations

import numpy as np


def triangle_areas(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area of each triangle."""
    p = points[triangles]
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)


def vertex_areas(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    r"""Vertex areas :math:`a_i = \int_\Gamma \phi_i\, d\Gamma` (paper eq. 10).

    For piecewise-linear hat functions :math:`\phi_i` each triangle gives a
    third of its area to each of its three vertices, so ``a.sum()`` is the
    surface area.  This is the lumped boundary mass that turns a traction
    :math:`p_j` into the nodal force :math:`a_j p_j`.
    """
    a = np.zeros(len(points))
    np.add.at(a, triangles.ravel(), np.repeat(triangle_areas(points, triangles) / 3.0, 3))
    return a


def triangle_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit outward normals (counter-clockwise vertex order seen from outside)."""
    p = points[triangles]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def vertex_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals."""
    p = points[triangles]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # 2 x area x unit normal
    vn = np.zeros_like(points, dtype=float)
    for k in range(3):
        np.add.at(vn, triangles[:, k], n)
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    return vn / np.where(norm > 0, norm, 1.0)


def edges(triangles: np.ndarray) -> np.ndarray:
    """Unique undirected edges (E, 2), smaller index first."""
    e = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def mean_edge_length(points: np.ndarray, triangles: np.ndarray) -> float:
    """Mean length of the unique edges of the triangulation."""
    e = edges(triangles)
    return float(np.linalg.norm(points[e[:, 0]] - points[e[:, 1]], axis=1).mean())


def triangle_neighbours(triangles: np.ndarray) -> np.ndarray:
    """(T, 3) index of the triangle across the edge opposite each vertex, -1 on an open edge.

    Edge k of triangle t joins vertices (k+1)%3 and (k+2)%3, so a walk that
    finds barycentric coordinate k negative steps to ``neighbours[t, k]``.
    """
    t = len(triangles)
    opp = np.stack([triangles[:, [1, 2]], triangles[:, [2, 0]], triangles[:, [0, 1]]], axis=1)  # (T,3,2)
    key = np.sort(opp, axis=2).reshape(-1, 2)
    order = np.lexsort((key[:, 1], key[:, 0]))
    k = key[order]
    same = np.all(k[1:] == k[:-1], axis=1)
    nb = np.full(3 * t, -1, dtype=np.int64)
    a, b = order[:-1][same], order[1:][same]
    nb[a] = b // 3
    nb[b] = a // 3
    return nb.reshape(t, 3)


def one_rings(n_vertices: int, triangles: np.ndarray) -> list[np.ndarray]:
    """Neighbouring vertex indices of every vertex."""
    e = edges(triangles)
    both = np.concatenate([e, e[:, ::-1]])
    both = both[np.argsort(both[:, 0], kind="stable")]
    split = np.searchsorted(both[:, 0], np.arange(n_vertices + 1))
    return [both[split[i]:split[i + 1], 1] for i in range(n_vertices)]
