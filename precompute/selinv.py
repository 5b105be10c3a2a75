r"""Selected inversion in numpy + SciPy's BLAS: the pip-only twin of ``_selected_inverse.c``.

Given a supernodal Cholesky factor :math:`P A P^T = L L^T` whose elimination tree is postordered,
the block of :math:`A^{-1}` on a set E of wanted dofs is

.. math::  (A^{-1})_{EE} = W^T W, \qquad W = L^{-1} P E,

where column w of W is non-zero only on the tree path from w's pivot to the root: the rows of
supernode s meet only the wanted columns of s's subtree, one contiguous range [lo_s, hi_s) once the
wanted dofs are sorted by pivot.  So W is computed supernode by supernode (trsm on the diagonal
block, gemm + scatter onto the ancestors' rows), and :math:`W^T W` is one syrk per supernode.
``precompute/_selected_inverse.c`` does the same in place and with CHOLMOD's METIS order; this
module serves machines without SuiteSparse (the factor then comes from cvxopt's CHOLMOD, in an AMD
order postordered here), and tests check the two against each other and against dense inverses.

The factor is a dict of arrays in CHOLMOD's supernodal layout (:data:`FACTOR_ARRAYS`): supernode s
has columns ``super[s]:super[s+1]``, row indices ``s[pi[s]:pi[s+1]]`` (its own columns first) and
values ``x[px[s]:...]``, an (nrow, ncol) column-major block, lower triangle valid; ``perm`` maps
pivot k to the original dof ``perm[k]``.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg.blas as blas
import scipy.sparse as sp

FACTOR_ARRAYS = ("super", "pi", "px", "s", "x", "perm")


def etree(colptr: np.ndarray, rowind: np.ndarray) -> np.ndarray:
    """Elimination tree of a Cholesky factor in CSC form (sorted rows): parent of column j is its
    first sub-diagonal row, -1 for a root."""
    n = len(colptr) - 1
    counts = np.diff(colptr)
    parent = np.full(n, -1, np.int64)
    has = counts > 1
    parent[has] = rowind[colptr[:-1][has] + 1]
    return parent


def postorder(parent: np.ndarray) -> np.ndarray:
    """A postorder of a forest (children before parents, every subtree contiguous)."""
    n = len(parent)
    order = np.argsort(parent, kind="stable")  # children grouped by parent, in index order
    roots = order[parent[order] == -1]
    first = np.searchsorted(parent[order], np.arange(n))
    last = np.searchsorted(parent[order], np.arange(n), side="right")
    post = np.empty(n, np.int64)
    k = 0
    stack = list(roots[::-1])
    expanded = np.zeros(n, bool)
    while stack:
        v = stack[-1]
        if expanded[v]:
            stack.pop()
            post[k] = v
            k += 1
            continue
        expanded[v] = True
        stack.extend(order[first[v]:last[v]][::-1].tolist())
    return post


def supernodal(colptr: np.ndarray, rowind: np.ndarray, values: np.ndarray, perm: np.ndarray) -> dict:
    """A CSC Cholesky factor (sorted rows; stored zeros allowed, e.g. from relaxed supernodes) of
    P A Pᵀ with ``perm`` = P's order, postordered and packed in CHOLMOD's supernodal layout.

    Postorder: for an ordering Q of the tree that puts every column after its descendants, Q L Qᵀ is
    still lower triangular (a column's stored rows are among its ancestors), so it *is* the Cholesky
    factor of Q P A Pᵀ Qᵀ: the factor is relabelled, not recomputed.
    Supernodes: columns j and j+1 share one when j+1 is j's parent and column j's rows are j followed
    by column j+1's rows (a column's rows below it are always among its parent's), so that the dense
    block holds exactly L's values.  Other children may hang off any column of the chain: the
    subtree of its last column is still one contiguous range of the postorder."""
    n = len(colptr) - 1
    post = postorder(etree(colptr, rowind))
    if np.any(post != np.arange(n)):
        Lq = sp.csc_matrix((values, rowind, colptr), shape=(n, n))[post][:, post].tocsc()
        Lq.sort_indices()
        colptr, rowind, values = Lq.indptr, Lq.indices, Lq.data
        perm = np.asarray(perm)[post]
    counts = np.diff(colptr)
    parent = etree(colptr, rowind)
    j = np.arange(n - 1)
    joins = (parent[:-1] == j + 1) & (counts[:-1] == counts[1:] + 1)
    starts = np.concatenate([[0], np.flatnonzero(~joins) + 1])
    sup = np.concatenate([starts, [n]]).astype(np.int64)
    ncol = np.diff(sup)
    nrow = counts[sup[:-1]]
    pi = np.concatenate([[0], np.cumsum(nrow)]).astype(np.int64)
    px = np.concatenate([[0], np.cumsum(nrow * ncol)]).astype(np.int64)
    first = np.repeat(sup[:-1], ncol)  # each column's supernode's first column
    snode = np.repeat(np.arange(len(ncol)), ncol)
    srows = np.concatenate([rowind[colptr[k]:colptr[k + 1]] for k in sup[:-1]]) if n else np.zeros(0, np.int64)
    x = np.zeros(px[-1])
    c = np.arange(n) - first  # position of the column within its supernode
    # column j's t-th value sits at row c + t of the block's column c
    col_of = np.repeat(np.arange(n), counts)
    t = np.arange(colptr[-1]) - np.repeat(colptr[:-1], counts)
    cj = c[col_of]
    x[px[snode[col_of]] + cj * nrow[snode[col_of]] + cj + t] = values
    return {"super": sup, "pi": pi, "px": px, "s": srows.astype(np.int64), "x": x,
            "perm": np.asarray(perm, np.int64)}


def selected_inverse(L: dict, want: np.ndarray, scale: np.ndarray) -> tuple[np.ndarray, dict]:
    """X[i, j] = (A⁻¹)[want_i, want_j] · scale_j (C order), as ``native.selected_inverse``."""
    sup, pi, px, Ls, Lx, perm = (np.asarray(L[k]) for k in FACTOR_ARRAYS)
    n, ns = len(perm), len(sup) - 1
    want = np.asarray(want, np.int64)
    scale = np.asarray(scale, float)
    nw = len(want)
    if scale.shape != (nw,):
        raise ValueError(f"{len(scale)} scale factors for {nw} wanted dofs")
    if nw and (want.min() < 0 or want.max() >= n or len(np.unique(want)) != nw):
        raise ValueError("wanted dofs must be distinct indices of the factorised matrix")
    iperm = np.empty(n, np.int64)
    iperm[perm] = np.arange(n)
    piv = iperm[want]
    is_w = np.zeros(n, bool)
    is_w[piv] = True
    cnt = np.concatenate([[0], np.cumsum(is_w)])
    sp_ = cnt[piv]  # sorted (pivot-order) position of want_i
    ncol = np.diff(sup)
    nrow = np.diff(pi)
    snode = np.repeat(np.arange(ns), ncol)
    parent = np.full(ns, -1)
    has = nrow > ncol
    parent[has] = snode[Ls[pi[:-1][has] + ncol[has]]]
    fc = sup[:-1].copy()
    sub = ncol.copy()  # columns in each subtree
    for s in range(ns):  # children precede parents
        if sub[s] != sup[s + 1] - fc[s]:
            raise ValueError(f"the factor's supernodes are not postordered (supernode {s}: columns "
                             f"{sup[s]}:{sup[s + 1]}, its subtree from column {fc[s]} has {sub[s]} columns)")
        if parent[s] >= 0:
            fc[parent[s]] = min(fc[parent[s]], fc[s])
            sub[parent[s]] += sub[s]
    lo, hi = cnt[fc], cnt[sup[1:]]
    W = [np.zeros((hi[s] - lo[s], ncol[s]), order="F") for s in range(ns)]
    for k in np.flatnonzero(is_w):
        s = snode[k]
        W[s][cnt[k] - lo[s], k - sup[s]] = 1.0
    D = np.zeros((nw, nw), order="F")
    flops = 0.0
    for s in range(ns):
        m, nc, nr = hi[s] - lo[s], ncol[s], nrow[s] - ncol[s]
        if m == 0:
            continue
        block = Lx[px[s]:px[s] + nrow[s] * nc].reshape(nc, nrow[s]).T  # (nrow, nc) view
        X = blas.dtrsm(1.0, np.asfortranarray(block[:nc]), W[s], side=1, lower=1, trans_a=1, overwrite_b=1)
        W[s] = X
        # in place when the block is all of D (the root); else on a copy of the block, put back
        C = blas.dsyrk(1.0, X, beta=1.0, c=D[lo[s]:hi[s], lo[s]:hi[s]], lower=1, overwrite_c=1)
        if not np.shares_memory(C, D):
            D[lo[s]:hi[s], lo[s]:hi[s]] = C
        flops += float(m) * nc * nc + float(m) * m * nc
        if nr == 0:
            continue
        U = X @ block[nc:].T  # (m, nr): the update of the ancestors' rows
        flops += 2.0 * m * nr * nc
        rows = Ls[pi[s] + nc:pi[s + 1]]
        owners = snode[rows]
        for t in np.unique(owners):
            sel = owners == t
            W[t][lo[s] - lo[t]:hi[s] - lo[t], rows[sel] - sup[t]] -= U[:, sel]
    _mirror_lower(D)
    X = D.T[np.ix_(sp_, sp_)]  # D is symmetric now; its C-ordered view gathers 4x faster, no copy
    del D
    X *= scale[None, :]
    return X, {"flops": flops}


def _mirror_lower(G: np.ndarray, block: int = 512) -> None:
    """Copy the strict lower triangle of G onto its upper triangle, in place, block by block."""
    n = G.shape[0]
    for i0 in range(0, n, block):
        i1 = min(i0 + block, n)
        G[i0:i1, i0:i1] = np.tril(G[i0:i1, i0:i1]) + np.tril(G[i0:i1, i0:i1], -1).T
        G[i0:i1, i1:] = G[i1:, i0:i1].T
