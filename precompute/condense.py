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

How G is formed (selected inversion): :math:`K_{FF}` over every unconstrained
dof is factorised once, :math:`P K_{FF} P^T = L L^T` in a fill-reducing order,
and the surface block of its inverse is

.. math::  G = E^T K_{FF}^{-1} E = W^T W, \qquad W = L^{-1} P E,

with E the unit columns of the free surface dofs.  A column of W is non-zero
only on its elimination-tree path, so with postordered supernodes each
supernode's rows of W meet one contiguous range of surface dofs and
:math:`W^T W` is one symmetric rank-k update (dsyrk) per supernode: ~14 Gflop
at the default kidney against ~82 Gflop to form the dense Schur complement S
and invert it (n³).  Reactions come from the same inverse: the support's
nodal forces are :math:`K_{UF} u_F`, and :math:`K_{UF}` touches only the free
dofs next to the support, so those dofs join the selected set.

Two backends, the same algorithm and the same numbers (tested): the native one
(:mod:`pmask.precompute.native`: C over the system's CHOLMOD, METIS order, the
inverse in place) and the pip-only one (cvxopt's CHOLMOD in an AMD order of the
vertex graph, :mod:`pmask.precompute.selinv` in numpy and SciPy's BLAS).
"""
from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from pmask.errors import InputError
from pmask.precompute import selinv
from pmask.precompute.elasticity import dofs

log = logging.getLogger(__name__)


class CondensationError(InputError):
    """The support does not hold the body (singular stiffness) or the sets are inconsistent."""


@dataclass
class SparseFactor:
    """The supernodal Cholesky factor of K_FF (every unconstrained dof), for selected inversion.

    L : the factor's arrays (:data:`pmask.precompute.selinv.FACTOR_ARRAYS`, CHOLMOD's layout).
    want : dofs of K_FF whose block of the inverse is needed: the contact dofs (the first
        ``n_contact``, in the order of ``free``), then the other dofs that ``coupling`` touches.
    coupling : K_UF restricted to the ``want`` columns (3 n_fixed x len(want)): reactions = K_UF u.
    """

    L: dict
    want: np.ndarray
    n_contact: int
    coupling: sp.csr_matrix
    stats: dict = field(default_factory=dict)


def factor_arrays(factor: SparseFactor) -> dict:
    """Everything a factor holds, as named arrays (for a checkpoint); :func:`factor_from_arrays` inverts it."""
    c = factor.coupling
    return {**{f"L_{k}": v for k, v in factor.L.items()}, "want": factor.want, "n_contact": factor.n_contact,
            "coupling_data": c.data, "coupling_indices": c.indices, "coupling_indptr": c.indptr,
            "coupling_shape": np.array(c.shape), "stats": json.dumps(factor.stats)}


def factor_from_arrays(ck) -> SparseFactor:
    """The factor saved by :func:`factor_arrays` (``ck``: the loaded npz)."""
    coupling = sp.csr_matrix((ck["coupling_data"], ck["coupling_indices"], ck["coupling_indptr"]),
                             shape=tuple(ck["coupling_shape"]))
    return SparseFactor(L={k: ck[f"L_{k}"] for k in selinv.FACTOR_ARRAYS}, want=ck["want"],
                        n_contact=int(ck["n_contact"]), coupling=coupling, stats=json.loads(str(ck["stats"])))


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


def available_memory() -> int | None:
    """Bytes this process can still allocate without swapping (Linux: MemAvailable), None if unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def cholmod_backend(prefer: str | None = None) -> str:
    """'native' (our C over Debian's CHOLMOD with METIS and threaded OpenBLAS, built by ``make venv``)
    when installed, else 'cvxopt' (CHOLMOD bundled with a single-threaded OpenBLAS, AMD, and the
    selected inversion in numpy; pip-only, slower).  ``PMASK_CHOLMOD=cvxopt`` forces the latter, as
    on a machine without SuiteSparse."""
    from pmask.precompute import native

    choice = prefer or os.environ.get("PMASK_CHOLMOD")
    if choice == "cvxopt":
        return "cvxopt"
    if choice not in (None, "", "native"):
        raise InputError(f"PMASK_CHOLMOD={choice!r} is not a backend: use 'native' or 'cvxopt'")
    if native.available():
        return "native"
    if choice == "native":
        raise InputError("PMASK_CHOLMOD=native, but the native library pmask.precompute._selinv is not built: "
                         "run `make system-deps` as root, then `make venv`")
    return "cvxopt"


