"""Accuracy for soft tissue: bending against Timoshenko beam theory (the soft-tissue issue).

A 100 x 10 x 10 mm cantilever, clamped on one end face, loaded by a uniform shear traction on the other,
meshed by gmsh from an STL with ``--edge-length 4`` (2.5 elements through the thickness).  The tip
deflection read from Ξ (δ = mean over the tip face of Σ_j Ξ_ij F_j / a_j, F_j the tip face's lumped
share of the load) against Timoshenko: δ = P L³ / (3 E I) + P L / (κ G A), κ = 10 (1 + ν) / (12 + 11 ν)
(Cowper's rectangular section).
"""
from __future__ import annotations

import numpy as np
import pytest

from pmask.pipeline.stages import Spec, run
from pmask.runtime import Model

L, B, E, NU, P = 0.1, 0.01, 1.0e4, 0.3, 1.0e-3  # m, m, Pa, -, N


def timoshenko_tip() -> float:
    I, A, G = B ** 4 / 12.0, B * B, E / (2.0 * (1.0 + NU))
    kappa = 10.0 * (1.0 + NU) / (12.0 + 11.0 * NU)
    return P * L ** 3 / (3.0 * E * I) + P * L / (kappa * G * A)


@pytest.fixture(scope="module")
def beam_stl(tmp_path_factory):
    import meshio
    import trimesh

    box = trimesh.creation.box(extents=(100.0, 10.0, 10.0))  # mm, centred: x in [-50, 50]
    stl = tmp_path_factory.mktemp("beam") / "beam.stl"
    meshio.write_points_cells(stl, box.vertices, [("triangle", box.faces)])
    return stl


def tip_deflection(model: Model) -> float:
    """Mean downward displacement of the tip face under a total downward force P on it (lumped P1 shares)."""
    pts, T = model.points, model.triangles
    on_tip = np.isclose(pts[:, 0], L / 2, atol=1e-9)
    tris = T[on_tip[T].all(axis=1)]
    e1, e2 = pts[tris[:, 1]] - pts[tris[:, 0]], pts[tris[:, 2]] - pts[tris[:, 0]]
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    share = np.zeros(len(pts))
    np.add.at(share, tris.ravel(), np.repeat(area / 3.0, 3))
    share /= share.sum()
    row = {v: k for k, v in enumerate(model.contact)}
    tip = np.flatnonzero(share)
    cols = np.array([3 * row[v] + 2 for v in tip])
    load = -P * share[tip] / model.vertex_areas[tip]  # traction p_j = F_j / a_j (eq. 10)
    Xi = np.asarray(model.Xi, float)
    uz = Xi[np.ix_(cols, cols)] @ load
    return float(-(share[tip] @ uz))


@pytest.mark.parametrize("element,tolerance,label", [
    ("P2", 0.02, "within 2 % (the issue's bound; P2 is within 0.8 % here)"),
])
def test_p2_cantilever_bends_as_timoshenko_says(beam_stl, tmp_path, element, tolerance, label):
    out = tmp_path / f"beam_{element}.h5"
    run(Spec(model="beam", surface=str(beam_stl), edge_length=4.0, units="mm", fixed="x<-49.99", E=E, nu=NU,
             element=element, r_max=0.01), out)
    d = tip_deflection(Model.load(out))
    assert d / timoshenko_tip() - 1 == pytest.approx(0.0, abs=tolerance), label


def test_p1_is_too_stiff_in_bending_on_the_same_mesh(beam_stl, tmp_path):
    """Why P2 exists: on the same 2.5-elements-thick mesh P1 is more than 10 % too stiff (the issue measured
    33 %); a P1 that passed this would mean the beam test above no longer measures bending."""
    out = tmp_path / "beam_P1.h5"
    run(Spec(model="beam", surface=str(beam_stl), edge_length=4.0, units="mm", fixed="x<-49.99", E=E, nu=NU,
             r_max=0.01), out)
    assert tip_deflection(Model.load(out)) / timoshenko_tip() - 1 < -0.10
