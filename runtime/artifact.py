"""The Green's-function artifact: one HDF5 file, its format, and its checks.

Layout (format 1.x)::

    /                      attrs: format_name, format_version (semver), definition,
                           model, units, material, element, r_max, input_hash,
                           parameters, provenance, timings, sha256_covers, metadata_sha256
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
    /greens/reactions      (3 n_u, 3 n_c)  support forces per unit traction at j (optional)
    /volume/points, /volume/tets           the tetrahedral mesh it came from

Format 1.8 stores a compressed Ξ's far-field factors in 16 bits (``/greens/hmatrix/U16`` and ``V16``, int16,
in place of ``U`` and ``V``, with ``U_scale`` and ``V_scale``: one float32 scale per column of each block,
:func:`pmask.runtime.compressed.encode_far`) where float32 took 32: the tiles truncate to half the tolerance and
the rounding, computed for each block, takes at most the other half.  A 1.7 reader refuses such a file as missing
``U``; a 1.7 file is read as before, and so is a 1.8 file compressed below 1e-4 (``--compress 1e-5``), whose
factors stay float32 or float64 in ``U`` and ``V``.

Format 1.7 stores a compressed Ξ's exact pairs in fixed point (``/greens/hmatrix/near_exact48`` in place of
``near_exact``: :func:`pmask.runtime.compressed.pack_exact`), each pair's nine values as 48-bit integers times
one power of two, within 1.4e-14 of the pair's largest magnitude, 56 bytes a pair where float64 took 72 (the
pairs within r_max are most of a large organ's bytes).  A 1.6 reader refuses such a file as missing its near
field; a 1.6 file (``near_exact``) is read as before, and so is a 1.7 file written with ``--float32``, whose
exact pairs stay float32 in ``near_exact``.

Format 1.6 stores a compressed Ξ's dense blocks pair by pair (``/greens/hmatrix/near_index``, ``near_exact``,
``near_mask``, ``near_q``, ``near_scale`` in place of ``dense``: :mod:`pmask.runtime.compressed`): the pairs
within r_max exactly, the others in 16 bits within the tolerance.  A 1.5 reader refuses such a file as missing
``/greens/hmatrix/dense`` (it would read the pairs as whole blocks); a file with ``dense`` (≤ 1.5) is read as
before.  Its near field (:data:`NEAR`) is stored in chunks through HDF5's byte shuffle and deflate filters
(:data:`NEAR_FILTERS`, files written since 2026-11-27; before, contiguous): lossless, undone by every HDF5 reader
as it reads, so the format's version is unchanged; the digests are of the values, as for every dataset.

Format 1.5 changes how the large datasets are checked, for the time to open a large organ: every dataset above
64 MiB also has the SHA-256 of each block of rows (``sha256_covers["blocks"][name]``: ``{"rows": R,
"sha256": [...]}``), which a reader hashes on both cores while it reads (its whole-dataset digest stays, so a
1.4 reader still verifies it), and only the datasets a reader may read in slices without hashing them (the
far field's factors U and V: :data:`SLICED`) carry HDF5's Fletcher-32; the others are contiguous.

Format 1.4 stores a symmetric compressed Ξ (P1: Ξ = G diag(a), G symmetric) once per pair of blocks:
``/greens/hmatrix/scale`` (the areas a) says so (:mod:`pmask.runtime.compressed`); a file without it (1.2,
1.3) has every block and is read as before.

Format 1.3 adds the display surface (optional; :mod:`pmask.runtime.display`): the user's surface at the
scan's resolution and its embedding in the simulation surface, the root attribute ``display`` (JSON: vertices,
triangles, folded, max_lift_m) and ``/display/{points (m, 3), triangles (k, 3), vertices (m, 3): the simulation
surface vertices of each display vertex's triangle, bary (m, 3), lift (m, 3)}``.

Format 1.2 adds Ξ in compressed form (``pmask precompute --compress``): the root attributes
``greens_form = "hmatrix"`` and ``tolerance``, and the group ``/greens/hmatrix`` in place of
``/greens/Xi`` (layout: :mod:`pmask.runtime.compressed`).  Dense files are unchanged; a 1.1 reader
refuses a compressed file as missing ``/greens/Xi``.

Checks.  ``sha256_covers`` (JSON) lists what the SHA-256 digests cover: the root attributes by name,
and every dataset with its own SHA-256 over its stored bytes (C order, stored dtype).
``metadata_sha256`` is the SHA-256 of those attributes and of the ``sha256_covers`` list itself, so
that no covered attribute, dataset digest or the list can change unnoticed.  A reader verifies the
datasets it reads (and only those: the runtime never reads the volume mesh or the reactions) and
accepts datasets and attributes it does not know, so that a newer minor version of the format stays
readable, as semver promises.  A newer major version is refused.  The datasets a reader may read in slices
(:data:`SLICED`) also carry HDF5's Fletcher-32 checksum, which HDF5 checks on every read and which names the
corrupt chunk (before format 1.5 every large dataset did).

Format 1.0 files (no ``sha256_covers``; the digest covered the attributes and the surface datasets)
are still read and checked as they were written.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from pmask.errors import PmaskError

FORMAT_NAME = "pmask.greens"
FORMAT_VERSION = "1.8.0"
DEFINITION = (
    "Xi = G diag(a): G is the condensed flexibility of the free surface vertices (displacement per unit "
    "nodal force, symmetric), a_i = integral of the hat function phi_i over the surface (vertex area). "
    "Block Xi[3i:3i+3, 3j:3j+3] is the displacement of contact vertex i per unit traction p_j at contact "
    "vertex j, i.e. per nodal force a_j p_j; sum_j rho_j Xi_ij is the displacement of vertex i under the "
    "traction rho*f, and rho = e_i / a_i is a point force. Reciprocity: a_i Xi_ij = a_j Xi_ji^T."
)
SURFACE = ("surface/points", "surface/triangles", "surface/vertex_areas", "surface/free", "surface/fixed",
           "surface/contact", "surface/contact_core", "surface/volume_index")
#: what the runtime reads: the surface and Ξ (for a compressed artifact, ``greens_form = "hmatrix"``, the
#: reader reads :data:`HMATRIX` in Ξ's place)
RUNTIME = SURFACE + ("greens/Xi",)
HMATRIX = tuple(f"greens/hmatrix/{k}" for k in ("perm", "leaves", "dense_index", "dense", "lowrank_index", "U", "V",
                                                 "scale", "near_index", "near_exact", "near_mask", "near_q",
                                                 "near_scale", "near_exact48", "U16", "V16", "U_scale", "V_scale"))
#: the datasets a reader may leave in the file and read in slices without their SHA-256 (a large organ's far
#: field: :class:`FileArray`); only these carry HDF5's Fletcher-32 (format 1.5)
SLICED = ("greens/hmatrix/U", "greens/hmatrix/V", "greens/hmatrix/U16", "greens/hmatrix/V16")
#: the exact near field, which a reader may read when first needed, a block at a time, each block checked by its
#: SHA-256 (:class:`BlocksOnDemand`)
NEAR = ("greens/hmatrix/dense", "greens/hmatrix/near_exact", "greens/hmatrix/near_exact48", "greens/hmatrix/near_q")
#: how the near field is stored: in chunks of about 1 MiB through HDF5's byte shuffle and deflate (level 1),
#: lossless, which every HDF5 reader undoes as it reads (h5py's wheels always have both filters).  The exact
#: values' exponent bytes repeat, their mantissas do not: 13 % fewer bytes on the float64 pairs within r_max and
#: 9 % on the 16-bit ones on a 3,882-vertex kidney, by hand; in fixed point (format 1.7), whose exponents are one
#: word a pair, about 2 % on the pairs (the compressed-Ξ tests measure it); the bench page's organ rows give the
#: sizes.  The far
#: field's factors (read in slices when left in the file) stay as they are: a slice would inflate whole chunks.
#: Deflate costs reading: zlib inflates about 0.55 GB/s a core, on top of the SHA-256 the blocks are checked by,
#: so reading the near field takes about 3x as long as reading it plain (the large-organs guide gives the bench's)
NEAR_FILTERS = {"shuffle": True, "compression": "gzip", "compression_opts": 1}
#: datasets above this size also get a SHA-256 per block of rows (format 1.5), verified on both cores
BLOCK_DIGEST_BYTES = 64 << 20
#: of these, optional (before format 1.4 every block was stored: no scale; format 1.6 stores its dense blocks pair
#: by pair, near_exact and the others in place of dense, whole blocks: the reader needs one of the two; format 1.8
#: the far field's factors in 16 bits, U16, V16 and their scales in place of U and V: one of the two again)
HMATRIX_OPTIONAL = ("greens/hmatrix/scale", "greens/hmatrix/dense", "greens/hmatrix/near_index",
                    "greens/hmatrix/near_exact", "greens/hmatrix/near_mask", "greens/hmatrix/near_q",
                    "greens/hmatrix/near_scale", "greens/hmatrix/near_exact48", "greens/hmatrix/U",
                    "greens/hmatrix/V", "greens/hmatrix/U16", "greens/hmatrix/V16", "greens/hmatrix/U_scale",
                    "greens/hmatrix/V_scale")
VOLUME = ("volume/points", "volume/tets")
REACTIONS = ("greens/reactions",)
#: the display surface (optional, format 1.3): read only when asked for (Model.display)
DISPLAY = tuple(f"display/{k}" for k in ("points", "triangles", "vertices", "bary", "lift"))
#: materials by region (optional): each tetrahedron's index into attrs material["regions"], -1 the body's
MATERIALS = ("volume/material_region",)
JSON_ATTRS = ("units", "material", "parameters", "provenance", "timings", "sha256_covers", "display")
#: format 1.0: the digest covered every attribute and these datasets
LEGACY_SMALL = SURFACE


class ArtifactError(PmaskError, ValueError):
    """A file that is not a readable artifact of a supported version (names file and problem)."""


def array_digest(arr: np.ndarray) -> str:
    """SHA-256 of an array's bytes in C order (its own dtype); what ``sha256_covers`` stores per dataset."""
    h = hashlib.sha256()
    update_array_digest(h, arr)
    return h.hexdigest()