def surface_factor(K: sp.spmatrix, tets: np.ndarray, interior: np.ndarray, free: np.ndarray,
                   fixed: np.ndarray, *, backend: str | None = None) -> SparseFactor:
    """Factorise K_FF for the Green's functions of the ``free`` (contact) vertices.

    ``interior`` (everything to eliminate, including free surface vertices a
    probe cannot touch), ``free`` and ``fixed`` are disjoint vertex index
    arrays that together cover every vertex of the mesh (``fixed`` non-empty).
    Native backend: CHOLMOD with METIS; pip-only: cvxopt's CHOLMOD with AMD on
    the vertex graph (METIS's nested dissection halves the selected inversion's
    flops at the default kidney).
    """
    n_vertices = K.shape[0] // 3
    if len(fixed) == 0:
        raise CondensationError("the fixed region is empty: nothing holds the body, its stiffness is singular")
    if len(interior) + len(free) + len(fixed) != n_vertices or len(
            np.unique(np.concatenate([interior, free, fixed]))) != n_vertices:
        raise CondensationError("interior, free and fixed vertex sets must partition the mesh")
    backend = cholmod_backend(backend)
    K = sp.csr_matrix(K)
    t0 = time.perf_counter()
    verts = np.sort(np.concatenate([interior, free]))
    keep = dofs(verts)  # the unconstrained dofs F, sorted
    pos = np.full(K.shape[0], -1, np.int64)
    pos[keep] = np.arange(len(keep))
    K_FF = K[keep][:, keep]
    K_UF = K[dofs(fixed)][:, keep]
    contact = pos[dofs(free)]
    touched = np.flatnonzero(np.asarray(abs(K_UF).sum(axis=0)).ravel())
    want = np.concatenate([contact, np.setdiff1d(touched, contact)])
    coupling = sp.csr_matrix(K_UF[:, want])
    t_setup = time.perf_counter() - t0
    t0 = time.perf_counter()
    order = None
    if backend != "native":  # AMD of the vertex graph: the 3 dofs of a vertex stay together
        order = dofs(amd_order(node_graph(n_vertices, tets)[verts][:, verts]))
    L, st = sparse_cholesky(K_FF, backend=backend, order=order)
    if order is not None:
        st["order"] = "AMD (vertex graph)"
    t_factor = time.perf_counter() - t0
    log.info("factor (%s, %s): %d dofs, %d stored in L, %d supernodes, %.2fs", backend, st["order"], len(keep),
             st["stored_L"], st["supernodes"], t_factor)
    return SparseFactor(L=L, want=want, n_contact=len(contact), coupling=coupling,
                        stats={"dofs": len(keep), "nnz_L": st["stored_L"], "backend": backend,
                               "route": "selected inversion", "order": st["order"], "setup_s": t_setup,
                               "analyse_s": st["analyse_s"], "numeric_s": st["numeric_s"], "factor_s": t_factor,
                               "factor_flops": st["factor_flops"], "supernodes": st["supernodes"],
                               "selected_dofs": len(want)})


