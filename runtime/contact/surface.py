r"""The surface the contact algorithm runs on: mesh, triangle frames and neighbours, contact normals, the
rendered per-vertex stiffness K_i, the taper λ, and what the contact law derives from them per vertex (the
normal stiffness k_j, its surface gradient ∇k, the shape operator S_j of the contact normals and the depth
δ_lin,j where the linear model stops), a spatial grid, and (for several contacts and the display) the ζ
table.  The arrays are what a runtime table stores (:mod:`pmask.runtime.table`); the per-tick code reads
plain-Python copies of them.

**Where the linear contact stops being meaningful.**  The law renders a point-like contact on the undeformed
surface: one contact normal, the stiffness of a mask of radius r, and the surface point under the probe.
Two things break with depth δ:

- *curvature*: a tool pressed δ into a surface of radius of curvature R touches a cap whose normals turn by θ
  with cos θ = 1 − δ/R; past θ = 45° (δ = (1 − cos 45°) R ≈ 0.29 R) no single normal stands for the contact,
  and the projection of the probe onto the surface approaches its focal point at δ = R, where the surface
  point under the probe slides away sideways (measured at the kidney's pole, R ≈ 7 mm: the force turned
  45-65° off the push and fell by a quarter between 9 and 12 mm);
- *size*: the mask spreads the load over radius r whatever the depth, a tool sunk deeper than its patch is
  wide is not point-like any more; past 1.5 r (on the kidney's flat top, where curvature does not limit)
  the force's tangential part, ½ δ² ‖∇k‖, turned the force more than 10° off the normal (measured).

Hence δ_lin = min(0.29 R_min, 1.5 r) per vertex (R_min = 1/κ_max, the largest principal curvature of the
contact-normal field): the status ``DEEP`` past it (:mod:`pmask.runtime.contact.law`, which also says how the
force keeps growing and its direction stays near the normal there).
"""
from __future__ import annotations

import functools
import logging
import math

import numpy as np

from pmask.runtime.geometry import (contact_normals, crease_blend, scatter_add, triangle_areas, triangle_frames,
                                    triangle_neighbours, vertex_normals)
from pmask.errors import InputError
from pmask.runtime.contact.subdivision import (MAX_LEVELS, MAX_TRIANGLES, choose_levels, mesh_point, round_creases,
                                               subdivide)
from pmask.runtime.spatial import TriangleGrid
from pmask.runtime.stiffness import table_block, zeta_compliance, zeta_deformation

#: the contact cap's half-angle past which one normal no longer stands for the contact (see the module
#: docstring): δ_lin ≤ (1 − cos DEEP_ANGLE) R_min
DEEP_ANGLE = math.radians(45.0)
#: and past this many mask radii of depth the contact is no longer point-like: δ_lin ≤ DEEP_MASK_RADII r
DEEP_MASK_RADII = 1.5

log = logging.getLogger(__name__)


def _rows(a) -> list:
    """An array's rows as a list of tuples of Python floats or ints."""
    return [tuple(r) for r in a.tolist()]