def update_array_digest(h, arr: np.ndarray) -> None:
    """Feed an array (or a block of rows of one, in order) to a running SHA-256."""
    a = np.ascontiguousarray(arr)
    h.update(memoryview(a).cast("B") if a.size else b"")


def metadata_digest(attrs: dict, covers: dict) -> str:
    """SHA-256 over the covered root attributes (by name, sorted) and the ``covers`` list itself."""
    h = hashlib.sha256()
    for key in sorted(covers["attributes"]):
        h.update(key.encode())
        h.update(_attr_bytes(attrs[key]))
    h.update(json.dumps(covers, sort_keys=True).encode())
    return h.hexdigest()


def legacy_metadata_digest(attrs: dict, small: dict) -> str:
    """Format 1.0's digest: every root attribute but the digest, and the surface datasets."""
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


def stored_bytes(path, names) -> int | None:
    """The bytes of these datasets' values in an artifact, or None when it lacks one of them (or there is no
    readable file: :func:`read_artifact` says what is wrong with it)."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            if not all(k in f for k in names):
                return None
            return int(sum(f[k].size * f[k].dtype.itemsize for k in names))
    except OSError:
        return None


def stored_input_hash(path) -> str | None:
    """The input hash an existing artifact records (attribute ``input_hash``), or None when there is no
    readable artifact at ``path``.  The pipeline compares it with the hash of the inputs it was given to
    decide whether an artifact is up to date; nothing else is read or verified."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            v = f.attrs.get("input_hash")
    except (OSError, KeyError):
        return None
    return v.decode() if isinstance(v, bytes) else v


