r"""Quadratic (P2) tetrahedra: stiffness, the consistent traction load, and Ξ by blocked solves.

The traction stays in the paper's piecewise-linear space (eq. 6): p(x) = Σ_j φ_j(x) p_j on the
surface.  With P2 displacements its consistent nodal forces live on the corner *and* edge nodes,
f_k = Σ_j (∫ ψ_k φ_j dΓ) p_j.  On a triangle of area A (ψ_k = φ_k(2φ_k − 1) at a corner,
4 φ_a φ_b at the midpoint of edge ab):

    corner k, j = k: A/30      corner k, j ≠ k: −A/60
    edge ab,  j ∈ {a, b}: 2A/15    edge ab, j opposite: A/15

(a P1 traction puts no net force on the corners; the column sums are a_j = ∫ φ_j dΓ).  So Ξ, the
displacement of contact vertex i per unit traction at contact vertex j, is read from solves with
these load columns.  P2 has ~4x the surface nodes of P1: selecting every loaded node for P1's
selected inversion was measured at 1 Tflop and no faster than solves at the default kidney, so P2
is meant for small contact regions (the half-space checks) and uses one sparse Cholesky
factorisation and blocked solves, 3 n_c right-hand sides in all.
"""
from __future__ import annotations

import logging
import os
import time

import numpy as np
import scipy.sparse as sp

log = logging.getLogger(__name__)


def p2_stiffness(points: np.ndarray, tets: np.ndarray, E: float, nu: float):
    """Vector P2 stiffness (dof 3·node + c; nodes: vertices, then edges) and the edges (n_e, 2)."""
    from skfem import Basis, ElementTetP2, ElementVector, MeshTet, asm
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    from pmask.precompute.elasticity import check_material

    check_material(E, nu)
    mesh = MeshTet(np.ascontiguousarray(points.T), np.ascontiguousarray(tets.T))
    basis = Basis(mesh, ElementVector(ElementTetP2()), intorder=2)
    N = mesh.nvertices
    if not (np.array_equal(basis.nodal_dofs, 3 * np.arange(N) + np.arange(3)[:, None])
            and basis.edge_dofs[0, 0] == 3 * N):
        raise RuntimeError("unexpected scikit-fem P2 dof layout")
    K = asm(linear_elasticity(*lame_parameters(E, nu)), basis).tocsr()
    return K, np.sort(mesh.edges.T, axis=1)


def surface_load_matrix(points: np.ndarray, triangles: np.ndarray, edges: np.ndarray) -> sp.csr_matrix:
    """Scalar (n_vertices + n_edges, n_vertices) matrix B_kj = ∫ ψ_k φ_j dΓ over the given triangles
    (volume vertex indices); ``kron(B, I3)`` maps nodal tractions to P2 nodal forces."""
    N = len(points)
    p = points[triangles]
    A = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    key = edges[:, 0] * N + edges[:, 1]
    order = np.argsort(key)

    def edge_node(a, b):
        k = np.minimum(a, b) * N + np.maximum(a, b)
        pos = order[np.searchsorted(key, k, sorter=order)]
        return N + pos

    rows, cols, vals = [], [], []
    for k in range(3):
        for j in range(3):
            rows.append(triangles[:, k])
            cols.append(triangles[:, j])
            vals.append(A / 30 if k == j else -A / 60)
        a, b = triangles[:, k], triangles[:, (k + 1) % 3]
        c = triangles[:, (k + 2) % 3]
        m = edge_node(a, b)
        for j, w in ((a, 2 * A / 15), (b, 2 * A / 15), (c, A / 15)):
            rows.append(m)
            cols.append(j)
            vals.append(w)
    B = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(N + len(edges), N))
    B.sum_duplicates()
    return B


