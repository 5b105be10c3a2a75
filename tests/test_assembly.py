"""The elasticity assembly (pmask.precompute.assembly) against scikit-fem's, the independent route: P1 and P2,
one material and a material per element, to round-off; and the invariants every stiffness matrix of a free
body has (symmetry, the six rigid-body modes in its null space, positive energy otherwise)."""
from __future__ import annotations

import numpy as np
import pytest

from pmask.precompute import assembly
from pmask.precompute.elasticity import rigid_body_modes
from pmask.precompute.elements import P2


def skfem_matrix(points, tets, E, nu, order):
    """scikit-fem: ElementVector(ElementTetP1/P2), 2μ ε:ε at order 2 and λ div div at the centroid (P2) or both at
    order 1 (P1), the Lamé parameters as a P0 field (one value per element)."""
    from skfem import Basis, BilinearForm, ElementTetP0, ElementTetP1, ElementTetP2, ElementVector, MeshTet, asm
    from skfem.helpers import ddot, div, sym_grad

    mesh = MeshTet(np.ascontiguousarray(points.T), np.ascontiguousarray(tets.T))
    lam, mu = assembly.lame(np.broadcast_to(E, (len(tets),)), np.broadcast_to(nu, (len(tets),)))
    el = ElementVector(ElementTetP2() if order == 2 else ElementTetP1())
    full, centroid = Basis(mesh, el, intorder=2 if order == 2 else 1), Basis(mesh, el, intorder=1)
    p0 = Basis(mesh, ElementTetP0(), intorder=2 if order == 2 else 1)
    p0c = Basis(mesh, ElementTetP0(), intorder=1)

    @BilinearForm
    def dev(u, v, w):
        return 2.0 * w["mu"] * ddot(sym_grad(u), sym_grad(v))

    @BilinearForm
    def vol(u, v, w):
        return w["lam"] * div(u) * div(v)

    return (asm(dev, full, mu=p0.interpolate(mu)) + asm(vol, centroid, lam=p0c.interpolate(lam))).tocsr()


@pytest.fixture(scope="module")
def small():
    from pmask.meshes.kidney import build

    m = build(size=0.012)
    return m.points, m.tets


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("material", ["uniform", "per element"])
def test_the_assembly_is_scikit_fems_to_round_off(small, order, material):
    points, tets = small
    rng = np.random.default_rng(order)
    E, nu = (1e4, 0.45) if material == "uniform" else (rng.uniform(2e3, 5e4, len(tets)), rng.uniform(0.2, 0.49, len(tets)))
    d = P2().discretise(points, tets)
    ours = assembly.stiffness(points, tets, E, nu, order=order, edges=d.edges if order == 2 else None,
                              n_nodes=d.n_nodes if order == 2 else len(points))
    ref = skfem_matrix(points, tets, E, nu, order)
    assert abs(ours - ref).max() <= 1e-13 * abs(ref).max()  # the same sums in another order: round-off


@pytest.mark.parametrize("order", [1, 2])
def test_rigid_body_modes_are_the_null_space(small, order):
    """Symmetric; K R = 0 for the six rigid-body modes (P2: the edge nodes move with the body too); every other
    displacement stores energy (the seventh eigenvalue is positive)."""
    points, tets = small
    d = P2().discretise(points, tets)
    nodes = d.points if order == 1 else np.vstack([d.points, d.points[d.edges].mean(axis=1)])
    K = assembly.stiffness(points, tets, 1e4, 0.45, order=order, edges=d.edges if order == 2 else None,
                           n_nodes=len(nodes))
    assert abs(K - K.T).max() <= 1e-14 * abs(K).max()
    R = rigid_body_modes(nodes)
    assert np.abs(K @ R).max() <= 1e-10 * abs(K).max() * np.abs(R).max()
    import scipy.sparse.linalg as spla

    # a fixed start vector and a wider Krylov space: ARPACK's random start once missed one of the six zero
    # eigenvalues (a degenerate cluster) and returned the seventh in its place
    v0 = np.random.default_rng(0).standard_normal(K.shape[0])
    low = spla.eigsh(K, k=7, sigma=-1e-3 * abs(K).max(), which="LM", return_eigenvectors=False, v0=v0, ncv=40)
    low = np.sort(low)
    assert np.all(np.abs(low[:6]) <= 1e-9 * abs(K).max()) and low[6] > 1e-6 * abs(K).max()