class ContactSurface:
    """What the contact algorithm reads of a stiffness: the mesh, triangle frames and neighbours, contact
    normals, per-vertex rendered K, taper λ, normal stiffness k, its gradient ∇k, the shape operator S and
    the linear depth δ_lin, a spatial grid, and (for several contacts and the display) the ζ table.  The
    arrays are what a runtime table stores (:mod:`pmask.runtime.table`), and :meth:`from_table` rebuilds one
    from a table; plain-Python copies serve the per-tick code.

    stiffness : a :class:`pmask.runtime.stiffness.Stiffness` (or any ``SurfaceStiffness``).
    normal_radius : see :class:`Contacts` (default 3 mask radii, or 6 mean edges without masks).
    levels : the contact surface, see :class:`Contacts`: None (default) or "auto" the automatic choice, n the mesh's
    Loop subdivision surface after n levels (:mod:`pmask.runtime.contact.subdivision`), its creases rounded, 0 the
    mesh.  The mesh's vertices keep their indices, and their positions away from creases (:attr:`mesh_points`);
    ``mesh_T``, ``parent`` and ``corners`` map a contact point to the mesh (:meth:`mesh_point`), where ζ, the
    deformation and the model's own arrays live.
    """

    # plain-Python copies of the arrays for the Python engine's per-tick code, made when it first reads them
    # (:meth:`python_views`): the native core reads the arrays, and making them took 0.5 s of the 1.2 s a
    # contact surface of the default kidney takes to build (by hand)
    _tri = functools.cached_property(lambda self: _rows(self.tri_geom))
    _nb = functools.cached_property(lambda self: _rows(self.neighbours))
    _idx = functools.cached_property(lambda self: _rows(self.T))
    _P = functools.cached_property(lambda self: _rows(self.P))
    _N = functools.cached_property(lambda self: _rows(self.vertex_normals))
    _K = functools.cached_property(lambda self: _rows(self.K))
    _lam = functools.cached_property(lambda self: self.taper.tolist())
    _k = functools.cached_property(lambda self: self.normal_stiffness.tolist())
    _G = functools.cached_property(lambda self: _rows(self.gradient))
    _S = functools.cached_property(lambda self: _rows(self.shape))
    _dlin = functools.cached_property(lambda self: self.linear_depth.tolist())
    _mesh_idx = functools.cached_property(lambda self: _rows(self.mesh_T))
    _parent = functools.cached_property(lambda self: self.parent.tolist())
    _corners = functools.cached_property(lambda self: _rows(self.corners))
    _VIEWS = ("_tri", "_nb", "_idx", "_P", "_N", "_K", "_lam", "_k", "_G", "_S", "_dlin", "_mesh_idx", "_parent",
              "_corners")
    #: the copies a point query reads (:func:`pmask.runtime.contact.tracking.point`, :meth:`mesh_point`): 0.14 s of
    #: the 0.38 s all of them take on the default kidney's contact surface (by hand)
    POINT_VIEWS = ("_idx", "_P", "_parent", "_corners")

    def python_views(self, names=None) -> "ContactSurface":
        """Make the plain-Python copies the Python engine reads every tick now, so that its first tick does not
        (:class:`pmask.runtime.haptics.Contacts` calls it when it runs the Python steps); ``names``: only those
        (e.g. :data:`POINT_VIEWS`, for a server that asks for points alongside the native engine)."""
        for name in self._VIEWS if names is None else names:
            getattr(self, name)
        return self

    def __init__(self, stiffness, normal_radius: float | None = None, levels: int | None = None):
        P0 = np.asarray(stiffness.points, float)
        T0 = np.asarray(stiffness.triangles, np.int64)
        e = np.linalg.norm(P0[T0[:, 1]] - P0[T0[:, 0]], axis=1)
        mean_edge = float(e.mean()) if len(e) else 1.0  # the mesh's: the contact's scales do not change with levels
        if levels is None or (isinstance(levels, str) and levels == "auto"):
            levels = choose_levels(P0, T0)
        elif not (isinstance(levels, (int, np.integer)) and 0 <= levels <= MAX_LEVELS
                  and (levels == 0 or 4 ** levels * len(T0) <= MAX_TRIANGLES)):
            raise InputError(f"levels={levels!r}: the contact surface takes 0 to {MAX_LEVELS} levels of subdivision "
                             f"and at most {MAX_TRIANGLES:,} triangles ({len(T0):,} on this mesh, x4 a level); "
                             "use fewer levels or 'auto'")
        K0 = np.asarray(stiffness.K_vertex, float).reshape(len(P0), 9)
        taper0 = np.asarray(getattr(stiffness, "taper", np.ones(len(P0))), float)
        fields = np.hstack([K0, taper0[:, None]])
        try:
            sub = subdivide(P0, T0, int(levels))
        except ValueError as err:  # not a manifold: the mesh's own triangles
            log.warning("contact surface not subdivided (%s)", err)
            sub = subdivide(P0, T0, 0)
        masks = getattr(stiffness, "masks", None)
        r = getattr(masks, "radius", 0.0) if masks is not None else 0.0
        mask_radius = r if r > 0 else 2.0 * mean_edge  # a single-vertex mask or a bare surface: 2 mean edges
        if normal_radius is None:
            normal_radius = 3.0 * mask_radius
        P, T, normals = self._shape(sub, P0, T0, float(normal_radius))
        frames = triangle_frames(P, T)
        fields = sub.interpolate(T0, fields) if sub.levels else fields  # eq. 15: K_i and λ linear over the mesh
        K, taper = np.ascontiguousarray(fields[:, :9]), np.ascontiguousarray(fields[:, 9])
        k = normal_stiffness(K, normals, taper)
        gradient = normal_stiffness_gradient(P, T, k, frames[:, 3:6], frames[:, 6:9])
        shape = shape_operators(P, T, normals, frames)
        grid = TriangleGrid(P, T, frames=frames)
        lo, hi = P.min(axis=0), P.max(axis=0)
        self._setup(P, T, frames, triangle_neighbours(T), normals, K, taper, k, gradient, shape,
                    linear_depths(shape, mask_radius), grid, lo, hi, mean_edge, float(np.linalg.norm(hi - lo)),
                    float(normal_radius), (T0, sub.parent, sub.corners.reshape(-1, 9)) if sub.levels else None)
        self.levels = sub.levels
        self.stiffness = stiffness
        self.meta = {}

    @classmethod
    def of(cls, stiffness, normal_radius: float | None = None, levels: int | None = None) -> "ContactSurface":
        """The contact surface of a stiffness, built once per normal radius and levels and kept on it (a
        stiffness's mesh and K do not change; a subdivided surface takes a second or so to build, and the native
        core's table is kept per surface)."""
        cache = stiffness.__dict__.setdefault("_contact_surfaces", {})
        key = (None if normal_radius is None else float(normal_radius), levels)
        if key not in cache:
            cache[key] = cls(stiffness, normal_radius, levels)
        return cache[key]

    @staticmethod
    def _shape(sub, P0, T0, normal_radius):
        """(points, triangles, contact normals) of the contact surface.  On the mesh: its own points and
        :func:`pmask.runtime.geometry.contact_normals`.  On a subdivided surface: its vertex normals, blended near
        the mesh's creases as the mesh's are (the blend weight β and the ball-averaged normals of the mesh,
        interpolated), and where β > 0 the surface itself moved along them until they are its own normals
        (:func:`pmask.runtime.contact.subdivision.round_creases`): the crease rounded at the blend's scale, so the
        force is the gradient of its energy there too, and the contact normals are the rounded surface's."""
        P, T = sub.points, sub.triangles
        if not sub.levels:
            return P, T, contact_normals(P0, T0, normal_radius)
        n = vertex_normals(P, T)
        blend = crease_blend(P0, T0, normal_radius)
        if blend is None:
            return P, T, n
        beta, smooth = (sub.interpolate(T0, x) for x in blend)
        target = (1.0 - beta) * n + beta * smooth
        target /= np.linalg.norm(target, axis=1, keepdims=True)
        try:
            P = P + round_creases(P, T, target, beta[:, 0] > 0.0)[:, None] * target
        except ValueError as err:  # (not seen): the creases stay sharp, with the blended normals
            log.warning("contact surface's creases not rounded (%s)", err)
            return P, T, target
        return P, T, vertex_normals(P, T)

    @classmethod
    def from_table(cls, table) -> "ContactSurface":
        """A contact surface from a runtime table (:func:`pmask.runtime.table.read_table`'s result or a path); its
        Green's functions, when the table has them, from the ζ table or (table 1.4) a compressed Ξ's sections
        (:func:`pmask.runtime.table.table_greens`), for coupled contacts and the deformation."""
        from pmask.runtime.table import read_table

        t = table if isinstance(table, dict) else read_table(table)
        P, T = t["points"], t["triangles"]
        grid = TriangleGrid(P, T, frames=t["frames"])
        mean_edge, diag = (float(x) for x in t["lengths"][0])
        srf = cls.__new__(cls)
        srf._setup(P, T, t["frames"], t["neighbours"], t["normals"], t["stiffness"], t["taper"][:, 0],
                   t["normal_stiffness"][:, 0], t["gradient"], t["shape"], t["linear_depth"][:, 0], grid,
                   t["bounds"][0], t["bounds"][1], mean_edge, diag, float(t["meta"].get("normal_radius", 0.0)),
                   (t["mesh_triangles"], t["parent"][:, 0], t["corners"]) if "parent" in t else None)
        srf.levels = (round(math.log(len(T) / len(t["mesh_triangles"]), 4)) if "parent" in t else 0)  # 4x a level
        srf.stiffness = None
        srf.meta = t["meta"]
        srf.table = t  # the native core borrows the same arrays (pmask.runtime.servo: no second read, no copy)
        if "zeta" in t:
            srf._coupling = (t["zeta"], t["contact_row"][:, 0])
        elif "greens" in t:  # a compressed Ξ's own sections (table 1.4): its blocks through the masks
            srf._table_greens = t["greens"]
            srf._block, srf._row = t["greens"].block, t["contact_row"][:, 0].tolist()
        return srf

    def _setup(self, P, T, frames, neighbours, normals, K, taper, k, gradient, shape, linear_depth, grid, lo, hi,
               mean_edge, diag, normal_radius, mesh=None):
        c = np.ascontiguousarray
        self.P, self.T = c(P, dtype=float), c(T, dtype=np.int64)
        self._mapped = mesh is not None
        if mesh is None:  # not subdivided: each triangle is its own mesh triangle
            mesh = (self.T, np.arange(len(self.T)), np.tile(np.eye(3).ravel(), (len(self.T), 1)))
        # the finite-element mesh under the contact surface (:mod:`pmask.runtime.contact.subdivision`): its
        # triangles, and each contact triangle's mesh triangle and corners' barycentrics there
        self.mesh_T = c(mesh[0], dtype=np.int64)
        self.parent = c(mesh[1], dtype=np.int64)
        self.corners = c(np.reshape(mesh[2], (len(self.T), 9)), dtype=float)
        self.n_mesh = int(self.mesh_T.max()) + 1 if len(self.mesh_T) else 0
        self.tri_geom = c(frames, dtype=float)
        self.neighbours = c(neighbours, dtype=np.int64)
        self.vertex_normals = c(normals, dtype=float)
        self.K = c(np.reshape(K, (len(P), 9)), dtype=float)
        self.taper = c(taper, dtype=float)
        self.normal_stiffness = c(k, dtype=float)
        self.gradient = c(gradient, dtype=float)
        self.shape = c(np.reshape(shape, (len(P), 9)), dtype=float)
        self.linear_depth = c(linear_depth, dtype=float)
        self.grid = grid
        self.lo, self.hi = np.asarray(lo, float), np.asarray(hi, float)
        self.mean_edge, self.diag, self.normal_radius = float(mean_edge), float(diag), float(normal_radius)
        self._coupling = None
        self._row = None
        self._block = None
        self._table_greens = None  # a table's compressed Green's functions (from_table)

    def coupling(self):
        """(ζ table, surface vertex -> its row in the table) for the coupled solve and the display;
        None for a surface stiffness without Green's functions, and for a compressed Ξ (no ζ table: it
        would be as large as Ξ; :attr:`greens` says whether contacts can be coupled all the same)."""
        if (self._coupling is None and self.stiffness is not None and hasattr(self.stiffness, "zeta_table")
                and not self.compressed):
            self._coupling = (self.stiffness.zeta_table(), self.stiffness._contact_row)
        return self._coupling

    @property
    def compressed(self) -> bool:
        """Whether the Green's functions are a compressed Ξ (:mod:`pmask.runtime.compressed`)."""
        return bool(getattr(self.stiffness, "compressed", False))

    @property
    def greens(self) -> bool:
        """Whether Green's functions are at hand (coupled contacts, the deformation): a ζ table (dense Ξ, or a
        runtime table exported with one), or a compressed Ξ read block by block."""
        return (self._coupling is not None or self._table_greens is not None
                or (self.stiffness is not None and hasattr(self.stiffness, "zeta_table")))

    def compliance(self, t_l, b_l, t_k, b_k) -> list:
        """C_lk (9 floats): :func:`pmask.runtime.stiffness.zeta_compliance` on this surface's ζ table, or on
        a compressed Ξ's blocks (:meth:`pmask.runtime.stiffness.Stiffness.zeta_block`)."""
        block, row = self._blocks()
        t_l, *b_l = self.mesh_point(t_l, *b_l)
        t_k, *b_k = self.mesh_point(t_k, *b_k)
        return zeta_compliance(block, row, self._mesh_idx, t_l, b_l, t_k, b_k)

    def mesh_point(self, t, b0, b1, b2):
        """(mesh triangle, β0, β1, β2): where the contact point (t, b) lies on the finite-element mesh, whose
        vertices carry ζ (:func:`pmask.runtime.contact.subdivision.mesh_point`)."""
        if not self._mapped:
            return t, b0, b1, b2
        return mesh_point(self._parent, self._corners, t, b0, b1, b2)

    @property
    def mesh_points(self) -> np.ndarray:
        """(n_mesh, 3) where the contact surface has the mesh's vertices (its first points): the mesh's own points,
        except near a crease of a subdivided surface, rounded (:mod:`pmask.runtime.contact.subdivision`).  Draw the
        deformation (:meth:`pmask.runtime.Contacts.deformation`) on these, and the shown surface meets every
        instrument."""
        return self.P[:self.n_mesh]

    def mesh_offset(self, t, b) -> tuple:
        """The contact point (t, b) less the point of the finite-element mesh under it (:meth:`mesh_point`), the mesh
        drawn at :attr:`mesh_points`: zero on the mesh itself, on a subdivided surface the limit surface's bulge over
        the flat triangle (up to about e²/8R for edges e on a radius of curvature R)."""
        from pmask.runtime.contact.tracking import point  # (tracking reads this module)

        if not self._mapped:
            return (0.0, 0.0, 0.0)
        x = point(self, t, *b)
        m, *beta = self.mesh_point(t, *b)
        P, i = self._P, self._mesh_idx[m]  # the mesh's vertices keep their indices (mesh_points)
        return tuple(x[c] - (beta[0] * P[i[0]][c] + beta[1] * P[i[1]][c] + beta[2] * P[i[2]][c]) for c in range(3))

    def _blocks(self):
        """(block function, row list) of :func:`pmask.runtime.stiffness.zeta_compliance`, made once."""
        if self._block is None:
            if self.compressed:
                self._block, row = self.stiffness.zeta_block, self.stiffness._contact_row
            else:
                Zt, row = self.coupling()
                self._block = table_block(Zt)
            self._row = np.asarray(row).tolist()
        return self._block, self._row

    def pair_blocks(self, t_l, t_k) -> list:
        """The nine vertex-pair blocks of two mesh triangles' coupling, 81 floats: for vertex x of t_l and y of t_k
        (x outer), P_xy = ½ (ζ_y(x) + ζ_x(y)ᵀ) row-major, zero where either vertex has no row.  The coupled
        solve keeps them while both contacts stay on their triangles and sums C_lk = Σ_x Σ_y φ_x φ_y P_xy
        each tick (:func:`pmask.runtime.contact.coupling.coupling_blocks`): 81 products from a small
        contiguous block instead of two gathers of nine blocks from the ζ table."""
        block, row = self._blocks()
        out = [0.0] * 81
        for x, i in enumerate(self._mesh_idx[t_l]):
            ri = row[i]
            for y, m in enumerate(self._mesh_idx[t_k]):
                rm = row[m]
                if ri < 0 or rm < 0:
                    continue
                z1, z2 = block(rm, ri), block(ri, rm)  # ζ_y(x)ᵀ, ζ_x(y)ᵀ as lists of rows
                o = 27 * x + 9 * y
                for r in range(3):
                    for c in range(3):
                        out[o + 3 * r + c] = 0.5 * (z1[c][r] + z2[r][c])
        return out

    def deformation_of(self, loads) -> np.ndarray:
        """The mesh surface's displacement (n_s, 3) for point loads [(triangle, barycentrics, force), ...] on
        the contact surface (eq. 16; :func:`zeta_deformation`)."""
        loads = [(t, np.asarray(b), f) for t, *b, f in
                 ((*self.mesh_point(t, *(float(x) for x in b)), f) for t, b, f in loads)]
        if self.compressed:  # no ζ table: Ξ's blocks of the loaded columns
            return self.stiffness.deformation_of(loads)
        if self._table_greens is not None:  # (the same, from a table's sections)
            return self._table_greens.deformation_of(self.mesh_T, self._row, loads)
        Zt, row = self.coupling()
        return zeta_deformation(Zt, row, self.mesh_T, loads)



