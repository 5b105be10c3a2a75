"""Artifacts are refused when foreign, newer, truncated or altered (data or metadata), naming file and problem."""
from __future__ import annotations

import shutil

import h5py
import numpy as np
import pytest

from pmask.pipeline.stages import Spec, run
from pmask.runtime import ArtifactError, Model


@pytest.fixture(scope="module")
def artifact(tmp_path_factory):
    out = tmp_path_factory.mktemp("art") / "loop1.h5"
    run(Spec(model="loop1"), out)
    return out


@pytest.fixture
def copy(artifact, tmp_path):
    dst = tmp_path / "copy.h5"
    shutil.copy(artifact, dst)
    return dst


def test_loads_intact(artifact):
    m = Model.load(artifact)
    assert m.Xi.shape == (3 * len(m.contact),) * 2


def test_refuses_missing_file(tmp_path):
    with pytest.raises(ArtifactError, match="no such file"):
        Model.load(tmp_path / "none.h5")


def test_refuses_foreign_hdf5(tmp_path):
    p = tmp_path / "foreign.h5"
    with h5py.File(p, "w") as f:
        f["x"] = np.arange(3)
    with pytest.raises(ArtifactError, match="foreign"):
        Model.load(p)


def test_refuses_non_hdf5(tmp_path):
    p = tmp_path / "text.h5"
    p.write_text("not hdf5")
    with pytest.raises(ArtifactError, match="not an HDF5"):
        Model.load(p)


def test_refuses_newer_major_version(copy):
    with h5py.File(copy, "r+") as f:
        f.attrs["format_version"] = "2.0.0"
    with pytest.raises(ArtifactError, match="version 2.0.0 is not supported"):
        Model.load(copy)


def test_accepts_newer_minor_version_only_if_checksum_matches(copy):
    with h5py.File(copy, "r+") as f:
        f.attrs["format_version"] = "1.1.0"
    with pytest.raises(ArtifactError, match="checksum"):  # metadata was altered after writing
        Model.load(copy)


@pytest.mark.parametrize("attr,value", [("material", '{"E": 20000.0, "nu": 0.45}'), ("r_max", 1.0),
                                        ("units", '{"length": "mm"}')])
def test_refuses_altered_metadata(copy, attr, value):
    with h5py.File(copy, "r+") as f:
        f.attrs[attr] = value
    with pytest.raises(ArtifactError, match=f"{copy.name}.*checksum"):
        Model.load(copy)


def test_refuses_altered_surface_data(copy):
    with h5py.File(copy, "r+") as f:
        a = f["surface/vertex_areas"][()]
        a[3] *= 1.01
        f["surface/vertex_areas"][...] = a
    with pytest.raises(ArtifactError, match="checksum"):
        Model.load(copy)


def test_refuses_bit_flip_in_greens_functions(copy):
    with h5py.File(copy, "r") as f:
        info = f["greens/Xi"].id.get_chunk_info(0)
    with open(copy, "r+b") as fh:
        fh.seek(info.byte_offset + info.size // 2)
        b = fh.read(1)
        fh.seek(-1, 1)
        fh.write(bytes([b[0] ^ 0x10]))
    with pytest.raises(ArtifactError, match=f"{copy.name}.*corrupt"):
        Model.load(copy)


def test_refuses_truncated_file(copy):
    data = copy.read_bytes()
    copy.write_bytes(data[: len(data) // 2])
    with pytest.raises(ArtifactError, match=copy.name):
        Model.load(copy)
