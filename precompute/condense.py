r"""Condensation of the solid onto its free surface: Schur complement and Green's functions.

With the support vertices Λu held (u_U = 0) the free dofs obey
:math:`K_{FF} u_F = f_F`.  Eliminating the interior leaves the free surface
dofs S with the condensed stiffness (Schur complement)

.. math::  S = K_{SS} - K_{SI} K_{II}^{-1} K_{IS},

whose inverse :math:`G = S^{-1}` is the *flexibility*: displacement of free
surface vertex i per unit nodal force at free surface vertex j (symmetric).
The paper's RSGFs (eq. 4-5) map *tractions* to displacements; a traction
:math:`p_j` acts as the nodal force :math:`a_j p_j` (lumped boundary mass,
eq. 10), so

.. math::  \Xi = G\,\mathrm{diag}(a), \qquad a_i \Xi_{ij} = a_j \Xi_{ji}^T .

How S is formed (the dense-algebra route): the sparse stiffness is permuted
to ``[interior (fill-reducing order), free surface, fixed surface]`` and
factorised by CHOLMOD's supernodal Cholesky with exactly that order.  The
trailing block of the factor is dense; its free-surface part :math:`L_{FF}` satisfies
:math:`L_{FF} L_{FF}^T = S`, so :math:`G = L_{FF}^{-T} L_{FF}^{-1}` by LAPACK
(trtri + lauum).  A positive diagonal added to the fixed block makes the
matrix definite without changing the free blocks, and the fixed rows of the
factor give the support reactions for free: with :math:`W = L_{FF}^{-1}`,
the nodal forces the support exerts for unit nodal loads are
:math:`S_{UF} G = L_{UF} W`.

Two routes, same numbers (tested): the native one (:mod:`precompute.native`,
C over the system's CHOLMOD) orders the interior by METIS, uses the trailing
block where CHOLMOD stores it and runs the LAPACK steps on it in place; the
pip-only one (cvxopt's CHOLMOD, AMD) copies the block out and uses SciPy.
"""
from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg.blas as blas
import scipy.linalg.lapack as lapack
import scipy.sparse as sp

from precompute.elasticity import dofs

log = logging.getLogger(__name__)


class CondensationError(ValueError):
    """The support does not hold the body (singular stiffness) or the sets are inconsistent."""


@dataclass
class SurfaceFactor:
    """Trailing Cholesky block of the stiffness with the surface ordered last.

    L_TT : (nt, nt) column-major (any leading dimension), lower triangle valid; its first
        ``n_free`` rows and columns are L_FF (L_FF L_FFᵀ = S, the free-surface Schur
        complement), the rows below them L_UF (S_UF = L_UF L_FFᵀ).  With the native backend
        it is a view into CHOLMOD's own storage.
    """

    L_TT: np.ndarray
    n_free: int
    stats: dict = field(default_factory=dict)

    @property
    def L_FF(self) -> np.ndarray:
        return np.tril(self.L_TT[:self.n_free, :self.n_free])

    @property
    def L_UF(self) -> np.ndarray:
        return np.array(self.L_TT[self.n_free:, :self.n_free])


def node_graph(n_vertices: int, tets: np.ndarray) -> sp.csr_matrix:
    """Vertex adjacency (with diagonal) of a tet mesh."""
    rows = np.repeat(tets, 4, axis=1).ravel()
    cols = np.tile(tets, (1, 4)).ravel()
    g = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n_vertices, n_vertices))
    g.sum_duplicates()
    return g


def amd_order(graph: sp.spmatrix) -> np.ndarray:
    """Approximate-minimum-degree fill-reducing order of a symmetric pattern (SuiteSparse AMD)."""
    import cvxopt
    import cvxopt.amd

    if graph.shape[0] == 0:
        return np.zeros(0, np.int64)
    g = graph.tocoo()
    A = cvxopt.spmatrix(1.0, cvxopt.matrix(g.row.astype(np.int64)), cvxopt.matrix(g.col.astype(np.int64)), g.shape)
    return np.array(cvxopt.amd.order(A), dtype=np.int64).ravel()


def cholmod_backend(prefer: str | None = None) -> str:
    """'native' (our C over Debian's CHOLMOD and threaded OpenBLAS, built by ``make venv``) when
    installed, else 'cvxopt' (CHOLMOD bundled with a single-threaded OpenBLAS; pip-only, slower).
    ``PMASK_CHOLMOD=cvxopt`` forces the latter (and SciPy's LAPACK for the inverse: the whole
    pip-only route, as on a machine without SuiteSparse)."""
    from precompute import native

    choice = prefer or os.environ.get("PMASK_CHOLMOD")
    if choice == "cvxopt":
        return "cvxopt"
    if choice not in (None, "", "native"):
        raise ValueError(f"unknown CHOLMOD backend {choice!r}: use 'native' or 'cvxopt'")
    if native.available():
        return "native"
    if choice == "native":
        raise RuntimeError(f"the native CHOLMOD library is not built ({native.LIBRARY}); run make venv "
                           "as root so that libsuitesparse-dev can be installed")
    return "cvxopt"


