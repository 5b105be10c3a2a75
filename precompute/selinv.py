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


class _Tree:
    """The supernodal elimination tree of a factor (:data:`FACTOR_ARRAYS`): each supernode's parent and
    the first column of its subtree, checked to be postordered (every subtree a contiguous range)."""

    def __init__(self, L: dict):
        self.sup, self.pi, self.px, self.Ls, self.Lx, self.perm = (np.asarray(L[k]) for k in FACTOR_ARRAYS)
        sup, pi, Ls = self.sup, self.pi, self.Ls
        self.n, self.ns = len(self.perm), len(sup) - 1
        self.iperm = np.empty(self.n, np.int64)
        self.iperm[self.perm] = np.arange(self.n)
        self.ncol, self.nrow = np.diff(sup), np.diff(pi)
        self.snode = np.repeat(np.arange(self.ns), self.ncol)
        parent = np.full(self.ns, -1)
        has = self.nrow > self.ncol
        parent[has] = self.snode[Ls[pi[:-1][has] + self.ncol[has]]]
        fc = sup[:-1].copy()
        sub = self.ncol.copy()  # columns in each subtree
        for s in range(self.ns):  # children precede parents
            if sub[s] != sup[s + 1] - fc[s]:
                raise ValueError(f"the factor's supernodes are not postordered (supernode {s}: columns "
                                 f"{sup[s]}:{sup[s + 1]}, its subtree from column {fc[s]} has {sub[s]} columns)")
            if parent[s] >= 0:
                fc[parent[s]] = min(fc[parent[s]], fc[s])
                sub[parent[s]] += sub[s]
        self.parent, self.fc = parent, fc

    def block(self, s: int) -> np.ndarray:
        """Supernode s's (nrow, ncol) block of L (a view; lower triangle of the top square valid)."""
        nr, nc = self.nrow[s], self.ncol[s]
        return self.Lx[self.px[s]:self.px[s] + nr * nc].reshape(nc, nr).T

    def ranges(self, starts: np.ndarray):
        """Columns placed at pivots ``starts`` (sorted by pivot): for every supernode the range
        [lo, hi) of those whose start lies in its subtree, and each column's sorted position."""
        counts = np.zeros(self.n + 1, np.int64)
        np.add.at(counts, np.minimum(starts, self.n) + 1, 1)
        cnt = np.cumsum(counts)  # cnt[k]: columns starting before pivot k
        order = np.argsort(starts, kind="stable")
        pos = np.empty(len(starts), np.int64)
        pos[order] = np.arange(len(starts))
        return cnt[self.fc], cnt[self.sup[1:]], pos


def _distinct(want: np.ndarray, n: int) -> np.ndarray:
    want = np.asarray(want, np.int64)
    if len(want) and (want.min() < 0 or want.max() >= n or len(np.unique(want)) != len(want)):
        raise ValueError("wanted dofs must be distinct indices of the factorised matrix")
    return want


def _forward(tree: _Tree, W: list, cols, s: int, size=None, alloc=None):
    """One supernode of the forward solve W = L⁻¹ R (W[s]: the transpose of W's rows of s, restricted
    to the columns that reach s): W[s] ← W[s] L_ssᵀ⁻¹, then the ancestors' rows are updated.
    ``cols``: the first column of each supernode's contiguous range (an array), or each supernode's
    sorted column set (a list of arrays).  ``size``: how many columns reach each supernode, to allocate
    an ancestor's W on its first update (W[t] None: :func:`forward_sweep`), or ``alloc(t)`` to make it.
    Returns W[s] and the flops spent."""
    nc, nr = tree.ncol[s], tree.nrow[s] - tree.ncol[s]
    m = W[s].shape[0]
    block = tree.block(s)
    X = blas.dtrsm(1.0, np.asfortranarray(block[:nc]), W[s], side=1, lower=1, trans_a=1, overwrite_b=1)
    W[s] = X
    flops = float(m) * nc * nc
    if nr:
        U = X @ block[nc:].T  # (m, nr): the update of the ancestors' rows
        flops += 2.0 * m * nr * nc
        rows = tree.Ls[tree.pi[s] + nc:tree.pi[s + 1]]
        owners = tree.snode[rows]
        for t in np.unique(owners):
            sel = owners == t
            if W[t] is None:
                W[t] = alloc(t) if alloc is not None else np.zeros((size[t], tree.ncol[t]), order="F")
            if isinstance(cols, np.ndarray):  # contiguous ranges: s's columns start at cols[s] - cols[t] in t
                W[t][cols[s] - cols[t]:cols[s] - cols[t] + m, rows[sel] - tree.sup[t]] -= U[:, sel]
            else:  # explicit sets: s's set is a subset of its ancestors'
                W[t][np.ix_(np.searchsorted(cols[t], cols[s]), rows[sel] - tree.sup[t])] -= U[:, sel]
    return X, flops