def _major_minor(version: str) -> tuple[int, int]:
    try:
        parts = [int(p) for p in str(version).split(".")[:2]]
        return parts[0], parts[1] if len(parts) > 1 else 0
    except ValueError:
        return -1, -1


class FileArray:
    """A dataset left in the artifact and read in slices when needed (a large organ's far field): ``a[i:j]``
    reads those values.  Its SHA-256 is not checked at load (that would read it all); HDF5 checks the
    Fletcher-32 of every chunk it reads, which names a corrupt chunk."""

    def __init__(self, path, name: str):
        import h5py

        self._file = h5py.File(path, "r")
        self._data = self._file[name]
        self.shape, self.dtype = self._data.shape, self._data.dtype
        self.nbytes = int(np.prod(self.shape)) * self.dtype.itemsize

    def __len__(self) -> int:
        return int(self.shape[0])

    def __getitem__(self, key):
        try:
            return self._data[key]
        except OSError as exc:
            raise ArtifactError(f"{self._file.filename}: cannot read {self._data.name} ({exc}); it is corrupt, "
                                "recompute it with --force") from exc

    def close(self) -> None:
        self._file.close()


def read_artifact(path, *, datasets=RUNTIME + VOLUME + REACTIONS + MATERIALS, verify: bool = True,
                  in_file=(), on_demand=(), on_demand_budget: int | None = None) -> dict:
    """Read and check an artifact; return the requested datasets and the decoded attributes.

    ``datasets``: the names to read (default: everything this reader knows; the runtime asks for
    :data:`RUNTIME` only).  An optional dataset the file does not have (``greens/reactions``) is
    returned as None.  ``in_file``: names among them returned as :class:`FileArray` (read when sliced,
    checked by HDF5's Fletcher-32 rather than by their SHA-256).  ``on_demand``: names among them returned as
    :class:`BlocksOnDemand` (read when first indexed, a block at a time, each checked by its SHA-256: format
    1.5's per-block digests, or the dataset's own as one block; read at once from a format 1.0 file), each
    holding at most ``on_demand_budget`` bytes of read blocks between them, shared in proportion to their sizes
    (None: all they read).  Raises
    :class:`ArtifactError` for a missing, truncated, corrupt, altered or foreign file, or one whose major
    format version this reader does not know.
    """
    import h5py

    path = Path(path)
    if not path.is_file():
        raise ArtifactError(f"{path}: no such file; write it with `pmask precompute MODEL -o {path}` (needs the precompute extra)")
    try:
        if not h5py.is_hdf5(path):
            raise ArtifactError(f"{path}: not an HDF5 file (truncated, or not a pmask artifact)")
        with h5py.File(path, "r") as f:
            attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
            name = attrs.get("format_name")
            if name != FORMAT_NAME:
                raise ArtifactError(f"{path}: foreign HDF5 file (format_name={name!r}, expected {FORMAT_NAME!r})")
            version = str(attrs.get("format_version", ""))
            if _major_minor(version)[0] != _major_minor(FORMAT_VERSION)[0]:
                raise ArtifactError(f"{path}: format version {version} is not supported by this reader "
                                    f"({FORMAT_VERSION}); recompute it with this version of pmask")
            legacy = "sha256_covers" not in attrs
            if attrs.get("greens_form") == "hmatrix" and "greens/Xi" in datasets:  # Ξ in compressed form
                datasets = [d for d in datasets if d != "greens/Xi"] + list(HMATRIX)
            wanted = list(datasets) + ([d for d in LEGACY_SMALL if d not in datasets] if legacy and verify else [])
            missing = [d for d in wanted if d not in f and d not in REACTIONS + MATERIALS + DISPLAY + HMATRIX_OPTIONAL]
            if missing:
                raise ArtifactError(f"{path}: incomplete artifact, missing {', '.join(missing)}")
            digests: dict = {}
            blocks = _block_digests(attrs) if verify and not legacy else {}
            finite: dict = {}  # datasets whose finiteness the reading threads checked, block by block
            later = [d for d in on_demand if d in datasets and d in f and not legacy and d not in in_file]
            size = {d: f[d].size * f[d].dtype.itemsize for d in later}
            data = {d: (_read(f[d], digests if verify and not legacy else None, d, blocks.get(d), finite)
                        if d in f else None) for d in wanted if d not in in_file and d not in later}
    except ArtifactError:
        raise
    except (OSError, KeyError, RuntimeError) as exc:
        raise ArtifactError(f"{path}: cannot read the artifact ({exc}); it is corrupt or truncated, "
                            "recompute it with --force") from exc
    if verify:
        _verify(path, attrs, data, legacy, digests)
    for key in JSON_ATTRS:
        if key in attrs:
            try:
                attrs[key] = json.loads(attrs[key])
            except (TypeError, ValueError) as exc:
                raise ArtifactError(f"{path}: attribute {key} is not valid JSON") from exc
    data = {k: v for k, v in data.items() if k in datasets}
    _check_shapes(path, data, finite)
    data.update({d: FileArray(path, d) for d in in_file if d in datasets})
    total = max(sum(size.values()), 1)
    for d in later:  # their digests, from sha256_covers, which the metadata digest has just vouched for
        covered = attrs["sha256_covers"]["datasets"] if verify else {}
        if verify and d not in covered:
            raise ArtifactError(f"{path}: dataset {d} is not covered by the file's checksums; recompute it")
        # several read on demand (format 1.6's near field: its exact pairs and its 16-bit part) share the budget
        # in proportion to their sizes
        budget = None if on_demand_budget is None else int(on_demand_budget) * size[d] // total
        if d in blocks:
            data[d] = BlocksOnDemand(path, d, int(blocks[d]["rows"]), blocks[d]["sha256"], budget)
        elif verify:  # below the per-block threshold: one block, the dataset's own digest
            data[d] = BlocksOnDemand(path, d, 1 << 62, [covered[d]], budget)
        else:
            data[d] = BlocksOnDemand(path, d, None, None, budget)
    return {"attrs": attrs, **data}