def at(srf, t, b0, b1, b2):
    """What the law reads at barycentric b of triangle t, interpolated (eq. 15's way): K(x) (9 floats
    row-major), λ(x), k(x), ∇k(x) (3), S(x) (9) and δ_lin(x).  Plain Python, for the per-tick code."""
    i0, i1, i2 = srf._idx[t]
    KK, G, SS = srf._K, srf._G, srf._S
    k0, k1, k2 = KK[i0], KK[i1], KK[i2]
    K = [b0 * k0[i] + b1 * k1[i] + b2 * k2[i] for i in range(9)]
    s0, s1, s2 = SS[i0], SS[i1], SS[i2]
    S = [b0 * s0[i] + b1 * s1[i] + b2 * s2[i] for i in range(9)]
    g0, g1, g2 = G[i0], G[i1], G[i2]
    g = (b0 * g0[0] + b1 * g1[0] + b2 * g2[0], b0 * g0[1] + b1 * g1[1] + b2 * g2[1],
         b0 * g0[2] + b1 * g1[2] + b2 * g2[2])
    lam, kn, dl = srf._lam, srf._k, srf._dlin
    return (K, b0 * lam[i0] + b1 * lam[i1] + b2 * lam[i2], b0 * kn[i0] + b1 * kn[i1] + b2 * kn[i2], g, S,
            b0 * dl[i0] + b1 * dl[i1] + b2 * dl[i2])


