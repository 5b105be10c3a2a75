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
                    "several shells", "overlapping shells"}}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(CASES))
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