def forward_sweep(tree: _Tree, want: np.ndarray, emit) -> dict:
    r"""W = L⁻¹ P E supernode by supernode, holding only what is still to be finished.

    The wanted dofs ``want`` sorted by pivot: supernode s meets the contiguous range
    [lo_s, hi_s) of them (its subtree's).  For each supernode with a non-empty range, in postorder,
    ``emit(s, lo_s, X_s)`` receives :math:`X_s`, the (hi_s − lo_s, ncol_s) rows of W's transpose
    (column-major; it may be kept: it is not reused).  A supernode's W is allocated (with its identity
    entries) when its first child updates it, or at its own turn, and dropped once emitted, so the live
    memory is the pending ancestors' only, not all of W (allocating every block that holds a wanted pivot
    at the start held 7.8 GiB before the first step at 47,467 contact vertices, by :func:`sweep_memory`'s
    count).  Returns ``pos`` (each wanted dof's sorted position), ``lo``, ``hi`` and ``flops``.  Then :math:`(A^{-1})_{EE}[\mathrm{pos}_i, \mathrm{pos}_j] = \sum_s X_s X_s^T` on the ranges.
    """
    want = _distinct(want, tree.n)
    piv = tree.iperm[want]
    lo, hi, pos = tree.ranges(piv)
    W = [None] * tree.ns
    size = hi - lo
    by = np.argsort(tree.snode[piv], kind="stable")  # the wanted pivots grouped by supernode
    first = np.searchsorted(tree.snode[piv][by], np.arange(tree.ns + 1))

    def alloc(t):  # W[t] with its identity entries (no update touches them: updates fill its children's rows)
        B = np.zeros((size[t], tree.ncol[t]), order="F")
        i = by[first[t]:first[t + 1]]
        B[pos[i] - lo[t], piv[i] - tree.sup[t]] = 1.0
        return B

    flops = 0.0
    for s in range(tree.ns):
        if size[s] == 0:
            continue
        if W[s] is None:
            W[s] = alloc(s)
        X, f = _forward(tree, W, lo, s, size, alloc)
        W[s] = None
        flops += f
        emit(s, int(lo[s]), X)
    return {"pos": pos, "lo": lo, "hi": hi, "flops": flops}


