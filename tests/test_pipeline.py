"""Models, artifact round trip, input hashing, CLI, and a user's STL end to end."""
from __future__ import annotations

import dataclasses

import h5py
import numpy as np
import pytest

from conftest import relerr
from pmask.meshes import kidney, loop
from pmask.errors import InputError
from pmask.pipeline.cli import main
from pmask.pipeline.stages import Spec, input_hash, run
from pmask.precompute.surface import boundary_surface
from pmask.runtime.artifact import read_artifact
from pmask.runtime.geometry import vertex_areas


@pytest.mark.parametrize("level,n", [(0, 34), (1, 130), (2, 514), (3, 2050)])
def test_loop_family_vertex_counts_and_exact_shape(level, n):
    pts, tris = loop.surface(level)
    assert len(pts) == n and len(tris) == 2 * n - 4  # closed genus-0 surface
    assert np.allclose(np.sum((pts / loop.SEMI_AXES) ** 2, axis=1), 1.0)


def test_loop_interior_keeps_the_surface():
    m = loop.build(1)
    sv, tris = boundary_surface(m.points, m.tets)
    spts, stris = loop.surface(1)
    assert np.array_equal(sv, np.arange(len(spts)))
    assert np.allclose(m.points[sv], spts)
    assert {tuple(sorted(t)) for t in tris} == {tuple(sorted(t)) for t in stris}


def test_kidney_default_size_and_spread():
    m = kidney.build()
    sv, tris = boundary_surface(m.points, m.tets)
    ext = m.points.max(axis=0) - m.points.min(axis=0)
    assert np.allclose(ext, [0.11, 0.06, 0.04], rtol=0.05)
    free = len(sv) - int(m.groups["hilum"][sv].sum())
    assert 1200 <= free <= 1800
    a = vertex_areas(m.points[sv], tris)
    assert np.percentile(a, 95) / np.percentile(a, 5) > 2.5  # a mesher's spread, not a uniform mesh


def test_kidney_graded_interior_keeps_the_surface_and_thins_the_volume():
    """``interior`` coarsens only the volume: the surface (where Ξ lives) keeps its resolution, the
    volume's vertices (the factor's size) drop, and the mesh is still one closed solid of the same volume."""
    from pmask.precompute.meshing import enclosed_volume

    size = 0.006
    plain, graded = kidney.build(size), kidney.build(size, interior=0.02)
    (sp_, tp), (sg, tg) = boundary_surface(plain.points, plain.tets), boundary_surface(graded.points, graded.tets)
    # the same surface: the field is the surface's size there, and sizes still extend into the surfaces
    assert len(sg) == len(sp_) and len(tg) == len(tp)
    # 30 % fewer inner vertices at least (measured 39 % fewer at this coarse size, where the kidney is only
    # ~6 edges thick; 4.7x fewer at 1.28 mm)
    assert len(graded.points) - len(sg) < 0.7 * (len(plain.points) - len(sp_))
    # the solid: both enclose the same volume to the surfaces' discretisation difference
    vp, vg = abs(enclosed_volume(plain.points[sp_], tp)), abs(enclosed_volume(graded.points[sg], tg))
    assert abs(vg - vp) <= 0.01 * vp
    with pytest.raises(InputError, match="interior must be at least size"):
        kidney.build(size, interior=0.001)


def test_artifact_round_trip(kidney_small):
    d = read_artifact(kidney_small)
    a = d["attrs"]
    assert a["material"]["E"] == 1e4 and a["material"]["nu"] == 0.45
    assert a["units"]["length"] == "m" and "Xi = G diag(a)" in a["definition"]
    # the vertex areas a_i = ∫ φ_i dΓ (eq. 10) against scikit-fem's own assembly of that integral
    # over the boundary facets of the stored volume mesh (an independent quadrature)
    from skfem import ElementTetP1, FacetBasis, LinearForm, MeshTet, asm

    P, T = d["volume/points"], d["volume/tets"]

    @LinearForm
    def hat(v, w):
        return v

    a_skfem = asm(hat, FacetBasis(MeshTet(P.T, T.T), ElementTetP1(), intorder=2))
    np.testing.assert_allclose(d["surface/vertex_areas"], a_skfem[d["surface/volume_index"]], rtol=1e-12)
    inner = np.setdiff1d(np.arange(len(P)), d["surface/volume_index"])
    assert np.abs(a_skfem[inner]).max() <= 1e-12 * a_skfem.max()  # no area on interior vertices (round-off only)
    with h5py.File(kidney_small, "r") as f:
        assert np.array_equal(f["greens/Xi"][()], d["greens/Xi"])
    free, fixed = d["surface/free"], d["surface/fixed"]
    assert len(np.intersect1d(free, fixed)) == 0 and len(free) + len(fixed) == len(d["surface/points"])


