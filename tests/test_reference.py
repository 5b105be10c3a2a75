"""CI recomputes the stored reference tables from the stored meshes and checks them against physics.

Tolerance for the recomputation: 1e-6 relative.  The meshes are stored, so the
same algebra runs on the same numbers; only floating-point summation order in
BLAS/CHOLMOD can differ between machines (measured here: identical to 1e-10),
while any change in the modelling (quadrature, vertex areas, masks, material
handling) moves these stiffnesses by 1e-3 or more.
"""
from __future__ import annotations

import numpy as np
import pytest

from pmask.pipeline.reference import REFERENCE_DIR, compare, compute_all, read_table

RTOL = 1e-6


@pytest.fixture(scope="module")
def recomputed(tmp_path_factory):
    """Every table, with the half-space table's P1 rows only (the P2 rows: the slow test below)."""
    return compute_all(REFERENCE_DIR / "meshes", tmp_path_factory.mktemp("reference"), elements=("P1",))


def check_against_stored(name, rows, element=None):
    stored_meta, stored = read_table(REFERENCE_DIR / f"{name}.csv")
    for key in ("model", "resolution", "mask", "units"):
        assert key in stored_meta  # the header says what the numbers are
    if element is not None:
        stored = [r for r in stored if r["element"] == element]
    new = [{k: str(v) for k, v in r.items()} for r in rows]
    diffs = compare(stored, new, RTOL)
    assert not diffs, "\n".join(diffs[:20])


@pytest.mark.parametrize("name", ["figure5", "halfspace", "figure6", "kidney_vertices"])
def test_recomputed_tables_match_stored(recomputed, name):
    check_against_stored(name, recomputed[name][1], element="P1" if name == "halfspace" else None)


@pytest.mark.slow
def test_recomputed_p2_rows_match_stored(tmp_path):
    from pmask.pipeline.reference import halfspace_table

    _, rows = halfspace_table(REFERENCE_DIR / "meshes", tmp_path, elements=("P2",))
    check_against_stored("halfspace", rows, element="P2")


def table(name):
    return read_table(REFERENCE_DIR / f"{name}.csv")[1]


def col(rows, key):
    return np.array([float(r[key]) for r in rows])


def test_figure5_single_falls_masked_converges():
    rows = table("figure5")
    single, masked = col(rows, "single_norm_N_per_m"), col(rows, "masked_norm_N_per_m")
    edge = col(rows, "mean_edge_m")
    assert np.all(np.diff(single) < 0)
    ratios = single[:-1] / single[1:]
    # roughly proportional to edge length once the mesh resolves the body (level 0 has 7 interior vertices)
    assert np.all(ratios[1:] >= 1.5), ratios
    assert ratios[-1] > ratios[0]  # approaching the asymptotic ratio 2 of halved edges
    assert np.all(edge[:-1] / edge[1:] > 1.9)
    assert abs(masked[3] / masked[2] - 1) <= 0.10
    assert single[-1] < 0.25 * masked[-1]  # single-vertex stiffness falls away from the masked one


def test_halfspace_matches_boussinesq_cerruti():
    rows = [r for r in table("halfspace") if float(r["nu"]) == 0.3 and r["element"] == "P1"]
    for kind in ("linear", "wendland", "gaussian", "disk"):
        rs = sorted((r for r in rows if r["mask"] == kind), key=lambda r: -float(r["h_over_r"]))
        h = col(rs, "h_over_r")
        kn_err, kt_err, ratio_err = (np.abs(col(rs, k)) for k in ("kn_error", "kt_error", "ratio_error"))
        assert np.all(np.diff(kn_err) < 0) and np.all(np.diff(kt_err) < 0), kind  # shrinks with h
        # a step profile collocated at vertices has an effective radius uncertain by about h/2
        tol = 0.05 + (0.5 * h[-1] if kind == "disk" else 0.0)
        assert kn_err[-1] <= tol and kt_err[-1] <= tol and ratio_err[-1] <= 0.05, (kind, kn_err, kt_err)
    single = sorted((r for r in rows if r["mask"] == "single"), key=lambda r: -float(r["h_over_r"]))
    kn = col(single, "kn_N_per_m")
    assert np.all(kn[:-1] / kn[1:] > 1.7)  # point-load stiffness ∝ h → 0