def sweep_memory(tree: _Tree, want: np.ndarray, emit_copy: int = 0, size: np.ndarray | None = None) -> dict:
    """The bytes :func:`forward_sweep` holds at its peak, from the tree alone (nothing is solved): the W
    block of each supernode from its first update (or its own turn) until its turn ends, and at each
    supernode its update U (m x nr), its diagonal block's copy (nc x nc) and the two temporaries of each
    ancestor's update, then the copy ``emit`` makes of its block (at most ``emit_copy`` bytes), and the
    sweep's own index arrays.  ``size``: how many columns reach each supernode, given instead of ``want``'s
    ranges (:func:`load_sweep`'s sets: the same allocations in the same order); ``want`` is then the number of
    the load's non-zeros (its index arrays).  Returns ``peak`` (bytes) and
    ``at`` (the supernode at the peak): the memory check's figure for the sweep, a simulation of the same
    allocations in the same order (tested against the measured peak)."""
    if size is None:
        want = _distinct(want, tree.n)
        lo, hi, _ = tree.ranges(tree.iperm[want])
        size, count = hi - lo, len(want)
    else:
        count = int(want)
    size = np.asarray(size, np.int64)
    blk = 8 * size * tree.ncol  # bytes of each supernode's W block
    live = np.zeros(tree.ns, bool)
    held = peak = 8 * (4 * count + 4 * tree.ns)  # want, piv, pos, the grouping; lo, hi, size, first
    at = -1
    for s in np.flatnonzero(size > 0):
        nc, nr = int(tree.ncol[s]), int(tree.nrow[s] - tree.ncol[s])
        if not live[s]:  # no child updated it: allocated at its own turn
            live[s] = True
            held += int(blk[s])
        base = held + 8 * int(size[s]) * nr + (8 * nc * nc if nr else 0)  # U and the diagonal block's copy
        # (none at a root: its block is the whole column panel, contiguous already)
        new, now = 0, base
        if nr:  # the ancestors in the sweep's order: a fresh one allocated, then its update made through two
            # m x (its rows) temporaries (U's columns gathered; its own gathered, subtracted, put back)
            owners, count = np.unique(tree.snode[tree.Ls[tree.pi[s] + nc:tree.pi[s + 1]]], return_counts=True)
            fresh = np.where(live[owners], 0, blk[owners])
            live[owners] = True
            new = int(fresh.sum())
            now = base + int(np.max(np.cumsum(fresh) + 16 * int(size[s]) * count))
        now = max(now, held + new + min(int(blk[s]), int(emit_copy)))  # U gone; the emitted block copied
        if now > peak:
            peak, at = now, int(s)
        held += new - int(blk[s])
        live[s] = False
    return {"peak": peak, "at": at}


def _load_blocks(tree: _Tree, B, posB: np.ndarray, sets: list, within: tuple[int, int] | None = None):
    """``alloc(t)``: supernode t's block of W_B = L⁻¹PB before its solve, its rows the columns of ``sets[t]``
    (positions ``posB``, :func:`column_sets`), holding B's entries whose pivots are t's; ``within``: only the
    columns at positions in that range (a batch)."""
    B = sp.csc_matrix(B)
    nz_piv = tree.iperm[B.indices]
    col_of = np.repeat(np.arange(B.shape[1]), np.diff(B.indptr))
    data = B.data
    if within is not None:
        keep = (posB[col_of] >= within[0]) & (posB[col_of] < within[1])
        nz_piv, col_of, data = nz_piv[keep], col_of[keep], data[keep]
    by = np.argsort(tree.snode[nz_piv], kind="stable")
    split = np.searchsorted(tree.snode[nz_piv][by], np.arange(tree.ns + 1))

    def alloc(t):
        W = np.zeros((len(sets[t]), tree.ncol[t]), order="F")
        i = by[split[t]:split[t + 1]]
        np.add.at(W, (np.searchsorted(sets[t], posB[col_of[i]]), nz_piv[i] - tree.sup[t]), data[i])
        return W

    return alloc


def load_sweep(tree: _Tree, B, sets: list, posB: np.ndarray, b0: int, b1: int, emit) -> dict:
    r"""W_B = L⁻¹ P B supernode by supernode for the columns of B at positions b0..b1 (:func:`column_sets`'s
    numbering, by lowest pivot), as :func:`forward_sweep` does for unit columns: ``emit(s, first, X_s)``
    receives X_s, the rows of W_Bᵀ of supernode s for those of its set ``sets[s]`` in the range (a run of it,
    from its position ``first``; the set is sorted), and a block is held only from its first update to the end
    of its turn.  With W_E from :func:`forward_sweep`, :math:`E^T A^{-1} B = W_E^T W_B` supernode by
    supernode (:func:`selected_columns` forms it in one pass; the compressed route stores both and forms it
    tile by tile).  Returns ``flops``."""
    first = [int(np.searchsorted(c, b0)) for c in sets]
    part = [c[f:int(np.searchsorted(c, b1))] for c, f in zip(sets, first)]
    alloc = _load_blocks(tree, B, posB, part, (b0, b1))
    W = [None] * tree.ns
    flops = 0.0
    for s in range(tree.ns):
        if len(part[s]) == 0:
            continue
        if W[s] is None:
            W[s] = alloc(s)
        X, f = _forward(tree, W, part, s, alloc=alloc)
        W[s] = None
        flops += f
        emit(s, first[s], X)
    return {"flops": flops}


