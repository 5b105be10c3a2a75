"""The surface the contact algorithm runs on: mesh, triangle frames and neighbours, contact normals, the
rendered per-vertex stiffness K_i, the taper λ, the normal-stiffness gradient ∇k_n, a spatial grid, and (for
several contacts and the display) the ζ table.  The arrays are what a runtime table stores
(:mod:`pmask.runtime.table`); the per-tick code reads plain-Python copies of them."""
from __future__ import annotations

import numpy as np

from pmask.runtime.geometry import contact_normals, triangle_frames, triangle_neighbours
from pmask.runtime.spatial import TriangleGrid
from pmask.runtime.stiffness import zeta_compliance, zeta_deformation


class ContactSurface:
    """What the contact algorithm reads of a stiffness: the mesh, triangle frames and neighbours, contact
    normals, per-vertex rendered K, taper λ and ∇k_n, a spatial grid, and (for several contacts and the
    display) the ζ table.  The arrays are what a runtime table stores (:mod:`pmask.runtime.table`), and
    :meth:`from_table` rebuilds one from a table; plain-Python copies serve the per-tick code.

    stiffness : a :class:`pmask.runtime.stiffness.Stiffness` (or any ``SurfaceStiffness``).
    normal_radius : see :class:`Contacts` (default 3 mask radii, or 6 mean edges without masks).
    """

    def __init__(self, stiffness, normal_radius: float | None = None):
        P = np.asarray(stiffness.points, float)
        T = np.asarray(stiffness.triangles, np.int64)
        frames = triangle_frames(P, T)
        e = np.linalg.norm(P[T[:, 1]] - P[T[:, 0]], axis=1)
        mean_edge = float(e.mean()) if len(e) else 1.0
        if normal_radius is None:  # 3 mask radii (a single-vertex mask or a bare surface: 6 mean edges)
            masks = getattr(stiffness, "masks", None)
            r = getattr(masks, "radius", 0.0) if masks is not None else 0.0
            normal_radius = 3.0 * (r if r > 0 else 2.0 * mean_edge)
        normals = contact_normals(P, T, float(normal_radius))
        K = np.asarray(stiffness.K_vertex, float).reshape(len(P), 9)
        taper = np.asarray(getattr(stiffness, "taper", np.ones(len(P))), float)
        gradient = normal_stiffness_gradient(P, T, normals, K, taper, frames[:, 3:6], frames[:, 6:9])
        grid = TriangleGrid(P, T, frames=frames)
        lo, hi = P.min(axis=0), P.max(axis=0)
        self._setup(P, T, frames, triangle_neighbours(T), normals, K, taper, gradient, grid, lo, hi,
                    mean_edge, float(np.linalg.norm(hi - lo)), float(normal_radius))
        self.stiffness = stiffness
        self.meta = {}

    @classmethod
    def from_table(cls, table) -> "ContactSurface":
        """A contact surface from a runtime table (:func:`pmask.runtime.table.read_table`'s result or a path)."""
        from pmask.runtime.table import read_table

        t = table if isinstance(table, dict) else read_table(table)
        P, T = t["points"], t["triangles"]
        grid = TriangleGrid(P, T, frames=t["frames"])
        mean_edge, diag = (float(x) for x in t["lengths"][0])
        srf = cls.__new__(cls)
        srf._setup(P, T, t["frames"], t["neighbours"], t["normals"], t["stiffness"], t["taper"][:, 0], t["gradient"],
                   grid, t["bounds"][0], t["bounds"][1], mean_edge, diag, float(t["meta"].get("normal_radius", 0.0)))
        srf.stiffness = None
        srf.meta = t["meta"]
        if not isinstance(table, (dict, bytes, bytearray, memoryview)):  # the native core loads the same file
            srf.table_source, srf.table_sections = str(table), frozenset(t)
        if "zeta" in t:
            srf._coupling = (t["zeta"], t["contact_row"][:, 0])
        return srf

    def _setup(self, P, T, frames, neighbours, normals, K, taper, gradient, grid, lo, hi, mean_edge, diag,
               normal_radius):
        c = np.ascontiguousarray
        self.P, self.T = c(P, dtype=float), c(T, dtype=np.int64)
        self.tri_geom = c(frames, dtype=float)
        self.neighbours = c(neighbours, dtype=np.int64)
        self.vertex_normals = c(normals, dtype=float)
        self.K = c(np.reshape(K, (len(P), 9)), dtype=float)
        self.taper = c(taper, dtype=float)
        self.gradient = c(gradient, dtype=float)
        self.grid = grid
        self.lo, self.hi = np.asarray(lo, float), np.asarray(hi, float)
        self.mean_edge, self.diag, self.normal_radius = float(mean_edge), float(diag), float(normal_radius)
        # plain-Python views for the per-tick code
        self._tri = [tuple(r) for r in self.tri_geom.tolist()]
        self._nb = [tuple(r) for r in self.neighbours.tolist()]
        self._idx = [tuple(r) for r in self.T.tolist()]
        self._P = [tuple(r) for r in self.P.tolist()]
        self._N = [tuple(r) for r in self.vertex_normals.tolist()]
        self._K = [tuple(r) for r in self.K.tolist()]
        self._lam = self.taper.tolist()
        self._G = [tuple(r) for r in self.gradient.tolist()]
        self._coupling = None
        self._row = None

    def coupling(self):
        """(ζ table, surface vertex -> its row in the table) for the coupled solve and the display;
        None for a surface stiffness without Green's functions."""
        if self._coupling is None and self.stiffness is not None and hasattr(self.stiffness, "zeta_table"):
            self._coupling = (self.stiffness.zeta_table(), self.stiffness._contact_row)
        return self._coupling

    def compliance(self, t_l, b_l, t_k, b_k) -> list:
        """C_lk (9 floats): :func:`pmask.runtime.stiffness.zeta_compliance` on this surface's ζ table."""
        Zt, row = self.coupling()
        if self._row is None:
            self._row = np.asarray(row).tolist()
        return zeta_compliance(Zt, self._row, self._idx, t_l, b_l, t_k, b_k)

    def deformation_of(self, loads) -> np.ndarray:
        """The surface's displacement (n_s, 3) for point loads (eq. 16; :func:`zeta_deformation`)."""
        if getattr(self.stiffness, "compressed", False):  # no ζ table: Ξ's blocks of the loaded columns
            return self.stiffness.deformation_of(loads)
        Zt, row = self.coupling()
        return zeta_deformation(Zt, row, self.T, loads)


