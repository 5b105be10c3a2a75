r"""Linear elasticity assembled element by element in numpy: P1 and P2 tetrahedra, a material per element.

The bilinear form is

.. math::  a(u, v) = \int_\Omega 2\mu\, \varepsilon(u) : \varepsilon(v) + \lambda\, (\nabla\cdot u)(\nabla\cdot v)\, dx,

with the Lamé parameters λ, μ of each tetrahedron (materials by region: :mod:`pmask.precompute.materials`).
For a basis function u = N_a e_i and a test function v = N_b e_j the integrand is
μ (δ_ij ∇N_a·∇N_b + ∂_j N_a ∂_i N_b) + λ ∂_i N_a ∂_j N_b.

- **P1**: the gradients are constant on a tetrahedron; one point integrates exactly.
- **P2**: N_a = λ_a(2λ_a − 1) at the corners and 4 λ_p λ_q at the edges' midpoints (λ the barycentric
  coordinates), so the gradients are linear: the 2μ ε:ε term is integrated exactly by the 4-point degree-2 rule,
  and the volumetric term by the centroid rule, which integrates the product of the elements' mean divergences
  exactly: the P2–P0 element with its pressure condensed, which does not lock as ν → 1/2.

This is scikit-fem's assembly (``ElementVector(ElementTetP1/P2)``, ``linear_elasticity``, intorder 2 and 1)
written as one batched product per block of tetrahedra instead of a Python call per pair of basis functions:
the P2 kidney's matrix in a third of the time, and any material per element.  ``tests/test_assembly.py`` holds
the two to round-off for uniform and per-element materials.  Dofs are node-major (``3 * node + component``);
P2's nodes are the vertices, then the edges in the order of the ``edges`` array given (scikit-fem's).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

#: the degree-2 rule on the tetrahedron: barycentric points (a, b, b, b) and permutations, equal weights
_A, _B = 0.5854101966249685, 0.1381966011250105
QUAD2 = np.array([[_A, _B, _B, _B], [_B, _A, _B, _B], [_B, _B, _A, _B], [_B, _B, _B, _A]])
#: P2's local edges as pairs of local vertices (each tetrahedron's six edge nodes in this order)
LOCAL_EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])
#: tetrahedra per batch: bounds the (batch, 30, 30) element matrices to ~60 MB
BATCH = 8192


def lame(E, nu):
    """(λ, μ) for Young's modulus E and Poisson's ratio ν (scalars or arrays)."""
    E, nu = np.asarray(E, float), np.asarray(nu, float)
    return E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)), E / (2.0 * (1.0 + nu))


def barycentric_gradients(points: np.ndarray, tets: np.ndarray):
    """∇λ_a of each tetrahedron (M, 4, 3) and its volume (M,) (positive for positively oriented ones)."""
    p = points[tets]
    J = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)  # columns: edges from v0
    vol = np.linalg.det(J) / 6.0
    Jinv = np.linalg.inv(J)  # rows: ∇λ_1..3
    g = np.empty((len(tets), 4, 3))
    g[:, 1:] = Jinv
    g[:, 0] = -Jinv.sum(axis=1)
    return g, vol


def _element_matrices(G_dev, w_dev, G_vol, w_vol, lam, mu):
    """(M, 3n, 3n) element matrices from the shape-function gradients (M, q, n, 3) at the deviatoric and
    volumetric points with their weights (M, q)."""
    A = np.einsum("tq,tqak,tqbk->tab", w_dev, G_dev, G_dev)              # ∫ ∇N_a·∇N_b
    C = np.einsum("tq,tqai,tqbj->taibj", w_dev, G_dev, G_dev)           # ∫ ∂_i N_a ∂_j N_b
    D = np.einsum("tq,tqai,tqbj->taibj", w_vol, G_vol, G_vol)           # at the volumetric points
    n = A.shape[1]
    Ke = mu[:, None, None, None, None] * (np.einsum("tab,ij->taibj", A, np.eye(3)) + C.transpose(0, 1, 4, 3, 2))
    Ke += lam[:, None, None, None, None] * D
    return Ke.reshape(len(A), 3 * n, 3 * n)


def _p2_gradients(g, bary):
    """∇N of P2's 10 shape functions (M, q, 10, 3) at barycentric points bary (q, 4), from ∇λ (M, 4, 3)."""
    q = len(bary)
    out = np.empty((len(g), q, 10, 3))
    for k in range(q):
        lam = bary[k]
        out[:, k, :4] = (4.0 * lam - 1.0)[None, :, None] * g
        p, r = LOCAL_EDGES[:, 0], LOCAL_EDGES[:, 1]
        out[:, k, 4:] = 4.0 * (lam[r][None, :, None] * g[:, p] + lam[p][None, :, None] * g[:, r])
    return out


