r"""The finite elements: each registers its assembly, its consistent traction load, its Green's-function
route and its memory estimate here, and :mod:`pmask.pipeline.stages` asks the registry, never the
element's name.

Dofs are node-major, ``3 * node + component``.  The traction is always in the paper's space
(eq. 6): piecewise linear over the surface triangles, p(x) = Σ_j φ_j(x) p_j.

``P1``  linear tetrahedra; nodes are the vertices.  A traction p_j acts as the nodal force a_j p_j
        (the lumped boundary mass of eq. 10), so B = E diag(a) and Ξ = G diag(a) with G symmetric:
        the symmetric selected inversion (one dsyrk per supernode).  Locks for nearly incompressible
        material: +8 % stiffness at ν = 0.45 and h = r/16 on the half-space (README).
``P2``  quadratic tetrahedra; nodes are the vertices, then the edges (scikit-fem's order).  The
        consistent load of a P1 traction, f_k = Σ_j (∫ ψ_k φ_j dΓ) p_j, lives on corner *and* edge
        nodes (:func:`surface_load_matrix`); Ξ is read at the corners: Ξ = Eᵀ K⁻¹ B, one dgemm per
        supernode.  The volumetric term λ ∫ div u div v is integrated with the one-point (centroid) rule:
        div u is linear on a P2 tetrahedron, so this is the exact integral of its element mean, i.e.
        the mixed P2–P0 displacement–pressure element with the pressure condensed, which does not lock
        as ν → 1/2 (measured in the README: full integration locks at ν = 0.499); the deviatoric term
        keeps the full (order 2) rule.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from pmask.errors import InputError
from pmask.precompute.elasticity import dofs


@dataclass
class Discretisation:
    """A tetrahedral mesh as an element sees it: its nodes and their connectivity."""

    element: str
    points: np.ndarray
    tets: np.ndarray
    n_nodes: int
    connectivity: np.ndarray  # (M, nodes per element): for the node graph of the pip-only AMD order
    edges: np.ndarray | None = None  # (n_edges, 2), P2: node n_vertices + e is the midpoint of edge e


def _skfem_mesh(points, tets):
    from skfem import MeshTet

    return MeshTet(np.ascontiguousarray(points.T), np.ascontiguousarray(tets.T))


class Element:
    """Interface; see :class:`P1` and :class:`P2`."""

    name = ""
    #: how many times P1's working memory per byte of Ξ the route needs (see :meth:`memory_estimate`)
    xi_factor = 1.6

    def discretise(self, points, tets) -> Discretisation:
        raise NotImplementedError

    def locking(self, nu: float) -> str | None:
        """A warning if this element locks at ν (or :class:`InputError` where it is useless); None if not."""
        return None

    def stiffness(self, d: Discretisation, E: float, nu: float) -> sp.csr_matrix:
        raise NotImplementedError

    def dirichlet_nodes(self, d: Discretisation, fixed: np.ndarray, facets: np.ndarray) -> np.ndarray:
        """Nodes held by the support: the fixed vertices (and, P2, the edge nodes of the fixed
        ``facets``, (k, 3) volume vertex indices: the support is held facet by facet, so an edge through
        the body between two fixed vertices keeps its midside node free)."""
        return np.asarray(fixed, np.int64)

    def load(self, d: Discretisation, triangles: np.ndarray, contact: np.ndarray, areas: np.ndarray):
        """The consistent load of unit tractions at the contact vertices: (B, None) with B sparse
        (3 n_nodes x 3 n_c), or (None, scale) when B is the contact dofs' unit columns times scale."""
        raise NotImplementedError

    def lump_reactions(self, d: Discretisation, fixed: np.ndarray, facets: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Reactions on the Dirichlet dofs -> reactions per fixed vertex (3 n_fixed x k)."""
        return R

    def memory_estimate(self, n_volume_vertices: int, n_contact: int) -> dict:
        """Bytes the Green's-function stage needs, before it runs: Ξ, the sparse factor and the
        working arrays.  The factor from a rule fitted to the kidney sizes (nnz(L) per dof)."""
        xi = 8.0 * (3 * n_contact) ** 2
        dof = 3 * n_volume_vertices * self.dofs_per_vertex
        factor = 8.0 * dof * self.l_per_dof(dof)
        return {"Xi": xi, "factor": factor, "total": self.xi_factor * xi + 1.5 * factor}

    dofs_per_vertex = 1.0

    def l_per_dof(self, dof: float) -> float:
        """Stored entries of L per dof, measured on the kidney with METIS (grows like dof^(1/3) in 3-D)."""
        return 212.0 * (dof / 7419.0) ** (1.0 / 3.0)


class P1(Element):
    name = "P1"
    xi_factor = 1.6  # the native route's result buffer also holds the rows next to the support
    #: P1 is warned about from this Poisson's ratio (and refused from REFUSE_NU); the automatic choice
    #: (:func:`default_element`) takes P2 from here on
    WARN_NU, REFUSE_NU = 0.4, 0.49

    def locking(self, nu: float) -> str | None:
        """Linear tetrahedra lock as ν → 1/2 (measured on the half-space, tests/reference/halfspace.csv):
        masked k_n +8 % (h = r/16) to +17 % (h = r/4) too stiff at ν = 0.45, 2.1x Boussinesq at ν = 0.499,
        and 5,000x at 0.4999999.  Refused from ν = 0.49, a warning from ν = 0.4."""
        if nu >= self.REFUSE_NU:
            raise InputError(f"P1 tetrahedra lock at nu = {nu:g} (at 0.499 the normal stiffness is 2.1x "
                             "Boussinesq's, at 0.4999999 5,000x): use --element P2, which does not lock (its "
                             "volumetric term is the P2-P0 element's: within 2.4 % of Boussinesq up to nu = 0.499)")
        if nu >= self.WARN_NU:
            return (f"P1 tetrahedra stiffen for nearly incompressible material (nu = {nu:g}): at nu = 0.45 the "
                    "masked normal stiffness on the half-space is 8 % (h = r/16) to 17 % (h = r/4) too high; "
                    "--element P2 does not lock (README, 'Analytic half-space')")
        return None

    def discretise(self, points, tets) -> Discretisation:
        return Discretisation("P1", points, tets, len(points), np.asarray(tets, np.int64))

    def stiffness(self, d, E, nu):
        """K of linear elasticity (:mod:`pmask.precompute.assembly`); E and ν scalars or one per tetrahedron."""
        from pmask.precompute.assembly import stiffness

        return stiffness(d.points, d.tets, E, nu, order=1, n_nodes=d.n_nodes)

    def load(self, d, triangles, contact, areas):
        return None, np.repeat(np.asarray(areas, float), 3)


class P2(Element):
    name = "P2"
    xi_factor = 2.0  # Ξ plus the rows next to the support, W_E and W_B are measured below Ξ's size
    dofs_per_vertex = 6.7  # (vertices + edges) / vertices of a tet mesh, measured on the kidney

    def l_per_dof(self, dof: float) -> float:
        return 547.0 * (dof / 49824.0) ** (1.0 / 3.0)  # 27.2 M entries for 49,824 dofs (kidney)

    def discretise(self, points, tets) -> Discretisation:
        mesh = _skfem_mesh(points, tets)
        edges = np.sort(mesh.edges.T, axis=1).astype(np.int64)
        t2e = mesh.t2e.T.astype(np.int64)  # (M, 6) edge indices of each tetrahedron
        conn = np.concatenate([np.asarray(tets, np.int64), len(points) + t2e], axis=1)
        return Discretisation("P2", points, tets, len(points) + len(edges), conn, edges)

    def stiffness(self, d, E, nu):
        """K with the volumetric term at the centroid (P2–P0; :mod:`pmask.precompute.assembly`, which
        tests/test_assembly.py holds to scikit-fem's ``ElementVector(ElementTetP2())`` assembly to round-off); E
        and ν scalars or one per tetrahedron."""
        from pmask.precompute.assembly import stiffness

        return stiffness(d.points, d.tets, E, nu, order=2, edges=d.edges, n_nodes=d.n_nodes)

    def dirichlet_nodes(self, d, fixed, facets):
        e = np.sort(np.concatenate([facets[:, [0, 1]], facets[:, [1, 2]], facets[:, [2, 0]]]), axis=1)
        n = len(d.points)
        fixed_edges = np.flatnonzero(np.isin(d.edges[:, 0] * n + d.edges[:, 1], e[:, 0] * n + e[:, 1]))
        return np.concatenate([np.asarray(fixed, np.int64), n + fixed_edges])

    def load(self, d, triangles, contact, areas):
        B = surface_load_matrix(d.points, triangles, d.edges)
        return sp.kron(B[:, contact], sp.identity(3), format="csr"), None

    def lump_reactions(self, d, fixed, facets, R):
        """Each fixed edge node's reaction split half and half onto its end vertices (same total force
        and moment: the midpoint is their average)."""
        nv = len(fixed)
        out = R[:3 * nv].copy()
        pos = np.full(len(d.points), -1)
        pos[fixed] = np.arange(nv)
        held_edges = self.dirichlet_nodes(d, fixed, facets)[nv:] - len(d.points)
        for q, e in enumerate(held_edges):
            r = R[3 * (nv + q):3 * (nv + q) + 3]
            for v in d.edges[e]:
                out[3 * pos[v]:3 * pos[v] + 3] += 0.5 * r
        return out


def surface_load_matrix(points: np.ndarray, triangles: np.ndarray, edges: np.ndarray) -> sp.csr_matrix:
    """Scalar (n_vertices + n_edges, n_vertices) matrix B_kj = ∫ ψ_k φ_j dΓ over the given triangles
    (volume vertex indices): P2 test functions ψ (corners, then edges in ``edges`` order) against the
    P1 traction hats φ.  On a triangle of area A (ψ_k = φ_k(2φ_k − 1) at a corner, 4 φ_a φ_b at the
    midpoint of edge ab):

        corner k, j = k: A/30      corner k, j ≠ k: −A/60
        edge ab,  j ∈ {a, b}: 2A/15    edge ab, j opposite: A/15

    (a P1 traction puts no net force on the corners; the column sums are a_j = ∫ φ_j dΓ).
    ``kron(B, I3)`` maps nodal tractions to P2 nodal forces."""
    N = len(points)
    p = points[triangles]
    A = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    key = edges[:, 0] * N + edges[:, 1]
    order = np.argsort(key)

    def edge_node(a, b):
        k = np.minimum(a, b) * N + np.maximum(a, b)
        pos = order[np.searchsorted(key, k, sorter=order)]
        return N + pos

    rows, cols, vals = [], [], []
    for k in range(3):
        for j in range(3):
            rows.append(triangles[:, k])
            cols.append(triangles[:, j])
            vals.append(A / 30 if k == j else -A / 60)
        a, b = triangles[:, k], triangles[:, (k + 1) % 3]
        c = triangles[:, (k + 2) % 3]
        m = edge_node(a, b)
        for j, w in ((a, 2 * A / 15), (b, 2 * A / 15), (c, A / 15)):
            rows.append(m)
            cols.append(j)
            vals.append(w)
    B = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(N + len(edges), N))
    B.sum_duplicates()
    return B


#: the elements a user can ask for (``--element``)
ELEMENTS = {"P1": P1(), "P2": P2()}


#: ``--element auto`` (the default): the element is chosen from the material (:func:`default_element`)
AUTO = "auto"


def default_element(nu: float) -> str:
    """The element ``--element auto`` takes: P2 wherever P1 would lock (its warning, from ν = 0.4: soft tissue,
    ν ≈ 0.45–0.499), P1 where it does not (ν = 0.3: the half-space and Figure 5 studies, and 4-5x faster).
    Measured on the default kidney (ν = 0.45, its own mesh): P1's masked ‖K_i‖ is a quarter above P2's at the
    median, and against a finer P2 kidney P1 is about as far off where P2 is within a per cent."""
    return "P2" if nu >= P1.WARN_NU else "P1"


def element_name(name: str, nu: float) -> str:
    """The element a run uses: ``name``, or :func:`default_element` for ``auto``."""
    return default_element(nu) if name == AUTO else name


def get_element(name: str) -> Element:
    """The element registered under ``name`` (``auto`` is resolved by :func:`element_name` first)."""
    try:
        return ELEMENTS[name]
    except KeyError:
        raise InputError(f"unknown element {name!r}; choose one of {', '.join(ELEMENTS)} or auto") from None


def observed_dofs(contact_vertices: np.ndarray) -> np.ndarray:
    """The dofs at which Ξ reads displacements: the contact vertices' (corner nodes')."""
    return dofs(contact_vertices)