def shape_at(srf, t, b0, b1, b2):
    """S(x) (9 floats) alone, interpolated as :func:`at` does: what step 1 reads every tick."""
    i0, i1, i2 = srf._idx[t]
    SS = srf._S
    s0, s1, s2 = SS[i0], SS[i1], SS[i2]
    return [b0 * s0[i] + b1 * s1[i] + b2 * s2[i] for i in range(9)]


def normal_stiffness(K, N, taper) -> np.ndarray:
    """(n_s,): the normal stiffness k_j = λ_j / (n_jᵀ K_j⁻¹ n_j) per vertex: the stiffness along the contact
    normal with the surface free to slide under the tool (the Schur complement of K's tangential block),
    tapered.  The law interpolates it linearly, k(x) = Σ_j φ_j(x) k_j, so that ½ k δ² is an energy whose
    surface gradient the vertex gradients below interpolate."""
    Kv = np.reshape(K, (-1, 3, 3))
    Ki = np.linalg.inv(Kv)
    return np.asarray(taper, float) / np.einsum("vi,vij,vj->v", N, Ki, N)


def normal_stiffness_gradient(P, T, k, dual_a, dual_b) -> np.ndarray:
    """(n_s, 3): the surface gradient ∇k of the normal stiffness, per vertex.

    On each triangle, the gradient of the linear interpolant of the vertex values (∇φ_1 = a, ∇φ_2 = b,
    ∇φ_0 = −a − b with a, b the duals of the edges); at a vertex, the area-weighted mean over its
    triangles.  Interpolated (eq. 15's way) it gives the tangential force that makes the frictionless force
    the gradient of the stored energy ½ k δ² (continuous across edges, unlike the per-triangle gradient,
    which jumps by a few % of the force)."""
    g_t = (k[T[:, 1]] - k[T[:, 0]])[:, None] * dual_a + (k[T[:, 2]] - k[T[:, 0]])[:, None] * dual_b
    return _vertex_mean(P, T, g_t)


