"""Artifacts are refused when foreign, newer, truncated or altered (data or metadata), naming file and problem."""
from __future__ import annotations

import json
import shutil

import h5py
import numpy as np
import pytest

from pmask.pipeline.stages import Spec, run
from pmask.runtime import ArtifactError, Model
from pmask.runtime.artifact import (FORMAT_VERSION, LEGACY_SMALL, array_digest, legacy_metadata_digest,
                                    metadata_digest)


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


def next_minor() -> str:
    major, minor = FORMAT_VERSION.split(".")[:2]
    return f"{major}.{int(minor) + 1}.0"


def rewrite_as_newer_minor(path, extra=np.arange(5.0)):
    """What a writer of the next minor version would produce: one more dataset and one more root
    attribute, both listed in sha256_covers, with the metadata digest recomputed over the new list."""
    with h5py.File(path, "r+") as f:
        f["greens/future_dataset"] = extra
        f.attrs["future_attribute"] = "added by format 1.x+1"
        f.attrs["format_version"] = next_minor()
        covers = json.loads(f.attrs["sha256_covers"])
        covers["attributes"] = sorted(covers["attributes"] + ["future_attribute"])
        covers["datasets"]["greens/future_dataset"] = array_digest(extra)
        f.attrs["sha256_covers"] = json.dumps(covers, sort_keys=True)
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
        f.attrs["metadata_sha256"] = metadata_digest(attrs, covers)


def test_accepts_a_newer_minor_version_with_more_data(artifact, copy):
    rewrite_as_newer_minor(copy)
    m, ref = Model.load(copy), Model.load(artifact)
    assert m.attrs["format_version"] == next_minor()
    np.testing.assert_array_equal(m.Xi, ref.Xi)


def test_a_version_changed_without_its_digest_is_refused(copy):
    with h5py.File(copy, "r+") as f:
        f.attrs["format_version"] = next_minor()
    with pytest.raises(ArtifactError, match="metadata .*altered"):
        Model.load(copy)


def test_reads_format_1_0(artifact, copy):
    """A file as format 1.0 wrote it: no sha256_covers, one digest over every attribute and the surface."""
    with h5py.File(copy, "r+") as f:
        del f.attrs["sha256_covers"]
        f.attrs["format_version"] = "1.0.0"
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
        small = {k: f[k][()] for k in LEGACY_SMALL}
        f.attrs["metadata_sha256"] = legacy_metadata_digest(attrs, small)
    np.testing.assert_array_equal(Model.load(copy).Xi, Model.load(artifact).Xi)
    with h5py.File(copy, "r+") as f:
        f.attrs["r_max"] = 1.0
    with pytest.raises(ArtifactError, match="altered"):
        Model.load(copy)


def test_refuses_sign_flipped_greens_functions_rewritten_through_h5py(copy):
    """Rewritten through h5py (which would keep any Fletcher-32 checksum valid): the SHA-256 sees it."""
    with h5py.File(copy, "r+") as f:
        f["greens/Xi"][...] = -f["greens/Xi"][()]
    with pytest.raises(ArtifactError, match="dataset greens/Xi was altered"):
        Model.load(copy)


