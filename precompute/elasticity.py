"""Linear elasticity on tetrahedra with scikit-fem.

The stiffness matrix is assembled in scikit-fem's node-major dof order for
vector P1: dof ``3*v + c`` is component c of vertex v.
"""
from __future__ import annotations

import os

import numpy as np

from pmask.errors import InputError
import scipy.sparse as sp


def check_material(E: float, nu: float) -> None:
    """Refuse Young's moduli and Poisson ratios outside the physical range."""
    if not (np.isfinite(E) and E > 0):
        raise InputError(f"Young's modulus E must be a finite number > 0 Pa, got {E}")
    if not (np.isfinite(nu) and -1.0 < nu < 0.5):
        raise InputError(f"Poisson's ratio nu must lie in (-1, 0.5), got {nu}")


def stiffness_matrix(points: np.ndarray, tets: np.ndarray, E: float, nu: float) -> sp.csr_matrix:
    """Global stiffness K (3N x 3N) of isotropic linear elasticity, vector P1 tets.

    K u = f with u the nodal displacements and f the nodal forces.  P1 strains
    are constant per element, so one quadrature point integrates exactly.
    """
    from skfem import Basis, ElementTetP1, ElementVector, MeshTet, asm
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    check_material(E, nu)
    mesh = MeshTet(np.ascontiguousarray(points.T), np.ascontiguousarray(tets.T))
    basis = Basis(mesh, ElementVector(ElementTetP1()), intorder=1)
    form = linear_elasticity(*lame_parameters(E, nu))
    form.nthreads = min(2, os.cpu_count() or 1)  # the 144 local-matrix entries split over threads
    K = asm(form, basis).tocsr()
    K.sum_duplicates()
    return K


def rigid_body_modes(points: np.ndarray) -> np.ndarray:
    """The six rigid-body displacement fields (3N x 6): three translations, three rotations."""
    n = len(points)
    R = np.zeros((n, 3, 6))
    for c in range(3):
        R[:, c, c] = 1.0
    x, y, z = (points - points.mean(axis=0)).T
    R[:, 1, 3], R[:, 2, 3] = -z, y
    R[:, 0, 4], R[:, 2, 4] = z, -x
    R[:, 0, 5], R[:, 1, 5] = -y, x
    return R.reshape(3 * n, 6)


def dofs(vertices: np.ndarray) -> np.ndarray:
    """Node-major dof indices (3 per vertex) of the given vertices."""
    v = np.asarray(vertices, dtype=np.int64)
    return (3 * v[:, None] + np.arange(3)).ravel()