def test_input_hash_changes_with_every_input_and_only_then(tmp_path):
    base = Spec(model="kidney", params={"size": 0.01})
    h = input_hash(base)
    assert input_hash(dataclasses.replace(base)) == h
    for change in ({"params": {"size": 0.011}}, {"E": 2e4}, {"nu": 0.3}, {"fixed": "x<0"},
                   {"contact": "z>0"}, {"r_max": 0.01}, {"units": "mm"}, {"model": "loop1"}):
        assert input_hash(dataclasses.replace(base, **change)) != h, change
    stl = tmp_path / "s.stl"
    stl.write_bytes(b"solid a\nendsolid a\n")
    s = Spec(model="s", surface=str(stl), edge_length=0.1)
    h1 = input_hash(s)
    stl.write_bytes(b"solid b\nendsolid b\n")
    assert input_hash(s) != h1


def test_cli_precompute_then_up_to_date(tmp_path, capsys):
    out = tmp_path / "loop1.h5"
    assert main(["-q", "precompute", "loop1", "-o", str(out)]) == 0
    assert "wrote" in capsys.readouterr().out
    stamp = out.stat().st_mtime_ns
    assert main(["-q", "precompute", "loop1", "-o", str(out)]) == 0
    assert "up to date" in capsys.readouterr().out and out.stat().st_mtime_ns == stamp
    assert main(["info", str(out)]) == 0
    assert "loop1" in capsys.readouterr().out
    assert not (tmp_path / ".work").exists()


def test_cli_unknown_model_lists_models(tmp_path, capsys):
    assert main(["precompute", "spleen", "-o", str(tmp_path / "x.h5")]) == 2
    err = capsys.readouterr().err
    assert "unknown model 'spleen'" in err and "liver" in err and "Traceback" not in err


def test_user_surface_stl_end_to_end(tmp_path):
    """A fine triangulated sphere in mm, remeshed by gmsh, fixed on its bottom cap."""
    import meshio
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=20.0)  # mm, 2562 vertices
    stl = tmp_path / "organ.stl"
    meshio.write_points_cells(stl, sphere.vertices, [("triangle", sphere.faces)])
    out = tmp_path / "organ.h5"
    s = run(Spec(model="organ", surface=str(stl), edge_length=6.0, units="mm", fixed="z<-15", E=5e3, nu=0.4), out)
    d = read_artifact(out)
    assert d["attrs"]["material"]["E"] == 5e3
    r = np.linalg.norm(d["surface/points"], axis=1)
    assert np.allclose(r, 0.02, rtol=0.02)  # remeshed in metres on the same sphere
    assert 100 < s["surface_vertices"] < len(sphere.vertices)  # coarser than the input
    assert np.all(d["surface/points"][d["surface/fixed"]][:, 2] < -0.015 + 1e-12)
    # ν = 0.4: --element auto takes P2 (P1 would warn); a pull on the top vertex moves it up, and Ξ's diagonal
    # blocks have a positive definite symmetric part.  (P2's consistent load spreads a vertex's hat traction onto
    # its edges' nodes, so Ξ_ii is symmetric only up to that spread, a few per cent here; the exact reciprocity
    # of the consistent load is tests/test_greens.py's.)
    assert d["attrs"]["element"] == "P2"
    Xi = d["greens/Xi"]
    top = int(np.argmax(d["surface/points"][d["surface/contact"], 2]))
    block = Xi[3 * top:3 * top + 3, 3 * top:3 * top + 3]
    assert block[2, 2] > 0 and np.all(np.linalg.eigvalsh(0.5 * (block + block.T)) > 0)
    assert relerr(block, block.T) < 0.05


def test_a_surface_file_is_parsed_once_a_run_and_again_when_its_bytes_change(tmp_path, monkeypatch):
    """A run reads its --surface for the checks, the remesh's worker process and the display surface; the file
    is parsed once (a 327,680-triangle ASCII STL took meshio 7-13 s a parse) and handed to the worker as
    parsed.  A file whose bytes change is parsed again, though its size stays the same."""
    import meshio
    import trimesh

    from pmask.precompute import meshing

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=20.0)
    stl = tmp_path / "organ.stl"
    meshio.write_points_cells(stl, sphere.vertices, [("triangle", sphere.faces)])  # ASCII, as meshio writes it
    parses, real = [], meshing.read_mesh_file
    monkeypatch.setattr(meshing, "read_mesh_file", lambda path: parses.append(path) or real(path))
    monkeypatch.setattr(meshing, "_READ", {})
    a = meshing.read_surface_file(stl, 1e-3)
    b = meshing.read_surface_file(stl, 1e-3)
    c = meshing.read_surface_file(stl)
    assert len(parses) == 1
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) and np.array_equal(c[0] * 1e-3, a[0])
    a[1][0] = -1  # a caller's change to what it was given is not what the next caller gets
    assert meshing.read_surface_file(stl, 1e-3)[1].min() == 0
    # the worker process's side: the parent's read, for the same bytes, in place of a parse
    job = meshing.save_surface_read(stl, tmp_path)
    meshing._READ.clear()
    meshing._load_surface_read(job)
    d = meshing.read_surface_file(stl, 1e-3)
    assert len(parses) == 1 and np.array_equal(d[0], a[0])
    # the same number of bytes, one coordinate's digits changed: parsed again, the new coordinate read
    text = stl.read_text()
    first = text.split("vertex", 1)[1].split()[0]
    moved = first.replace(first[-1], "1" if first[-1] != "1" else "2")
    assert len(moved) == len(first)
    stl.write_text(text.replace(first, moved, 1))
    e = meshing.read_surface_file(stl)
    assert len(parses) == 2 and not np.array_equal(e[0], c[0])
    assert meshing.save_surface_read(tmp_path / "missing.stl", tmp_path) == {}


