r"""Vertex stiffness (paper eq. 12, 14), surface stiffness (eq. 15) and deformation (eq. 13, 16).

Masked vertex stiffness of free vertex i:

.. math::  K_i = \Big(\sum_{j \in \mathcal{M}_i} \rho^i_j\, \Xi_{ij}\Big)^{-1}      \quad (12)

and the surface stiffness at a point x of triangle t with barycentric coordinates b is

.. math::  K(x) = \sum_k b_k K_{t_k}                                            \quad (15)

which is continuous across edges because neighbouring triangles share the vertex values.  A contact
force f at x deforms the surface by

.. math::  v = \sum_i \phi_i(x)\, \zeta_i f, \qquad
           \zeta_i = \sum_{j \in \mathcal{M}_i} \rho^i_j\, \xi_j              \quad (13, 16)

What is rendered differs from the paper in three documented places, each for a haptic reason:

- **Symmetric.** K_i is not symmetric in general (normal–tangential coupling of Ξ_ij for i ≠ j); a
  sticking contact with a non-symmetric stiffness does net work round a closed loop, so the tables
  hold :math:`(K_i + K_i^T)/2` unless ``symmetric=False``.
- **The support is blended, not a step** (eq. 14 with a ramp).  A fixed vertex gets the stiffness of
  the free tissue next to it (a Gaussian-weighted average), ramping to :math:`k_{rigid} I` with its
  distance d into the support over ``support_blend``: :math:`K_j = (1 - s) K_{ext} + s\,k_{rigid} I`,
  :math:`s = \mathrm{smoothstep}(d / w)`.  A step from ~75 N/m to k_rigid within one triangle changed
  the force by up to 3 N in one 1 ms tick.
- **The contact region tapers.**  With ``--contact`` the vertices within r_max outside the region
  have Green's functions but truncated masks; their K_i (from the truncated masks) are rendered with a
  weight λ falling smoothly from 1 at the region to 0 at r_max, and λ = 0 beyond, so leaving the
  region fades the force out instead of dropping it in one tick.

The deformation for display (eq. 16) uses the ζ table, computed once per stiffness
(:meth:`Stiffness.zeta_table`); see :mod:`pmask.runtime.haptics` for the force it is fed.
"""
from __future__ import annotations

import numpy as np

from pmask.errors import InputError, PmaskError
from pmask.runtime.compressed import CompressedXi, MaskedXi, xi_blocks
from pmask.runtime.geometry import one_rings
from pmask.runtime.masks import Masks
from pmask.runtime.spatial import bounded_runs, concatenated_ranges

#: tolerance on barycentric coordinates (negativity and sum) accepted by the query API: barycentrics
#: computed in float32 are off by a few 1e-8 (float32's epsilon is 1.2e-7), so 1e-6 accepts them;
#: they are renormalised before use
BARY_TOL = 1e-6
#: Jacobi sweeps that relax the support's rendered stiffness (see ``Stiffness._blend_support``)
SUPPORT_RELAX_SWEEPS = 20
#: queries per piece in ``at_batch``: the gathered rows (27 floats each) stay in cache (measured:
#: 1 M random queries 7 -> 14 M/s on 500 vertices, 4 -> 7 M/s on 50,000)
BATCH_CHUNK = 32768
#: columns of the ζ table built at a time (16 KiB of each row of Ξᵀ): the rows of Ξᵀ that neighbouring masks
#: share are then read from cache (1024-4096 measured alike at the default kidney; whole rows 1.5x slower)
ZETA_COLUMNS = 2048


class StiffnessError(PmaskError, ValueError):
    """Green's functions whose vertex stiffnesses cannot be rendered (not positive definite)."""


#: mask pairs gathered at a time by :func:`masked_flexibility` (its temporaries: ~250 bytes per pair)
PAIRS_PER_PASS = 1 << 18


