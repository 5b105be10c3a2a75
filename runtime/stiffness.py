r"""Vertex stiffness (paper eq. 12, 14), surface stiffness (eq. 15) and deformation (eq. 13, 16).

Masked vertex stiffness of free vertex i:

.. math::  K_i = \Big(\sum_{j \in \mathcal{M}_i} \rho^i_j\, \Xi_{ij}\Big)^{-1}      \quad (12)

rigid vertices get :math:`K_j = k_{rigid} I` (14), and the surface stiffness
at a point x of triangle t with barycentric coordinates b is

.. math::  K(x) = \sum_k b_k K_{t_k}                                            \quad (15)

which is continuous across edges because neighbouring triangles share the
vertex values.  A contact force f at x deforms the surface by

.. math::  v = \sum_i \phi_i(x)\, \zeta_i f, \qquad
           \zeta_i = \sum_{j \in \mathcal{M}_i} \rho^i_j\, \xi_j              \quad (13, 16)

K_i is not symmetric in general; a non-symmetric stiffness is not passive (it
can pump energy into a haptic device), so the tables hold the symmetric part
:math:`(K_i + K_i^T)/2` unless ``symmetric=False`` is asked for.
"""
from __future__ import annotations

import numpy as np

from pmask.errors import InputError

from pmask.runtime.masks import Masks

#: tolerance on barycentric coordinates (negativity and sum) accepted by the query API
BARY_TOL = 1e-9
#: queries per piece in ``at_batch``: the gathered rows (27 floats each) stay in cache (measured:
#: 1 M random queries 7 -> 14 M/s on 500 vertices, 4 -> 7 M/s on 50,000)
BATCH_CHUNK = 32768


def masked_flexibility(Xi: np.ndarray, masks: Masks) -> np.ndarray:
    r"""(n, 3, 3) blocks :math:`\sum_j \rho^i_j \Xi_{ij}`, one per mask centre i."""
    n = Xi.shape[1] // 3
    X4 = Xi.reshape(Xi.shape[0] // 3, 3, n, 3)
    rows = masks.centres
    counts = np.diff(masks.indptr)
    i = np.repeat(rows, counts)
    blocks = X4[i, :, masks.indices, :] * masks.values[:, None, None]  # (pairs, 3, 3)
    out = np.zeros((len(rows), 3, 3))
    nz = counts > 0
    out[nz] = np.add.reduceat(blocks, masks.indptr[:-1][nz], axis=0)
    return out


def vertex_stiffness(Xi: np.ndarray, masks: Masks) -> np.ndarray:
    """K_i = (Σ_j ρ^i_j Ξ_ij)⁻¹ (eq. 12) for every mask centre i; (n, 3, 3)."""
    A = masked_flexibility(Xi, masks)
    return np.linalg.inv(A)


def asymmetry(K: np.ndarray) -> np.ndarray:
    """‖K − Kᵀ‖_F / ‖K‖_F per 3x3 block."""
    return np.linalg.norm(K - np.swapaxes(K, -1, -2), axis=(-2, -1)) / np.linalg.norm(K, axis=(-2, -1))


def _check_query(triangle, bary, n_triangles: int):
    try:
        t = int(triangle)
    except (TypeError, ValueError):
        raise InputError(f"triangle index must be an integer, got {triangle!r}") from None
    if t != triangle or not 0 <= t < n_triangles:
        raise InputError(f"triangle index {triangle!r} out of range [0, {n_triangles})")
    b = np.asarray(bary, dtype=float)
    if b.shape != (3,):
        raise InputError(f"barycentric coordinates must be 3 numbers, got shape {b.shape}")
    if not np.all(np.isfinite(b)):
        raise InputError(f"barycentric coordinates must be finite, got {b.tolist()}")
    if b.min() < -BARY_TOL or abs(b.sum() - 1.0) > BARY_TOL:
        raise InputError(f"barycentric coordinates must be >= 0 and sum to 1, got {b.tolist()} (sum {b.sum():.12g})")
    return t, b


class SurfaceStiffness:
    """The surface stiffness K(x) of eq. 15 over a triangle mesh, queried in O(1).

    Parameters
    ----------
    points, triangles : the surface.
    K_vertex : (n_s, 3, 3) vertex stiffness of every surface vertex (free: eq. 12, fixed: eq. 14).
    touchable : bool per triangle; a probe can be rendered only on touchable triangles (those whose
        free vertices all have complete masks).
    """

    def __init__(self, points, triangles, K_vertex, touchable=None):
        self.points = np.asarray(points, float)
        self.triangles = np.asarray(triangles, np.int64)
        self.K_vertex = np.asarray(K_vertex, float)
        if not np.all(np.isfinite(self.K_vertex)):
            raise InputError("vertex stiffness holds NaN or inf")
        self.touchable = np.ones(len(self.triangles), bool) if touchable is None else np.asarray(touchable, bool)
        # per-triangle table: (T, 3, 9), row k = K of the triangle's k-th vertex, flattened
        self.table = np.ascontiguousarray(self.K_vertex[self.triangles].reshape(len(self.triangles), 3, 9))

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)

    def at(self, triangle, bary) -> np.ndarray:
        """K(x) (3x3) at barycentric ``bary`` of ``triangle`` (eq. 15); validates its input."""
        t, b = _check_query(triangle, bary, self.n_triangles)
        if not self.touchable[t]:
            raise InputError(f"triangle {t} lies outside the precomputed contact region")
        return (b @ self.table[t]).reshape(3, 3)

    def at_batch(self, triangles, barys, *, validate: bool = True) -> np.ndarray:
        """K(x) for many points at once: (n, 3, 3)."""
        t = np.asarray(triangles)
        b = np.asarray(barys, dtype=float)
        if validate:
            if t.ndim != 1 or b.shape != (len(t), 3):
                raise InputError(f"need triangles (n,) and barycentrics (n, 3), got {t.shape} and {b.shape}")
            if not np.issubdtype(t.dtype, np.integer):
                raise InputError("triangle indices must be integers")
            if len(t) and (t.min() < 0 or t.max() >= self.n_triangles):
                raise InputError(f"triangle index out of range [0, {self.n_triangles})")
            if not np.all(np.isfinite(b)):
                raise InputError("barycentric coordinates must be finite")
            if len(t) and (b.min() < -BARY_TOL or np.abs(b.sum(axis=1) - 1).max() > BARY_TOL):
                raise InputError("barycentric coordinates must be >= 0 and sum to 1")
            if not np.all(self.touchable[t]):
                raise InputError("some triangles lie outside the precomputed contact region")
        out = np.empty((len(t), 9))
        for i in range(0, len(t), BATCH_CHUNK):  # gather + combine in cache-sized pieces
            np.einsum("nk,nkj->nj", b[i:i + BATCH_CHUNK], self.table[t[i:i + BATCH_CHUNK]],
                      out=out[i:i + BATCH_CHUNK])
        return out.reshape(-1, 3, 3)

    def force(self, triangle, bary, u_bar) -> np.ndarray:
        """Contact force f = K(x) ū for a displacement constraint ū at x (the force on the body)."""
        u = np.asarray(u_bar, dtype=float)
        if u.shape != (3,) or not np.all(np.isfinite(u)):
            raise InputError(f"displacement must be 3 finite numbers, got {u_bar!r}")
        return self.at(triangle, bary) @ u


