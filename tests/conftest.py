"""Shared fixtures: small artifacts built once per session, and an independent FE solver."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

ROOT = Path(__file__).resolve().parent.parent

from pmask.pipeline.stages import Spec, run  # noqa: E402
from pmask.precompute.elasticity import dofs, stiffness_matrix  # noqa: E402


def gmsh_volume(path, solids, size: float) -> Path:
    """A user's tet mesh written by gmsh: ``solids(gmsh)`` adds OCC solids (fragmented into a conformal mesh)
    and returns {physical group name: (dimension, entity tags)} after the model is synchronised; each group's
    tags are picked by ``solids`` from the entities then present."""
    import gmsh

    gmsh.initialize(["-noenv"])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        groups = solids(gmsh)
        for name, (dim, tags) in groups.items():
            gmsh.model.addPhysicalGroup(dim, list(tags), name=name)
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        gmsh.model.mesh.generate(3)
        gmsh.write(str(path))
    finally:
        gmsh.finalize()
    return Path(path)


def build(tmp_path_factory, name: str, spec: Spec) -> Path:
    """The artifact ``name`` of ``spec``, precomputed once for the whole session: under ``make test``'s two
    processes (pytest-xdist) in their shared temporary folder, the first to ask building it under a file lock and
    the other reading the same file (each built its own before: the default kidney alone took 18 s a process)."""
    import fcntl
    import os

    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the session's folder, above each process's own
    folder = root / "artifacts"
    folder.mkdir(exist_ok=True)
    out = folder / f"{name}.h5"
    with open(folder / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not out.exists():  # (the pipeline writes it whole or not at all: runtime.files.atomic_write)
            run(spec, out)
    return out


@pytest.fixture(scope="session")
def kidney_small(tmp_path_factory) -> Path:
    """A coarse kidney (about 500 surface vertices): the default model (P2, as --element auto makes it at the
    kidney's ν = 0.45) at a CI-friendly size."""
    return build(tmp_path_factory, "kidney_small", Spec(model="kidney", params={"size": 0.009}))


@pytest.fixture(scope="session")
def kidney_small_p1(tmp_path_factory) -> Path:
    """The coarse kidney with linear tetrahedra (P1, as --element P1 makes it): the routes of the P1 load."""
    return build(tmp_path_factory, "kidney_small_p1", Spec(model="kidney", params={"size": 0.009}, element="P1"))


@pytest.fixture(scope="session")
def halfspace_small(tmp_path_factory) -> Path:
    """A coarse half-space with a contact region (Ξ over a subset of the free surface)."""
    return build(tmp_path_factory, "halfspace_small",
                 Spec(model="halfspace", params={"h_load": 0.0025, "far": 10.0}, reactions=True))


class _Permuted:
    """A factor of P A Pᵀ solving A x = b: x[p] = (P A Pᵀ)⁻¹ b[p]."""

    def __init__(self, lu, p):
        self.lu, self.p = lu, p

    def solve(self, b):
        b = np.asarray(b, float)
        x = np.empty_like(b)
        x[self.p] = self.lu.solve(b[self.p])
        return x


def spd_lu(A):
    """SuperLU of a symmetric positive definite system (a stiffness with its support held), ordered by approximate
    minimum degree (AMD, cvxopt's: a permutation only) and factorised without pivoting in symmetric mode (SPD
    needs none: the same accuracy as a Cholesky factor).  SuperLU's own orderings were slower on the same fill:
    the 32,928-dof P2 half-space system of ``test_contacts`` took 21 s with its minimum degree on A + Aᵀ (and 52 s
    with its default, COLAMD with partial pivoting) against 11 s ordered by AMD (by hand, 58 M entries of L + U in
    both).  Still SuperLU: independent of pmask's CHOLMOD factorisation."""
    import cvxopt
    import cvxopt.amd

    A = A.tocsc()
    low = sp.tril(A).tocoo()
    p = np.array(list(cvxopt.amd.order(cvxopt.spmatrix(low.data, low.row.tolist(), low.col.tolist(), size=A.shape))),
                 np.int64)
    lu = spla.splu(A[p][:, p].tocsc(), permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    return _Permuted(lu, p)


def full_solve(points, tets, E, nu, fixed_vertices, loads):
    """Independent route for P1: the whole free system K_FF u = f by SuperLU (no condensation), the stiffness by
    scikit-fem.

    loads : (3N, k) nodal forces.  Returns (u (3N, k) with zeros on fixed dofs, reactions (3N, k) = K u
    restricted to fixed dofs, i.e. the forces the support exerts).
    """
    K = stiffness_matrix(points, tets, E, nu).tocsc()
    n = K.shape[0]
    fixed = dofs(fixed_vertices)
    free = np.setdiff1d(np.arange(n), fixed)
    lu = spd_lu(K[free][:, free])
    u = np.zeros((n, loads.shape[1]))
    u[free] = lu.solve(np.asarray(loads[free], float))
    r = np.zeros_like(u)
    r[fixed] = (K @ u)[fixed] - loads[fixed]
    return u, r


class FullSystem:
    """The independent route for an artifact, P1 or P2 as it was made: the whole free system of its volume mesh,
    the stiffness assembled by scikit-fem (``ElementVector(ElementTetP1/P2)``; P2 with the volumetric term at the
    centroid, the P2-P0 element), the traction's load as pmask defines it (P1: the lumped a_j p_j; P2: the
    consistent load of the piecewise-linear traction, scikit-fem's mixed P1 x P2 facet mass), the support held
    (P1: the fixed vertices; P2: also the edge nodes of the facets it holds), factorised once by SuperLU
    (:func:`spd_lu`).  No pmask assembly, load, factorisation or condensation takes part."""

    def __init__(self, path):
        from skfem import (Basis, BilinearForm, ElementTetP1, ElementTetP2, ElementVector, FacetBasis, MeshTet,
                           asm)
        from skfem.helpers import ddot, div, sym_grad

        from pmask.runtime.artifact import read_artifact

        d = read_artifact(path)
        self.element = d["attrs"].get("element", "P1")
        P, T = d["volume/points"], d["volume/tets"]
        vi, fixed, tris = d["surface/volume_index"], d["surface/fixed"], d["surface/triangles"]
        self.vi, self.areas, self.fixed_volume = vi, d["surface/vertex_areas"], vi[fixed]
        self.points = P
        material = d["attrs"]["material"]
        E, nu = material["E"], material["nu"]
        if material.get("regions"):  # materials by region: each tetrahedron's from the artifact's own record
            label = np.asarray(d["volume/material_region"])
            E = np.where(label >= 0, np.array([r["E"] for r in material["regions"]] + [E])[label], E)
            nu = np.where(label >= 0, np.array([r["nu"] for r in material["regions"]] + [nu])[label], nu)
        N = len(P)
        mesh = MeshTet(np.ascontiguousarray(P.T), np.ascontiguousarray(T.T))
        lam, mu = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))

        @BilinearForm
        def dev(u, v, w):
            return 2.0 * w.mu * ddot(sym_grad(u), sym_grad(v))

        @BilinearForm
        def vol(u, v, w):
            return w.lam * div(u) * div(v)

        def per_element(x, basis):  # a scalar, or one value per tetrahedron at each quadrature point
            return x if np.ndim(x) == 0 else np.repeat(np.asarray(x, float)[:, None], basis.X.shape[1], axis=1)

        if self.element == "P1":
            if np.ndim(E) == 0:
                K = stiffness_matrix(P, T, E, nu)
            else:
                b1 = Basis(mesh, ElementVector(ElementTetP1()), intorder=1)
                K = (asm(dev, b1, mu=per_element(mu, b1)) + asm(vol, b1, lam=per_element(lam, b1))).tocsr()
            held = dofs(self.fixed_volume)
            self.B = None
        else:
            el = ElementVector(ElementTetP2())
            full, centroid = Basis(mesh, el, intorder=2), Basis(mesh, el, intorder=1)
            assert np.array_equal(full.nodal_dofs, 3 * np.arange(N) + np.arange(3)[:, None])
            assert full.edge_dofs[0, 0] == 3 * N

            @BilinearForm
            def mass(u, v, w):
                return u * v

            K = (asm(dev, full, mu=per_element(mu, full)) + asm(vol, centroid, lam=per_element(lam, centroid))).tocsr()
            self.B = asm(mass, FacetBasis(mesh, ElementTetP1(), intorder=4),
                         FacetBasis(mesh, ElementTetP2(), intorder=4))
            fixed_mask = np.zeros(len(d["surface/points"]), bool)
            fixed_mask[fixed] = True
            facets = vi[tris[np.all(fixed_mask[tris], axis=1)]]
            e = np.sort(np.concatenate([facets[:, [0, 1]], facets[:, [1, 2]], facets[:, [2, 0]]]), axis=1)
            edges = np.sort(mesh.edges.T, axis=1)
            self.held_edges = np.flatnonzero(np.isin(edges[:, 0] * N + edges[:, 1], e[:, 0] * N + e[:, 1]))
            self.edges = edges
            held = np.concatenate([dofs(self.fixed_volume), 3 * (N + self.held_edges)[:, None].repeat(3, 1).ravel()
                                   + np.tile(np.arange(3), len(self.held_edges))])
        self.K = K.tocsc()
        self.N, self.n = N, K.shape[0]
        self.held = np.sort(held)
        self.free = np.setdiff1d(np.arange(self.n), self.held)
        self.lu = spd_lu(self.K[self.free][:, self.free])

    _built: dict = {}

    @classmethod
    def of(cls, path) -> "FullSystem":
        """The system of the artifact at ``path``, assembled and factorised once per process (several tests solve
        the default kidney's; the artifact is read-only, keyed by its path and modification time)."""
        key = (str(path), Path(path).stat().st_mtime_ns)
        if key not in cls._built:
            cls._built[key] = cls(path)
        return cls._built[key]

    def loads(self, tractions):
        """Nodal forces (n_dofs, k) of nodal traction values (n_surface, 3, k) at the surface vertices."""
        tr = np.asarray(tractions, float)
        tr = tr.reshape(tr.shape[0], 3, -1)
        k = tr.shape[2]
        f = np.zeros((self.n, k))
        if self.B is None:
            f[dofs(self.vi)] = (self.areas[:, None, None] * tr).reshape(-1, k)
        else:
            pv = np.zeros((self.N, 3, k))
            pv[self.vi] = tr
            for c in range(3):
                f[c::3] = self.B @ pv[:, c, :]
        return f

    def field(self, tractions) -> tuple[np.ndarray, np.ndarray]:
        """(every dof's displacement (n_dofs, k): P2's edge nodes too, the nodal forces) for the tractions."""
        f = self.loads(tractions)
        u = np.zeros_like(f)
        u[self.free] = self.lu.solve(f[self.free])
        return u, f

    def value_at(self, u, triangle, bary) -> np.ndarray:
        """The finite-element displacement (3, k) at barycentrics ``bary`` of a surface triangle (its volume
        vertices) from :meth:`field`'s ``u``: P1's linear interpolant, P2's quadratic one through the edge nodes
        (vertex shape functions b_i (2 b_i - 1), edge ones 4 b_i b_j)."""
        v, b = [int(x) for x in triangle], np.asarray(bary, float)
        if self.B is None:
            return sum(b[i] * u[3 * v[i]:3 * v[i] + 3] for i in range(3))
        if not hasattr(self, "_edge_of"):
            self._edge_of = {(int(a), int(c)): e for e, (a, c) in enumerate(self.edges)}
        out = sum(b[i] * (2 * b[i] - 1) * u[3 * v[i]:3 * v[i] + 3] for i in range(3))
        for i, j in ((0, 1), (1, 2), (2, 0)):
            e = 3 * (self.N + self._edge_of[min(v[i], v[j]), max(v[i], v[j])])
            out = out + 4 * b[i] * b[j] * u[e:e + 3]
        return out

    def solve(self, tractions):
        """(u at the volume vertices (N, 3, k), support reactions per fixed vertex (n_fixed, 3, k)) for the
        tractions (n_surface, 3, k); P2's edge-node reactions go half to each end of their edge."""
        u, f = self.field(tractions)
        r = np.zeros_like(f)
        r[self.held] = (self.K @ u)[self.held] - f[self.held]
        k = f.shape[1]
        react = r[dofs(self.fixed_volume)].reshape(-1, 3, k)
        if self.B is not None:
            pos = {int(v): i for i, v in enumerate(self.fixed_volume)}
            for e in self.held_edges:
                re = r[3 * (self.N + e):3 * (self.N + e) + 3]
                for v in self.edges[e]:
                    react[pos[int(v)]] += 0.5 * re
        return u[:3 * self.N].reshape(self.N, 3, k), react