def masked_flexibility(Xi: np.ndarray, masks: Masks) -> np.ndarray:
    r"""(n, 3, 3) blocks :math:`\sum_j \rho^i_j \Xi_{ij}`, one per mask centre i (Ξ dense or compressed: a
    mask's pairs lie within r ≤ r_max, in the compressed form's exact near field).  The pairs are gathered
    in passes of whole masks, at most about :data:`PAIRS_PER_PASS` pairs each, so that the memory does not
    grow with the model (a 20,000-vertex organ with 10 mm masks has 12 million pairs: 3 GB of temporaries
    at once).  The masks are taken in the order of Ξ's stored rows (a compressed Ξ's cluster order), so
    that a pass reads nearby values: at 20,000 vertices with 10 mm masks, 3.9-4.4 s against 7.0 s in the masks'
    own order (by hand), bitwise the same (each mask's pairs are summed in the same order)."""
    rows = masks.centres
    counts = np.diff(masks.indptr)
    out = np.zeros((len(rows), 3, 3))
    ptr = masks.indptr
    order = np.argsort(Xi.position[rows], kind="stable") if isinstance(Xi, CompressedXi) else np.arange(len(rows))
    for start, stop in bounded_runs(counts[order], PAIRS_PER_PASS):
        m = order[start:stop]  # whole masks, at least one
        lens = counts[m]
        at = concatenated_ranges(ptr[m], lens)  # their pairs
        blocks = xi_blocks(Xi, np.repeat(rows[m], lens), masks.indices[at]) * masks.values[at, None, None]
        nz = np.flatnonzero(lens > 0)
        if len(nz):
            out[m[nz]] = np.add.reduceat(blocks, (np.cumsum(lens) - lens)[nz], axis=0)
    return out


def vertex_stiffness(Xi: np.ndarray, masks: Masks) -> np.ndarray:
    """K_i = (Σ_j ρ^i_j Ξ_ij)⁻¹ (eq. 12) for every mask centre i; (n, 3, 3)."""
    A = masked_flexibility(Xi, masks)
    return np.linalg.inv(A)


def asymmetry(K: np.ndarray) -> np.ndarray:
    """‖K − Kᵀ‖_F / ‖K‖_F per 3x3 block."""
    return np.linalg.norm(K - np.swapaxes(K, -1, -2), axis=(-2, -1)) / np.linalg.norm(K, axis=(-2, -1))


def check_positive_definite(K: np.ndarray, surface_vertices: np.ndarray, what: str = "K_i",
                            cause: str | None = None) -> None:
    """Refuse stiffnesses whose symmetric part is not positive definite, naming the vertices: such a
    contact would pull the tool into the body (a sign-flipped Ξ, whatever its checksums say).  ``cause``
    replaces the default explanation (corrupt Green's functions)."""
    lam = np.linalg.eigvalsh(0.5 * (K + np.swapaxes(K, -1, -2)))[:, 0] if len(K) else np.zeros(0)
    bad = np.flatnonzero(~(lam > 0))
    if len(bad):
        names = ", ".join(str(int(v)) for v in surface_vertices[bad[:10]]) + (" ..." if len(bad) > 10 else "")
        raise StiffnessError(
            f"the rendered vertex stiffness {what} is not positive definite at {len(bad)} of {len(K)} surface vertices "
            f"({names}; smallest eigenvalue {lam[bad].min():.3g} N/m): "
            + (cause or "these Green's functions cannot come from an elastic body held by its support; recompute the "
                        "artifact (pmask precompute --force)"))