def element_nodes(tets: np.ndarray, n_vertices: int, edges: np.ndarray | None):
    """Each tetrahedron's nodes (M, 4) for P1, (M, 10) for P2: its vertices, then its edges' nodes in
    :data:`LOCAL_EDGES` order, numbered n_vertices + the edge's row in ``edges`` (sorted vertex pairs)."""
    if edges is None:
        return np.asarray(tets, np.int64)
    key = edges[:, 0] * n_vertices + edges[:, 1]
    order = np.argsort(key)
    a, b = tets[:, LOCAL_EDGES[:, 0]], tets[:, LOCAL_EDGES[:, 1]]
    k = np.minimum(a, b) * n_vertices + np.maximum(a, b)
    pos = order[np.searchsorted(key, k, sorter=order)]
    if not np.array_equal(key[pos], k):
        raise ValueError("an edge of a tetrahedron is missing from the edge list")
    return np.concatenate([np.asarray(tets, np.int64), n_vertices + pos], axis=1)


def stiffness(points, tets, E, nu, *, order: int = 1, edges: np.ndarray | None = None, n_nodes: int | None = None):
    """K (3 n_nodes x 3 n_nodes, CSR) of isotropic linear elasticity on P1 (``order=1``) or P2 (``order=2``,
    with ``edges``) tetrahedra; E and ν scalars or one per tetrahedron.  The element matrices are summed as
    3x3 node blocks (a tenth of the entries a scalar assembly sorts), then expanded."""
    points = np.asarray(points, float)
    tets = np.asarray(tets, np.int64)
    M = len(tets)
    lam, mu = lame(np.broadcast_to(E, (M,)), np.broadcast_to(nu, (M,)))
    nodes = element_nodes(tets, len(points), edges if order == 2 else None)
    n_nodes = int(n_nodes if n_nodes is not None else nodes.max() + 1)
    k = nodes.shape[1]
    keys, blocks = [], []
    for t0 in range(0, M, BATCH):
        sl = slice(t0, min(t0 + BATCH, M))
        g, vol = barycentric_gradients(points, tets[sl])
        vol = np.abs(vol)
        if order == 1:
            G = g[:, None]                       # (m, 1, 4, 3)
            w = vol[:, None]
            Ke = _element_matrices(G, w, G, w, lam[sl], mu[sl])
        else:
            Gq = _p2_gradients(g, QUAD2)
            Gc = _p2_gradients(g, np.full((1, 4), 0.25))
            Ke = _element_matrices(Gq, np.repeat(vol[:, None] / 4.0, 4, axis=1), Gc, vol[:, None], lam[sl], mu[sl])
        nd = nodes[sl]
        keys.append((np.repeat(nd, k, axis=1) * n_nodes + np.tile(nd, (1, k))).ravel())
        blocks.append(Ke.reshape(-1, k, 3, k, 3).transpose(0, 1, 3, 2, 4).reshape(-1, 3, 3))
    key, block = np.concatenate(keys), np.concatenate(blocks)
    order_ = np.argsort(key, kind="stable")
    key = key[order_]
    starts = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]]))
    data = np.add.reduceat(block[order_], starts, axis=0)
    rows, cols = np.divmod(key[starts], n_nodes)
    indptr = np.searchsorted(rows, np.arange(n_nodes + 1))
    return sp.bsr_matrix((data, cols, indptr), shape=(3 * n_nodes, 3 * n_nodes)).tocsr()