class Stiffness(SurfaceStiffness):
    """Surface stiffness built from Green's functions and pressure masks, with deformation (eq. 16).

    Made by :meth:`pmask.runtime.Model.stiffness`; holds the masks and a reference to Ξ.
    """

    def __init__(self, model, masks: Masks, K_free: np.ndarray, k_rigid: float, symmetric: bool):
        self.model = model
        self.masks = masks
        self.k_rigid = float(k_rigid)
        self.symmetric = bool(symmetric)
        self.K_full = K_free  # unsymmetrised K_i of the core contact vertices (eq. 12)
        self.asymmetry = asymmetry(K_free)
        n_s = len(model.points)
        Kv = np.zeros((n_s, 3, 3))
        Kv[:] = self.k_rigid * np.eye(3)  # eq. 14 on fixed vertices (free ones overwritten below)
        K_render = 0.5 * (K_free + np.swapaxes(K_free, 1, 2)) if symmetric else K_free
        core_surface = model.contact[masks.centres]
        Kv[core_surface] = K_render
        vertex_ok = np.zeros(n_s, bool)
        vertex_ok[model.fixed] = True
        vertex_ok[core_surface] = True
        super().__init__(model.points, model.triangles, Kv, touchable=vertex_ok[model.triangles].all(axis=1))
        self._row_of_surface = np.full(n_s, -1)
        self._row_of_surface[core_surface] = np.arange(len(core_surface))

    @property
    def single_vertex_masks(self) -> int:
        """How many masks reached no neighbour (the single-vertex case for that vertex)."""
        return self.masks.single_vertex

    def zeta(self, vertex: int) -> np.ndarray:
        """ζ_i (eq. 13): (3 n_c, 3) displacement of the contact vertices per unit force at surface vertex i."""
        k = self._row_of_surface[vertex]
        if k < 0:
            return np.zeros((self.model.Xi.shape[0], 3))  # fixed vertex: rigid, no deformation
        cols, w = self.masks.row(k)
        X = self.model.Xi.reshape(self.model.Xi.shape[0], -1, 3)[:, cols, :]  # (3n_c, |M|, 3)
        return np.einsum("rmc,m->rc", X, w)

    def deformation(self, triangle, bary, force) -> np.ndarray:
        """Displacement (n_s, 3) of every surface vertex for contact force ``force`` at x (eq. 16).

        Vertices outside Ξ (fixed, or free but outside the contact region) report zero.
        """
        t, b = _check_query(triangle, bary, self.n_triangles)
        f = np.asarray(force, dtype=float)
        if f.shape != (3,) or not np.all(np.isfinite(f)):
            raise InputError(f"force must be 3 finite numbers, got {force!r}")
        if not self.touchable[t]:
            raise InputError(f"triangle {t} lies outside the precomputed contact region")
        v_contact = np.zeros(self.model.Xi.shape[0])
        for vertex, phi in zip(self.triangles[t], b):
            if phi != 0.0:
                v_contact += phi * (self.zeta(vertex) @ f)
        v = np.zeros((len(self.points), 3))
        v[self.model.contact] = v_contact.reshape(-1, 3)
        return v

    def report(self) -> dict:
        """Numbers a user should see: mask reach, asymmetry of K_i, stiffness range."""
        norms = np.linalg.norm(self.K_full, ord=2, axis=(1, 2))
        return {
            "mask": self.masks.kind, "radius": self.masks.radius,
            "vertices": len(self.masks.centres), "single_vertex_masks": self.single_vertex_masks,
            "mean_mask_size": float(np.mean(np.diff(self.masks.indptr))),
            "asymmetry_max": float(self.asymmetry.max()), "asymmetry_mean": float(self.asymmetry.mean()),
            "stiffness_norm_min": float(norms.min()), "stiffness_norm_median": float(np.median(norms)),
            "stiffness_norm_max": float(norms.max()), "k_rigid": self.k_rigid, "symmetric": self.symmetric,
        }