def normal_stiffness_gradient(P, T, VN, K, taper, dual_a, dual_b) -> np.ndarray:
    """(n_s, 3): the surface gradient of the normal stiffness k_n = λ / (nᵀ K⁻¹ n), per vertex.

    On each triangle, the gradient of the linear interpolant of the vertex values (∇φ_1 = a, ∇φ_2 = b,
    ∇φ_0 = −a − b with a, b the duals of the edges); at a vertex, the area-weighted mean over its
    triangles.  Interpolated (eq. 15's way) and projected on the tangent plane, it gives the tangential
    force ½ δ² ∇k_n that makes the frictionless force the gradient of the stored energy ½ k_n δ²
    (continuous across edges, unlike the per-triangle gradient, which jumps by a few % of the force)."""
    Kv = K.reshape(-1, 3, 3)
    Ki = np.linalg.inv(Kv + 1e-300 * np.eye(3))
    k = taper / np.maximum(np.einsum("vi,vij,vj->v", VN, Ki, VN), 1e-300)
    g_t = (k[T[:, 1]] - k[T[:, 0]])[:, None] * dual_a + (k[T[:, 2]] - k[T[:, 0]])[:, None] * dual_b
    area = 0.5 * np.linalg.norm(np.cross(P[T[:, 1]] - P[T[:, 0]], P[T[:, 2]] - P[T[:, 0]]), axis=1)
    g = np.zeros_like(P)
    w = np.zeros(len(P))
    for c in range(3):
        np.add.at(g, T[:, c], area[:, None] * g_t)
        np.add.at(w, T[:, c], area)
    return g / np.maximum(w, 1e-300)[:, None]
