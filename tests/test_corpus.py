"""The real-inputs issue's corpus, made by the test (no downloads): damaged and awkward surfaces as
segmentation exports carry them, and a label image.  Over every case and with or without --repair, the
CLI either writes an artifact the runtime loads or refuses in one line with no traceback; the cases that
--repair exists for go through with it."""
from __future__ import annotations

import numpy as np
import pytest

from pmask.pipeline.cli import main
from pmask.pipeline.corpus import corpus
from pmask.runtime import Model

CASES = corpus()
#: the damaged cases each repair route is for: refused without it, precomputed with it
#: (bench/repair_compare.py measures how much of the intended solid each keeps)
MENDED = {"meshfix": {"touching shells", "touching at a point", "holes", "flipped patch", "self-intersection",
                      "several shells", "overlapping shells"},
          "voxel": {"touching shells", "touching at a point", "holes", "flipped patch", "self-intersection",
                    "several shells", "overlapping shells", "shared wall", "open thin parts"}}


@pytest.mark.slow
# the largest cases first, so that no process is left waiting on one at the end
@pytest.mark.parametrize("name", sorted(CASES, key=lambda name: (len(CASES[name][1]) < 100_000, name)))
@pytest.mark.parametrize("repair", [None, "meshfix", "voxel"])
def test_every_corpus_case_is_an_artifact_or_one_line(tmp_path, capsys, name, repair):
    import meshio

    v, f = CASES[name]
    stl = tmp_path / "case.stl"
    meshio.write_points_cells(stl, v, [("triangle", f)])
    out = tmp_path / "case.h5"
    code = main(["precompute", "--surface", str(stl), "--units", "mm", "--edge-length", "5", "--fixed", "z<-8",
                 "-o", str(out)] + (["--repair", repair] if repair else []))
    err = capsys.readouterr().err
    assert "Traceback" not in err and "internal error" not in err, err
    if code == 0:
        assert len(Model.load(out).points) > 50
    else:
        assert code == 2 and len([l for l in err.splitlines() if l.startswith("pmask: error")]) == 1, err
    if repair is None and name in MENDED["meshfix"] | MENDED["voxel"]:
        assert code == 2, err
    if repair and name in MENDED[repair]:
        assert code == 0, err


@pytest.mark.slow
def test_label_images_in_the_corpus(tmp_path, capsys):
    """The ellipsoid's label is precomputed; the 3 mm neighbouring organ, 3-4 voxels across, is refused in
    one line because smoothing its staircase would change its volume by more than 1 %."""
    nibabel = pytest.importorskip("nibabel")
    from test_segmentation import labels

    data, affine = labels()
    img = nibabel.Nifti1Image(data, affine)
    img.header.set_xyzt_units("mm")
    path = tmp_path / "labels.nii.gz"
    nibabel.save(img, str(path))
    assert main(["precompute", "--segmentation", str(path), "--label", "2", "--edge-length", "4",
                 "--fixed", "x>25", "-o", str(tmp_path / "organ.h5")]) == 0
    capsys.readouterr()
    code = main(["precompute", "--segmentation", str(path), "--label", "5", "--edge-length", "1",
                 "--fixed", "z<-1", "-o", str(tmp_path / "small.h5")])
    err = capsys.readouterr().err
    assert code == 2 and "few voxels thick" in err and "Traceback" not in err, err


@pytest.mark.slow
@pytest.mark.parametrize("repair", [None, "meshfix", "voxel"])
def test_a_real_scan_the_stanford_bunny(tmp_path, capsys, repair):
    """A public real mesh: the Stanford bunny scan that pymeshfix ships (99,785 triangles, 353 boundary and
    132 non-manifold edges; one of the inputs the issue saw crash with a traceback).  Refused in one line
    without --repair, naming it; precomputed with MeshFix; the voxel route is an artifact or one line
    (measured: one line, its ears are about three voxels thin at 2.5 mm edges and fold)."""
    pymeshfix = pytest.importorskip("pymeshfix")
    from pathlib import Path

    bunny = Path(pymeshfix.__file__).parent / "examples" / "StanfordBunny.ply"
    if not bunny.exists():
        pytest.skip("this pymeshfix ships no StanfordBunny.ply")
    out = tmp_path / "bunny.h5"
    code = main(["precompute", "--surface", str(bunny), "--units", "mm", "--edge-length", "2.5", "--fixed", "z<3",
                 "-o", str(out)] + (["--repair", repair] if repair else []))
    err = capsys.readouterr().err
    assert "Traceback" not in err and "internal error" not in err, err
    if repair is None:
        assert code == 2 and "the surface is open (353 boundary edges)" in err and "--repair" in err
    elif repair == "meshfix":
        assert code == 0 and len(Model.load(out).points) > 1000, err
    else:
        assert code == 0 or len([l for l in err.splitlines() if l.startswith("pmask: error")]) == 1, err


def _precompute(tmp_path, capsys, v, f, *args):
    import meshio

    stl = tmp_path / "case.stl"
    meshio.write_points_cells(stl, v, [("triangle", f)])
    out = tmp_path / "case.h5"
    code = main(["precompute", "--surface", str(stl), "--units", "mm", "--edge-length", "5", "-o", str(out), *args])
    said = capsys.readouterr()
    return code, said.out, said.err, out


def _solid_volume(path):
    """The artifact's tetrahedral volume in mm³."""
    p, t = Model.load(path).volume()
    e = p[t[:, 1:]] - p[t[:, :1]]
    return 1e9 * np.abs(np.linalg.det(e)).sum() / 6.0


