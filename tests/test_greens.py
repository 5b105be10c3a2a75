"""Ξ against an independent solver; reciprocity on separate solves; equilibrium; rigid modes; patch test."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import full_solve, relerr
from pmask.precompute.elasticity import dofs, rigid_body_modes, stiffness_matrix
from pmask.runtime.artifact import read_artifact


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
    """The native backend (CHOLMOD with METIS, the inverse in C) and the pip-only one (cvxopt's
    CHOLMOD with AMD, the inverse in numpy) factorise in different orders: they give the same Ξ and
    reactions to rounding, and so do the two inverses on the same factor."""
    from pmask.precompute import native
    from pmask.precompute.greens import factorise, greens_functions

    if not native.available():
        pytest.skip("native CHOLMOD library not built (needs libsuitesparse-dev)")

    d = read_artifact(kidney_small)
    P, T, vi = d["volume/points"], d["volume/tets"], d["surface/volume_index"]
    K = stiffness_matrix(P, T, d["attrs"]["material"]["E"], d["attrs"]["material"]["nu"])
    contact, fixed = vi[d["surface/contact"]], vi[d["surface/fixed"]]
    scale = np.repeat(d["surface/vertex_areas"][d["surface/contact"]], 3)
    a = factorise(K, dofs(fixed), dofs(contact), scale=scale, graph_elements=T, backend="native")
    b = factorise(K, dofs(fixed), dofs(contact), scale=scale, graph_elements=T, backend="cvxopt")
    assert (a.stats["backend"], a.stats["order"]) == ("native", "METIS")
    assert (b.stats["backend"], b.stats["order"]) == ("cvxopt", "AMD (node graph)")
    Xa, Ra = greens_functions(a, backend="native")
    Xb, Rb = greens_functions(b, backend="cvxopt")
    assert relerr(Xa, Xb) < 1e-12 and relerr(Ra, Rb) < 1e-12
    assert relerr(Xa, d["greens/Xi"]) < 1e-12
    Xc, Rc = greens_functions(b, backend="native")
    assert relerr(Xc, Xb) < 1e-13 and relerr(Rc, Rb) < 1e-13


@pytest.fixture(scope="module")
def halfspace_p2(tmp_path_factory):
    from pmask.pipeline.stages import Spec, run

    out = tmp_path_factory.mktemp("p2") / "hs_p2.h5"
    run(Spec(model="halfspace", params={"h_load": 0.0025, "far": 10.0}, element="P2", reactions=True), out)
    return out


def test_p2_load_matrix_against_scikit_fem_facet_assembly(halfspace_p2):
    """B_kj = ∫ ψ_k φ_j dΓ (P2 test functions ψ, the paper's P1 traction space φ) from our closed-form
    triangle formula, against scikit-fem's mixed P1 x P2 mass matrix on the boundary facets (Gauss
    quadrature of order 4, exact for these quadratic-times-linear products)."""
    from skfem import BilinearForm, ElementTetP1, ElementTetP2, FacetBasis, MeshTet, asm

    from pmask.precompute.elements import surface_load_matrix
    from pmask.precompute.surface import boundary_surface

    d = read_artifact(halfspace_p2)
    P, T = d["volume/points"], d["volume/tets"]
    mesh = MeshTet(P.T, T.T)
    sv, tris = boundary_surface(P, T)
    B = surface_load_matrix(P, sv[tris], np.sort(mesh.edges.T, axis=1))

    @BilinearForm
    def mass(u, v, w):
        return u * v

    ref = asm(mass, FacetBasis(mesh, ElementTetP1(), intorder=4), FacetBasis(mesh, ElementTetP2(), intorder=4))
    assert B.shape == ref.shape
    assert abs(B - ref).max() <= 1e-12 * abs(ref).max()
    assert d["attrs"]["element"] == "P2"


@pytest.mark.slow
def test_p2_columns_and_equilibrium_against_full_solve(halfspace_p2):
    """P2 Ξ columns equal a SuperLU solve of the whole free P2 system, with stiffness and load both
    assembled by scikit-fem here: 2μ ε:ε with the order-2 rule plus λ div u div v with the centroid rule
    (the P2-P0 element), and the P1-traction-to-P2 load as a mixed facet mass matrix; reactions balance
    the load."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla
    from skfem import (Basis, BilinearForm, ElementTetP1, ElementTetP2, ElementVector, FacetBasis, MeshTet,
                       asm)
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    d = read_artifact(halfspace_p2)
    P, T, vi = d["volume/points"], d["volume/tets"], d["surface/volume_index"]
    mat = d["attrs"]["material"]
    mesh = MeshTet(P.T, T.T)
    lam, mu = lame_parameters(mat["E"], mat["nu"])

    @BilinearForm
    def mass(u, v, w):
        return u * v

    @BilinearForm
    def volumetric(u, v, w):
        return lam * (u.grad[0][0] + u.grad[1][1] + u.grad[2][2]) * (v.grad[0][0] + v.grad[1][1] + v.grad[2][2])

    vector = ElementVector(ElementTetP2())
    K = (asm(linear_elasticity(0.0, mu), Basis(mesh, vector, intorder=2))
         + asm(volumetric, Basis(mesh, vector, intorder=1))).tocsr()
    edges = np.sort(mesh.edges.T, axis=1)

    B = asm(mass, FacetBasis(mesh, ElementTetP1(), intorder=4), FacetBasis(mesh, ElementTetP2(), intorder=4)).tocsr()
    fixed = vi[d["surface/fixed"]]
    is_f = np.zeros(len(P), bool)
    is_f[fixed] = True
    fe = np.flatnonzero(is_f[edges[:, 0]] & is_f[edges[:, 1]])
    dd = dofs(np.concatenate([fixed, len(P) + fe]))
    free = np.setdiff1d(np.arange(K.shape[0]), dd)
    lu = spla.splu(K[free][:, free].tocsc())
    contact = vi[d["surface/contact"]]
    j = 0
    load = sp.kron(B[:, contact[j:j + 1]], sp.identity(3)).toarray()
    u = np.zeros((K.shape[0], 3))
    u[free] = lu.solve(load[free])
    Xi = d["greens/Xi"]
    assert relerr(Xi[:, 3 * j:3 * j + 3], u[dofs(contact)]) < 1e-8
    a_j = d["surface/vertex_areas"][d["surface/contact"][j]]
    R = d["greens/reactions"][:, 3 * j:3 * j + 3].reshape(-1, 3, 3)  # (vertex, component, load direction)
    np.testing.assert_allclose(R.sum(axis=0), -a_j * np.eye(3), atol=1e-9 * a_j)


def test_pip_only_route_gives_the_same_artifact(halfspace_small, tmp_path, monkeypatch):
    """PMASK_CHOLMOD=cvxopt runs the whole pip-only route (cvxopt's CHOLMOD, SciPy's LAPACK on
    copies), as on a machine without SuiteSparse: same Ξ and reactions as the default route, on a
    model whose Ξ covers only part of the free surface."""
    from pmask.pipeline.stages import Spec, run

    monkeypatch.setenv("PMASK_CHOLMOD", "cvxopt")
    out = tmp_path / "hs_cvxopt.h5"
    run(Spec(model="halfspace", params={"h_load": 0.0025, "far": 10.0}, reactions=True), out)
    a, b = read_artifact(halfspace_small), read_artifact(out)
    assert b["attrs"]["provenance"]["factor"]["backend"] == "cvxopt"
    assert relerr(b["greens/Xi"], a["greens/Xi"]) < 1e-12
    assert relerr(b["greens/reactions"], a["greens/reactions"]) < 1e-12