def selected_inverse(L: dict, want: np.ndarray, scale: np.ndarray) -> tuple[np.ndarray, dict]:
    """X[i, j] = (A⁻¹)[want_i, want_j] · scale_j (C order), as ``native.selected_inverse``: the
    symmetric case, one syrk per supernode of :func:`forward_sweep`."""
    tree = _Tree(L)
    want = _distinct(want, tree.n)
    scale = np.asarray(scale, float)
    nw = len(want)
    if scale.shape != (nw,):
        raise ValueError(f"{len(scale)} scale factors for {nw} wanted dofs")
    D = np.zeros((nw, nw), order="F")
    syrk_flops = [0.0]

    def syrk(s, lo, X):
        hi = lo + X.shape[0]
        syrk_flops[0] += float(X.shape[0]) ** 2 * tree.ncol[s]
        # in place when the block is all of D (the root); else on a copy of the block, put back
        C = blas.dsyrk(1.0, X, beta=1.0, c=D[lo:hi, lo:hi], lower=1, overwrite_c=1)
        if not np.shares_memory(C, D):
            D[lo:hi, lo:hi] = C

    st = forward_sweep(tree, want, syrk)
    _mirror_lower(D)
    sp_ = st["pos"]
    X = D.T[np.ix_(sp_, sp_)]  # D is symmetric now; its C-ordered view gathers 4x faster, no copy
    del D
    X *= scale[None, :]
    return X, {"flops": st["flops"] + syrk_flops[0]}


def column_sets(tree: _Tree, B) -> tuple[list, np.ndarray]:
    """For every supernode, the sorted positions of the columns of W_B = L⁻¹PB that are non-zero in
    its rows: the columns with a non-zero pivot in its subtree (a column is non-zero exactly on the
    union of the tree paths up from its non-zeros).  Columns are numbered by their lowest pivot, so
    that the sets are nearly contiguous.  Returns (sets, position of each column of B)."""
    nz_piv = tree.iperm[B.indices]
    col_of = np.repeat(np.arange(B.shape[1]), np.diff(B.indptr))
    start = np.full(B.shape[1], tree.n, np.int64)
    np.minimum.at(start, col_of, nz_piv)
    order = np.argsort(start, kind="stable")
    pos = np.empty(B.shape[1], np.int64)
    pos[order] = np.arange(B.shape[1])
    owner = tree.snode[nz_piv]
    by_owner = np.argsort(owner, kind="stable")
    split = np.searchsorted(owner[by_owner], np.arange(tree.ns + 1))
    children = [[] for _ in range(tree.ns)]
    for s in range(tree.ns):
        if tree.parent[s] >= 0:
            children[tree.parent[s]].append(s)
    sets = []
    for s in range(tree.ns):  # children before parents
        own = pos[col_of[by_owner[split[s]:split[s + 1]]]]
        sets.append(np.unique(np.concatenate([own] + [sets[c] for c in children[s]])))
    return sets, pos