def greens_by_solves(K: sp.spmatrix, B: sp.spmatrix, edges: np.ndarray, contact: np.ndarray,
                     fixed: np.ndarray, *, block: int = 384, backend: str | None = None):
    """Ξ (3 n_c, 3 n_c) and support reactions (3 n_fixed, 3 n_c) for P2 by blocked sparse solves.

    B : scalar load matrix from :func:`surface_load_matrix`; contact, fixed : volume vertex indices.
    Dirichlet nodes: the fixed vertices and the edges joining two of them.  Reactions on the edge
    nodes are split half and half to their end vertices (same total force and moment).
    """
    from pmask.precompute.condense import CondensationError
    from pmask.precompute.elasticity import dofs

    N = B.shape[1]
    n_nodes = B.shape[0]
    is_fixed = np.zeros(N, bool)
    is_fixed[fixed] = True
    fixed_edges = np.flatnonzero(is_fixed[edges[:, 0]] & is_fixed[edges[:, 1]])
    dnodes = np.concatenate([fixed, N + fixed_edges])
    ddofs = dofs(dnodes)
    free = np.setdiff1d(np.arange(3 * n_nodes), ddofs)
    Kc = sp.csr_matrix(K)
    A = Kc[free][:, free].tocsc()
    Bv = sp.kron(B[:, contact], sp.identity(3), format="csr")  # (3 n_nodes, 3 n_c)
    t0 = time.perf_counter()
    backend = _solver_backend(backend)
    if backend == "sksparse":
        from sksparse.cholmod import CholmodNotPositiveDefiniteError, cholesky

        try:
            solve = cholesky(A)
        except CholmodNotPositiveDefiniteError as exc:
            raise CondensationError("the P2 stiffness is singular with this fixed region") from exc
    else:
        import cvxopt
        import cvxopt.cholmod as cholmod

        low = sp.tril(A, format="coo")
        Ac = cvxopt.spmatrix(low.data, cvxopt.matrix(low.row.astype(np.int64)),
                             cvxopt.matrix(low.col.astype(np.int64)), A.shape)
        F = cholmod.symbolic(Ac)
        try:
            cholmod.numeric(Ac, F)
        except ArithmeticError as exc:
            raise CondensationError("the P2 stiffness is singular with this fixed region") from exc

        def solve(b):
            x = cvxopt.matrix(np.asfortranarray(b))
            cholmod.solve(F, x)
            return np.array(x)
    t_factor = time.perf_counter() - t0
    rows = np.searchsorted(free, dofs(contact))
    nc3 = Bv.shape[1]
    Xi = np.empty((nc3, nc3))
    R_nodes = np.empty((len(ddofs), nc3))
    Bf = Bv[free]
    Bd = Bv[ddofs]
    t0 = time.perf_counter()
    for c0 in range(0, nc3, block):
        c1 = min(c0 + block, nc3)
        u = np.zeros((3 * n_nodes, c1 - c0))
        u[free] = solve(Bf[:, c0:c1].toarray())
        Xi[:, c0:c1] = u[free][rows]
        R_nodes[:, c0:c1] = (Kc[ddofs] @ u) - Bd[:, c0:c1].toarray()
    t_solve = time.perf_counter() - t0
    # lump the edge nodes' reactions onto the fixed vertices
    nv = len(fixed)
    R = R_nodes[:3 * nv].copy()
    pos = {v: k for k, v in enumerate(fixed)}
    for q, e in enumerate(fixed_edges):
        r = R_nodes[3 * (nv + q):3 * (nv + q) + 3]
        for v in edges[e]:
            R[3 * pos[v]:3 * pos[v] + 3] += 0.5 * r
    log.info("P2 (%s): %d dofs, factor %.2fs, %d solves %.2fs", backend, len(free), t_factor, nc3, t_solve)
    return Xi, R, {"dofs": int(len(free)), "backend": backend, "factor_s": t_factor, "solve_s": t_solve,
                   "element": "P2"}


def _solver_backend(prefer: str | None) -> str:
    """scikit-sparse (system CHOLMOD, threaded BLAS, fast multi-RHS solves) when importable and not
    ruled out by ``PMASK_CHOLMOD=cvxopt``; else cvxopt's bundled CHOLMOD."""
    import importlib.util

    choice = prefer or os.environ.get("PMASK_CHOLMOD")
    if choice != "cvxopt" and importlib.util.find_spec("sksparse") is not None:
        return "sksparse"
    return "cvxopt"