def traced_peak(f, *args, **kwargs):
    """f(*args, **kwargs) and the peak bytes tracemalloc counts above what was held when it started, with the
    cyclic collector off so that no earlier test's garbage is finalised inside (tracemalloc counts every thread's
    allocations: where another thread may allocate, measure in an interpreter of its own, as test_compress
    does)."""
    import gc
    import tracemalloc

    gc.collect()
    gc.disable()
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        out = f(*args, **kwargs)
        return out, tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
        gc.enable()


def relerr(a, b) -> float:
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / np.linalg.norm(b))



def laplacian_3d(k: int, seed: int):
    """SPD: a k^3 grid Laplacian plus a random positive diagonal (CSC)."""
    import scipy.sparse as sp

    one = sp.diags([-np.ones(k - 1), 2 * np.ones(k), -np.ones(k - 1)], [-1, 0, 1])
    eye = sp.identity(k)
    L = (sp.kron(sp.kron(one, eye), eye) + sp.kron(sp.kron(eye, one), eye) + sp.kron(sp.kron(eye, eye), one))
    return (L + sp.diags(np.random.default_rng(seed).uniform(0.1, 1.0, k ** 3))).tocsc()


def random_spd(n: int, density: float, rng):
    """SPD by diagonal dominance, any sparsity (CSC)."""
    import scipy.sparse as sp

    R = sp.random(n, n, density=density, random_state=rng)
    A = R + R.T
    return (A + sp.diags(np.asarray(abs(A).sum(axis=1)).ravel() + rng.uniform(0.1, 1.0, n))).tocsc()


