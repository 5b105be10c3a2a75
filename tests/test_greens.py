"""Ξ against an independent solver; reciprocity on separate solves; equilibrium; rigid modes; patch test."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import FullSystem, relerr, spd_lu
from pmask.precompute.elasticity import dofs, rigid_body_modes, stiffness_matrix
from pmask.runtime.artifact import read_artifact


def load_case(path):
    d = read_artifact(path)
    vi = d["surface/volume_index"]
    return d, vi


@pytest.fixture(scope="module", params=["kidney_small", "halfspace_small"])
def solved(request):
    """Artifact (the kidney P2, the half-space P1, as --element auto makes them) plus independent full-system
    solves (conftest.FullSystem) for unit tractions at three sampled contact vertices: u at the volume vertices
    (N, 3, 9) and the support reactions per fixed vertex (n_fixed, 3, 9)."""
    path = request.getfixturevalue(request.param)
    d, vi = load_case(path)
    contact = d["surface/contact"]
    rng = np.random.default_rng(7)
    cols = np.sort(rng.choice(len(contact), 3, replace=False))
    tractions = np.zeros((len(d["surface/points"]), 3, 9))
    for k, c in enumerate(cols):
        for comp in range(3):
            tractions[contact[c], comp, 3 * k + comp] = 1.0  # a unit traction p_j (the paper's hat)
    system = FullSystem(path)
    u, r = system.solve(tractions)
    return d, vi, cols, system, u, r


def test_columns_match_full_solve(solved):
    d, vi, cols, _, u, _ = solved
    Xi = d["greens/Xi"]
    U = u[vi[d["surface/contact"]]]  # (n_c, 3, 9)
    for k, c in enumerate(cols):
        assert relerr(Xi[:, 3 * c:3 * c + 3], U[:, :, 3 * k:3 * k + 3].reshape(-1, 3)) < 1e-8


def test_reciprocity_on_separate_solves(solved):
    """a_i Ξ_ij = a_j Ξ_jiᵀ, with each side taken from a different full solve (not Ξ's mirror).  (For P2 the
    reciprocal pair is the consistent load's: B_jᵀ u_i = B_iᵀ u_j, with B the load of the unit hat tractions;
    with the lumped load of P1 that is a_i Ξ_ij = a_j Ξ_jiᵀ.)"""
    d, vi, cols, system, u, _ = solved
    contact = d["surface/contact"]
    n_s = len(d["surface/points"])
    U = u.reshape(-1, 9)  # volume-vertex dofs only: the loads' work needs every node for P2
    for p in range(3):
        for q in range(p + 1, 3):
            i, j = cols[p], cols[q]
            ti, tj = np.zeros((n_s, 3, 3)), np.zeros((n_s, 3, 3))
            ti[contact[i]] = np.eye(3)
            tj[contact[j]] = np.eye(3)
            fi, fj = system.loads(ti), system.loads(tj)
            ui = np.zeros((system.n, 3))
            uj = np.zeros((system.n, 3))
            ui[system.free] = system.lu.solve(fi[system.free])
            uj[system.free] = system.lu.solve(fj[system.free])
            assert relerr(fj.T @ ui, (fi.T @ uj).T) < 1e-9
            if system.B is None:  # P1: the same statement on Ξ's blocks, as the docs state it
                a = d["surface/vertex_areas"][contact]
                Xi_ij = U[3 * vi[contact[i]]:3 * vi[contact[i]] + 3, 3 * q:3 * q + 3]
                Xi_ji = U[3 * vi[contact[j]]:3 * vi[contact[j]] + 3, 3 * p:3 * p + 3]
                assert relerr(a[i] * Xi_ij, a[j] * Xi_ji.T) < 1e-9


def test_masked_load_matches_full_solve(solved):
    """Σ_j ρ_j Ξ_ij is the displacement under the traction ρ f (a cone around a vertex)."""
    d, vi, cols, system, _, _ = solved
    contact, a = d["surface/contact"], d["surface/vertex_areas"]
    x = d["surface/points"][contact]
    i = cols[0]
    r = 3.0 * np.median(np.linalg.norm(x - x[i], axis=1)[np.argsort(np.linalg.norm(x - x[i], axis=1))[1:4]])
    s = np.linalg.norm(x - x[i], axis=1)
    rho = np.clip(1 - s / r, 0, None)
    rho /= a[contact] @ rho
    assert np.count_nonzero(rho) > 1
    f = np.array([0.3, -1.0, 0.5])
    tractions = np.zeros((len(d["surface/points"]), 3, 1))
    tractions[contact, :, 0] = rho[:, None] * f
    u, _ = system.solve(tractions)
    Xi = d["greens/Xi"]
    v = sum(rho[j] * Xi[:, 3 * j:3 * j + 3] @ f for j in np.flatnonzero(rho))
    assert relerr(v, u[vi[contact], :, 0].ravel()) < 1e-8


def test_equilibrium_of_forces_and_moments(solved):
    """The stored support reactions balance the applied load's force and moment, and are the reactions the
    independent solve finds (P2's edge-node reactions split half to each end in both)."""
    d, vi, cols, system, _, r_full = solved
    contact, fixed = d["surface/contact"], d["surface/fixed"]
    xs = d["surface/points"]
    R = d["greens/reactions"]
    n_s = len(xs)
    for k, c in enumerate(cols):
        for comp in range(3):
            t = np.zeros((n_s, 3, 1))
            t[contact[c], comp, 0] = 1.0
            f = system.loads(t)[:, 0]
            nodes = np.vstack([d["volume/points"], d["volume/points"][system.edges].mean(axis=1)]) \
                if system.B is not None else d["volume/points"]
            F = f.reshape(-1, 3)
            load, load_moment = F.sum(axis=0), np.cross(nodes, F).sum(axis=0)
            react = R[:, 3 * c + comp].reshape(-1, 3)
            scale = np.abs(F).sum()
            np.testing.assert_allclose(react.sum(axis=0), -load, atol=1e-9 * scale)
            moment = load_moment + np.cross(xs[fixed], react).sum(axis=0)
            assert np.linalg.norm(moment) < 1e-9 * scale * np.linalg.norm(xs, axis=1).max()
            assert relerr(react.ravel(), r_full[:, :, 3 * k + comp].ravel()) < 1e-8


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


def test_cholmod_backends_agree(kidney_small_p1):
    """The native backend (CHOLMOD with METIS, the inverse in C) and the pip-only one (cvxopt's
    CHOLMOD with AMD, the inverse in numpy) factorise in different orders: they give the same Ξ and
    reactions to rounding, and so do the two inverses on the same factor."""
    from pmask.precompute import native
    from pmask.precompute.greens import factorise, greens_functions

    if not native.available():
        pytest.skip("native CHOLMOD library not built (needs libsuitesparse-dev)")

    d = read_artifact(kidney_small_p1)
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
    lu = spd_lu(K[free][:, free])
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
