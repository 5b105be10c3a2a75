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

Two routes, the same numbers (tested):

*Selected inversion* (the native route, :mod:`precompute.native`, C over the
system's CHOLMOD).  :math:`K_{FF}` over every unconstrained dof is factorised
once, :math:`P K_{FF} P^T = L L^T` with a METIS nested-dissection order, and
the surface block of its inverse is

.. math::  G = E^T K_{FF}^{-1} E = W^T W, \qquad W = L^{-1} P E,

with E the unit columns of the free surface dofs.  A column of W is non-zero
only on its elimination-tree path, so with postordered supernodes each
supernode's rows of W meet one contiguous range of surface dofs and
:math:`W^T W` is one symmetric rank-k update (dsyrk) per supernode: ~13 Gflop
at the default kidney against ~82 Gflop to invert the dense S (n³).
Reactions come from the same inverse: the support's nodal forces are
:math:`K_{UF} u_F`, and :math:`K_{UF}` touches only the free dofs next to the
support, so those dofs join the selected set.

*Dense Schur complement* (the pip-only route: cvxopt's CHOLMOD, SciPy's
LAPACK).  The stiffness is permuted to ``[interior (AMD), free surface, fixed
surface]``, factorised in that order, and the trailing block gives
:math:`L_{SS} L_{SS}^T = S`, so :math:`G = L_{SS}^{-T} L_{SS}^{-1}` (trtri +
lauum).  A positive diagonal added to the fixed block makes the matrix
definite without changing the others, and the fixed rows of the factor give
the reactions :math:`S_{US} G = L_{US} L_{SS}^{-1}` (code: ``L_FF``, ``L_UF``).
"""
from __future__ import annotations

import json
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
    """Trailing Cholesky block of the stiffness with the surface ordered last (pip-only route).

    L_TT : (nt, nt) column-major, lower triangle valid; its first ``n_free`` rows and columns
        are L_FF (L_FF L_FFᵀ = S, the free-surface Schur complement), the rows below them L_UF
        (S_UF = L_UF L_FFᵀ).
    """

    L_TT: np.ndarray
    n_free: int
    stats: dict = field(default_factory=dict)


@dataclass
class SparseFactor:
    """CHOLMOD's supernodal factor of K_FF (every unconstrained dof), for selected inversion.

    L : the factor's arrays (:data:`precompute.native.FACTOR_ARRAYS`).
    want : dofs of K_FF whose block of the inverse is needed: the contact dofs (the first
        ``n_contact``, in the order of ``free``), then the other dofs that ``coupling`` touches.
    coupling : K_UF restricted to the ``want`` columns (3 n_fixed x len(want)): reactions = K_UF u.
    """

    L: dict
    want: np.ndarray
    n_contact: int
    coupling: sp.csr_matrix
    stats: dict = field(default_factory=dict)


def factor_arrays(factor) -> dict:
    """Everything a factor holds, as named arrays (for a checkpoint); :func:`factor_from_arrays` inverts it."""
    if isinstance(factor, SparseFactor):
        c = factor.coupling
        return {"kind": "sparse", **{f"L_{k}": v for k, v in factor.L.items()}, "want": factor.want,
                "n_contact": factor.n_contact, "coupling_data": c.data, "coupling_indices": c.indices,
                "coupling_indptr": c.indptr, "coupling_shape": np.array(c.shape), "stats": json.dumps(factor.stats)}
    # saved transposed: numpy writes a column-major array's transpose without a copy
    return {"kind": "dense", "L_TT_T": factor.L_TT.T, "n_free": factor.n_free, "stats": json.dumps(factor.stats)}


def factor_from_arrays(ck) -> "SparseFactor | SurfaceFactor":
    from precompute import native

    stats = json.loads(str(ck["stats"]))
    if str(ck["kind"]) == "sparse":
        coupling = sp.csr_matrix((ck["coupling_data"], ck["coupling_indices"], ck["coupling_indptr"]),
                                 shape=tuple(ck["coupling_shape"]))
        return SparseFactor(L={k: ck[f"L_{k}"] for k in native.FACTOR_ARRAYS}, want=ck["want"],
                            n_contact=int(ck["n_contact"]), coupling=coupling, stats=stats)
    return SurfaceFactor(L_TT=np.asfortranarray(ck["L_TT_T"].T), n_free=int(ck["n_free"]), stats=stats)


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
    """'native' (selected inversion: our C over Debian's CHOLMOD and threaded OpenBLAS, built by
    ``make venv``) when installed, else 'cvxopt' (the dense Schur complement: CHOLMOD bundled with a
    single-threaded OpenBLAS, SciPy's LAPACK; pip-only, slower).  ``PMASK_CHOLMOD=cvxopt`` forces the
    latter, as on a machine without SuiteSparse."""
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
                   fixed: np.ndarray, *, backend: str | None = None) -> "SparseFactor | SurfaceFactor":
    """Factorise the stiffness for the Green's functions of the ``free`` (contact) vertices.

    ``interior`` (everything to eliminate, including free surface vertices a
    probe cannot touch), ``free`` and ``fixed`` are disjoint vertex index
    arrays that together cover every vertex of the mesh (``fixed`` non-empty).
    The native backend returns a :class:`SparseFactor` (K_FF in METIS order, for
    selected inversion); the pip-only one a :class:`SurfaceFactor` (the dense
    trailing block with the surface ordered last, the interior by AMD).
    """
    n_vertices = K.shape[0] // 3
    if len(fixed) == 0:
        raise CondensationError("the fixed region is empty: nothing holds the body, its stiffness is singular")
    if len(interior) + len(free) + len(fixed) != n_vertices or len(
            np.unique(np.concatenate([interior, free, fixed]))) != n_vertices:
        raise CondensationError("interior, free and fixed vertex sets must partition the mesh")
    backend = cholmod_backend(backend)
    if backend == "native":
        return _sparse_factor(sp.csr_matrix(K), interior, free, fixed)
    t0 = time.perf_counter()
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
    (indptr, indices, data), t_factor, t_extract = _factor_cvxopt(A)
    t0 = time.perf_counter()
    L_TT = _trailing_block(indptr, indices, data, n, nt)
    t_extract += time.perf_counter() - t0
    nnz = int(indptr[-1])
    log.info("factor (cvxopt): %d dofs, nnz(L) = %.3g, order %.2fs, factor %.2fs, extract %.2fs",
             n, nnz, t_order, t_factor, t_extract)
    return SurfaceFactor(L_TT=L_TT, n_free=nf,
                         stats={"dofs": n, "nnz_L": nnz, "backend": backend, "route": "dense Schur complement",
                                "order": "AMD", "order_s": t_order, "factor_s": t_factor, "extract_s": t_extract})


def _sparse_factor(K: sp.csr_matrix, interior, free, fixed) -> SparseFactor:
    from precompute import native

    t0 = time.perf_counter()
    keep = np.sort(np.concatenate([dofs(interior), dofs(free)]))  # the unconstrained dofs F
    pos = np.full(K.shape[0], -1, np.int64)
    pos[keep] = np.arange(len(keep))
    KF = K[keep]
    A = sp.tril(KF[:, keep], format="csc")
    A.sort_indices()
    K_UF = K[dofs(fixed)][:, keep]
    contact = pos[dofs(free)]
    touched = np.flatnonzero(np.asarray(abs(K_UF).sum(axis=0)).ravel())
    want = np.concatenate([contact, np.setdiff1d(touched, contact)])
    coupling = sp.csr_matrix(K_UF[:, want])
    t_setup = time.perf_counter() - t0
    t0 = time.perf_counter()
    try:
        L, st = native.factor(A)
    except ArithmeticError as exc:
        raise _singular(exc.args[0]) from None
    t_factor = time.perf_counter() - t0
    log.info("factor (native, %s): %d dofs, nnz(L) = %.3g, %.2f Gflop, %.2fs", st["order"], len(keep),
             st["stored_L"], st["factor_flops"] / 1e9, t_factor)
    return SparseFactor(L=L, want=want, n_contact=len(contact), coupling=coupling,
                        stats={"dofs": len(keep), "nnz_L": st["stored_L"], "backend": "native",
                               "route": "selected inversion", "order": st["order"], "setup_s": t_setup,
                               "analyse_s": st["analyse_s"], "numeric_s": st["numeric_s"], "factor_s": t_factor,
                               "factor_flops": st["factor_flops"], "supernodes": st["supernodes"],
                               "selected_dofs": len(want)})


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


def greens_functions(factor: "SparseFactor | SurfaceFactor", areas: np.ndarray, *, overwrite: bool = True):
    r"""Green's functions Ξ (traction → displacement) and support reactions.

    Parameters
    ----------
    factor : from :func:`surface_factor`.
    areas : vertex areas a of the free (contact) vertices, in the order of ``free``.
    overwrite : a dense factor's block may be worked on in place (it is consumed:
        ``factor.L_TT`` becomes None).

    Returns
    -------
    Xi : (3 n, 3 n) with block (i, j) the displacement of vertex i per unit traction at
        vertex j: :math:`\Xi = G\,\mathrm{diag}(a)` (with the native route a view of a slightly
        larger array that also holds the rows the reactions need).
    reactions : (3 n_fixed, 3 n), the nodal forces the support exerts per unit traction
        at vertex j (equilibrium: they sum to :math:`-a_j p_j`).
    """
    a = np.repeat(np.asarray(areas, float), 3)
    if isinstance(factor, SparseFactor):
        from precompute import native

        nc = factor.n_contact
        if len(a) != nc:
            raise CondensationError(f"{len(a) // 3} vertex areas for {nc // 3} free vertices")
        scale = np.concatenate([a, np.ones(len(factor.want) - nc)])
        D, st = native.selected_inverse(factor.L, factor.want, scale)
        t0 = time.perf_counter()
        rows = np.unique(factor.coupling.indices)  # the dofs next to the support
        reactions = factor.coupling[:, rows] @ D[rows, :nc]  # K_UF u for every load
        st["reactions_s"] = time.perf_counter() - t0
        log.info("greens (selected inversion): %.1f Gflop, solve %.2fs, syrk %.2fs, permute %.2fs, "
                 "reactions %.2fs, prefault wait %.2fs", st["flops"] / 1e9, st["solve_s"], st["syrk_s"], st["permute_s"],
                 st["reactions_s"], st["prefault_wait_s"])
        factor.stats["greens_s"] = st
        return D[:nc, :nc], np.ascontiguousarray(reactions)
    nf = factor.n_free
    if len(a) != nf:
        raise CondensationError(f"{len(a) // 3} vertex areas for {nf // 3} free vertices")
    L_TT = factor.L_TT if overwrite else np.array(factor.L_TT, order="F")
    if overwrite:
        factor.L_TT = None
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