def surface_factor(K: sp.spmatrix, tets: np.ndarray, interior: np.ndarray, free: np.ndarray,
                   fixed: np.ndarray, *, backend: str | None = None) -> SurfaceFactor:
    """Factorise K with the ``free`` (contact) and ``fixed`` vertices last; return the trailing block.

    ``interior`` (everything to eliminate, including free surface vertices a
    probe cannot touch), ``free`` and ``fixed`` are disjoint vertex index
    arrays that together cover every vertex of the mesh (``fixed`` non-empty).
    The interior is ordered by AMD, or with the native backend by METIS nested
    dissection (measured: 7 % fewer flops in all at the default kidney, 19 % at
    3,882 free vertices).
    """
    n_vertices = K.shape[0] // 3
    if len(fixed) == 0:
        raise CondensationError("the fixed region is empty: nothing holds the body, its stiffness is singular")
    if len(interior) + len(free) + len(fixed) != n_vertices or len(
            np.unique(np.concatenate([interior, free, fixed]))) != n_vertices:
        raise CondensationError("interior, free and fixed vertex sets must partition the mesh")
    backend = cholmod_backend(backend)
    t0 = time.perf_counter()
    if backend == "native":
        order = interior  # reordered inside, by METIS on the interior's graph
    else:
        graph = node_graph(n_vertices, tets)
        order = interior[amd_order(graph[interior][:, interior])]
    perm = np.concatenate([dofs(order), dofs(free), dofs(fixed)])
    n, nf, nu = len(perm), 3 * len(free), 3 * len(fixed)
    nt = nf + nu
    Kp = sp.csr_matrix(K)[perm][:, perm]
    shift = np.zeros(n)
    shift[n - nu:] = Kp.diagonal()[n - nu:]  # makes the fixed block definite; leaves L_FF, L_UF unchanged
    A = sp.tril(Kp + sp.diags(shift), format="csc")
    A.sort_indices()
    t_order = time.perf_counter() - t0
    t0 = time.perf_counter()
    if backend == "native":
        from precompute import native

        try:
            L_TT, st = native.factor(A, nt)
        except ArithmeticError as exc:
            raise _singular(exc.args[0]) from None
        t_factor, t_extract, nnz = time.perf_counter() - t0, st["locate_s"], st["stored_L"]
        log.info("interior order: %s", st["interior_order"])
    else:
        (indptr, indices, data), t_factor, t_extract = _factor_cvxopt(A)
        t0 = time.perf_counter()
        L_TT = _trailing_block(indptr, indices, data, n, nt)
        t_extract += time.perf_counter() - t0
        nnz = int(indptr[-1])
    log.info("factor (%s): %d dofs, nnz(L) = %.3g, order %.2fs, factor %.2fs, extract %.2fs",
             backend, n, nnz, t_order, t_factor, t_extract)
    return SurfaceFactor(L_TT=L_TT, n_free=nf,
                         stats={"dofs": n, "nnz_L": nnz, "backend": backend, "order_s": t_order,
                                "interior_order": st["interior_order"] if backend == "native" else "AMD",
                                "numeric_s": st["numeric_s"] if backend == "native" else None,
                                "factor_s": t_factor, "extract_s": t_extract})


def _singular(column) -> CondensationError:
    return CondensationError(
        "the stiffness matrix is singular with this fixed region: the support must hold the body against "
        "rigid motion (at least three non-collinear fixed vertices) and every part of the mesh must be "
        f"connected to it (CHOLMOD stopped at column {column})")


def _factor_cvxopt(A: sp.csc_matrix):
    """The same through cvxopt's bundled CHOLMOD (user order only, no postordering)."""
    import cvxopt
    import cvxopt.cholmod as cholmod

    n = A.shape[0]
    low = A.tocoo()
    Ac = cvxopt.spmatrix(low.data, cvxopt.matrix(low.row.astype(np.int64)),
                         cvxopt.matrix(low.col.astype(np.int64)), (n, n))
    saved = dict(cholmod.options)
    cholmod.options.update({"supernodal": 2, "nmethods": 1, "postorder": False})
    try:
        t0 = time.perf_counter()
        F = cholmod.symbolic(Ac, p=cvxopt.matrix(np.arange(n, dtype=np.int64)))
        try:
            cholmod.numeric(Ac, F)
        except ArithmeticError as exc:
            raise _singular(exc.args[0] if exc.args else "?") from exc
        t_factor = time.perf_counter() - t0
        t0 = time.perf_counter()
        L = cholmod.getfactor(F)
    finally:
        cholmod.options.clear()
        cholmod.options.update(saved)
    colptr, rowind, values = (np.array(x, copy=False).ravel() for x in L.CCS)
    return (colptr, rowind, values), t_factor, time.perf_counter() - t0