@pytest.mark.parametrize("name, route, volume", [
    ("holes", "meshfix", 4.0 / 3.0 * np.pi * 20.0 ** 3),
    ("flipped patch", "meshfix", 4.0 / 3.0 * np.pi * 20.0 ** 3),
    ("overlapping shells", "voxel", None),  # the union of the two balls (corpus.union_volume)
    ("shared wall", "voxel", 2 * 20.0 ** 3),  # two chambers sharing a wall: their union (MeshFix keeps one, 83 %)
])
def test_repair_auto_takes_the_first_route_that_works_and_says_what_it_did(tmp_path, capsys, name, route, volume):
    """The scans issue's item 1: --repair auto tries the surface as it is, MeshFix (when it keeps 95 % of the
    area), the voxel route, in that order, and reports the route, why the earlier ones were passed over, and
    the distance to the input.  The solid is the intended one: the sphere within 4 % (icosphere facets and
    the remesh's chords: -1.5 % and -1.8 % measured), the union of overlapping balls within 5 % (the voxel
    route rounds the crease where they meet)."""
    from pmask.pipeline.corpus import union_volume

    v, f = CASES[name]
    code, out, err, path = _precompute(tmp_path, capsys, v, f, "--fixed", "z<-8", "--repair", "auto")
    assert code == 0, err
    assert f"repair auto: route {route}" in out and "of the input (Hausdorff)" in out and "not used: as it is" in out
    expected = volume if volume is not None else union_volume()
    assert abs(_solid_volume(path) / expected - 1) < (0.04 if volume is not None else 0.05)


def test_a_hollow_organ_is_meshed_as_its_wall_and_shell_1_fills_it(tmp_path, capsys):
    """#25 item 1: a wall between an outer shell and an inner one facing inwards (a bladder's, a stomach's)
    was refused as "shells that run into each other ... --repair voxel builds their union", and --repair
    auto then built a solid ball (the cavity filled: 33,000 mm³ where the wall holds 12,900).  Now the body is
    the wall, with or without --repair auto (which needs no route): its volume within 4 % of the shell's (the
    chords of both walls; measured -1.6 % at the corpus's 5 mm edges on a 3 mm wall), the cavity named in the
    summary, and `pmask inspect` calls it ready and names the cavity (it had said "several bodies" and advised
    the voxel route, which fills it); --shell 1 still takes the outer surface alone, filled."""
    v, f = CASES["hollow wall"]
    wall = 4.0 / 3.0 * np.pi * (20.0 ** 3 - 17.0 ** 3)
    for extra in ([], ["--repair", "auto"]):
        code, out, err, path = _precompute(tmp_path, capsys, v, f, "--fixed", "z<-8", *extra)
        assert code == 0 and "hollow: 1 cavity (group:cavity" in out, err
        assert abs(_solid_volume(path) / wall - 1) < 0.04
    assert "repair auto: no repair needed" in out
    assert main(["inspect", str(tmp_path / "case.stl"), "--units", "mm"]) == 0  # inspect agrees: ready, a cavity
    said = capsys.readouterr().out
    assert "ready for pmask precompute" in said and "face inwards: cavities" in said, said
    code, _, err, path = _precompute(tmp_path, capsys, v, f, "--fixed", "z<-8", "--shell", "1")
    assert code == 0, err
    assert abs(_solid_volume(path) / (4.0 / 3.0 * np.pi * 20.0 ** 3) - 1) < 0.04  # the outer ball, filled


def test_repair_auto_on_a_sound_surface_changes_nothing(tmp_path, capsys):
    v, f = CASES["holes"][0], __import__("trimesh").creation.icosphere(subdivisions=3, radius=20.0).faces
    code, out, err, _ = _precompute(tmp_path, capsys, v, np.asarray(f), "--fixed", "z<-8", "--repair", "auto")
    assert code == 0 and "repair auto: no repair needed" in out, err


def test_several_bodies_are_listed_and_one_is_chosen_with_shell(tmp_path, capsys):
    """The scans issue's item 2: a file of three separate bodies is refused in one line that lists them with
    their share of the area and names --shell (no repair route guesses which body is the organ, --repair
    auto included); --shell 2 precomputes the second largest, a 20 mm ball (volume within 4 %, as above)."""
    v, f = CASES["several shells"]
    for extra in ([], ["--repair", "auto"]):
        code, _, err, _ = _precompute(tmp_path, capsys, v, f, "--fixed", "z<-8", *extra)
        assert code == 2 and "3 separate shells" in err and "1: 33.3 % of the area" in err and "--shell K" in err
    code, _, err, path = _precompute(tmp_path, capsys, v, f, "--fixed", "z<-8", "--shell", "2")
    assert code == 0, err
    assert abs(_solid_volume(path) / (4.0 / 3.0 * np.pi * 20.0 ** 3) - 1) < 0.04
    code, _, err, _ = _precompute(tmp_path, capsys, v, f, "--fixed", "z<-8", "--shell", "4")
    assert code == 2 and "--shell 4, but the surface has 3 shell(s)" in err


def test_repair_auto_that_finds_no_route_says_what_each_ran_into_and_never_advises_a_tried_one(tmp_path, capsys):
    """An open flat sheet bounds no solid by any route: one line naming each route's reason, and no advice to
    try a --repair route (the issue's heart was told "try --repair" after --repair had failed)."""
    import trimesh

    g = trimesh.creation.box(extents=(40.0, 40.0, 1e-3))
    top = np.asarray(g.faces)[np.asarray(g.face_normals)[:, 2] > 0.5]
    code, _, err, _ = _precompute(tmp_path, capsys, np.asarray(g.vertices), top, "--fixed", "x<-15",
                                  "--repair", "auto")
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "as it is:" in err and "meshfix:" in err and "voxel:" in err and "try --repair" not in err
