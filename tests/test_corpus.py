"""The real-inputs issue's corpus, made by the test (no downloads): damaged and awkward surfaces as
segmentation exports carry them, and a label image.  Over every case and with or without --repair, the
CLI either writes an artifact the runtime loads or refuses in one line with no traceback; the cases that
--repair exists for go through with it."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from pmask.pipeline.cli import main
from pmask.runtime import Model


def sphere(r=20.0, sub=3, at=(0.0, 0.0, 0.0)):
    s = trimesh.creation.icosphere(subdivisions=sub, radius=r)
    return np.asarray(s.vertices) + at, np.asarray(s.faces)


def join(*parts):
    P, T, n = [], [], 0
    for v, f in parts:
        P.append(v)
        T.append(f + n)
        n += len(v)
    return np.vstack(P), np.vstack(T)


def corpus():
    v, f = sphere()
    cases = {}
    cases["several shells"] = join(sphere(), sphere(at=(50.0, 0, 0)), sphere(at=(0, 50.0, 0)))
    a, b = sphere(), sphere(r=10.0, sub=2)
    b = (b[0] + a[0][a[1][0][0]] - b[0][b[1][0][0]] + [0, 0, 0.0], b[1])
    P, T = join(a, b)
    n = len(a[0])
    edge, point = T.copy(), T.copy()
    edge[edge == b[1][0][0] + n], edge[edge == b[1][0][1] + n] = a[1][0][0], a[1][0][1]  # one shared edge
    point[point == b[1][0][0] + n] = a[1][0][0]  # one shared vertex
    cases["touching shells"] = (P, edge)
    cases["touching at a point"] = (P, point)
    cases["holes"] = (v, np.delete(f, [0, 7, 40, 41], axis=0))
    flipped = f.copy()
    patch = np.flatnonzero(v[f].mean(axis=1)[:, 2] > 15.0)
    flipped[patch] = flipped[patch][:, ::-1]
    cases["flipped patch"] = (v, flipped)
    poked = v.copy()
    poked[0] = -1.6 * poked[0]
    cases["self-intersection"] = (poked, f)
    plate = trimesh.creation.box(extents=(40.0, 40.0, 0.4))
    cases["thin feature"] = (np.asarray(plate.vertices), np.asarray(plate.faces))
    cases["debris"] = join(sphere(), sphere(r=0.4, sub=1, at=(30.0, 0, 0)), sphere(r=0.4, sub=1, at=(0, 30.0, 0)))
    big = trimesh.creation.icosphere(subdivisions=7, radius=20.0)  # 327,680 triangles
    cases["over 300,000 triangles"] = (np.asarray(big.vertices), np.asarray(big.faces))
    return cases


CASES = corpus()
#: the damaged cases --repair is for: refused without it, precomputed with it
MENDED_BY_REPAIR = {"touching shells", "touching at a point", "holes", "flipped patch"}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(CASES))
@pytest.mark.parametrize("repair", [False, True])
def test_every_corpus_case_is_an_artifact_or_one_line(tmp_path, capsys, name, repair):
    import meshio

    v, f = CASES[name]
    stl = tmp_path / "case.stl"
    meshio.write_points_cells(stl, v, [("triangle", f)])
    out = tmp_path / "case.h5"
    code = main(["precompute", "--surface", str(stl), "--units", "mm", "--edge-length", "5", "--fixed", "z<-8",
                 "-o", str(out)] + (["--repair"] if repair else []))
    err = capsys.readouterr().err
    assert "Traceback" not in err
    if code == 0:
        assert len(Model.load(out).points) > 50
    else:
        assert code == 2 and len([l for l in err.splitlines() if l.startswith("pmask: error")]) == 1, err
    if name in MENDED_BY_REPAIR:
        assert code == (0 if repair else 2), err


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