def test_p2_matches_at_coarser_meshes_and_locks_less():
    rows = table("halfspace")
    err = {(r["element"], r["mesh"], float(r["nu"]), r["mask"]): abs(float(r["kn_error"])) for r in rows}
    assert err[("P2", "halfspace_h4", 0.3, "linear")] <= 0.05  # the cone: P2 needs h = r/4 where P1 needs r/16
    for mesh in ("halfspace_h4", "halfspace_h8"):
        for kind in ("linear", "wendland", "gaussian"):
            assert err[("P2", mesh, 0.3, kind)] < err[("P1", mesh, 0.3, kind)]
            if mesh == "halfspace_h8":  # the more concentrated profiles need r/8
                assert err[("P2", mesh, 0.3, kind)] <= 0.05, (mesh, kind)
    assert err[("P2", "halfspace_h8", 0.3, "linear")] < err[("P2", "halfspace_h4", 0.3, "linear")]
    # the locking gap (error at nu = 0.45 minus error at nu = 0.3): P1 locks, P2 much less
    gap = {e: err[(e, "halfspace_h8", 0.45, "linear")] - err[(e, "halfspace_h8", 0.3, "linear")] for e in ("P1", "P2")}
    assert gap["P1"] > 0.02 and gap["P2"] < 0.5 * gap["P1"], gap


def test_figure6_masks_remove_mesh_artefacts():
    """The paper's Figure 6 in numbers (the default kidney, P2): single-vertex stiffness follows the vertex area
    and is rough (mesh artefacts), the masked one much less.  The normal stiffness a frictionless contact
    renders: with P2 the single-vertex load is already the hat traction's consistent load spread over its one
    ring, so its normal stiffness is about as smooth as the mask's (with P1's point loads it was rougher); what
    the table must show is that the masked one varies from vertex to vertex by well under what a hand tells
    apart (stiffness discrimination thresholds are 15-25 %: a 5 % bound)."""
    single, masked = table("figure6")
    assert float(masked["vertex_roughness"]) <= 0.5 * float(single["vertex_roughness"])
    assert float(masked["rank_correlation_with_area"]) < 0.5 * float(single["rank_correlation_with_area"])
    assert float(single["rank_correlation_with_area"]) > 0.5  # single-vertex stiffness follows vertex area
    assert float(masked["normal_stiffness_roughness"]) <= 0.05


@pytest.mark.slow
def test_recomputed_incompressible_rows_match_stored(tmp_path):
    from pmask.pipeline.reference import incompressible_table

    _, rows = incompressible_table(REFERENCE_DIR / "meshes", tmp_path)
    check_against_stored("incompressible", rows)


def test_p2_does_not_lock_up_to_nu_0499():
    """Nearly incompressible tissue on the far half-space (R = 120 r) at h = r/4 with P2: the cone's and
    the disk's k_n and k_t within 3 % of Boussinesq/Cerruti at ν = 0.45, 0.49 and 0.499 (the soft-tissue
    issue's bound; stored values 0.2-1.8 %), and the cone's k_n error moves by less than one point from
    ν = 0.3 to 0.499 (P1 on the nearer model: +10 % to +321 % over the same range)."""
    rows = table("incompressible")
    for r in rows:
        if r["mask"] in ("linear", "disk") and float(r["nu"]) >= 0.45:
            assert abs(float(r["kn_error"])) <= 0.03 and abs(float(r["kt_error"])) <= 0.03, r
    cone = {float(r["nu"]): float(r["kn_error"]) for r in rows if r["mask"] == "linear"}
    assert abs(cone[0.499] - cone[0.3]) < 0.01


@pytest.mark.slow
def test_recomputed_figure5_p2_matches_stored(tmp_path):
    from pmask.pipeline.reference import figure5_table

    _, rows = figure5_table(REFERENCE_DIR / "meshes", tmp_path, "P2")
    check_against_stored("figure5_p2", rows)


def test_figure5_with_p2_converges_where_p1_moved_8_percent():
    """The soft-tissue issue's Figure 5 targets with P2 (supports held by area): the masked stiffness
    changes ≤ 3 % between the two finest levels (stored −1.4 %; P1 −7.5 %), and the single-vertex stiffness
    falls by ≥ 1.8 from 514 to 2,050 vertices (stored 1.87).

    The coarser ratios (1.50, 1.78) fall short of 1.8, and that is the body, not the element: a point
    load's compliance is 1/k = α/h + β, a local part growing as the edges shrink plus the body's own
    bending, which does not.  Halving h multiplies k by (2x + 1)/(x + 1), x = α/(hβ), which reaches 1.8
    only from x = 4.  Fitted to levels 1 and 2, the law predicts level 3 within 1 % (the rest: the local
    part's O(h) correction), so the ratios are what the geometry gives."""
    rows = table("figure5_p2")
    single, masked, h = col(rows, "single_norm_N_per_m"), col(rows, "masked_norm_N_per_m"), col(rows, "mean_edge_m")
    assert abs(masked[3] / masked[2] - 1) <= 0.03
    assert single[2] / single[3] >= 1.8
    alpha, beta = np.linalg.solve(np.c_[1 / h[1:3], np.ones(2)], 1 / single[1:3])
    assert abs((alpha / h[3] + beta) * single[3] - 1) < 0.01
    x = alpha / (h * beta)
    ratio = single[:-1] / single[1:]
    assert np.all((ratio >= 1.8) == (x[:-1] >= 4)), (ratio, x)