#: datasets larger than this are read in row blocks of about this size, each hashed while the next is read
READ_BLOCK_BYTES = 32 << 20


def digest_block_rows(shape, itemsize: int) -> int:
    """The rows of a block a dataset's per-block SHA-256 covers (format 1.5): about :data:`READ_BLOCK_BYTES`."""
    row_bytes = max(1, int(np.prod(shape[1:])) * itemsize)
    return max(1, READ_BLOCK_BYTES // row_bytes)


def _block_digests(attrs: dict) -> dict:
    """``sha256_covers["blocks"]`` (format 1.5), {} when the file has none or the list is unreadable (then
    :func:`_verify` says so, with the whole-dataset digests)."""
    try:
        blocks = json.loads(attrs["sha256_covers"]).get("blocks", {})
        return {k: v for k, v in blocks.items() if int(v["rows"]) > 0 and isinstance(v["sha256"], list)}
    except (TypeError, ValueError, KeyError, AttributeError):
        return {}


def _read(ds, digests: dict | None, name: str, blocks: dict | None = None, finite: dict | None = None) -> np.ndarray:
    """A dataset's values; with ``digests``, also its SHA-256 (:func:`array_digest`) into ``digests[name]``,
    computed in a second thread on each block of rows while the next block is read (hashlib releases the
    GIL): a 20,000-vertex compressed artifact's 0.7 GB near field is read and hashed in the time of the
    slower of the two, not of both.  With ``blocks`` (the file's per-block digests, format 1.5), each block of
    ``blocks["rows"]`` rows is hashed on its own, by two threads while the next is read, and
    ``digests[name]`` is the list of their digests: one SHA-256 of the whole is a serial chain, the blocks'
    are not (0.54 s on one core, 0.32 on two for that near field, by hand).  The same threads check each block
    for NaN and inf (:func:`all_finite`) into ``finite[name]``, which the shape checks then use instead of
    another pass over the array."""
    if blocks is not None and digests is not None and ds.ndim > 0 and ds.size:
        return _read_blocks(ds, digests, name, int(blocks["rows"]), finite)
    if digests is None or ds.ndim == 0 or ds.size * ds.dtype.itemsize <= READ_BLOCK_BYTES:
        arr = ds[()]
        if digests is not None:
            digests[name] = array_digest(arr)
        return arr
    from concurrent.futures import ThreadPoolExecutor

    arr = np.empty(ds.shape, ds.dtype)
    h = hashlib.sha256()
    rows = max(1, READ_BLOCK_BYTES // max(1, arr[0].nbytes))
    with ThreadPoolExecutor(1) as pool:
        pending = None
        for r0 in range(0, len(arr), rows):
            block = np.s_[r0:r0 + rows]
            ds.read_direct(arr, block, block)
            if pending is not None:
                pending.result()  # the hash takes the blocks in order
            pending = pool.submit(update_array_digest, h, arr[block])
        if pending is not None:
            pending.result()
    digests[name] = h.hexdigest()
    return arr


def _read_blocks(ds, digests: dict, name: str, rows: int, finite: dict | None = None) -> np.ndarray:
    """:func:`_read` for a dataset with per-block digests: its blocks of ``rows`` rows read in order, each
    hashed (and checked for NaN and inf) by one of two threads while the next is read."""
    arr = np.empty(ds.shape, ds.dtype)
    done = _read_and_hash(ds, arr, rows, range(-(-len(arr) // rows)))
    digests[name] = [h for h, _ in done]
    if finite is not None:
        finite[name] = all(ok for _, ok in done)
    return arr


def _read_and_hash(ds, arr: np.ndarray, rows: int, blocks) -> list:
    """Read the given blocks of ``rows`` rows of ``ds`` into ``arr`` in order, each hashed and checked for NaN
    and inf (:func:`_digest_and_finite`) by one of two threads while the next is read; their (digest, finite)."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(2) as pool:
        pending = []
        for k in blocks:
            block = np.s_[k * rows:(k + 1) * rows]
            _read_rows(ds, arr, k * rows, min((k + 1) * rows, len(arr)), pool)
            pending.append(pool.submit(_digest_and_finite, arr[block]))
        return [p.result() for p in pending]


def take_runs(values: np.ndarray, starts: np.ndarray, width: int) -> np.ndarray:
    """``values[starts[:, None] + arange(width)]`` for 1-D ``values``: as rows of a (-1, width) view when every run
    starts on a multiple of ``width`` (a compressed Ξ's exact pairs, nine values each, always do), one gather of
    whole rows instead of one per value."""
    if len(values) % width == 0 and not np.any(starts % width):
        return values.reshape(-1, width)[starts // width]
    return values[starts[:, None] + np.arange(width)]


def _deflated(ds) -> bool:
    """Whether ``ds`` is stored as :data:`NEAR_FILTERS` stores the near field: 1-D chunks through shuffle and
    deflate and no other filter (then :func:`_read_rows` inflates its chunks itself, on two threads)."""
    return (ds.ndim == 1 and ds.chunks is not None and ds.compression == "gzip" and bool(ds.shuffle)
            and not ds.fletcher32 and ds.scaleoffset is None)


def _read_rows(ds, arr: np.ndarray, r0: int, r1: int, pool) -> None:
    """``arr[r0:r1] = ds[r0:r1]``.  A deflated dataset's chunks are read as stored and inflated and unshuffled
    by ``pool``'s threads (zlib and numpy's copies release the GIL), where HDF5 inflates them one after another
    in the reading thread; with the blocks' SHA-256 on the same two threads the read is bound by the cores
    (about 1.7 core-seconds a GB here, by hand, a third of it besides inflating).  A corrupt chunk raises
    OSError, as HDF5's own read would."""
    if not _deflated(ds):
        ds.read_direct(arr, np.s_[r0:r1], np.s_[r0:r1])
        return
    c = ds.chunks[0]
    jobs = []
    for s in range(r0 // c * c, r1, c):
        mask, raw = ds.id.read_direct_chunk((s,))
        lo, hi = max(s, r0), min(s + c, r1)
        if mask:  # a filter was skipped when this chunk was written: HDF5 knows how to read it
            ds.read_direct(arr, np.s_[lo:hi], np.s_[lo:hi])
            continue
        jobs.append(pool.submit(_inflate_chunk, raw, lo - s, arr[lo:hi]))
    for j in jobs:
        j.result()


def deflate_chunk(part: np.ndarray, c: int) -> bytes:
    """A chunk of ``c`` values as HDF5's shuffle then deflate store it (the last chunk whole, zero beyond the
    dataset's end): what :func:`_inflate_chunk` undoes, the writer's half of the near field's storage."""
    import zlib

    full = np.zeros(c, part.dtype)
    full[:len(part)] = part
    shuffled = np.ascontiguousarray(full.view(np.uint8).reshape(c, part.dtype.itemsize).T)
    return zlib.compress(shuffled.tobytes(), NEAR_FILTERS["compression_opts"])


def _inflate_chunk(raw: bytes, skip: int, out: np.ndarray) -> None:
    """Elements ``skip:skip + len(out)`` of a chunk stored through shuffle (byte k of every element, then byte
    k + 1, ...) and deflate, into ``out``."""
    import zlib

    try:
        b = zlib.decompress(raw)
    except zlib.error as exc:
        raise OSError(f"a chunk does not inflate: {exc}") from None
    it = out.dtype.itemsize
    m = len(b) // it
    if m * it != len(b) or skip + len(out) > m:
        raise OSError(f"a chunk inflates to {len(b)} bytes, not whole {it}-byte values for its rows")
    out.view(np.uint8).reshape(len(out), it)[...] = np.frombuffer(b, np.uint8).reshape(it, m)[:, skip:skip + len(out)].T


class BlocksOnDemand:
    """A dataset read a block of rows at a time when first indexed, each block checked by its SHA-256 and for
    NaN and inf as it is read (a large organ's exact near field: the artifact opens without reading it, and the
    first K_i or coupling reads the blocks it touches).

    ``rows`` and ``sha256``: the blocks and their digests (format 1.5's per-block list, or the whole dataset's
    digest as one block; None reads them unchecked, as ``verify=False`` does, in blocks of about
    :data:`READ_BLOCK_BYTES` unless ``rows`` is given).  Indexing with a slice reads the blocks it spans, with
    an integer array the blocks its indices fall in; a block whose digest or values are wrong raises
    :class:`ArtifactError` naming its rows, and is read (and refused) again if asked for again.

    ``budget``: the bytes of read blocks held (None: all of them, kept once read).  Beyond it the least recently
    used blocks are let go (their pages returned to the system) and read, and checked, again when next needed,
    so that every K_i of an organ whose near field is larger than the memory to spare runs within it; one
    indexing's own blocks are held whatever the budget.  With a budget, a slice is returned as a copy (a view
    could outlive its block).  Safe to index from several threads."""

    def __init__(self, path, name: str, rows: int | None, sha256: list | None, budget: int | None = None):
        import collections
        import mmap
        import threading

        import h5py

        self._file = h5py.File(path, "r")
        self._data = self._file[name]
        self.name, self.path = name, str(path)
        self.shape, self.dtype = self._data.shape, self._data.dtype
        self.ndim = len(self.shape)
        self.nbytes = int(np.prod(self.shape)) * self.dtype.itemsize
        self.rows = max(1, int(rows if rows is not None else digest_block_rows(self.shape, self.dtype.itemsize)))
        self.row_bytes = int(np.prod(self.shape[1:], dtype=np.int64)) * self.dtype.itemsize
        n_blocks = -(-self.shape[0] // self.rows)
        self._sha256 = None if sha256 is None else list(sha256)  # None: read unverified (verify=False)
        if self._sha256 is not None and len(self._sha256) != n_blocks:
            self.close()
            raise ArtifactError(f"{path}: the block digests of {name} do not cover its rows; "
                                "recompute it with --force")
        self.budget = None if budget is None or budget >= self.nbytes else max(0, int(budget))
        # anonymous memory the blocks are read into: pages are taken as blocks are read, and given back
        # (madvise) when a block is let go
        self._map = mmap.mmap(-1, max(self.nbytes, 1), flags=mmap.MAP_PRIVATE)  # private: madvise frees it
        if hasattr(mmap, "MADV_NOHUGEPAGE"):  # 4 KiB pages: with transparent huge pages "always" the kernel may
            self._map.madvise(mmap.MADV_NOHUGEPAGE)  # back a block with 2 MiB ones (the likely cause of 3.7 MB
            # resident for 0.8 MB held, seen once in the budget test under load)
        self._arr = np.frombuffer(self._map, self.dtype, int(np.prod(self.shape))).reshape(self.shape)
        self._read = np.zeros(n_blocks, bool)
        self._used = collections.OrderedDict()  # read blocks, least recently used first
        self.reads = 0  # blocks read (again, after being let go, too)
        self._lock = threading.Lock()
        self.complete = n_blocks == 0

    def __len__(self) -> int:
        return int(self.shape[0])

    @property
    def fraction_read(self) -> float:
        """Share of the blocks held now."""
        return float(self._read.mean()) if len(self._read) else 1.0

    @property
    def held_bytes(self) -> int:
        """Bytes of the blocks held now."""
        return int(self._read.sum()) * self.rows * self.row_bytes

    def __getitem__(self, key):
        if self.complete:
            return self._arr[key]
        if isinstance(key, slice):
            lo, hi, _ = key.indices(self.shape[0])
            want = np.arange(max(lo, 0) // self.rows, -(-min(hi, self.shape[0]) // self.rows))
        else:
            idx = np.asarray(key)
            if not np.issubdtype(idx.dtype, np.integer) or idx.size and idx.min() < 0:
                want = np.arange(len(self._read))  # a mask, a tuple, negative indices: all of it
            elif idx.size:
                want = np.flatnonzero(np.bincount((idx // self.rows).ravel(), minlength=len(self._read)))
            else:
                want = np.zeros(0, np.int64)
        with self._lock:  # held while the values are taken: another thread may let a block go
            self._ensure(want)
            out = self._arr[key]
            return out.copy() if self.budget is not None and isinstance(key, slice) else out

    def runs(self, starts, width: int) -> np.ndarray:
        """``self[starts[:, None] + arange(width)]``: runs of ``width`` consecutive values (a compressed Ξ's exact
        pairs, nine values each), the blocks to read found from the runs' two ends alone (a run shorter than a
        block lies in at most two), not from every index as ``[]`` does."""
        starts = np.asarray(starts, np.int64)
        if not starts.size or starts.min() < 0 or not 0 < width <= self.rows or self.ndim != 1:
            return self[starts[:, None] + np.arange(width)]
        if self.complete:
            return take_runs(self._arr, starts, width)
        ends = np.concatenate([starts // self.rows, (starts + (width - 1)) // self.rows])
        want = np.flatnonzero(np.bincount(ends, minlength=len(self._read)))
        with self._lock:  # (a gather: a copy, which a block let go later cannot change)
            self._ensure(want)
            return take_runs(self._arr, starts, width)

    def _ensure(self, want: np.ndarray) -> None:
        """Read (and check) the blocks ``want`` that are not held, then let go of the least recently used
        others beyond the budget.  Called with the lock held."""
        for k in want:
            if self._read[k]:
                self._used.move_to_end(int(k))
        todo = want[~self._read[want]]
        try:
            done = _read_and_hash(self._data, self._arr, self.rows, todo) if len(todo) else []
        except OSError as exc:
            raise ArtifactError(f"{self.path}: cannot read {self.name} ({exc}); it is corrupt or truncated, "
                                "recompute it with --force") from exc
        for k, (digest, finite) in zip(todo, done):
            where = f"{self.name} (rows {k * self.rows} to {min((k + 1) * self.rows, self.shape[0]) - 1})"
            if self._sha256 is not None and digest != self._sha256[k]:
                raise ArtifactError(f"{self.path}: checksum mismatch: dataset {where} was altered after "
                                    "writing; recompute it with --force")
            if not finite:
                raise ArtifactError(f"{self.path}: inconsistent artifact: {where} holds NaN or inf")
            self._read[k] = True
            self._used[int(k)] = None
            self.reads += 1
        if self.budget is not None and self.held_bytes > self.budget:
            keep = set(want.tolist())
            for k in list(self._used):
                if self.held_bytes <= self.budget:
                    break
                if k not in keep:
                    self._let_go(k)
        elif self.budget is None and len(todo) and self._read.all():
            self.complete = True
            self.close()

    def _let_go(self, k: int) -> None:
        """Forget block k and give its whole pages back (they read as zeros until it is read again)."""
        import mmap

        del self._used[k]
        self._read[k] = False
        page = mmap.PAGESIZE
        start = k * self.rows * self.row_bytes
        stop = min((k + 1) * self.rows, self.shape[0]) * self.row_bytes
        a, b = -(-start // page) * page, stop // page * page
        if b > a:
            self._map.madvise(mmap.MADV_DONTNEED, a, b - a)

    def close(self) -> None:
        try:
            self._file.close()
        except Exception:  # noqa: BLE001  (already closed)
            pass


def _digest_and_finite(block: np.ndarray) -> tuple[str, bool]:
    return array_digest(block), all_finite(block)


def all_finite(x) -> bool:
    """Whether an array holds no NaN or inf: its sum is finite (any NaN or inf makes it NaN or inf), in one
    pass without a boolean temporary; only a sum that overflows is looked at element by element."""
    x = np.asarray(x)
    if x.size == 0 or x.dtype.kind not in "fc":
        return True
    with np.errstate(over="ignore", invalid="ignore"):
        total = np.sum(x, dtype=np.float64)
    return bool(np.isfinite(total)) or bool(np.isfinite(x).all())


def _verify(path, attrs: dict, data: dict, legacy: bool, digests: dict | None = None) -> None:
    altered = (f"{path}: checksum mismatch: %s was altered after writing; recompute it with --force")
    if legacy:
        digest = legacy_metadata_digest(attrs, {k: data[k] for k in LEGACY_SMALL})
        if digest != attrs.get("metadata_sha256"):
            raise ArtifactError(altered % "the metadata (attributes or surface data)")
        return
    try:
        covers = json.loads(attrs["sha256_covers"])
        missing = [k for k in covers["attributes"] if k not in attrs]
    except (TypeError, ValueError, KeyError) as exc:
        raise ArtifactError(f"{path}: attribute sha256_covers is unreadable ({exc}); recompute it with --force")
    if missing:
        raise ArtifactError(f"{path}: incomplete artifact, missing the covered attributes {', '.join(missing)}")
    if metadata_digest(attrs, covers) != attrs.get("metadata_sha256"):
        raise ArtifactError(altered % "the metadata (attributes or the list of dataset digests)")
    for name, arr in data.items():
        if arr is None:
            continue
        if name not in covers["datasets"]:
            raise ArtifactError(f"{path}: dataset {name} is not covered by the file's checksums; recompute it")
        digest = (digests or {}).get(name) or array_digest(arr)
        if isinstance(digest, list):  # per-block digests (format 1.5): the first block that differs is named
            want = covers.get("blocks", {}).get(name, {})
            rows, expected = int(want.get("rows", 0)), list(want.get("sha256", []))
            if digest != expected:
                bad = next((k for k, (a, b) in enumerate(zip(digest, expected)) if a != b), min(len(digest),
                                                                                                 len(expected)))
                raise ArtifactError(altered % f"dataset {name} (rows {bad * rows} to {(bad + 1) * rows - 1})")
        elif digest != covers["datasets"][name]:
            raise ArtifactError(altered % f"dataset {name}")


def _check_shapes(path, d, finite: dict | None = None) -> None:
    finite = finite or {}

    def is_finite(name):  # as the reading threads found it, else one pass now
        return finite[name] if name in finite else all_finite(d[name])

    problems = []
    ns = len(d["surface/points"]) if "surface/points" in d else None
    nc = len(d["surface/contact"]) if "surface/contact" in d else None
    nu = len(d["surface/fixed"]) if "surface/fixed" in d else None
    if d.get("greens/Xi") is not None and nc is not None:
        if d["greens/Xi"].shape != (3 * nc, 3 * nc):
            problems.append(f"Xi has shape {d['greens/Xi'].shape}, expected {(3 * nc, 3 * nc)}")
        elif not is_finite("greens/Xi"):
            problems.append("Xi holds NaN or inf")
    if d.get("greens/hmatrix/perm") is not None and nc is not None:
        perm = d["greens/hmatrix/perm"]
        if len(perm) != nc or not np.array_equal(np.sort(perm), np.arange(nc)):
            problems.append("the compressed Green's functions' vertex order is not a permutation of the contact vertices")
        elif not all(is_finite(f"greens/hmatrix/{k}") for k in ("dense", "near_exact", "U", "V", "near_scale",
                                                                 "U_scale", "V_scale")
                     if d.get(f"greens/hmatrix/{k}") is not None):  # (a far field left in the file: as it is read)
            problems.append("Xi holds NaN or inf")
    if d.get("greens/reactions") is not None and nu is not None and nc is not None:
        if d["greens/reactions"].shape != (3 * nu, 3 * nc):
            problems.append("reactions have the wrong shape")
    for key in ("surface/triangles", "surface/free", "surface/fixed", "surface/contact"):
        arr = d.get(key)
        if arr is not None and ns is not None and arr.size and (arr.min() < 0 or arr.max() >= ns):
            problems.append(f"{key} indexes outside the {ns} surface vertices")
    if problems:
        raise ArtifactError(f"{path}: inconsistent artifact: " + "; ".join(problems))
