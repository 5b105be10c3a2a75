r"""Pressure masks (paper §3.1): collocated, compact, normalised scalar traction densities.

A force f applied "at" free vertex i is spread as the traction
:math:`p_j = \rho^i_j f` (eq. 11) over the masked vertices
:math:`\mathcal{M}_i`.  The mask is a spherical functional of radius r
collocated at the vertices (§3.1.2, Figure 3) and scaled so that
:math:`a^T \rho^i = 1` (eq. 9): the tractions then sum to the force f.
Masks live on the free boundary only; every profile below is 1 at the centre,
so vertex i is always in its own mask, and a mask that reaches no neighbour
is the single-vertex mask :math:`\rho^i = e_i / a_i` (a point force).

Profiles of s = ‖x − x_i‖ / r on s < 1 (zero outside):

=============  ====================================  ===========================
``linear``     1 - s                                 the paper's cone (§3.1.3)
``gaussian``   exp(-s² / (2 σ²)), σ = 1/3            truncated at 3 σ
``wendland``   (1 - s)⁴ (4 s + 1)                    Wendland C2, smooth at s = 1
``disk``       1                                     uniform pressure disk
``single``     e_i / a_i                             no spreading (radius unused)
=============  ====================================  ===========================
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pmask.errors import InputError
from pmask.runtime.spatial import pairs_within

PROFILES = {
    "linear": lambda s: 1.0 - s,
    "gaussian": lambda s: np.exp(-4.5 * s * s),
    "wendland": lambda s: (1.0 - s) ** 4 * (4.0 * s + 1.0),
    "disk": lambda s: np.ones_like(s),
}
MASK_KINDS = tuple(PROFILES) + ("single",)


@dataclass
class Masks:
    """Masks of ``centres`` in CSR form over the candidate vertices.

    Row k (centre ``centres[k]``) has candidate indices ``indices[indptr[k]:indptr[k+1]]``
    and weights ``values[...]`` (units 1/area) with Σ a_j ρ_j = 1.
    ``single_vertex`` counts masks that reached no neighbour.
    """

    indptr: np.ndarray
    indices: np.ndarray
    values: np.ndarray
    centres: np.ndarray
    kind: str
    radius: float
    single_vertex: int

    def row(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        s = slice(self.indptr[k], self.indptr[k + 1])
        return self.indices[s], self.values[s]

    def dense(self, n_candidates: int) -> np.ndarray:
        """(n_centres, n_candidates) matrix, for tests and small models."""
        out = np.zeros((len(self.centres), n_candidates))
        rows = np.repeat(np.arange(len(self.centres)), np.diff(self.indptr))
        out[rows, self.indices] = self.values
        return out


def check_radius(kind: str, radius, r_max: float = np.inf) -> float:
    """Validate a mask kind and radius; return the radius as float."""
    if kind not in MASK_KINDS:
        raise InputError(f"unknown mask '{kind}'; choose one of {', '.join(MASK_KINDS)}")
    if kind == "single":
        return 0.0
    try:
        r = float(radius)
    except (TypeError, ValueError):
        raise InputError(f"mask radius must be a number, got {radius!r}") from None
    if not np.isfinite(r) or r <= 0:
        raise InputError(f"mask radius must be a finite length > 0, got {radius!r}")
    if r > r_max:
        raise InputError(f"mask radius {r:.6g} exceeds this artifact's r_max = {r_max:.6g}: masks that wide "
                         "would reach vertices without Green's functions; recompute with a larger --r-max")
    return r


def pressure_masks(points: np.ndarray, areas: np.ndarray, centres: np.ndarray, kind: str = "linear",
                   radius: float | None = None) -> Masks:
    """Collocated, normalised masks around each of ``centres``.

    Parameters
    ----------
    points, areas
        positions and vertex areas of the candidate vertices (the free
        vertices that have Green's functions).
    centres
        indices into ``points`` of the vertices to build masks for.
    """
    r = check_radius(kind, radius)
    centres = np.asarray(centres, dtype=np.int64)
    if kind == "single":
        vals = 1.0 / areas[centres]
        return Masks(np.arange(len(centres) + 1), centres.copy(), vals, centres, kind, 0.0, len(centres))
    profile = PROFILES[kind]
    idx_parts, val_parts, counts = [], [], []
    # vertex i is always in its own mask, at s = 0 exactly; a grid of cells finds the rest (pairs_within).  Each
    # run of centres is normalised (eq. 9) as it comes, so that the only arrays the size of all the masks are the
    # runs and one concatenation at a time (1.5x the masks' bytes; normalising after the concatenation took 3x,
    # tests/test_runtime.py): the pairs grow like n² at a fixed radius (11.9 million at 20,427 vertices with 10 mm
    # masks, by hand; about 5.4 times that at 47,467)
    for c, rows, cols, d2 in pairs_within(points, centres, r):
        w = profile(np.sqrt(d2) / r)  # (a sum of squares: never negative)
        count = np.bincount(rows, minlength=len(c))  # ≥ 1: each centre is in its own mask
        w /= np.repeat(np.add.reduceat(areas[cols] * w, np.cumsum(count) - count), count)
        idx_parts.append(cols)
        val_parts.append(w)
        counts.append(count)
    indices = np.concatenate(idx_parts) if idx_parts else np.zeros(0, np.int64)
    del idx_parts
    values = np.concatenate(val_parts) if val_parts else np.zeros(0)
    del val_parts
    indptr = np.concatenate([[0], np.cumsum(np.concatenate(counts) if counts else [])]).astype(np.int64)
    single = int(np.sum(np.diff(indptr) == 1))
    return Masks(indptr, indices.astype(np.int64, copy=False), values, centres, kind, r, single)
