r"""Ξ's columns without a sparse factor: smoothed-aggregation AMG and preconditioned CG (pyamg).

Where even the sparse factor of K_FF does not fit (its fill grows like n^{4/3} in 3-D; 1.5 GiB at 100k
volume vertices), the columns of Ξ a tile needs, :math:`\Xi_{:,J} = E^T K_{FF}^{-1} B_J`, can come from
iterative solves: memory is K_FF and a multigrid hierarchy, a few times K_FF's own size.

* Preconditioner: smoothed aggregation (Vaněk, Mandel & Brezina 1996; ``pyamg.smoothed_aggregation_solver``)
  with the six rigid-body modes of the free nodes as the near-null space, the modes an elasticity
  operator barely penalises and that plain aggregation would otherwise have to discover.
* Solver: conjugate gradients on a block of right-hand sides at once: one sparse product with the
  block per step (K_FF read once for all columns), the V-cycle applied per column, and each column's
  own step lengths (the columns converge independently; finished ones drop out).
* Accuracy: stopped at a relative residual :data:`RTOL`; measured on the kidney (508–3,882 contact
  vertices), a 64-column panel agrees with the factor's to 3–4e-12 relative, in 24–26 steps.
* Cost (``make bench``): 90–250x the factor's per-panel solve (the V-cycle runs per column in Python),
  for 1.0x / 1.7x / 3.0x less memory than the factor at 1.9k / 7.1k / 26k dofs (the factor's fill grows
  like dof^{4/3}, the hierarchy like dof).  So the factor wins wherever it fits; this route is for where
  it does not, and is not the default.

:class:`AmgSystem` stands in for the factor in :func:`pmask.precompute.compress.tile`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from pmask.errors import ResourceError

#: relative residual at which a column's CG stops
RTOL = 1e-10
#: load columns block CG solves at once: its working set is PCG_ARRAYS arrays of n x PCG_COLUMNS doubles (a whole
#: 512-vertex panel at once, 1,536 columns, held ~0.8 GB per worker at 7,128 dofs, which no model counted)
PCG_COLUMNS = 64
#: block CG's peak working set in n x k arrays (B, X, R, Z, P, A·P, the fancy-indexed temporaries and the
#: preconditioned columns' list): tracemalloc measured about 10.5 at 1,914, 7,128 and 26,304 dofs (k = 64)
PCG_ARRAYS = 12
#: CG steps before a column is declared not converging
MAXITER = 2000


def rigid_body_modes(points: np.ndarray, free_dofs: np.ndarray) -> np.ndarray:
    """(len(free_dofs), 6): three translations and three rotations about the centroid, on the free dofs
    (dof = 3·node + component), columns scaled to unit norm."""
    node, comp = free_dofs // 3, free_dofs % 3
    x = points[node] - points[node].mean(axis=0)
    B = np.zeros((len(free_dofs), 6))
    for c in range(3):
        B[comp == c, c] = 1.0
    # rotation about axis a: u = e_a × x; component c of e_a × x
    for a, (i, j) in enumerate(((1, 2), (2, 0), (0, 1))):  # ω_x: (0, -z, y), ω_y: (z, 0, -x), ω_z: (-y, x, 0)
        B[comp == i, 3 + a] = -x[comp == i, j]
        B[comp == j, 3 + a] = x[comp == j, i]
    return B / np.linalg.norm(B, axis=0)


@dataclass
class AmgSystem:
    """K_FF, where Ξ reads (``rows``: the observed dofs among the free ones, in contact-dof order) and the
    load (P1: ``scale`` per observed dof; P2: ``load`` columns), with the AMG hierarchy built on first use
    (on the worker that solves, not shipped)."""

    K: sp.csr_matrix
    rows: np.ndarray
    n_observed: int
    near_null: np.ndarray
    scale: np.ndarray | None = None
    load: sp.csc_matrix | None = None
    stats: dict = field(default_factory=dict)
    _ml: object = field(default=None, repr=False, compare=False)

    def __getstate__(self):
        return {k: v for k, v in self.__dict__.items() if k != "_ml"} | {"_ml": None}

    def hierarchy(self):
        if self._ml is None:
            import pyamg

            t0 = time.perf_counter()
            # the coarse level by sparse LU: the default pseudo-inverse of a 2,874-unknown coarse level (six
            # near-null vectors per aggregate) held 63 MiB and peaked at 442 MiB in its SVD on the first solve at
            # 26,304 dofs; LU holds 6 MiB, in the same time and CG steps (by hand)
            self._ml = pyamg.smoothed_aggregation_solver(self.K, B=self.near_null, max_coarse=500,
                                                         coarse_solver="splu")
            self.stats["setup_s"] = time.perf_counter() - t0
        return self._ml

    def nbytes(self) -> int:
        """Bytes of K_FF and the hierarchy (its operators, prolongators and near-null spaces)."""
        ml = self.hierarchy()
        total = 0
        for lvl in ml.levels:
            for name in ("A", "P", "R", "B"):
                m = getattr(lvl, name, None)
                if m is None:
                    continue
                total += (m.data.nbytes + m.indices.nbytes + m.indptr.nbytes) if sp.issparse(m) else np.asarray(m).nbytes
        return int(total)

    def columns(self, dof_columns: np.ndarray) -> np.ndarray:
        """Ξ's columns for the observed dofs ``dof_columns`` ((n_observed, k), rows in contact-dof order),
        solved :data:`PCG_COLUMNS` at a time (:meth:`solve_bytes`)."""
        n = self.K.shape[0]
        dof_columns = np.asarray(dof_columns)
        out = np.empty((self.n_observed, len(dof_columns)))
        M = self.hierarchy().aspreconditioner(cycle="V")
        for c0 in range(0, len(dof_columns), PCG_COLUMNS):
            cols = dof_columns[c0:c0 + PCG_COLUMNS]
            if self.load is None:
                B = np.zeros((n, len(cols)))
                B[self.rows[cols], np.arange(len(cols))] = self.scale[cols]
            else:
                B = self.load[:, cols].toarray()
            Y, iters = block_pcg(self.K, B, M)
            self.stats.setdefault("iterations", []).append(int(iters.max()))
            out[:, c0:c0 + len(cols)] = Y[self.rows[:self.n_observed]]
        return out

    def solve_bytes(self, k: int) -> int:
        """The peak working memory of :meth:`columns` for ``k`` columns, beyond K_FF and the hierarchy
        (:func:`solve_bytes`)."""
        return solve_bytes(self.K.shape[0], self.n_observed, k)


def solve_bytes(n_dofs: int, n_observed: int, k: int) -> int:
    """:meth:`AmgSystem.columns`' peak working memory for ``k`` columns: the result (n_observed x k doubles)
    and block CG's arrays for one group of :data:`PCG_COLUMNS` (:data:`PCG_ARRAYS` of n_dofs x group)."""
    return 8 * (n_observed * k + PCG_ARRAYS * n_dofs * min(k, PCG_COLUMNS))