def lower(A):
    """The lower triangle in CSC with sorted rows (what CHOLMOD reads)."""
    import scipy.sparse as sp

    low = sp.tril(A, format="csc")
    low.sort_indices()
    return low


def dense_factor(L: dict) -> np.ndarray:
    """The supernodal arrays read back into a dense lower-triangular L."""
    n = len(L["perm"])
    out = np.zeros((n, n))
    for s in range(len(L["super"]) - 1):
        k1, k2 = L["super"][s], L["super"][s + 1]
        rows = L["s"][L["pi"][s]:L["pi"][s + 1]]
        block = L["x"][L["px"][s]:L["px"][s] + len(rows) * (k2 - k1)].reshape(k2 - k1, len(rows)).T
        out[np.ix_(rows, np.arange(k1, k2))] = block
    return np.tril(out)


def element_spd(n: int, n_elements: int, rng, size: int = 4):
    """SPD like an assembled finite-element matrix: random cliques of ``size`` nodes ("elements"),
    each adding a random SPD block, plus a positive diagonal (CSC).  Returns (A, elements)."""
    import scipy.sparse as sp

    elements = np.array([rng.choice(n, size, replace=False) for _ in range(n_elements)]).reshape(-1, size)
    rows, cols, vals = [], [], []
    for e in elements:
        X = rng.standard_normal((size, size))
        blk = X @ X.T
        rows.append(np.repeat(e, size))
        cols.append(np.tile(e, size))
        vals.append(blk.ravel())
    A = sp.csc_matrix((np.concatenate(vals) if vals else [], (np.concatenate(rows) if rows else [],
                       np.concatenate(cols) if cols else [])), shape=(n, n))
    return (A + sp.diags(rng.uniform(0.5, 1.5, n))).tocsc(), elements