def shape_operators(P, T, VN, frames) -> np.ndarray:
    """(n_s, 9): the shape operator S_j = P ∇N P of the contact-normal field per vertex (row-major,
    symmetric, on the triangle planes): per triangle the gradient of the linearly interpolated normals
    projected on its plane, area-averaged at the vertices.  Its eigenvalues are the principal curvatures
    (1/R; positive where the surface is convex), and a probe δ below a point of the surface moves that
    point's projection (I − δ S)⁻¹ times as fast as it moves itself."""
    a, b, n = frames[:, 3:6], frames[:, 6:9], frames[:, 9:12]
    d1, d2 = VN[T[:, 1]] - VN[T[:, 0]], VN[T[:, 2]] - VN[T[:, 0]]
    grad = np.einsum("ti,tj->tij", d1, a) + np.einsum("ti,tj->tij", d2, b)
    Pf = np.eye(3)[None] - np.einsum("ti,tj->tij", n, n)
    S = Pf @ grad @ Pf
    S = 0.5 * (S + np.swapaxes(S, 1, 2))
    return _vertex_mean(P, T, S.reshape(-1, 9))


def linear_depths(shape, mask_radius: float) -> np.ndarray:
    """(n_s,): δ_lin = min((1 − cos 45°) / κ_max, 1.5 r) per vertex, the depth past which the linear contact
    stops being meaningful (the module docstring)."""
    kmax = np.linalg.eigvalsh(np.reshape(shape, (-1, 3, 3)))[:, -1]
    by_size = DEEP_MASK_RADII * float(mask_radius)
    by_curvature = (1.0 - math.cos(DEEP_ANGLE)) / np.maximum(kmax, 1e-300)
    return np.minimum(by_curvature, by_size)


def _vertex_mean(P, T, per_triangle) -> np.ndarray:
    """Area-weighted mean over each vertex's triangles of a per-triangle quantity (n_t, m)."""
    area = triangle_areas(P, T)
    corner = np.asarray(T).T  # corner 0's triangles, then 1's, then 2's: the order the sums ran in
    out = scatter_add(corner, np.tile(area[:, None] * per_triangle, (3, 1)), len(P))
    w = scatter_add(corner, np.tile(area, 3), len(P))
    return out / np.maximum(w, 1e-300)[:, None]
