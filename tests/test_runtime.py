"""Runtime: masks, vertex/surface stiffness against full FE solves, deformation, continuity, validation."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT, FullSystem, relerr
from pmask.precompute.elasticity import dofs
from pmask.runtime import MASK_KINDS, Model, pressure_masks
from pmask.runtime.geometry import vertex_areas


@pytest.fixture(scope="module")
def model(kidney_small):
    return Model.load(kidney_small)


def test_runtime_imports_no_heavy_packages():
    code = ("import sys, pmask.runtime; heavy = [m for m in ('scipy', 'gmsh', 'skfem', 'meshio', 'trimesh', 'cvxopt', "
            "'pmask.precompute', 'pmask.pipeline', 'pmask.meshes', 'matplotlib') if m in sys.modules]; "
            "print(heavy); sys.exit(bool(heavy))")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def uneven_surface(seed=0):
    """A graded, very uneven triangulation of the unit square (triangle areas spanning 4 decades)."""
    rng = np.random.default_rng(seed)
    xs = np.cumsum(np.r_[0, np.geomspace(1e-3, 0.2, 24)])
    ys = np.cumsum(np.r_[0, rng.uniform(0.002, 0.1, 20)])
    X, Y = np.meshgrid(xs / xs[-1], ys / ys[-1])
    pts = np.column_stack([X.ravel(), Y.ravel(), 0 * X.ravel()])
    nx = len(xs)
    q = np.array([(j * nx + i, j * nx + i + 1, (j + 1) * nx + i + 1, (j + 1) * nx + i)
                  for j in range(len(ys) - 1) for i in range(nx - 1)])
    tris = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    return pts, tris


@pytest.mark.parametrize("kind", MASK_KINDS)
def test_masks_normalised_and_compact_on_uneven_mesh(kind):
    pts, tris = uneven_surface()
    a = vertex_areas(pts, tris)
    assert a.max() / a.min() > 1e3
    r = 0.05
    m = pressure_masks(pts, a, np.arange(len(pts)), kind, r)
    rho = m.dense(len(pts))
    np.testing.assert_allclose(rho @ a, 1.0, rtol=1e-12)           # eq. 9
    assert np.all(rho[np.arange(len(pts)), np.arange(len(pts))] > 0)  # i ∈ M_i
    assert np.all(rho >= 0)
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    assert np.all(rho[d >= r] == 0)                                  # compact support
    if kind == "single":
        assert m.single_vertex == len(pts)
    else:
        # the fine corner has neighbours within r, the coarse one does not: both cases reported
        assert 0 < m.single_vertex < len(pts)
        assert m.single_vertex == int(np.sum(np.sum(d < r, axis=1) == 1))



def test_masks_are_built_within_twice_their_own_size(monkeypatch):
    """The masks grow like n² at a fixed radius (11.9 million pairs at 20,427 vertices with 10 mm masks, by hand:
    about 1 GiB of indices and values at 47,467), and building them held twice that again on top (the runs, their
    concatenation, then the normalisation's temporaries over all of it: the 47,467-vertex organ's every-K_i
    process peaked at 3.5 GiB, the bench's organ row before this).  Normalised a run at a time, the peak is the runs and one of their concatenations at a time: 1.5x
    the masks' own bytes (measured 1.51x; 3.0x before), held here to 2x (slack for a run's temporaries and the
    arrays the size of the centres), with the neighbour search's runs made small so that its own temporaries (a
    fixed budget, ~0.4 GB) do not hide the rest.  The same values as normalising the whole at once, to the bit."""
    from functools import partial

    from conftest import traced_peak
    from pmask.runtime import masks as masks_module
    from pmask.runtime.spatial import pairs_within

    rng = np.random.default_rng(5)
    pts = rng.random((12000, 3)) * 0.05  # a 5 cm cube: ~250 neighbours within 9 mm
    areas = rng.random(len(pts)) + 0.5
    monkeypatch.setattr(masks_module, "pairs_within", partial(pairs_within, candidates=1 << 16))
    m, peak = traced_peak(pressure_masks, pts, areas, np.arange(len(pts)), "linear", 0.009)
    own = m.indices.nbytes + m.values.nbytes
    assert own > 30e6  # the pairs, not the run's temporaries, dominate
    assert peak <= 2.0 * own, (peak / own)
    rows = np.repeat(np.arange(len(pts)), np.diff(m.indptr))
    d = np.linalg.norm(pts[rows] - pts[m.indices], axis=1)
    w = 1.0 - d / 0.009
    assert np.array_equal(m.values, w / np.repeat(np.add.reduceat(areas[m.indices] * w, m.indptr[:-1]),
                                                 np.diff(m.indptr)))

def test_pairs_within_a_radius_are_those_a_whole_scan_finds():
    """The masks' neighbour search (a grid of cells of edge at least r, spatial.pairs_within) finds exactly the
    pairs a scan of every vertex finds, columns ascending per centre, with |p_c − p_j|² to round-off: on points
    spread over three decades of spacing, including pairs exactly r apart on the axes (excluded: d² < r²),
    centres a subset in any order, and runs of centres cut by the candidates' budget; a radius far below the
    spacing (cells then larger than r, the keys' range bounded) finds each centre alone."""

    from pmask.runtime.spatial import pairs_within

    rng = np.random.default_rng(7)
    r = 0.01
    pts = np.vstack([rng.random((400, 3)) * 0.05, rng.random((200, 3)) * 0.002 + 0.02,
                     [[0.03, 0.03, 0.03], [0.03 + r, 0.03, 0.03], [0.03, 0.03 - r, 0.03]]])
    centres = rng.permutation(len(pts))[:350]
    centres = np.concatenate([centres, [len(pts) - 3]])
    d2 = ((pts[centres][:, None] - pts[None]) ** 2).sum(axis=2)
    want_rows, want_cols = np.nonzero(d2 < r * r)
    got = list(pairs_within(pts, centres, r, candidates=3000))
    assert len(got) > 5 and np.array_equal(np.concatenate([c for c, *_ in got]), centres)
    offset = np.cumsum([0] + [len(c) for c, *_ in got])
    rows = np.concatenate([offset[k] + rr for k, (_, rr, _, _) in enumerate(got)])
    cols = np.concatenate([cc for _, _, cc, _ in got])
    dd = np.concatenate([x for *_, x in got])
    np.testing.assert_array_equal(rows, want_rows)
    np.testing.assert_array_equal(cols, want_cols)
    np.testing.assert_allclose(dd, d2[want_rows, want_cols], rtol=1e-12, atol=1e-20)
    assert np.all(dd[cols == centres[rows]] == 0.0) and np.sum(cols == centres[rows]) == len(centres)
    assert list(pairs_within(np.zeros((0, 3)), np.zeros(0, np.int64), r)) == []
    (c, rows, cols, dd), = pairs_within(pts, centres, 1e-30)
    np.testing.assert_array_equal(cols, centres)
    np.testing.assert_array_equal(rows, np.arange(len(centres)))
    assert np.all(dd == 0.0)


def test_a_stiffness_and_its_zeta_table_go_when_the_last_reference_does(model):
    """A stiffness holds its ζ table (as large as Ξ: 1.1 GiB at 3,882 contact vertices) and reads Ξ through its
    MaskedXi; nothing of it may refer back to it, or dropping it waits for the cyclic garbage collector (which
    held two such tables in the benchmark's process: its client peaked at 2.5 GiB where it had 0.54)."""
    import gc
    import weakref

    enabled = gc.isenabled()
    gc.disable()
    try:
        s = model.stiffness("linear")
        s.zeta_table()
        s.zeta_block(0, 1)
        gone = weakref.ref(s)
        del s
        assert gone() is None
    finally:
        if enabled:
            gc.enable()


def test_radius_validation(model):
    for bad in (0.0, -1.0, np.nan, np.inf, "a"):
        with pytest.raises(ValueError, match="radius"):
            model.stiffness("linear", bad)
    with pytest.raises(ValueError, match="r_max"):
        model.stiffness("linear", 2 * model.r_max)
    with pytest.raises(ValueError, match="unknown mask"):
        model.stiffness("cone", 0.01)


@pytest.fixture(scope="module")
def small(kidney_small):
    """The coarse kidney: its whole free system is small enough for SuperLU (the default kidney's P2 system
    took SuperLU 27 s)."""
    return Model.load(kidney_small)


@pytest.fixture(scope="module")
def small_probe(small):
    """A cone mask of the default radius around one free vertex with at least five mask vertices."""
    model = small
    stiff = model.stiffness("linear", symmetric=False)
    k = int(np.flatnonzero(np.diff(stiff.masks.indptr) >= 5)[3])
    cols, rho = stiff.masks.row(k)
    return stiff, k, cols, rho


def _full_displacements(model, cols, rho):
    """The independent route (conftest.FullSystem): tractions ρ_j e_c at the mask's contact vertices, for c =
    x, y, z; returns u at the volume vertices (N, 3, 3) and the surface's volume indices."""
    tractions = np.zeros((len(model.points), 3, 3))
    for j, w in zip(cols, rho):
        tractions[model.contact[j]] += w * np.eye(3)
    system = FullSystem(model.path)
    u, _ = system.solve(tractions)
    return u, system.vi


def test_masked_vertex_stiffness_is_inverse_of_full_solve(small, small_probe):
    """K_i (eq. 12) is the inverse of vertex i's displacement under its mask's traction, from an independent
    full solve of the default element (P2 on the kidney), masked and single-vertex."""
    model = small
    stiff, k, cols, rho = small_probe
    u, vi = _full_displacements(model, cols, rho)
    i_surface = model.contact[stiff.masks.centres[k]]
    U = u[vi[i_surface]]  # 3x3: column c = displacement of vertex i for f = e_c
    assert relerr(stiff.K_full[k], np.linalg.inv(U)) < 1e-8
    # and the single-vertex stiffness is the inverse of the point-load response
    single = model.stiffness("single")
    u1, _ = _full_displacements(model, [stiff.masks.centres[k]], [1.0 / model.vertex_areas[i_surface]])
    assert relerr(single.K_full[k], np.linalg.inv(u1[vi[i_surface]])) < 1e-8
    # the mask spreads the load: the masked vertex is stiffer than the single one
    assert np.linalg.norm(stiff.K_full[k], 2) > 1.2 * np.linalg.norm(single.K_full[k], 2)


def test_masked_stiffness_gathered_in_passes_is_the_same_and_the_full_solves(small, small_probe, monkeypatch):
    """#27 item 4 (all K_i in bounded memory): masked_flexibility gathers whole masks in passes of about
    PAIRS_PER_PASS pairs.  With passes of 5 pairs (a pass per mask or two) every K_i is bitwise the one-pass
    value (each mask's pairs are summed in the same order), and the probed one still inverts the full solve."""
    from pmask.runtime import stiffness as st

    model = small
    stiff, k, cols, rho = small_probe
    whole = model.stiffness(stiff.masks.kind, stiff.masks.radius).K_full
    monkeypatch.setattr(st, "PAIRS_PER_PASS", 5)
    passes = model.stiffness(stiff.masks.kind, stiff.masks.radius).K_full
    assert np.array_equal(passes, whole)
    u, vi = _full_displacements(model, cols, rho)
    U = u[vi[model.contact[stiff.masks.centres[k]]]]
    assert relerr(passes[k], np.linalg.inv(U)) < 1e-8


def test_zeta_reproduces_full_displacement_field(small, small_probe):
    model = small
    stiff, k, cols, rho = small_probe
    u, vi = _full_displacements(model, cols, rho)
    i_surface = model.contact[stiff.masks.centres[k]]
    Z = stiff.zeta(i_surface)
    assert relerr(Z, u[vi[model.contact]].reshape(-1, 3)) < 1e-8
    # eq. 16 at a vertex (b = e_k) is ζ_i f
    t = int(np.flatnonzero(np.any(model.triangles == i_surface, axis=1))[0])
    b = (model.triangles[t] == i_surface).astype(float)
    f = np.array([0.1, -0.2, 0.3])
    v = stiff.deformation(t, b, f)
    assert relerr(v[model.contact].ravel(), u[vi[model.contact]].reshape(-1, 3) @ f) < 1e-8
    assert np.all(v[model.fixed] == 0)


def test_the_zeta_table_holds_every_zeta_in_pieces_of_columns(small, small_probe, monkeypatch):
    """The ζ table, built ZETA_COLUMNS columns at a time, holds ζ_mᵀ (eq. 13, formed from Ξ's columns by
    ``zeta``, which the test above holds against full solves) in rows 3m..3m+2 of every mask centre m, and
    zeros elsewhere, with pieces of 7 columns (which do not divide 3 n_c) as with the default."""
    from pmask.runtime import stiffness as st

    stiff = small_probe[0]
    for width in (st.ZETA_COLUMNS, 7):
        monkeypatch.setattr(st, "ZETA_COLUMNS", width)
        s = small.stiffness(stiff.masks.kind, stiff.masks.radius)
        Zt = s.zeta_table()
        rows = np.zeros(len(Zt) // 3, bool)
        for m in s.masks.centres:
            assert np.abs(Zt[3 * m:3 * m + 3] - s.zeta(small.contact[m]).T).max() <= 1e-15 * np.abs(Zt).max()
            rows[m] = True
        assert not np.any(Zt.reshape(-1, 3, Zt.shape[1])[~rows])


def test_surface_stiffness_continuous_and_interpolating(model):
    stiff = model.stiffness("linear", 2 * model.mean_edge_length)
    T = model.triangles
    for t in range(0, len(T), 17):
        for k in range(3):
            e = np.zeros(3)
            e[k] = 1.0
            np.testing.assert_allclose(stiff.at(t, e), stiff.K_vertex[T[t, k]], rtol=1e-13)
    # across every shared edge the two triangles agree at the edge's points
    from pmask.runtime.geometry import triangle_neighbours

    nb = triangle_neighbours(T)
    worst = 0.0
    for t in range(len(T)):
        for k in range(3):
            s = nb[t, k]
            a, b = T[t, (k + 1) % 3], T[t, (k + 2) % 3]
            for w in (0.25, 0.5):
                bt = np.zeros(3)
                bt[(k + 1) % 3], bt[(k + 2) % 3] = w, 1 - w
                bs = np.zeros(3)
                bs[list(T[s]).index(a)], bs[list(T[s]).index(b)] = w, 1 - w
                Kt, Ks = stiff.at(t, bt), stiff.at(s, bs)
                worst = max(worst, np.abs(Kt - Ks).max() / np.abs(Kt).max())
    assert worst < 1e-13


def test_symmetric_by_default_and_asymmetry_reported(model):
    r = 2 * model.mean_edge_length
    sym, full = model.stiffness("linear", r), model.stiffness("linear", r, symmetric=False)
    K = sym.K_vertex[model.contact[model.core]]
    np.testing.assert_allclose(K, np.swapaxes(K, 1, 2))
    rep = full.report()
    assert rep["asymmetry_max"] > 1e-3  # the masked K_i really are non-symmetric
    Kf = full.K_vertex[model.contact[model.core]]
    np.testing.assert_allclose(0.5 * (Kf + np.swapaxes(Kf, 1, 2)), K, rtol=1e-12)


@pytest.mark.parametrize("bad", [
    (np.nan, [1, 0, 0]), (-1, [1, 0, 0]), (10**9, [1, 0, 0]), (1.5, [1, 0, 0]), ("0", [1, 0, 0]),
    (0, [0.5, 0.6, -0.1]), (0, [0.5, 0.6, 0.1]), (0, [np.nan, 0.5, 0.5]), (0, [1, 0]), (0, [np.inf, 0, 0]),
])
def test_query_validation(model, bad):
    stiff = model.stiffness("linear", 2 * model.mean_edge_length)
    with pytest.raises(ValueError):
        stiff.at(*bad)


def test_force_and_deformation_validation(model):
    stiff = model.stiffness("linear", 2 * model.mean_edge_length)
    t = int(np.flatnonzero(stiff.touchable)[0])
    for bad in ([np.nan, 0, 0], [0, np.inf, 0], [1, 2]):
        with pytest.raises(ValueError, match="finite|3"):
            stiff.force(t, [1, 0, 0], bad)
        with pytest.raises(ValueError, match="finite|3"):
            stiff.deformation(t, [1, 0, 0], bad)


@pytest.mark.parametrize("dtype", [np.int32, np.int64])
def test_edges_are_each_shared_edge_once(model, dtype):
    """geometry.edges (one integer key per edge for np.unique): on the kidney's closed surface every edge is
    shared by two triangles, so there are 3T/2 of them and Euler's V − E + F = 2 holds; each is (smaller, larger)
    and they are the sorted unique rows of the triangles' sides; an empty mesh has none."""
    from pmask.runtime.geometry import edges

    T = model.triangles.astype(dtype)
    e = edges(T)
    sides = np.sort(np.concatenate([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]]), axis=1)
    assert e.dtype == dtype and len(e) == 3 * len(T) // 2
    assert len(model.points) - len(e) + len(T) == 2
    assert np.all(e[:, 0] < e[:, 1])
    np.testing.assert_array_equal(e, np.unique(sides, axis=0))
    assert edges(np.zeros((0, 3), dtype)).shape == (0, 2)


def test_unique_rows_are_numpys_unique_rows():
    """geometry.unique_rows (one integer key per row) gives np.unique(axis=0)'s rows, order, inverse, counts, shapes
    and dtype, for one to four columns of each integer type, duplicates many or none, empty and one row; rows whose
    key would pass 63 bits, or with a negative entry, or of floats, take numpy's own way to the same answer."""
    from pmask.runtime.geometry import unique_rows

    rng = np.random.default_rng(3)
    cases = [rng.integers(0, hi, (n, m)).astype(dt) for dt in (np.int16, np.int32, np.int64, np.uint32, np.uint64)
             for m in (1, 2, 3, 4) for n, hi in ((0, 5), (1, 5), (300, 3), (3000, 30000))]
    cases += [np.array([[2 ** 40, 1, 3], [0, 0, 0], [2 ** 40, 1, 3]]), np.array([[-1, 2], [3, 4], [-1, 2]]),
              np.array([[0.5, 1.0], [0.5, 1.0]])]
    for R in cases:
        for inverse in (False, True):
            for counts in (False, True):
                want = np.unique(R, axis=0, return_inverse=inverse, return_counts=counts)
                got = unique_rows(R, return_inverse=inverse, return_counts=counts)
                want, got = (x if isinstance(x, tuple) else (x,) for x in (want, got))
                assert len(got) == len(want)
                for g, w in zip(got, want):
                    assert g.dtype == w.dtype and g.shape == w.shape, (R.dtype, R.shape, g.dtype, w.dtype)
                    np.testing.assert_array_equal(g, w)