def _trailing_block(indptr, indices, data, n: int, nt: int) -> np.ndarray:
    """Dense lower-triangular trailing nt x nt block of a CSC factor (Fortran order, for LAPACK)."""
    L_TT = np.zeros((nt, nt), order="F")
    off = n - nt
    for j in range(nt):
        a, b = indptr[off + j], indptr[off + j + 1]
        rows = indices[a:b] - off
        if len(rows) == nt - j and rows[0] == j and np.all(rows[1:] - rows[:-1] == 1):
            L_TT[j:, j] = data[a:b]  # the dense block: a contiguous column copy
        else:
            L_TT[rows, j] = data[a:b]
    return L_TT


def greens_functions(factor: SurfaceFactor, areas: np.ndarray, *, overwrite: bool = True,
                     lapack_route: str | None = None):
    r"""Green's functions Ξ (traction → displacement) and support reactions.

    Parameters
    ----------
    factor : from :func:`surface_factor`.
    areas : vertex areas a of the free (contact) vertices, in the order of ``free``.
    overwrite : work in the factor's storage (it is consumed: ``factor.L_TT`` becomes None).
    lapack_route : 'native' (our C: in place, one pass for the mirror and the scaling; the
        default when built, unless ``PMASK_CHOLMOD=cvxopt`` asks for the pip-only route) or
        'scipy' (SciPy's LAPACK on copies); same numbers.

    Returns
    -------
    Xi : (3 n, 3 n) with block (i, j) the displacement of vertex i per unit traction at
        vertex j: :math:`\Xi = G\,\mathrm{diag}(a)`.  With the native route Ξ and the
        reactions are (non-contiguous) views of the factor's storage: no 3n x 3n copy.
    reactions : (3 n_fixed, 3 n), the nodal forces the support exerts per unit traction
        at vertex j (equilibrium: they sum to :math:`-a_j p_j`).
    """
    from precompute import native

    nf = factor.n_free
    a = np.repeat(np.asarray(areas, float), 3)
    if len(a) != nf:
        raise CondensationError(f"{len(a) // 3} vertex areas for {nf // 3} free vertices")
    L_TT = factor.L_TT if overwrite else np.array(factor.L_TT, order="F")
    if overwrite:
        factor.L_TT = None
    pip_only = os.environ.get("PMASK_CHOLMOD") == "cvxopt"  # behave as without SuiteSparse
    route = lapack_route or ("native" if native.available() and not pip_only else "scipy")
    if route == "native":
        # W = L_FF⁻¹ (trtri), reactions L_UF W (trmm), G = Wᵀ W (lauum), Ξ = G diag(a) in one pass;
        # Ξ and the reactions are views of the factor's storage (row stride > row length)
        Xi, reactions, times, info = native.greens(L_TT, nf, a)
        if info != 0:
            raise CondensationError(f"the condensed surface stiffness is singular (LAPACK info={info})")
        log.info("greens (native): trtri %.2fs, reactions %.2fs, lauum %.2fs, mirror %.2fs",
                 times["trtri_s"], times["reactions_s"], times["lauum_s"], times["mirror_s"])
        factor.stats["greens_s"] = times
        return Xi, reactions
    W, info = lapack.dtrtri(np.asfortranarray(L_TT[:nf, :nf]), lower=1, overwrite_c=1)
    if info != 0:
        raise CondensationError(f"the condensed surface stiffness is singular (LAPACK trtri info={info})")
    # trmm reads only the lower triangle of W: reactions L_UF W
    reactions = blas.dtrmm(1.0, W, np.asfortranarray(L_TT[nf:, :nf]), side=1, lower=1) * a[None, :]
    del L_TT
    G, info = lapack.dlauum(W, lower=1, overwrite_c=1)  # lower triangle of Wᵀ W = S⁻¹
    if info != 0:
        raise CondensationError(f"LAPACK lauum failed (info={info})")
    _mirror_lower(G)  # reciprocity is tested against separate solves, not this mirror
    G *= a[None, :]
    return np.ascontiguousarray(G), np.ascontiguousarray(reactions)


def _mirror_lower(G: np.ndarray, block: int = 512) -> None:
    """Copy the strict lower triangle of G onto its upper triangle, in place, block by block."""
    n = G.shape[0]
    for i0 in range(0, n, block):
        i1 = min(i0 + block, n)
        G[i0:i1, i0:i1] = np.tril(G[i0:i1, i0:i1]) + np.tril(G[i0:i1, i0:i1], -1).T
        G[i0:i1, i1:] = G[i1:, i0:i1].T
