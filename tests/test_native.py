"""The C route over CHOLMOD (precompute/native.py) against dense linear algebra on small matrices."""
import numpy as np
import pytest
import scipy.sparse as sp

from conftest import dense_factor, laplacian_3d, lower
from pmask.precompute import native

pytestmark = pytest.mark.skipif(not native.available(), reason="native CHOLMOD library not built")


def test_factor_arrays_are_the_cholesky_factor_in_metis_order():
    A = laplacian_3d(7, 0)
    L, stats = native.factor(lower(A))
    assert stats["order"] == "METIS" and stats["supernodes"] > 1
    assert not L["x"].flags.owndata  # CHOLMOD's own storage, no copy
    p = L["perm"]
    assert sorted(p) == list(range(A.shape[0])) and np.any(p != np.arange(A.shape[0]))
    Ld = dense_factor(L)
    Ap = A.toarray()[np.ix_(p, p)]
    assert np.abs(Ld @ Ld.T - Ap).max() < 1e-12 * np.abs(Ap).max()


@pytest.mark.parametrize("k, nw, seed", [(7, 60, 1), (6, 216, 2), (5, 1, 3), (6, 0, 4)])
def test_selected_inverse_matches_the_dense_inverse(k, nw, seed):
    """Any wanted set, in any order (here a random one; all dofs; one; none), any scaling."""
    A = laplacian_3d(k, seed)
    rng = np.random.default_rng(seed)
    want = rng.permutation(A.shape[0])[:nw]
    scale = rng.uniform(0.5, 2.0, nw)
    L, _ = native.factor(lower(A))
    X, st = native.selected_inverse(L, want, scale)
    G = np.linalg.inv(A.toarray())[np.ix_(want, want)]
    assert X.shape == (nw, nw) and X.flags.c_contiguous
    if nw:
        assert np.abs(X - G * scale[None, :]).max() < 1e-12 * np.abs(G).max() * scale.max()
        assert st["flops"] > 0
    # the same from arrays that went through a file (a checkpoint) instead of CHOLMOD's memory
    X2, _ = native.selected_inverse({k_: np.array(v) for k_, v in L.items()}, want, scale)
    assert np.array_equal(X, X2)


def test_selected_inverse_of_bodies_in_pieces():
    """Two decoupled bodies: the elimination tree is a forest, the inverse block-diagonal."""
    B1, B2 = laplacian_3d(5, 1), laplacian_3d(4, 2)
    A = sp.block_diag([B1, B2]).tocsc()
    n1 = B1.shape[0]
    want = np.r_[np.arange(0, n1, 3), np.arange(n1, A.shape[0], 2)]
    L, _ = native.factor(lower(A))
    X, _ = native.selected_inverse(L, want, np.ones(len(want)))
    G = np.linalg.inv(A.toarray())[np.ix_(want, want)]
    assert np.abs(X - G).max() < 1e-12 * np.abs(G).max()
    m1 = int(np.sum(want < n1))
    assert np.abs(X[:m1, m1:]).max() == 0.0  # nothing couples the bodies


def test_not_positive_definite_is_reported():
    A = laplacian_3d(4, 5).tolil()
    A[10, 10] = -5.0
    with pytest.raises(ArithmeticError):
        native.factor(lower(A.tocsc()))


def test_bad_wanted_dofs_are_refused():
    L, _ = native.factor(lower(laplacian_3d(4, 6)))
    with pytest.raises(ValueError, match="distinct"):
        native.selected_inverse(L, np.array([3, 5, 3]), np.ones(3))
    with pytest.raises(ValueError, match="distinct"):
        native.selected_inverse(L, np.array([0, 64]), np.ones(2))  # 64 dofs: 0..63
    with pytest.raises(ValueError, match="scale"):
        native.selected_inverse(L, np.array([0, 1]), np.ones(3))


def test_stale_library_is_refused(tmp_path, monkeypatch):
    """A library built from another version of the C source is not called (wrong signatures would
    crash); the precompute falls back to the pip-only route with a warning that says what to do."""
    import shutil
    import subprocess

    if shutil.which("gcc") is None:
        pytest.skip("no gcc")
    src = tmp_path / "old.c"
    src.write_text("int pmask_abi_version(void) { return 2; }\n")
    lib = tmp_path / "libold.so"
    subprocess.run(["gcc", "-shared", "-fPIC", str(src), "-o", str(lib)], check=True)
    monkeypatch.setattr(native, "LIBRARY", lib)
    native._lib.cache_clear()
    try:
        with pytest.warns(RuntimeWarning, match="make venv"):
            assert not native.available()
    finally:
        native._lib.cache_clear()