def selected_columns(L: dict, rows: np.ndarray, B) -> tuple[np.ndarray, dict]:
    r"""X = Eᵀ A⁻¹ B: the rows ``rows`` of A⁻¹B, (len(rows), B.shape[1]) in C order, as
    ``native.selected_columns``.

    .. math::  E^T A^{-1} B = (L^{-1} P E)^T (L^{-1} P B) = W_E^T W_B

    W_E's unit columns meet each supernode in a contiguous range (as in :func:`selected_inverse`).
    A column of W_B = L⁻¹PB is non-zero on the union of the tree paths up from its non-zeros' pivots:
    for a consistent P2 load at vertex j those are j's neighbours, which lie on j's path or below j in
    several branches (2-4 on the kidney), so each supernode keeps the explicit set of W_B columns that
    reach it (:func:`column_sets`).  Then W_Eᵀ W_B is one gemm per supernode, scattered into the
    set's columns.  A supernode's W_E and W_B are held from its first update to the end of its turn, so
    the peak is the answer twice (D in pivot order and its gather) and little else (tested).
    """
    import scipy.sparse as sp

    tree = _Tree(L)
    rows = _distinct(rows, tree.n)
    B = sp.csc_matrix(B)
    if B.shape[0] != tree.n:
        raise ValueError(f"B has {B.shape[0]} rows for a factor of {tree.n} dofs")
    B.sum_duplicates()
    k = B.shape[1]
    pivE = tree.iperm[rows]
    loE, hiE, posE = tree.ranges(pivE)
    sets, posB = column_sets(tree, B)
    byE = np.argsort(tree.snode[pivE], kind="stable")  # the rows' pivots by supernode
    firstE = np.searchsorted(tree.snode[pivE][byE], np.arange(tree.ns + 1))

    def alloc_E(t):  # W_E[t] with its unit entries, on its first update or at its own turn (forward_sweep)
        W = np.zeros((hiE[t] - loE[t], tree.ncol[t]), order="F")
        i = byE[firstE[t]:firstE[t + 1]]
        W[posE[i] - loE[t], pivE[i] - tree.sup[t]] = 1.0
        return W

    alloc_B = _load_blocks(tree, B, posB, sets)  # W_B[t] with B's entries whose pivots are t's

    # W_E and W_B held only from a supernode's first update to the end of its turn, as in forward_sweep
    # (allocating every block at the start held all of both)
    WE, WB = [None] * tree.ns, [None] * tree.ns
    D = np.zeros((len(rows), k))
    flops = 0.0
    for s in range(tree.ns):
        mE, mB = hiE[s] - loE[s], len(sets[s])
        XE = XB = None
        if mE:
            if WE[s] is None:
                WE[s] = alloc_E(s)
            XE, f = _forward(tree, WE, loE, s, alloc=alloc_E)
            flops += f
        if mB:
            if WB[s] is None:
                WB[s] = alloc_B(s)
            XB, f = _forward(tree, WB, sets, s, alloc=alloc_B)
            flops += f
        if mE and mB:
            c = sets[s]
            V = D[loE[s]:hiE[s], c[0]:c[-1] + 1] if c[-1] - c[0] + 1 == mB else None
            if V is not None and V.flags.c_contiguous:  # whole rows of D (the root's, the largest): Vᵀ += XB XEᵀ
                R = blas.dgemm(1.0, XB, XE, beta=1.0, c=V.T, trans_b=1, overwrite_c=1)  # in place, no product copy
                if not np.shares_memory(R, D):
                    V[...] = R.T
            elif V is not None:
                V += XE @ XB.T
            else:
                D[loE[s]:hiE[s], c] += XE @ XB.T
            flops += 2.0 * mE * mB * tree.ncol[s]
        WE[s] = WB[s] = XE = XB = None
    return np.ascontiguousarray(D[np.ix_(posE, posB)]), {"flops": flops}


def _mirror_lower(G: np.ndarray, block: int = 512) -> None:
    """Copy the strict lower triangle of G onto its upper triangle, in place, block by block."""
    n = G.shape[0]
    for i0 in range(0, n, block):
        i1 = min(i0 + block, n)
        G[i0:i1, i0:i1] = np.tril(G[i0:i1, i0:i1]) + np.tril(G[i0:i1, i0:i1], -1).T
        G[i0:i1, i1:] = G[i1:, i0:i1].T