def test_halfspace_contact_region_is_widened_by_r_max(halfspace_small):
    d = read_artifact(halfspace_small)
    x = d["surface/points"][d["surface/contact"]]
    core = d["surface/contact_core"]
    r_max = float(d["attrs"]["r_max"])
    free_x = d["surface/points"][d["surface/free"]]
    # every free vertex within r_max of a core vertex is in Ξ
    dist = np.linalg.norm(free_x[:, None, :] - x[core][None, :, :], axis=2).min(axis=1)
    assert np.sum(dist <= r_max) == len(x)
    assert core.sum() < len(x) < len(free_x)
    assert np.all(np.abs(x[:, 2]) < 1e-12)  # all on the flat face


def test_p1_is_refused_where_it_locks_and_warned_about_where_it_stiffens(tmp_path, caplog):
    """ν = 0.499 with P1 (2.1x Boussinesq on the half-space) is one line before any meshing, naming the
    element that does not lock; ν = 0.45 with P1 warns with the measured excess; P2 at 0.499 is accepted; and
    --element auto (the default) takes P2 wherever P1 would warn, P1 below, without a word."""
    import logging

    from pmask.pipeline.stages import _warn_once, validate
    from pmask.precompute.elements import default_element

    out = tmp_path / "x.h5"
    with pytest.raises(InputError, match=r"P1 tetrahedra lock at nu = 0.499.*--element P2"):
        run(Spec(model="kidney", nu=0.499, element="P1"), out)
    assert not out.exists() and not (tmp_path / ".work").exists()
    _warn_once.cache_clear()
    with caplog.at_level(logging.WARNING, logger="pmask.pipeline.stages"):
        validate(Spec(model="kidney", nu=0.45, element="P1"), out)
        validate(Spec(model="kidney", nu=0.499, element="P2"), out)
        validate(Spec(model="kidney", nu=0.499), out)
        validate(Spec(model="kidney", nu=0.45), out)
    warned = [r.getMessage() for r in caplog.records]
    assert len(warned) == 1 and "nu = 0.45" in warned[0] and "17 %" in warned[0]
    assert [default_element(nu) for nu in (0.3, 0.39, 0.4, 0.45, 0.499)] == ["P1", "P1", "P2", "P2", "P2"]


def test_the_remesh_reports_how_far_it_moved_the_surface(tmp_path, caplog):
    """A 20 mm sphere remeshed coarsely (12 mm edges): the reported Hausdorff distance agrees with the
    analytic one (max | |x| - R | over the remeshed surface, the input being the sphere to 0.04 mm) within
    the sampling spacing, the volume change with trimesh's own volumes of both surfaces, both are stored
    in the artifact, and the change is warned about; at 3 mm edges it is small and not warned about."""
    import json

    import meshio
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=20.0)
    stl = tmp_path / "s.stl"
    meshio.write_points_cells(stl, sphere.vertices, [("triangle", sphere.faces)])
    for h, warned in ((12.0, True), (3.0, False)):
        caplog.clear()
        out = tmp_path / f"s{h:g}.h5"
        run(Spec(model="s", surface=str(stl), edge_length=h, units="mm", fixed="z<-8"), out)
        d = read_artifact(out)
        g = json.loads(d["attrs"]["parameters"])["model_info"]["remesh"] if isinstance(d["attrs"]["parameters"], str) \
            else d["attrs"]["parameters"]["model_info"]["remesh"]
        P, T = d["surface/points"] * 1e3, d["surface/triangles"]
        # analytic: sample the remeshed triangles densely, distance to the sphere of radius 20 mm
        bary = np.random.default_rng(1).dirichlet([1, 1, 1], size=(len(T), 20))
        x = np.einsum("tsk,tkj->tsj", bary, P[T]).reshape(-1, 3)
        analytic = max(np.abs(np.linalg.norm(x, axis=1) - 20.0).max(), np.abs(np.linalg.norm(P, axis=1) - 20.0).max())
        spacing = 1e3 * g["sample_spacing_m"]
        assert abs(1e3 * g["hausdorff_m"] - analytic) <= spacing + 0.05, (g, analytic)
        remeshed = trimesh.Trimesh(P, T, process=False)
        # the stored surface is the remesh fitted to the support's rim (pmask.precompute.supports), whose own
        # volume change is stored beside the remesh's
        fit = (json.loads(d["attrs"]["parameters"]) if isinstance(d["attrs"]["parameters"], str)
               else d["attrs"]["parameters"])["model_info"]["support_fit"]["volume_change"]
        assert (1 + g["volume_change"]) * (1 + fit) - 1 == pytest.approx(remeshed.volume / sphere.volume - 1, abs=1e-6)
        assert ("the remesh moved the surface" in caplog.text) == warned