def test_large_datasets_hashed_block_by_block_still_see_one_changed_value(artifact, copy, monkeypatch):
    """Datasets above READ_BLOCK_BYTES are read in row blocks and hashed in a second thread while the next
    block is read: with blocks of 4 KiB (thousands of blocks for this Ξ) the intact file loads with
    the digests written whole, and one value changed in Ξ's last row (valid Fletcher-32) is refused."""
    from pmask.runtime import artifact as art

    monkeypatch.setattr(art, "READ_BLOCK_BYTES", 4096)
    np.testing.assert_array_equal(Model.load(artifact).Xi, Model.load(artifact, verify=False).Xi)
    with h5py.File(copy, "r+") as f:
        f["greens/Xi"][-1, -1] = 2 * f["greens/Xi"][-1, -1]
    with pytest.raises(ArtifactError, match="dataset greens/Xi was altered"):
        Model.load(copy)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_a_nan_signed_with_every_digest_is_found_by_the_reading_threads(tmp_path, monkeypatch, bad):
    """Format 1.5's block reads check each block for NaN and inf in the threads that hash it (the shape checks
    then skip their own pass over the array): a NaN or inf written into Ξ with the block's, the dataset's and
    the metadata's digests all recomputed (so every SHA-256 passes) is still refused, and the intact file's
    datasets were all found finite that way."""
    from pmask.precompute import writer
    from pmask.runtime import artifact as art

    monkeypatch.setattr(writer, "BLOCK_DIGEST_BYTES", 1 << 16)
    monkeypatch.setattr(art, "READ_BLOCK_BYTES", 1 << 14)
    out = tmp_path / "blocks.h5"
    run(Spec(model="loop1"), out)
    seen = {}
    real = art._check_shapes
    monkeypatch.setattr(art, "_check_shapes", lambda path, d, finite=None: (seen.update(finite or {}),
                                                                            real(path, d, finite))[1])
    Model.load(out)
    assert seen.get("greens/Xi") is True  # checked by the threads, not again
    with h5py.File(out, "r+") as f:
        covers = json.loads(f.attrs["sha256_covers"])
        rows = covers["blocks"]["greens/Xi"]["rows"]
        Xi = f["greens/Xi"][()]
        r = len(Xi) - 2
        Xi[r, 1] = bad
        f["greens/Xi"][...] = Xi
        covers["blocks"]["greens/Xi"]["sha256"][r // rows] = array_digest(Xi[(r // rows) * rows:(r // rows + 1) * rows])
        covers["datasets"]["greens/Xi"] = array_digest(Xi)
        f.attrs["sha256_covers"] = json.dumps(covers, sort_keys=True)
        attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
        f.attrs["metadata_sha256"] = metadata_digest(attrs, covers)
    with pytest.raises(ArtifactError, match="NaN or inf"):
        Model.load(out)
    assert seen.get("greens/Xi") is False


def test_per_block_digests_are_verified_and_name_the_altered_rows(tmp_path, monkeypatch):
    """Format 1.5: a dataset above BLOCK_DIGEST_BYTES also has the SHA-256 of each block of rows, which the
    reader hashes on two threads (one SHA-256 of the whole is a serial chain).  With the threshold at 64 KiB and
    blocks of 16 KiB, Ξ gets a block list covering every row; the whole-dataset digest a 1.4 reader checks is
    still right; the file loads equal to an unverified load; one value changed (through h5py) is refused,
    naming rows that hold it."""
    from pmask.precompute import writer
    from pmask.runtime import artifact as art

    monkeypatch.setattr(writer, "BLOCK_DIGEST_BYTES", 1 << 16)
    monkeypatch.setattr(art, "READ_BLOCK_BYTES", 1 << 14)
    out = tmp_path / "blocks.h5"
    run(Spec(model="loop1"), out)
    with h5py.File(out, "r") as f:
        covers = json.loads(f.attrs["sha256_covers"])
        Xi = f["greens/Xi"][()]
    blocks = covers["blocks"]["greens/Xi"]
    rows = blocks["rows"]
    assert rows == art.digest_block_rows(Xi.shape, 8) and len(blocks["sha256"]) == -(-len(Xi) // rows) > 10
    assert array_digest(Xi) == covers["datasets"]["greens/Xi"]  # what a 1.4 reader verifies
    np.testing.assert_array_equal(Model.load(out).Xi, Model.load(out, verify=False).Xi)
    row = len(Xi) - 3
    with h5py.File(out, "r+") as f:
        f["greens/Xi"][row, 0] = 2 * f["greens/Xi"][row, 0] + 1e-30
    import re

    with pytest.raises(ArtifactError, match="dataset greens/Xi \\(rows") as err:
        Model.load(out)
    first, last = map(int, re.search(r"rows (\d+) to (\d+)", str(err.value)).groups())
    assert first <= row <= last


def test_a_nan_anywhere_in_a_large_array_is_found():
    """all_finite (one summing pass instead of isfinite's boolean array): a NaN or an inf anywhere is found,
    and finite values whose sum overflows are not mistaken for one."""
    from pmask.runtime.artifact import all_finite

    x = np.zeros(10_001)
    assert all_finite(x)
    for bad in (np.nan, np.inf, -np.inf):
        y = x.copy()
        y[7_777] = bad
        assert not all_finite(y) and not all_finite(y.astype(np.float32))
    assert all_finite(np.full(4, 1e308))  # the sum overflows; every value is finite


def test_the_runtime_reads_only_what_it_uses(copy):
    """Altering the volume mesh (which the runtime never reads) does not stop Model.load, but is
    caught when the volume is asked for."""
    with h5py.File(copy, "r+") as f:
        f["volume/points"][0, 0] += 1.0
    m = Model.load(copy)
    with pytest.raises(ArtifactError, match="dataset volume/points was altered"):
        m.volume()


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
    """One bit flipped on disk in the middle of Ξ (stored contiguous, format 1.5: its SHA-256 is its check)."""
    with h5py.File(copy, "r") as f:
        offset, size = f["greens/Xi"].id.get_offset(), f["greens/Xi"].id.get_storage_size()
    with open(copy, "r+b") as fh:
        fh.seek(offset + size // 2)
        b = fh.read(1)
        fh.seek(-1, 1)
        fh.write(bytes([b[0] ^ 0x10]))
    with pytest.raises(ArtifactError, match=f"{copy.name}.*dataset greens/Xi was altered"):
        Model.load(copy)


def test_refuses_truncated_file(copy):
    data = copy.read_bytes()
    copy.write_bytes(data[: len(data) // 2])
    with pytest.raises(ArtifactError, match=copy.name):
        Model.load(copy)
