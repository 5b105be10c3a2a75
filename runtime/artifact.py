"""The Green's-function artifact: one HDF5 file, its format, and its checks.

Layout (format 1.x)::

    /                      attrs: format_name, format_version (semver), definition,
                           model, units, material, element, r_max, input_hash,
                           parameters, provenance, timings, metadata_sha256
    /surface/points        (n_s, 3) surface vertex positions [length unit]
    /surface/triangles     (n_t, 3) int64, counter-clockwise seen from outside
    /surface/vertex_areas  (n_s,)   a_i = ∫ φ_i dΓ  (paper eq. 10)
    /surface/free          (n_p,)   surface indices of Λp (traction-constrained, free)
    /surface/fixed         (n_u,)   surface indices of Λu (displacement-constrained, fixed)
    /surface/contact       (n_c,)   surface indices of the rows and columns of Ξ (subset of free;
                                    all of Λp unless a contact region was given)
    /surface/contact_core  (n_c,)   bool: the probe may touch it (masks up to r_max are complete)
    /surface/volume_index  (n_s,)   index of each surface vertex in /volume/points
    /greens/Xi             (3 n_c, 3 n_c)  Ξ: block (i, j) = displacement of contact vertex i
                                           per unit traction at contact vertex j
    /greens/reactions      (3 n_u, 3 n_c)  support forces per unit traction at j
    /volume/points, /volume/tets           the tetrahedral mesh it came from

The large datasets carry HDF5's Fletcher-32 checksum (checked by HDF5 on every
read); the attributes and every small dataset are covered by a SHA-256 digest
stored in ``metadata_sha256``, because Fletcher-32 does not cover attributes.
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np

from pmask.errors import PmaskError

FORMAT_NAME = "pmask.greens"
FORMAT_VERSION = "1.0.0"
DEFINITION = (
    "Xi = G diag(a): G is the condensed flexibility of the free surface vertices (displacement per unit "
    "nodal force, symmetric), a_i = integral of the hat function phi_i over the surface (vertex area). "
    "Block Xi[3i:3i+3, 3j:3j+3] is the displacement of contact vertex i per unit traction p_j at contact "
    "vertex j, i.e. per nodal force a_j p_j; sum_j rho_j Xi_ij is the displacement of vertex i under the "
    "traction rho*f, and rho = e_i / a_i is a point force. Reciprocity: a_i Xi_ij = a_j Xi_ji^T."
)
LARGE = ("greens/Xi", "greens/reactions", "volume/points", "volume/tets")
SMALL = ("surface/points", "surface/triangles", "surface/vertex_areas", "surface/free", "surface/fixed",
         "surface/contact", "surface/contact_core", "surface/volume_index")
JSON_ATTRS = ("units", "material", "parameters", "provenance", "timings")


class ArtifactError(PmaskError, ValueError):
    """A file that is not a readable artifact of a supported version (names file and problem)."""


def metadata_digest(attrs: dict, small: dict) -> str:
    """SHA-256 over the root attributes (but the digest itself) and the small datasets."""
    h = hashlib.sha256()
    for key in sorted(attrs):
        if key == "metadata_sha256":
            continue
        h.update(key.encode())
        h.update(_attr_bytes(attrs[key]))
    for name in sorted(small):
        arr = np.ascontiguousarray(small[name])
        h.update(name.encode())
        h.update(str(arr.dtype.str).encode() + str(arr.shape).encode())
        h.update(arr.tobytes())
    return h.hexdigest()


def _attr_bytes(value) -> bytes:
    if isinstance(value, bytes):
        return value
    if isinstance(value, str):
        return value.encode()
    return np.asarray(value).tobytes() + str(np.asarray(value).dtype.str).encode()


def _major(version: str) -> int:
    try:
        return int(str(version).split(".")[0])
    except ValueError:
        return -1


def read_artifact(path, *, verify: bool = True) -> dict:
    """Read and check an artifact; return its arrays and decoded attributes.

    Raises :class:`ArtifactError` for a missing, truncated, corrupt or foreign
    file, or one whose major format version this reader does not know.
    """
    import h5py

    path = Path(path)
    if not path.is_file():
        raise ArtifactError(f"{path}: no such file; run 'make precompute MODEL=...' to create it")
    try:
        if not h5py.is_hdf5(path):
            raise ArtifactError(f"{path}: not an HDF5 file (truncated, or not a pmask artifact)")
        with h5py.File(path, "r") as f:
            attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
            name = attrs.get("format_name")
            if name != FORMAT_NAME:
                raise ArtifactError(f"{path}: foreign HDF5 file (format_name={name!r}, expected {FORMAT_NAME!r})")
            version = str(attrs.get("format_version", ""))
            if _major(version) != _major(FORMAT_VERSION):
                raise ArtifactError(f"{path}: format version {version} is not supported by this reader "
                                    f"({FORMAT_VERSION}); recompute it with this version of pmask")
            missing = [d for d in SMALL + LARGE if d not in f]
            if missing:
                raise ArtifactError(f"{path}: incomplete artifact, missing {', '.join(missing)}")
            data = {d: f[d][()] for d in SMALL + LARGE}
    except ArtifactError:
        raise
    except (OSError, KeyError, RuntimeError) as exc:
        raise ArtifactError(f"{path}: cannot read the artifact ({exc}); it is corrupt or truncated, "
                            "recompute it with --force") from exc
    if verify:
        digest = metadata_digest(attrs, {k: data[k] for k in SMALL})
        if digest != attrs.get("metadata_sha256"):
            raise ArtifactError(f"{path}: metadata checksum mismatch (attributes or surface data were altered); "
                                "recompute it with --force")
    for key in JSON_ATTRS:
        if key in attrs:
            try:
                attrs[key] = json.loads(attrs[key])
            except (TypeError, ValueError) as exc:
                raise ArtifactError(f"{path}: attribute {key} is not valid JSON") from exc
    _check_shapes(path, data)
    return {"attrs": attrs, **data}


def _check_shapes(path, d) -> None:
    ns, nu, nc = len(d["surface/points"]), len(d["surface/fixed"]), len(d["surface/contact"])
    problems = []
    if d["greens/Xi"].shape != (3 * nc, 3 * nc):
        problems.append(f"Xi has shape {d['greens/Xi'].shape}, expected {(3 * nc, 3 * nc)}")
    if d["greens/reactions"].shape != (3 * nu, 3 * nc):
        problems.append("reactions have the wrong shape")
    for key in ("surface/triangles", "surface/free", "surface/fixed", "surface/contact"):
        arr = d[key]
        if arr.size and (arr.min() < 0 or arr.max() >= ns):
            problems.append(f"{key} indexes outside the {ns} surface vertices")
    if not np.all(np.isfinite(d["greens/Xi"])):
        problems.append("Xi holds NaN or inf")
    if problems:
        raise ArtifactError(f"{path}: inconsistent artifact: " + "; ".join(problems))


def write_atomic_hdf5(path, fill) -> None:
    """Create ``path`` through a temporary file in the same folder, fsync, then rename.

    ``fill(h5file)`` writes the content.  An interrupted run leaves at most the
    temporary file, never a half-written file under the final name.
    """
    import h5py

    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with h5py.File(tmp, "w") as f:
            fill(f)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