def sparse_cholesky(A: sp.spmatrix, *, backend: str | None = None, order: np.ndarray | None = None):
    """Supernodal Cholesky P A Pᵀ = L Lᵀ of a symmetric positive definite A, for :func:`inverse_block`.

    Native: CHOLMOD's METIS order; pip-only: ``order`` if given, else AMD of A's pattern, through
    cvxopt's CHOLMOD, postordered and packed by :func:`pmask.precompute.selinv.supernodal`.
    Returns the factor's arrays and stats; raises :class:`CondensationError` if A is singular."""
    backend = cholmod_backend(backend)
    A = sp.csc_matrix(A)
    if backend == "native":
        from pmask.precompute import native

        low = sp.tril(A, format="csc")
        low.sort_indices()
        try:
            return native.factor(low)
        except ArithmeticError as exc:
            raise _singular(exc.args[0]) from None
    t0 = time.perf_counter()
    p = amd_order(A) if order is None else np.asarray(order, np.int64)
    t_order = time.perf_counter() - t0
    low = sp.tril(A[p][:, p], format="csc")
    low.sort_indices()
    (colptr, rowind, values), t_numeric, _ = _factor_cvxopt(low)
    L = selinv.supernodal(colptr, rowind, values, p)
    return L, {"order": "AMD" if order is None else "given", "analyse_s": t_order, "numeric_s": t_numeric,
               "stored_L": len(L["x"]), "factor_flops": None, "supernodes": len(L["super"]) - 1}


def inverse_block(L: dict, want: np.ndarray, scale: np.ndarray, *, backend: str | None = None):
    """X[i, j] = (A⁻¹)[want_i, want_j] · scale_j (C order) from :func:`sparse_cholesky`'s factor, by the
    C library (native) or :mod:`pmask.precompute.selinv`; returns X and timings."""
    from pmask.precompute import native

    if cholmod_backend(backend) == "native":
        return native.selected_inverse(L, want, scale)
    t0 = time.perf_counter()
    X, st = selinv.selected_inverse(L, want, scale)
    st["selinv_s"] = time.perf_counter() - t0
    return X, st


def _singular(column) -> CondensationError:
    return CondensationError(
        "the stiffness matrix is singular with this fixed region: the support must hold the body against "
        "rigid motion (at least three non-collinear fixed vertices) and every part of the mesh must be "
        f"connected to it (CHOLMOD stopped at column {column})")


def _factor_cvxopt(A: sp.csc_matrix):
    """CSC Cholesky factor of the lower-triangular A in its own order by cvxopt's bundled CHOLMOD
    (supernodal numeric, then converted: rows sorted, relaxed supernodes' zeros stored)."""
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


def greens_functions(factor: SparseFactor, areas: np.ndarray, *, backend: str | None = None):
    r"""Green's functions Ξ (traction → displacement) and support reactions.

    Parameters
    ----------
    factor : from :func:`surface_factor`.
    areas : vertex areas a of the free (contact) vertices, in the order of ``free``.
    backend : 'native' (C) or 'cvxopt' (numpy: :mod:`pmask.precompute.selinv`) for the inverse; any
        factor works with either.  Default as :func:`cholmod_backend`.

    Returns
    -------
    Xi : (3 n, 3 n) with block (i, j) the displacement of vertex i per unit traction at
        vertex j: :math:`\Xi = G\,\mathrm{diag}(a)` (a view of a slightly larger array that also
        holds the rows the reactions need).
    reactions : (3 n_fixed, 3 n), the nodal forces the support exerts per unit traction
        at vertex j (equilibrium: they sum to :math:`-a_j p_j`).
    """
    a = np.repeat(np.asarray(areas, float), 3)
    nc = factor.n_contact
    if len(a) != nc:
        raise CondensationError(f"{len(a) // 3} vertex areas for {nc // 3} free vertices")
    scale = np.concatenate([a, np.ones(len(factor.want) - nc)])
    D, st = inverse_block(factor.L, factor.want, scale, backend=backend)
    t0 = time.perf_counter()
    rows = np.unique(factor.coupling.indices)  # the dofs next to the support
    reactions = factor.coupling[:, rows] @ D[rows, :nc]  # K_UF u for every load
    st["reactions_s"] = time.perf_counter() - t0
    log.info("greens (selected inversion): %s", ", ".join(f"{k} {v:.3g}" for k, v in st.items()))
    factor.stats["greens_s"] = st
    return D[:nc, :nc], np.ascontiguousarray(reactions)
