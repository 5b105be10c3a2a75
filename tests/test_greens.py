"""Ξ against an independent solver; reciprocity on separate solves; equilibrium; rigid modes; patch test."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import full_solve, relerr
from precompute.elasticity import dofs, rigid_body_modes, stiffness_matrix
from runtime.artifact import read_artifact


def load_case(path):
    d = read_artifact(path)
    vi = d["surface/volume_index"]
    return d, vi


@pytest.fixture(scope="module", params=["kidney_small", "halfspace_small"])
def solved(request):
    """Artifact plus full-system solves for point loads at three sampled contact vertices."""
    path = request.getfixturevalue(request.param)
    d, vi = load_case(path)
    mat = d["attrs"]["material"]
    P, T = d["volume/points"], d["volume/tets"]
    contact = d["surface/contact"]
    rng = np.random.default_rng(7)
    cols = np.sort(rng.choice(len(contact), 3, replace=False))
    loads = np.zeros((3 * len(P), 9))
    a = d["surface/vertex_areas"]
    for k, c in enumerate(cols):
        v = vi[contact[c]]
        for comp in range(3):
            loads[3 * v + comp, 3 * k + comp] = a[contact[c]]  # unit traction -> nodal force a_j
    u, r = full_solve(P, T, mat["E"], mat["nu"], vi[d["surface/fixed"]], loads)
    return d, vi, cols, loads, u, r


def test_columns_match_full_solve(solved):
    d, vi, cols, _, u, _ = solved
    Xi = d["greens/Xi"]
    rows = dofs(vi[d["surface/contact"]])
    for k, c in enumerate(cols):
        assert relerr(Xi[:, 3 * c:3 * c + 3], u[rows, 3 * k:3 * k + 3]) < 1e-8


def test_reciprocity_on_separate_solves(solved):
    """a_i Ξ_ij = a_j Ξ_jiᵀ, with each side taken from a different full solve (not Ξ's mirror)."""
    d, vi, cols, _, u, _ = solved
    a = d["surface/vertex_areas"][d["surface/contact"]]
    cv = vi[d["surface/contact"]]
    for p in range(3):
        for q in range(p + 1, 3):
            i, j = cols[p], cols[q]
            Xi_ij = u[dofs([cv[i]])][:, 3 * q:3 * q + 3]  # displacement at i, load at j
            Xi_ji = u[dofs([cv[j]])][:, 3 * p:3 * p + 3]
            assert relerr(a[i] * Xi_ij, a[j] * Xi_ji.T) < 1e-9


def test_masked_load_matches_full_solve(solved):
    """Σ_j ρ_j Ξ_ij is the displacement under the traction ρ f (a cone around a vertex)."""
    d, vi, cols, _, _, _ = solved
    contact, a = d["surface/contact"], d["surface/vertex_areas"]
    x = d["surface/points"][contact]
    i = cols[0]
    r = 3.0 * np.median(np.linalg.norm(x - x[i], axis=1)[np.argsort(np.linalg.norm(x - x[i], axis=1))[1:4]])
    s = np.linalg.norm(x - x[i], axis=1)
    rho = np.clip(1 - s / r, 0, None)
    rho /= a[contact] @ rho
    assert np.count_nonzero(rho) > 1
    f = np.array([0.3, -1.0, 0.5])
    P, T = d["volume/points"], d["volume/tets"]
    load = np.zeros((3 * len(P), 1))
    for j in np.flatnonzero(rho):
        load[dofs([vi[contact[j]]]), 0] = a[contact[j]] * rho[j] * f
    mat = d["attrs"]["material"]
    u, _ = full_solve(P, T, mat["E"], mat["nu"], vi[d["surface/fixed"]], load)
    Xi = d["greens/Xi"]
    v = sum(rho[j] * Xi[:, 3 * j:3 * j + 3] @ f for j in np.flatnonzero(rho))
    assert relerr(v, u[dofs(vi[contact]), 0]) < 1e-8


def test_equilibrium_of_forces_and_moments(solved):
    """Applied load and its moment equal minus those of the stored support reactions."""
    d, vi, cols, _, _, r_full = solved
    a = d["surface/vertex_areas"]
    contact, fixed = d["surface/contact"], d["surface/fixed"]
    xs = d["surface/points"]
    R = d["greens/reactions"]
    for k, c in enumerate(cols):
        for comp in range(3):
            load = np.zeros(3)
            load[comp] = a[contact[c]]
            react = R[:, 3 * c + comp].reshape(-1, 3)
            scale = np.abs(load).sum()
            np.testing.assert_allclose(react.sum(axis=0), -load, atol=1e-9 * scale)
            moment = np.cross(xs[contact[c]], load) + np.cross(xs[fixed], react).sum(axis=0)
            assert np.linalg.norm(moment) < 1e-9 * scale * np.linalg.norm(xs, axis=1).max()
            # and they are the reactions the independent solve finds
            assert relerr(react.ravel(), r_full[dofs(vi[fixed]), 3 * k + comp]) < 1e-8


def test_stiffness_annihilates_rigid_modes(kidney_small):
    d = read_artifact(kidney_small)
    P, T = d["volume/points"], d["volume/tets"]
    K = stiffness_matrix(P, T, 1e4, 0.45)
    R = rigid_body_modes(P)
    scale = abs(K).max() * np.abs(R).max()
    assert np.abs(K @ R).max() < 1e-10 * scale
    # and it is not trivially zero: a non-rigid field has energy
    x = P[:, 0] ** 2
    assert (K @ np.repeat(x, 3)) @ np.repeat(x, 3) > 0


def test_patch_test_linear_field_reproduced(kidney_small):
    """A linear displacement prescribed on the whole boundary is reproduced exactly inside."""
    import scipy.sparse.linalg as spla

    d = read_artifact(kidney_small)
    P, T = d["volume/points"], d["volume/tets"]
    K = stiffness_matrix(P, T, 1e4, 0.45).tocsr()
    A = np.array([[1e-3, 2e-3, -1e-3], [0.5e-3, -2e-3, 1e-3], [3e-3, 1e-3, 2e-3]])
    exact = (P @ A.T + np.array([1e-4, -2e-4, 3e-4])).ravel()
    B = dofs(d["surface/volume_index"])
    inner = np.setdiff1d(np.arange(len(P)), d["surface/volume_index"])
    assert len(inner) > 10
    Id = dofs(inner)
    u_inner = spla.spsolve(K[Id][:, Id].tocsc(), -K[Id][:, B] @ exact[B])
    assert relerr(u_inner, exact[Id]) < 1e-9


def test_cholmod_backends_agree(kidney_small):
    """scikit-sparse (system SuiteSparse) and cvxopt (bundled CHOLMOD) give the same surface factor."""
    pytest.importorskip("sksparse.cholmod")
    from precompute.condense import surface_factor

    d = read_artifact(kidney_small)
    P, T, vi = d["volume/points"], d["volume/tets"], d["surface/volume_index"]
    K = stiffness_matrix(P, T, 1e4, 0.45)
    free, fixed = vi[d["surface/contact"]], vi[d["surface/fixed"]]
    interior = np.setdiff1d(np.arange(len(P)), np.concatenate([free, fixed]))
    a = surface_factor(K, T, interior, free, fixed, backend="sksparse")
    b = surface_factor(K, T, interior, free, fixed, backend="cvxopt")
    assert a.stats["backend"] == "sksparse" and b.stats["backend"] == "cvxopt"
    assert relerr(a.L_FF, b.L_FF) < 1e-12 and relerr(a.L_UF, b.L_UF) < 1e-12