def hierarchy_bytes(K_bytes: float) -> float:
    """K_FF with its smoothed-aggregation hierarchy (six near-null vectors: operators, prolongators, smoother
    data) and the coarse level's LU, built on the first solve: tracemalloc measured 1.4-1.5x K_FF's bytes for
    the hierarchy at 1,914, 7,128 and 26,304 dofs, and the LU 0.5x K_FF at 26,304; modelled as 3x K_FF."""
    return 3.0 * K_bytes


def block_pcg(A: sp.csr_matrix, B: np.ndarray, M, rtol: float = RTOL, maxiter: int = MAXITER):
    """Solve A X = B (A SPD) for a block of right-hand sides by preconditioned CG, every column with its own
    step lengths; one product A·P per step for the block.  Returns X and the steps per column."""
    X = np.zeros_like(B)
    R = B.copy()
    Z = np.column_stack([M @ R[:, c] for c in range(R.shape[1])])
    P = Z.copy()
    rz = np.einsum("ij,ij->j", R, Z)
    bnorm = np.linalg.norm(B, axis=0)
    active = np.flatnonzero(bnorm > 0)
    iters = np.zeros(B.shape[1], np.int64)
    for it in range(maxiter):
        if len(active) == 0:
            break
        AP = A @ P[:, active]
        alpha = rz[active] / np.einsum("ij,ij->j", P[:, active], AP)
        X[:, active] += P[:, active] * alpha
        R[:, active] -= AP * alpha
        iters[active] += 1
        done = np.linalg.norm(R[:, active], axis=0) <= rtol * bnorm[active]
        active = active[~done]
        if len(active) == 0:
            break
        Z[:, active] = np.column_stack([M @ R[:, c] for c in active])
        rz_new = np.einsum("ij,ij->j", R[:, active], Z[:, active])
        P[:, active] = Z[:, active] + P[:, active] * (rz_new / rz[active])
        rz[active] = rz_new
    if len(active):
        raise ResourceError(f"AMG-preconditioned CG did not reach a relative residual of {rtol:g} in {maxiter} steps "
                            f"for {len(active)} load columns: the support may not hold the body; use the sparse "
                            "factor (leave out --solver amg)")
    return X, iters


def amg_system(K: sp.spmatrix, dirichlet: np.ndarray, observed: np.ndarray, points: np.ndarray, load=None, *,
               scale=None) -> AmgSystem:
    """The free system and the observed rows, like :func:`pmask.precompute.greens.factorise` but without
    a factor (the hierarchy is built where the tiles are solved)."""
    n = K.shape[0]
    keep = np.setdiff1d(np.arange(n), np.unique(dirichlet))
    pos = np.full(n, -1, np.int64)
    pos[keep] = np.arange(len(keep))
    rows = pos[np.asarray(observed, np.int64)]
    K_FF = sp.csr_matrix(K)[keep][:, keep]
    B = sp.csc_matrix(sp.csr_matrix(load)[keep]) if load is not None else None
    return AmgSystem(K=K_FF, rows=rows, n_observed=len(rows), near_null=rigid_body_modes(points, keep),
                     scale=None if scale is None else np.asarray(scale, float), load=B,
                     stats={"dofs": len(keep), "route": "amg", "backend": "pyamg"})