def patch_loads(elements, n: int, k: int, rng):
    """k load columns, each spread over some nodes of one random element (a consistent load on an
    element patch), as a sparse (n, k) matrix."""
    import scipy.sparse as sp

    B = sp.lil_matrix((n, k))
    for c in range(k):
        e = elements[rng.integers(len(elements))]
        for node in e[:rng.integers(1, len(e) + 1)]:
            B[node, c] = rng.uniform(-1.0, 1.0)
    return B.tocsc()


@pytest.fixture(scope="session")
def kidney_default(tmp_path_factory) -> Path:
    """The default kidney (1,446 free vertices): what the haptics issue measured on."""
    return build(tmp_path_factory, "kidney_default", Spec(model="kidney"))


@pytest.fixture(scope="session")
def model(kidney_default):
    """The default kidney loaded once (test modules about the small kidney override this fixture)."""
    from pmask.runtime import Model

    return Model.load(kidney_default)


@pytest.fixture(scope="session")
def stiff(model):
    """The cone mask at 2 mean edge lengths, the runtime's default radius."""
    return model.stiffness("linear", 2 * model.mean_edge_length)


@pytest.fixture(scope="session")
def surface(stiff):
    """The haptic surface built once (normals, gradients, grid), shared by the haptics and servo tests."""
    from pmask.runtime.contact import ContactSurface

    return ContactSurface(stiff)


@pytest.fixture(scope="session")
def kidney_top(tmp_path_factory) -> Path:
    """The default kidney with a contact region (the upper half, z > 0): Ξ only there, widened by r_max."""
    return build(tmp_path_factory, "kidney_top", Spec(model="kidney", contact="z>0"))


#: test files whose tests share no fixture and are handed out one by one (``make test`` otherwise sends a whole file
#: to one process, so that its module fixtures, a precomputed model or a LocalCluster, are built once): the slow
#: corpus, a minute a test at most, which as one file kept one process busy long after the other had finished
SPREAD_FILES = ("tests/test_corpus.py",)


def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile`` as pytest-xdist schedules it, but test by test in :data:`SPREAD_FILES`."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class Scheduling(LoadFileScheduling):
        def _split_scope(self, nodeid):
            return nodeid if nodeid.split("::", 1)[0] in SPREAD_FILES else super()._split_scope(nodeid)

    return Scheduling(config, log)
