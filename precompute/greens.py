r"""Green's functions of the free surface by selected inversion of the stiffness (paper §2.3).

With the support Λu held (u = 0 on the Dirichlet dofs D) the other dofs F obey
:math:`K_{FF} u_F = f_F`.  A traction :math:`p_j` on the free surface, in the paper's
piecewise-linear space (eq. 6), acts through the element's consistent load: nodal forces
:math:`f = B p` (P1 with the lumped boundary mass: :math:`B = E\,\mathrm{diag}(a)`, a traction
:math:`p_j` acts as the nodal force :math:`a_j p_j` at vertex j, eq. 10; P2: corner and edge nodes,
:mod:`pmask.precompute.elements`).  The displacements of the contact vertices per unit traction are

.. math::  \Xi = E^T K_{FF}^{-1} B = (L^{-1} P E)^T (L^{-1} P B) = W_E^T W_B,
           \qquad P K_{FF} P^T = L L^T,

with E the unit columns of the contact vertices' dofs.  K_FF is factorised once (CHOLMOD's
supernodal Cholesky in a fill-reducing order), and only the rows and columns of the inverse that Ξ
needs are formed: a column of W is non-zero on the elimination-tree paths up from its non-zeros, so
with postordered supernodes the work is one dense product per supernode (:mod:`pmask.precompute.selinv`
explains the bookkeeping).  For P1 the load is a scaled unit column, W_B = W_E diag(a), and the block is
one symmetric rank-k update (dsyrk) per supernode: ~14 Gflop at the default kidney against ~82 Gflop to
form the dense Schur complement of the surface and invert it.  For P2 it is one dgemm per supernode.

Reactions: the support's nodal forces are :math:`R = K_{DF} u_F - B_D p` (the load a traction puts
directly on Dirichlet nodes is carried by the support without deforming anything); :math:`K_{DF}` touches
only the free dofs next to the support, so those dofs join the selected rows.

Two backends, the same algorithm and the same numbers (tested): ``native`` (C over the system's
CHOLMOD with METIS: :mod:`pmask.precompute.native`) and ``cvxopt`` (pip-only: cvxopt's CHOLMOD in an
AMD order of the node graph, the selected inversion in numpy and SciPy's BLAS:
:mod:`pmask.precompute.selinv`).  ``PMASK_CHOLMOD`` chooses; :func:`cholmod_backend` is the only place
that reads it.
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
from pmask.runtime.memory import available_memory, parse_bytes  # noqa: F401 (callers read them here too)
from pmask.precompute.elasticity import dofs

log = logging.getLogger(__name__)


class CondensationError(InputError):
    """The support does not hold the body (singular stiffness) or the sets are inconsistent."""


@dataclass
class SparseFactor:
    """The supernodal Cholesky factor of K_FF and what the selected inversion needs from it.

    Attributes
    ----------
    L
        the factor's arrays (:data:`pmask.precompute.selinv.FACTOR_ARRAYS`, CHOLMOD's layout).
    rows
        dofs of K_FF whose rows of K_FF⁻¹B are needed: the observed dofs (the first
        ``n_observed``, the contact vertices' dofs in order), then the free dofs the support touches.
    load
        B_F, the load columns on the free dofs (sparse, n_F x k); for P1 None, with ``scale``:
        the load is then the unit columns of the first ``n_observed`` rows times ``scale``.
    coupling
        K_DF restricted to the ``rows`` (#D x len(rows)), None without reactions;
    load_on_support
        B_D (#D x k).
    """

    L: dict
    rows: np.ndarray
    n_observed: int
    coupling: sp.csr_matrix | None
    load: sp.csc_matrix | None = None
    scale: np.ndarray | None = None
    load_on_support: sp.csr_matrix | None = None
    stats: dict = field(default_factory=dict)


def factor_arrays(factor: SparseFactor) -> dict:
    """Everything a factor holds, as named arrays (a checkpoint); :func:`factor_from_arrays` inverts it."""
    out = {**{f"L_{k}": v for k, v in factor.L.items()}, "rows": factor.rows, "n_observed": factor.n_observed,
           "stats": json.dumps(factor.stats)}
    for name in ("coupling", "load", "load_on_support"):
        m = getattr(factor, name)
        if m is not None:
            m = sp.csr_matrix(m)
            out.update({f"{name}_data": m.data, f"{name}_indices": m.indices, f"{name}_indptr": m.indptr,
                        f"{name}_shape": np.array(m.shape)})
    if factor.scale is not None:
        out["scale"] = factor.scale
    return out


class CheckpointError(ValueError):
    """A factor checkpoint whose arrays are not a factor (damaged on disk): the caller factorises again."""


def check_factor_arrays(L: dict) -> None:
    """Refuse supernodal arrays (:data:`pmask.precompute.selinv.FACTOR_ARRAYS`) whose indices would reach
    outside the factor: the checks the native selected inversion makes before it uses them (``check_factor``
    in ``_selected_inverse.c``), for both routes."""
    try:
        sup, pi, px, Ls, x, perm = (np.asarray(L[k]) for k in selinv.FACTOR_ARRAYS)
        n, ns = len(perm), len(sup) - 1
        nc, nrow = np.diff(sup), np.diff(pi)
        ok = (ns >= 0 and sup[0] == 0 and sup[-1] == n and pi[0] == 0 and px[0] == 0 and np.all(nc > 0)
              and np.all(nrow >= nc) and pi[-1] <= len(Ls) and np.all(np.diff(px) >= nrow * nc) and px[-1] <= len(x)
              and np.array_equal(np.sort(perm), np.arange(n)) and (len(Ls) == 0 or (Ls.min() >= 0 and Ls.max() < n)))
        if ok:  # each supernode's rows start with its own columns
            first = pi[:-1][:, None] + np.arange(int(nc.max()) if ns else 0)[None, :]
            own = np.arange(int(nc.max()) if ns else 0)[None, :] < nc[:, None]
            ok = np.array_equal(Ls[first[own]], (sup[:-1][:, None] + np.arange(first.shape[1]))[own])
    except (KeyError, ValueError, TypeError, IndexError):
        ok = False
    if not ok:
        raise CheckpointError("the factor checkpoint's arrays are not a supernodal factor (damaged on disk?)")


def factor_from_arrays(ck) -> SparseFactor:
    """The factor saved by :func:`factor_arrays` (``ck``: the loaded npz); :class:`CheckpointError` when its
    arrays are not a factor."""
    check_factor_arrays({k: ck[f"L_{k}"] for k in selinv.FACTOR_ARRAYS})
    def matrix(name):
        if f"{name}_data" not in ck:
            return None
        return sp.csr_matrix((ck[f"{name}_data"], ck[f"{name}_indices"], ck[f"{name}_indptr"]),
                             shape=tuple(ck[f"{name}_shape"]))

    load = matrix("load")
    return SparseFactor(L={k: ck[f"L_{k}"] for k in selinv.FACTOR_ARRAYS}, rows=ck["rows"],
                        n_observed=int(ck["n_observed"]), coupling=matrix("coupling"),
                        load=None if load is None else load.tocsc(), load_on_support=matrix("load_on_support"),
                        scale=ck["scale"] if "scale" in ck else None, stats=json.loads(str(ck["stats"])))


def load_checkpoint(path) -> SparseFactor | None:
    """The factor checkpoint at ``path`` (:func:`save_checkpoint`), or None where there is none or it is damaged
    on disk (then it is removed, with a warning: the caller factorises again)."""
    from pathlib import Path

    path = Path(path)
    if not path.exists():
        return None
    try:
        return factor_from_arrays(np.load(path))
    except (CheckpointError, OSError, ValueError, KeyError) as exc:
        log.warning("the factor checkpoint %s cannot be used (%s); factorising again", path, exc)
        path.unlink(missing_ok=True)
        return None


def save_checkpoint(path, factor: SparseFactor) -> None:
    """Write ``factor`` to ``path`` atomically (:func:`factor_arrays`), so that a rerun after a crash does not
    factorise again."""
    from pmask.runtime.files import atomic_write

    atomic_write(path, lambda tmp: np.savez(tmp, **factor_arrays(factor)), suffix=".npz")


def node_graph(n_nodes: int, elements: np.ndarray) -> sp.csr_matrix:
    """Node adjacency (with diagonal) of a mesh given as (M, nodes per element) connectivity."""
    k = elements.shape[1]
    rows = np.repeat(elements, k, axis=1).ravel()
    cols = np.tile(elements, (1, k)).ravel()
    g = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n_nodes, n_nodes))
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
    """The backend of the factorisation and the selected inversion, the one place that reads
    ``PMASK_CHOLMOD``: 'native' (C over the system's CHOLMOD with METIS and threaded OpenBLAS, built
    by the build backend when SuiteSparse's headers are there) when built, else 'cvxopt' (CHOLMOD
    bundled with a single-threaded OpenBLAS, AMD, the selected inversion in numpy; pip-only, slower).
    ``PMASK_CHOLMOD=cvxopt`` forces the latter, as on a machine without SuiteSparse;
    ``PMASK_CHOLMOD=native`` requires the former (CI)."""
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


def factorise(K: sp.spmatrix, dirichlet: np.ndarray, observed: np.ndarray, load=None, *, scale=None,
              graph_elements: np.ndarray | None = None, reactions: bool | None = None,
              backend: str | None = None) -> SparseFactor:
    """Factorise K_FF for the Green's functions.

    Parameters
    ----------
    K
        the assembled stiffness (dof 3·node + component); dirichlet : its fixed dofs (non-empty).
    observed
        dofs whose displacements Ξ holds (the contact vertices' dofs, in order).
    load
        the consistent load of the unit tractions (n_dofs x k, sparse); or None with ``scale``
        (P1): the load is then the observed dofs' unit columns times ``scale``.
    graph_elements
        element connectivity over nodes, for the pip-only route's AMD order of the node
        graph (the three dofs of a node stay together).
    reactions
        also prepare the support reactions (their rows join the selected set); None: when
        those rows are no more than the observed ones (a kidney's hilum, not a half-space's far
        hemisphere, whose ~10^4 rows would cost more than Ξ itself).
    """
    n = K.shape[0]
    dirichlet = np.unique(np.asarray(dirichlet, np.int64))
    if len(dirichlet) == 0:
        raise CondensationError("the fixed region is empty: nothing holds the body, its stiffness is singular")
    backend = cholmod_backend(backend)
    K = sp.csr_matrix(K)
    t0 = time.perf_counter()
    keep = np.setdiff1d(np.arange(n), dirichlet)  # the free dofs F, sorted
    pos = np.full(n, -1, np.int64)
    pos[keep] = np.arange(len(keep))
    obs = pos[np.asarray(observed, np.int64)]
    if np.any(obs < 0):
        raise CondensationError("an observed (contact) dof is also fixed")
    K_FF = K[keep][:, keep]
    K_DF = K[dirichlet][:, keep]
    touched = np.setdiff1d(np.flatnonzero(np.asarray(abs(K_DF).sum(axis=0)).ravel()), obs)
    if reactions is None:
        reactions = len(touched) <= len(obs)
    rows = np.concatenate([obs, touched]) if reactions else obs
    coupling = sp.csr_matrix(K_DF[:, rows]) if reactions else None
    B_F = B_D = None
    if load is not None:
        load = sp.csr_matrix(load)
        B_F, B_D = sp.csc_matrix(load[keep]), sp.csr_matrix(load[dirichlet])
    t_setup = time.perf_counter() - t0
    t0 = time.perf_counter()
    order = None
    free_nodes = keep[::3] // 3
    if backend != "native" and graph_elements is not None and np.array_equal(keep, dofs(free_nodes)):
        # AMD of the node graph (the supports hold whole nodes): a node's three dofs stay together
        order = dofs(amd_order(node_graph(n // 3, graph_elements)[free_nodes][:, free_nodes]))
    L, st = sparse_cholesky(K_FF, backend=backend, order=order)
    if order is not None:
        st["order"] = "AMD (node graph)"
    t_factor = time.perf_counter() - t0
    log.info("factor (%s, %s): %d dofs, %d stored in L, %d supernodes, %.2fs", backend, st["order"], len(keep),
             st["stored_L"], st["supernodes"], t_factor)
    return SparseFactor(L=L, rows=rows, n_observed=len(obs), coupling=coupling, load=B_F, load_on_support=B_D,
                        scale=None if scale is None else np.asarray(scale, float),
                        stats={"dofs": len(keep), "nnz_L": st["stored_L"], "backend": backend,
                               "route": "selected inversion", "order": st["order"], "setup_s": t_setup,
                               "analyse_s": st["analyse_s"], "numeric_s": st["numeric_s"], "factor_s": t_factor,
                               "factor_flops": st["factor_flops"], "supernodes": st["supernodes"],
                               "selected_dofs": len(rows)})


def sparse_cholesky(A: sp.spmatrix, *, backend: str | None = None, order: np.ndarray | None = None):
    """Supernodal Cholesky P A Pᵀ = L Lᵀ of a symmetric positive definite A, for the selected inversion.

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
    """X[i, j] = (A⁻¹)[want_i, want_j] · scale_j (C order) from :func:`sparse_cholesky`'s factor (the
    symmetric case), by the C library (native) or :mod:`pmask.precompute.selinv`; returns X and timings."""
    if cholmod_backend(backend) == "native":
        from pmask.precompute import native

        return native.selected_inverse(L, want, scale)
    t0 = time.perf_counter()
    X, st = selinv.selected_inverse(L, want, scale)
    st["selinv_s"] = time.perf_counter() - t0
    return X, st


def inverse_columns(L: dict, rows: np.ndarray, B, *, backend: str | None = None):
    """X = Eᵀ A⁻¹ B (the rows ``rows`` of A⁻¹B, C order) for a sparse load B; returns X and timings."""
    if cholmod_backend(backend) == "native":
        from pmask.precompute import native

        return native.selected_columns(L, rows, B)
    t0 = time.perf_counter()
    X, st = selinv.selected_columns(L, rows, B)
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


def greens_functions(factor: SparseFactor, *, backend: str | None = None):
    r"""Green's functions Ξ and the support reactions from a factor.

    Returns
    -------
    Xi : (n_observed, k): Ξ[:, c] is the displacement of the observed dofs under load column c (for
        the contact vertices' unit tractions: block (i, j) is the displacement of vertex i per unit
        traction at vertex j).  P1: a view of a slightly larger array that also holds the rows the
        reactions need.
    reactions : (#D, k), the nodal forces the support exerts per load column, on the Dirichlet dofs
        (equilibrium: with the load they sum to zero force and moment); None if not prepared.
    """
    nobs = factor.n_observed
    t0 = time.perf_counter()
    if factor.load is None:  # P1: the symmetric block of the inverse, scaled
        scale = np.concatenate([factor.scale, np.ones(len(factor.rows) - nobs)])
        if len(factor.scale) != nobs:
            raise CondensationError(f"{len(factor.scale)} load scales for {nobs} observed dofs")
        D, st = inverse_block(factor.L, factor.rows, scale, backend=backend)
        D = D[:, :nobs]
    else:
        D, st = inverse_columns(factor.L, factor.rows, factor.load, backend=backend)
    st["total_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    reactions = None
    if factor.coupling is not None:
        near = np.unique(factor.coupling.indices)  # the selected rows next to the support
        reactions = factor.coupling[:, near] @ D[near]  # K_DF u for every load
        if factor.load_on_support is not None and factor.load_on_support.nnz:
            reactions = reactions - factor.load_on_support.toarray()
        reactions = np.ascontiguousarray(reactions)
    st["reactions_s"] = time.perf_counter() - t0
    log.info("greens (selected inversion): %s", ", ".join(f"{k} {v:.3g}" for k, v in st.items()))
    factor.stats["greens_s"] = st
    return D[:nobs], reactions
