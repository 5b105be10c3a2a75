"""The pip-only selected inversion (precompute/selinv.py): postorder, packing, inverse; and the C twin."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from conftest import dense_factor, element_spd, laplacian_3d, lower, patch_loads, random_spd, traced_peak
from pmask.precompute import native, selinv
from pmask.precompute.greens import sparse_cholesky


def cvxopt_factor(A, rng=None):
    """The pip-only factor (cvxopt's CHOLMOD, relaxed supernodes, postordered and packed here) in a
    random order, or in AMD order without ``rng``."""
    order = None if rng is None else rng.permutation(A.shape[0])
    L, stats = sparse_cholesky(A, backend="cvxopt", order=order)
    assert stats["order"] == ("AMD" if rng is None else "given")
    return L


@settings(max_examples=50, deadline=None)
@given(parent_seed=st.integers(0, 2**32 - 1), n=st.integers(1, 200))
def test_postorder_puts_children_first_and_keeps_subtrees_contiguous(parent_seed, n):
    rng = np.random.default_rng(parent_seed)
    up = np.array([rng.integers(i + 1, n) if i < n - 1 and rng.random() > 0.1 else -1 for i in range(n)])
    label = rng.permutation(n)  # a random forest under random labels
    parent = np.full(n, -1)
    parent[label] = np.where(up >= 0, label[np.maximum(up, 0)], -1)
    post = selinv.postorder(parent)
    assert sorted(post) == list(range(n))
    where = np.empty(n, int)
    where[post] = np.arange(n)
    size = np.ones(n, int)
    for v in post:  # children first, so their sizes are final here
        if parent[v] >= 0:
            assert where[parent[v]] > where[v]
            size[parent[v]] += size[v]
    first = where.copy()
    for v in post:
        if parent[v] >= 0:
            first[parent[v]] = min(first[parent[v]], first[v])
    assert np.array_equal(where - first + 1, size)  # each subtree is the range ending at its root


def test_packed_factor_is_the_cholesky_factor_of_the_postordered_matrix():
    A = laplacian_3d(6, 7)
    L = cvxopt_factor(A)
    n = A.shape[0]
    dense = dense_factor(L)
    p = L["perm"]
    assert np.abs(dense @ dense.T - A.toarray()[np.ix_(p, p)]).max() < 1e-12
    assert len(L["super"]) - 1 < n  # columns did merge into supernodes


@settings(max_examples=60, deadline=None)
@given(n=st.integers(1, 90), density=st.floats(0.0, 0.3), frac=st.floats(0.0, 1.0), seed=st.integers(0, 2**32 - 1))
def test_selected_inverse_matches_the_dense_inverse(n, density, frac, seed):
    """Any sparsity (diagonal, banded-like, dense-ish, many components), any wanted set, both twins."""
    rng = np.random.default_rng(seed)
    A = random_spd(n, density, rng)
    want = rng.permutation(n)[:int(frac * n)]
    scale = rng.uniform(0.5, 2.0, len(want))
    L = cvxopt_factor(A, rng)
    X, _ = selinv.selected_inverse(L, want, scale)
    G = np.linalg.inv(A.toarray())[np.ix_(want, want)]
    assert X.flags.c_contiguous and X.shape == (len(want), len(want))
    assert np.abs(X - G * scale[None, :]).max(initial=0.0) <= 2e-12 * max(np.abs(G).max(initial=0.0), 1e-300)
    if native.available():
        Xc, _ = native.selected_inverse(L, want, scale)  # the C twin on the same factor
        assert np.abs(Xc - X).max(initial=0.0) <= 1e-13 * max(np.abs(G).max(initial=0.0), 1e-300)
        Ln, _ = native.factor(lower(A))  # and on CHOLMOD's own factor (METIS order)
        Xn, _ = native.selected_inverse(Ln, want, scale)
        assert np.abs(Xn - G * scale[None, :]).max(initial=0.0) <= 2e-12 * max(np.abs(G).max(initial=0.0), 1e-300)


def test_bad_input_is_refused():
    L = cvxopt_factor(laplacian_3d(3, 1), np.random.default_rng(1))
    with pytest.raises(ValueError, match="distinct"):
        selinv.selected_inverse(L, np.array([1, 1]), np.ones(2))
    with pytest.raises(ValueError, match="scale"):
        selinv.selected_inverse(L, np.array([1, 2]), np.ones(1))


def unordered_factor():
    """A valid Cholesky factor in supernodal layout whose elimination tree is not postordered: column 0's
    parent is column 2 while column 1 is a root of its own, so the subtree of column 2 ({0, 2}) is not a
    contiguous range of columns."""
    dense = np.array([[2.0, 0.0, 0.0], [0.0, 1.5, 0.0], [0.5, 0.0, 1.2]])  # L: rows {0, 2}, {1}, {2}
    return {"super": np.array([0, 1, 2, 3]), "pi": np.array([0, 2, 3, 4]), "px": np.array([0, 2, 3, 4]),
            "s": np.array([0, 2, 1, 2]), "x": np.array([2.0, 0.5, 1.5, 1.2]), "perm": np.arange(3)}, dense


def test_a_factor_that_is_not_postordered_is_refused():
    L, dense = unordered_factor()
    from conftest import dense_factor

    np.testing.assert_array_equal(dense_factor(L), dense)  # the arrays hold exactly this L
    with pytest.raises(ValueError, match="not postordered"):
        selinv.selected_inverse(L, np.array([0, 2]), np.ones(2))
    if native.available():
        with pytest.raises(ValueError, match="not postordered"):
            native.selected_inverse(L, np.array([0, 2]), np.ones(2))


@settings(max_examples=60, deadline=None)
@given(n=st.integers(4, 80), per_node=st.floats(0.0, 1.5), frac=st.floats(0.0, 1.0), k=st.integers(0, 30),
       seed=st.integers(0, 2**32 - 1))
def test_selected_columns_match_the_dense_inverse(n, per_node, frac, k, seed):
    """Eᵀ A⁻¹ B (rows of A⁻¹ times loads on element patches: the P2 Green's functions' shape) from both
    twins, against the dense inverse, for FE-like matrices of any connectivity (a forest when few
    elements), any wanted rows and any number of load columns."""
    rng = np.random.default_rng(seed)
    A, elements = element_spd(n, int(per_node * n), rng)
    if len(elements) == 0:
        elements = np.arange(n)[:, None]
    rows = rng.permutation(n)[:int(frac * n)]
    B = patch_loads(elements, n, k, rng)
    G = np.linalg.inv(A.toarray())
    expect = G[rows] @ B.toarray()
    scale = max(np.abs(G).max() * max(np.abs(B.toarray()).sum(axis=0).max(initial=0.0), 1.0), 1e-300)
    L = cvxopt_factor(A, rng)
    X, _ = selinv.selected_columns(L, rows, B)
    assert X.shape == (len(rows), k) and X.flags.c_contiguous
    assert np.abs(X - expect).max(initial=0.0) <= 2e-12 * scale
    if native.available():
        Ln, _ = native.factor(lower(A))  # CHOLMOD's METIS order, and its supernodes
        Xn, _ = native.selected_columns(Ln, rows, B)
        assert np.abs(Xn - expect).max(initial=0.0) <= 2e-12 * scale
        Xc, _ = native.selected_columns(L, rows, B)  # the C twin on the numpy twin's factor
        assert np.abs(Xc - X).max(initial=0.0) <= 1e-13 * scale


@pytest.mark.parametrize("k, which", [(22, "surface"), (22, "top"), (16, "all")])
def test_the_sweeps_memory_is_what_the_sweep_holds(k, which):
    """sweep_memory (the memory check's figure for the W sweep, from the tree alone) against the peak
    tracemalloc measures while forward_sweep runs (numpy's buffers are traced; BLAS's own workspace and
    Python's small objects are not in the model: 5 %, where 2 % was measured).  The cases: a cube's surface dofs (the
    contact vertices' shape), its top face only, and every dof."""
    A = laplacian_3d(k, 1)
    idx = np.arange(k ** 3).reshape(k, k, k)
    want = {"surface": np.unique(np.concatenate([idx[[0, -1]].ravel(), idx[:, [0, -1]].ravel(),
                                                 idx[:, :, [0, -1]].ravel()])),
            "top": idx[-1].ravel(), "all": idx.ravel()}[which]
    L = native.factor(lower(A))[0] if native.available() else cvxopt_factor(A)
    tree = selinv._Tree(L)
    model = selinv.sweep_memory(tree, want)
    _, peak = traced_peak(selinv.forward_sweep, tree, want, lambda s, lo, X: None)
    assert model["peak"] > 1e6  # a case where the blocks, not Python's bookkeeping, make the peak
    assert abs(peak - model["peak"]) <= 0.05 * model["peak"], (peak, model)


def test_selected_columns_hold_the_answer_twice_and_little_else():
    """The pure-Python selected_columns (the P2 route where the C twin is not built) on a cube's surface dofs,
    B their unit loads (so the answer is the surface's block of A⁻¹, checked against the C twin): W_E and W_B
    are held only from a supernode's first update to the end of its turn and the root's product goes into
    D in place, so the peak tracemalloc measures is D and the answer gathered from it (two answers' bytes:
    the gather by pivot order needs both) plus under 5 % for the live blocks and temporaries (measured
    1.0 %); allocating all of W_E and W_B up front, and the root's product and gathered copy, held 3.8
    answers' bytes here."""
    import scipy.sparse as sp

    k = 22
    A = laplacian_3d(k, 1)
    idx = np.arange(k ** 3).reshape(k, k, k)
    want = np.unique(np.concatenate([idx[[0, -1]].ravel(), idx[:, [0, -1]].ravel(), idx[:, :, [0, -1]].ravel()]))
    L = native.factor(lower(A))[0] if native.available() else cvxopt_factor(A)
    B = sp.identity(k ** 3, format="csc")[:, want]
    (X, _), peak = traced_peak(selinv.selected_columns, L, want, B)
    answer = X.nbytes
    assert answer > 5e7  # the blocks, not Python's bookkeeping, make the peak
    assert peak <= 2.05 * answer, (peak / answer)
    if native.available():
        Xc, _ = native.selected_columns(L, want, B)
        assert np.abs(X - Xc).max() <= 1e-13 * np.abs(Xc).max()
