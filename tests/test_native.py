"""The C route over CHOLMOD (precompute/native.py) against dense linear algebra on small matrices."""
import numpy as np
import pytest
import scipy.sparse as sp

from precompute import native

pytestmark = pytest.mark.skipif(not native.available(), reason="native CHOLMOD library not built")


def laplacian_3d(k: int, seed: int) -> sp.csc_matrix:
    """SPD: a k^3 grid Laplacian plus a random positive diagonal."""
    one = sp.diags([-np.ones(k - 1), 2 * np.ones(k), -np.ones(k - 1)], [-1, 0, 1])
    eye = sp.identity(k)
    L = (sp.kron(sp.kron(one, eye), eye) + sp.kron(sp.kron(eye, one), eye) + sp.kron(sp.kron(eye, eye), one))
    return (L + sp.diags(np.random.default_rng(seed).uniform(0.1, 1.0, k ** 3))).tocsc()


def schur(A: np.ndarray, nt: int) -> np.ndarray:
    n = A.shape[0]
    I, T = slice(0, n - nt), slice(n - nt, n)
    return A[T, T] - A[T, I] @ np.linalg.solve(A[I, I], A[I, T])


def lower(A) -> sp.csc_matrix:
    low = sp.tril(A, format="csc")
    low.sort_indices()
    return low


@pytest.mark.parametrize("reorder", [True, False])
def test_trailing_block_is_the_cholesky_factor_of_the_schur_complement(reorder):
    A = laplacian_3d(7, 0)
    nt = 60  # the last 60 grid points: a slab, coupled through the interior into one dense block
    L_TT, stats = native.factor(lower(A), nt, reorder=reorder)
    assert stats["interior_order"] == ("METIS" if reorder else "given")
    assert stats["in_place"] and not L_TT.flags.owndata  # CHOLMOD's own storage, no copy
    expect = np.linalg.cholesky(schur(A.toarray(), nt))
    assert np.abs(np.tril(L_TT) - expect).max() < 1e-12 * np.abs(expect).max()
    assert stats["stored_L"] > 0


def test_disconnected_trailing_block_is_copied():
    """Two decoupled bodies: the trailing columns span several supernodes and are gathered."""
    B1, B2 = laplacian_3d(5, 1), laplacian_3d(4, 2)
    n1, n2, t1, t2 = B1.shape[0], B2.shape[0], 20, 15
    # order: interior of 1, interior of 2, trailing of 1, trailing of 2
    A = sp.block_diag([B1, B2]).tocsc()
    perm = np.r_[0:n1 - t1, n1:n1 + n2 - t2, n1 - t1:n1, n1 + n2 - t2:n1 + n2]
    Ap = A[perm][:, perm].tocsc()
    L_TT, stats = native.factor(lower(Ap), t1 + t2)
    assert not stats["in_place"]
    expect = np.linalg.cholesky(schur(Ap.toarray(), t1 + t2))
    assert np.abs(np.tril(L_TT) - expect).max() < 1e-12 * np.abs(expect).max()
    assert np.abs(L_TT[t1:, :t1]).max() == 0.0  # no coupling between the bodies


def test_greens_in_place_matches_dense_inverse():
    A = laplacian_3d(7, 3)
    nf, nu = 45, 15
    L_TT, _ = native.factor(lower(A), nf + nu)
    a = np.random.default_rng(4).uniform(0.5, 2.0, nf)
    Xi, R, _, info = native.greens(L_TT, nf, a)
    assert info == 0
    S = schur(A.toarray(), nf + nu)
    G = np.linalg.inv(S[:nf, :nf])
    assert np.abs(Xi - G * a[None, :]).max() < 1e-12 * np.abs(G).max() * a.max()
    assert np.abs(R - S[nf:, :nf] @ G * a[None, :]).max() < 1e-11 * np.abs(R).max()
    # reciprocity a_i Xi_ij = a_j Xi_ji holds to rounding: the mirror copies, the scaling differs
    assert np.abs(a[:, None] * Xi - (a[:, None] * Xi).T).max() < 1e-14 * np.abs(a[:, None] * Xi).max()


def test_not_positive_definite_is_reported():
    A = laplacian_3d(4, 5).tolil()
    A[10, 10] = -5.0
    with pytest.raises(ArithmeticError):
        native.factor(lower(A.tocsc()), 8)


def test_bad_block_is_refused():
    with pytest.raises(ValueError, match="column-major"):
        native.greens(np.zeros((6, 6)), 3, np.ones(3))  # C order


def test_stale_library_is_refused(tmp_path, monkeypatch):
    """A library built from another version of the C source is not called (wrong signatures would
    crash); the precompute falls back to the pip-only route with a warning that says what to do."""
    import shutil
    import subprocess

    if shutil.which("gcc") is None:
        pytest.skip("no gcc")
    src = tmp_path / "old.c"
    src.write_text("int pmask_abi_version(void) { return 1; }\n")
    lib = tmp_path / "libold.so"
    subprocess.run(["gcc", "-shared", "-fPIC", str(src), "-o", str(lib)], check=True)
    monkeypatch.setattr(native, "LIBRARY", lib)
    native._lib.cache_clear()
    try:
        with pytest.warns(RuntimeWarning, match="make venv"):
            assert not native.available()
    finally:
        native._lib.cache_clear()