def smoothstep(x):
    """0 below 0, 1 above 1, 3x² − 2x³ between: continuous with a continuous slope."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


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
    b = np.maximum(b, 0.0)
    return t, b / b.sum()


class SurfaceStiffness:
    """The surface stiffness K(x) of eq. 15 over a triangle mesh, queried in O(1).

    Parameters
    ----------
    points, triangles : the surface.
    K_vertex : (n_s, 3, 3) rendered vertex stiffness of every surface vertex.
    touchable : bool per triangle (default: λ > 0 at a vertex of it).
    taper : (n_s,) the weight λ the force is rendered with (default 1): 1 where Ξ is complete, falling
        to 0 across the band outside a contact region.
    """

    def __init__(self, points, triangles, K_vertex, touchable=None, taper=None):
        self.points = np.asarray(points, float)
        self.triangles = np.asarray(triangles, np.int64)
        self.K_vertex = np.asarray(K_vertex, float)
        if not np.all(np.isfinite(self.K_vertex)):
            raise InputError("vertex stiffness holds NaN or inf")
        self.taper = np.ones(len(self.points)) if taper is None else np.asarray(taper, float)
        self.touchable = ((self.taper[self.triangles] > 0).any(axis=1) if touchable is None
                          else np.asarray(touchable, bool))
        # per-triangle table: (T, 3, 9), row k = K of the triangle's k-th vertex, flattened
        self.table = np.ascontiguousarray(self.K_vertex[self.triangles].reshape(len(self.triangles), 3, 9))

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)

    def locate(self, point) -> tuple[int, np.ndarray]:
        """The surface point nearest ``point`` (3 numbers, model units): (triangle, barycentrics), what
        :meth:`at` and :meth:`deformation` take.  A spatial grid built on first use makes it O(1) expected
        (:class:`pmask.runtime.spatial.TriangleGrid`; the contact tracking uses the same grid)."""
        p = np.asarray(point, dtype=float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise InputError(f"point must be 3 finite numbers, got {point!r}")
        grid = getattr(self, "_grid", None)
        if grid is None:
            from pmask.runtime.spatial import TriangleGrid

            grid = self._grid = TriangleGrid(self.points, self.triangles)
        t = grid.nearest(tuple(p))
        v = self.points[self.triangles[t]]
        # the closest point of the triangle (not only of its plane): minimise over the face and its edges
        best = None
        for b in _closest_barycentrics(v, p):
            d = np.linalg.norm(b @ v - p)
            if best is None or d < best[0]:
                best = (d, b)
        return int(t), best[1]

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


def core_mask_rows(masks, mask_of_contact):
    """c -> (columns, weights) of the core mask centred at contact vertex c, empty where it has none (the
    ``mask_row`` of :class:`pmask.runtime.compressed.MaskedXi`)."""
    none = (np.zeros(0, np.int64), np.zeros(0))

    def row(c: int):
        k = mask_of_contact[c]
        return masks.row(k) if k >= 0 else none

    return row


class Stiffness(SurfaceStiffness):
    """Surface stiffness built from Green's functions and pressure masks, with deformation (eq. 16).

    Made by :meth:`pmask.runtime.Model.stiffness`; holds the masks and a reference to Ξ.
    ``K_full``: the unsymmetrised K_i of the core contact vertices (eq. 12), in mask-centre order.
    """

    def __init__(self, model, masks: Masks, K_free: np.ndarray, k_rigid: float, symmetric: bool, *,
                 band_masks: Masks | None = None, K_band: np.ndarray | None = None, support_blend: float,
                 device=None):
        self.model = model
        self.masks = masks
        self.k_rigid = float(k_rigid)
        self.symmetric = bool(symmetric)
        self.support_blend = float(support_blend)
        self.device = device
        self.K_full = K_free
        self.asymmetry = asymmetry(K_free)
        n_s = len(model.points)
        sym = (lambda K: 0.5 * (K + np.swapaxes(K, 1, 2))) if symmetric else (lambda K: K)
        Kv = np.zeros((n_s, 3, 3))
        taper = np.zeros(n_s)
        known = np.zeros(n_s, bool)
        core_surface = model.contact[masks.centres]
        Kv[core_surface] = sym(K_free)
        taper[core_surface] = 1.0
        known[core_surface] = True
        if band_masks is not None and len(band_masks.centres):
            band_surface = model.contact[band_masks.centres]
            Kv[band_surface] = sym(K_band)
            known[band_surface] = True
            d = _nearest_distance(model.points[band_surface], model.points[core_surface])
            taper[band_surface] = smoothstep(1.0 - d / max(model.r_max, 1e-300))
        self._fill_unknown_free(Kv, known)
        self._blend_support(Kv, taper)
        super().__init__(model.points, model.triangles, Kv, taper=taper)
        self._row_of_surface = np.full(n_s, -1)
        self._row_of_surface[core_surface] = np.arange(len(core_surface))
        self._contact_row = np.full(n_s, -1)
        self._contact_row[model.contact] = np.arange(len(model.contact))
        self._zeta_table = None
        self._mask_of_contact = np.full(len(model.contact), -1)
        self._mask_of_contact[masks.centres] = np.arange(len(masks.centres))
        # (a closure over the masks, not a bound method: a stiffness that held itself through its MaskedXi would
        # wait for the cyclic garbage collector, its ζ table and the model's Ξ with it)
        self._masked = MaskedXi(model.Xi, core_mask_rows(masks, self._mask_of_contact))

    def _fill_unknown_free(self, Kv: np.ndarray, known: np.ndarray) -> None:
        """Free vertices outside Ξ (λ = 0 there): the nearest known vertex's K, so that K(x) stays
        positive definite where the taper reaches zero."""
        m = self.model
        unknown = np.setdiff1d(m.free, np.flatnonzero(known))
        if len(unknown) and known.any():
            src = np.flatnonzero(known)
            Kv[unknown] = Kv[src[_nearest_index(m.points[unknown], m.points[src])]]

    def _blend_support(self, Kv: np.ndarray, taper: np.ndarray) -> None:
        """Fixed vertices: the nearby free tissue's K, ramping to k_rigid I with the distance into the support."""
        m = self.model
        fixed = m.fixed
        if len(fixed) == 0:
            return
        src = m.contact[self.masks.centres]
        taper[fixed] = 1.0
        if len(src) == 0:
            Kv[fixed] = self.k_rigid * np.eye(3)
            return
        h = m.mean_edge_length
        d = _nearest_distance(m.points[fixed], m.points[src])
        sigma = d + 2.0 * h
        K_ext = np.empty((len(fixed), 3, 3))
        for k0 in range(0, len(fixed), 256):
            k1 = min(k0 + 256, len(fixed))
            r2 = _sq_dist(m.points[fixed[k0:k1]], m.points[src])
            w = np.exp(-r2 / sigma[k0:k1, None] ** 2)
            w[r2 > (3.0 * sigma[k0:k1, None]) ** 2] = 0.0
            K_ext[k0:k1] = np.einsum("fs,sij->fij", w, Kv[src]) / w.sum(axis=1)[:, None, None]
        s = smoothstep(d / max(self.support_blend, 1e-300))[:, None, None]
        Kv[fixed] = (1.0 - s) * K_ext + s * self.k_rigid * np.eye(3)
        # relax the fixed vertices' values (Jacobi, one-ring means; the free ones stay eq. 12's): the
        # nearest-vertex distance has kinks along the support's medial lines, and the force's tangential
        # term ½ δ² ∇k_n, large on the ramp at 5 mm depth, followed them (~8 % change per tick there)
        rings = one_rings(n_s := len(Kv), m.triangles)
        nbr = [rings[j] for j in fixed]
        for _ in range(SUPPORT_RELAX_SWEEPS):
            Kv[fixed] = np.array([Kv[r].mean(axis=0) if len(r) else Kv[j] for j, r in zip(fixed, nbr)])

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
        if self.compressed:
            x = np.zeros((self.model.Xi.shape[0] // 3, 3, 3))
            x[cols] = w[:, None, None] * np.eye(3)
            return self.model.Xi.matvec(x.reshape(-1, 3))
        X = self.model.Xi.reshape(self.model.Xi.shape[0], -1, 3)[:, cols, :]  # (3n_c, |M|, 3)
        return np.einsum("rmc,m->rc", X, w)

    @property
    def compressed(self) -> bool:
        """Whether Ξ is in compressed form (:mod:`pmask.runtime.compressed`): no ζ table then (it is as
        large as Ξ); deformation and coupling read Ξ's blocks instead."""
        return isinstance(self.model.Xi, CompressedXi)

    def zeta_table(self, rows=None) -> np.ndarray:
        r"""Zt (3 n_c, 3 n_c) with rows 3m..3m+2 = ζ_mᵀ for every core contact vertex m (zero rows
        elsewhere): the deformation of eq. 16 for a force f at vertex m is ``f @ Zt[3m:3m+3]``, three
        contiguous rows (a column of ζ would be a strided gather of Ξ, 8-10x slower).  Computed once, from
        the transpose of Ξ, one mask at a time: Zt_m = Σ_j ρ^m_j Ξ[:, j]ᵀ, a product of the mask's few
        weights with its few contiguous rows of Ξᵀ (blocks of 64 centres as one dense product multiplied
        mostly zeros: 2-7x slower at the default kidney, measured, and a viewer rebuilds this table on every
        change of the mask radius), over ``ZETA_COLUMNS`` columns at a time so that the rows neighbouring
        masks share stay in cache (whole rows: 0.35 s against 0.24 s at the default kidney, by hand).
        ``rows(XiT3, masks, Zt3)``, when given, fills the centres' rows instead of this loop (the native core's
        :func:`pmask.runtime.servo.zeta_rows`, 0.09 s, which a viewer's radius change uses)."""
        if self._zeta_table is not None:
            return self._zeta_table
        if self.compressed:
            n3 = self.model.Xi.shape[0]
            raise InputError(f"{self.model.path}: its Green's functions are compressed, and a ζ table of its "
                             f"{n3 // 3} contact vertices would be a dense {n3} x {n3} array ({n3 * n3 * 8 / 2**30:.1f} "
                             "GiB); couple contacts with Stiffness.coupled_forces and deform with deformation_of, "
                             "or precompute without --compress")
        Xi = self.model.Xi
        n3 = Xi.shape[0]
        Zt = np.zeros((n3, n3))
        XiT3 = getattr(self.model, "xi_rows", None)  # held by Model.hold_transpose (a viewer), or made here:
        if XiT3 is None:
            XiT3 = np.ascontiguousarray(Xi.T, dtype=float).reshape(n3 // 3, 3 * n3)  # row j = Ξ[:, 3j:3j+3]ᵀ
        Zt3 = Zt.reshape(n3 // 3, 3 * n3)
        masks = self.masks
        ptr, idx, val = masks.indptr, masks.indices, masks.values
        if rows is not None:
            rows(XiT3, masks, Zt3)
        else:
            for a in range(0, 3 * n3, ZETA_COLUMNS):
                cols = slice(a, a + ZETA_COLUMNS)
                for k, m in enumerate(masks.centres):
                    np.dot(val[ptr[k]:ptr[k + 1]], XiT3[idx[ptr[k]:ptr[k + 1]], cols], out=Zt3[m, cols])
        del XiT3
        self._zeta_table = Zt
        return Zt

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
        return self.deformation_of([(t, b, f)])

    def deformation_of(self, loads) -> np.ndarray:
        """Displacement (n_s, 3) for several point loads ``[(triangle, barycentrics, force), ...]`` (eq. 16
        summed); see :func:`zeta_deformation` (compressed Ξ: one product Ξ x with x the loads spread by their
        masks, which touches only the blocks of the loaded columns)."""
        if not self.compressed:
            return zeta_deformation(self.zeta_table(), self._contact_row, self.triangles, loads)
        return self._masked.deformation_of(self.triangles, self._contact_row, loads)

    def compliance_between(self, t_l, b_l, t_k, b_k) -> np.ndarray:
        r"""C_lk (3x3): displacement at point l (interpolated, eq. 16) per unit force at point k
        (:func:`zeta_compliance` on :meth:`zeta_block`)."""
        return np.array(zeta_compliance(self.zeta_block, self._contact_row, self.triangles,
                                        t_l, b_l, t_k, b_k)).reshape(3, 3)

    def zeta_block(self, rm: int, ri: int) -> list:
        r"""ζ_m(i)ᵀ = (Σ_j ρ^m_j Ξ_ij)ᵀ (eq. 13) for contact vertices m (the force's) and i (the displaced
        one), three lists of three: the block function of :func:`zeta_compliance`.

        From the ζ table when it has been formed; otherwise from Ξ's blocks of mask m's columns at row i
        (compressed Ξ: the exact near field, or the far field's low-rank factors, work of the mask's size
        times the rank whatever n),
        kept in a bounded cache, since contacts stay on the same vertices for many ticks.  This is how
        contacts on a compressed artifact couple without the ζ table, which is as large as Ξ."""
        if self._zeta_table is not None:
            Zt = self._zeta_table
            return Zt[3 * rm:3 * rm + 3, 3 * ri:3 * ri + 3].tolist()
        return self._masked.block(rm, ri)

    def coupled_forces(self, points, displacements) -> np.ndarray:
        r"""Forces at several contact points that impose the given displacements, solved together through the
        body (the capacitance method of James & Pai's companion paper, which the paper's §3 defers to).

        points : [(triangle, barycentrics), ...] of s contact points x_l; displacements : (s, 3) ū_l.
        Solves Σ_k C_lk f_k = ū_l with C_lk = Σ_i Σ_m φ_i(x_l) φ_m(x_k) ζ_m(i) (exact: unsymmetrised, every
        component constrained); at a vertex and s = 1 this is eq. 12, f = K_i ū.  Returns f (s, 3), the
        forces on the body; :meth:`deformation_of` gives the surface they deform.
        """
        pts = [_check_query(t, b, self.n_triangles) for t, b in points]
        u = np.asarray(displacements, float).reshape(len(pts), 3)
        if not np.all(np.isfinite(u)):
            raise InputError("displacements must be finite")
        s = len(pts)
        C = np.zeros((3 * s, 3 * s))
        for i, (ta, ba) in enumerate(pts):
            for j, (tb, bb) in enumerate(pts):
                C[3 * i:3 * i + 3, 3 * j:3 * j + 3] = self.compliance_between(ta, ba, tb, bb)
        try:
            return np.linalg.solve(C, u.ravel()).reshape(s, 3)
        except np.linalg.LinAlgError:
            raise InputError(f"the {s} contact points cannot take these displacements together: a point lies where "
                             "nothing moves (on the support's held vertices) or two points coincide; drop that "
                             "point or move it onto the free surface") from None

    def report(self) -> dict:
        """Numbers a user should see: mask reach, asymmetry of K_i, stiffness range, k_rigid and the bound."""
        norms = np.linalg.norm(self.K_full, ord=2, axis=(1, 2))
        out = {
            "mask": self.masks.kind, "radius": self.masks.radius,
            "vertices": len(self.masks.centres), "single_vertex_masks": self.single_vertex_masks,
            "mean_mask_size": float(np.mean(np.diff(self.masks.indptr))),
            "asymmetry_max": float(self.asymmetry.max()), "asymmetry_mean": float(self.asymmetry.mean()),
            "stiffness_norm_min": float(norms.min()), "stiffness_norm_median": float(np.median(norms)),
            "stiffness_norm_max": float(norms.max()), "k_rigid": self.k_rigid, "symmetric": self.symmetric,
            "support_blend": self.support_blend,
        }
        if self.device is not None:
            out["stable_stiffness"] = self.device.stable_stiffness()
            out["device"] = {"rate": self.device.rate, "damping": self.device.damping}
        return out


def zeta_compliance(block, row, triangles, t_l, b_l, t_k, b_k) -> list:
    r"""C_lk = Σ_i Σ_m φ_i(x_l) φ_m(x_k) ζ_m(i), 9 floats row-major: the displacement at x_l (interpolated,
    eq. 16) per unit force at x_k (spread by the masks, eq. 13), from nine 3x3 blocks ζ_m(i).

    block : (r_m, r_i) -> ζ_m(i)ᵀ as three lists of three, r the rows of the force vertex m and the displaced
    vertex i (:func:`table_block` reads them from a ζ table, :meth:`Stiffness.zeta_block` from Ξ's blocks);
    row : surface vertex -> its row (-1: none).  Plain Python floats in a fixed order: the haptic step
    couples contacts with it, and the native core computes the same sums in the same order."""
    C = [0.0] * 9
    for i, pi in zip(triangles[t_l], b_l):
        ri = row[i]
        if pi == 0.0 or ri < 0:
            continue
        for m, pm in zip(triangles[t_k], b_k):
            rm = row[m]
            if pm == 0.0 or rm < 0:
                continue
            w = pi * pm
            blk = block(rm, ri)  # ζ_m(i)ᵀ
            for r in range(3):
                for c in range(3):
                    C[3 * r + c] += w * blk[c][r]
    return C


def table_block(Zt):
    """The block function of :func:`zeta_compliance` for a ζ table Zt (rows 3m..3m+2 = ζ_mᵀ)."""
    return lambda rm, ri: Zt[3 * rm:3 * rm + 3, 3 * ri:3 * ri + 3].tolist()


def zeta_deformation(Zt, row, triangles, loads) -> np.ndarray:
    """Displacement (n_s, 3) of the surface for point loads ``[(triangle, barycentrics, force), ...]``
    (eq. 16 summed): three contiguous rows of the ζ table per load vertex, one vector-matrix product
    each; zero at vertices without a row (fixed, or outside the contact region)."""
    v_contact = np.zeros(Zt.shape[1])
    for t, b, f in loads:
        for vertex, phi in zip(triangles[t], b):
            r = row[vertex]
            if phi != 0.0 and r >= 0:
                v_contact += (phi * np.asarray(f, float)) @ Zt[3 * r:3 * r + 3]
    row = np.asarray(row)
    v = np.zeros((len(row), 3))
    has = row >= 0
    v[has] = v_contact.reshape(-1, 3)[row[has]]
    return v


def _closest_barycentrics(v: np.ndarray, p: np.ndarray):
    """Candidate barycentrics of the point of triangle v (3x3) closest to p: the face's (if inside) and each
    edge's clamped projection."""
    e1, e2 = v[1] - v[0], v[2] - v[0]
    G = np.array([[e1 @ e1, e1 @ e2], [e1 @ e2, e2 @ e2]])
    try:
        b1, b2 = np.linalg.solve(G, [e1 @ (p - v[0]), e2 @ (p - v[0])])
        if b1 >= 0 and b2 >= 0 and b1 + b2 <= 1:
            yield np.array([1 - b1 - b2, b1, b2])
    except np.linalg.LinAlgError:
        pass
    for i, j in ((0, 1), (1, 2), (2, 0)):
        d = v[j] - v[i]
        s = float(np.clip((p - v[i]) @ d / max(d @ d, 1e-300), 0.0, 1.0))
        b = np.zeros(3)
        b[i], b[j] = 1.0 - s, s
        yield b


def _sq_dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.maximum(np.sum(a * a, axis=1)[:, None] + np.sum(b * b, axis=1)[None, :] - 2.0 * a @ b.T, 0.0)


def _nearest_index(a: np.ndarray, b: np.ndarray, chunk: int = 512) -> np.ndarray:
    out = np.empty(len(a), np.int64)
    for k in range(0, len(a), chunk):
        out[k:k + chunk] = np.argmin(_sq_dist(a[k:k + chunk], b), axis=1)
    return out


def _nearest_distance(a: np.ndarray, b: np.ndarray, chunk: int = 512) -> np.ndarray:
    out = np.empty(len(a))
    for k in range(0, len(a), chunk):
        out[k:k + chunk] = np.sqrt(np.min(_sq_dist(a[k:k + chunk], b), axis=1))
    return out
