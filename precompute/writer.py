"""Write the Green's-function artifact (format and checks: :mod:`pmask.runtime.artifact`)."""
from __future__ import annotations

import hashlib
import json
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from pmask.runtime.artifact import (BLOCK_DIGEST_BYTES, DEFINITION, FORMAT_NAME, FORMAT_VERSION, NEAR, NEAR_FILTERS,
                                    SLICED, array_digest, deflate_chunk, digest_block_rows, metadata_digest,
                                    update_array_digest)
from pmask.runtime.files import atomic_write, check_interrupt


def write_artifact(path, *, meta: dict, volume_points, tets, surface_vertices, triangles, areas, regions,
                   Xi, reactions, dtype=np.float64, display: dict | None = None) -> None:
    """Write one artifact atomically; ``meta`` holds model, input_hash, E, nu, r_max, parameters,
    provenance and timings (and ``tolerance`` when ``Xi`` is the compressed form's dict of arrays).  ``dtype`` float32 halves Ξ's size (measured effect: see README)."""
    small = {
        "surface/points": np.asarray(volume_points[surface_vertices], float),
        "surface/triangles": np.asarray(triangles, np.int64),
        "surface/vertex_areas": np.asarray(areas, float),
        "surface/free": np.asarray(regions.free, np.int64),
        "surface/fixed": np.asarray(regions.fixed, np.int64),
        "surface/contact": np.asarray(regions.contact, np.int64),
        "surface/contact_core": np.asarray(regions.core, bool),
        "surface/volume_index": np.asarray(surface_vertices, np.int64),
    }
    attrs = {
        "format_name": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "definition": DEFINITION,
        "model": meta["model"],
        "element": meta.get("element", "P1"),
        "units": json.dumps({"length": "m", "force": "N", "pressure": "Pa", "Xi": "m/Pa",
                             "reactions": "N/Pa", "vertex_areas": "m^2"}),
        "material": json.dumps({"E": meta["E"], "nu": meta["nu"], "model": "isotropic linear elastic",
                                **({"regions": meta["materials"]["regions"]} if meta.get("materials") else {})}),
        "r_max": float(meta["r_max"]),
        "fixed_selector": meta["fixed_selector"],
        "contact_selector": meta["contact_selector"],
        "input_hash": meta["input_hash"],
        "parameters": json.dumps(meta["parameters"], sort_keys=True, default=str),
        "provenance": json.dumps(meta["provenance"], sort_keys=True, default=str),
        "timings": json.dumps(meta["timings"], sort_keys=True),
    }
    big = {"volume/points": (volume_points, np.float64), "volume/tets": (tets, np.int64)}
    if meta.get("materials"):  # materials by region: each tetrahedron's region in material["regions"], -1 the body
        big["volume/material_region"] = (meta["materials"]["label"], np.int64)
    if isinstance(Xi, dict):  # compressed (pmask.precompute.compress): its arrays in the dtypes it chose
        attrs.update({"greens_form": "hmatrix", "tolerance": float(meta["tolerance"])})
        for k, arr in Xi.items():  # (the near field in ``dtype``, the far field's factors maybe narrower, the 16-bit
            # near-field values and their mask as they are)
            big[f"greens/hmatrix/{k}"] = (arr, arr.dtype if arr.dtype.kind in "fiu" else np.int64)
    else:
        big["greens/Xi"] = (Xi, dtype)
    if reactions is not None:
        big["greens/reactions"] = (reactions, dtype)
    if display is not None:  # the display surface and its embedding (pmask.precompute.display)
        for k, dt in (("points", np.float64), ("triangles", np.int64), ("vertices", np.int64), ("bary", np.float64),
                      ("lift", np.float64)):
            big[f"display/{k}"] = (display[k], dt)
        attrs["display"] = json.dumps({"vertices": int(len(display["points"])), "triangles": int(len(display["triangles"])),
                                       "folded": int(display["folded"]), "max_lift_m": float(display["max_lift"])})
    digests = {name: array_digest(arr) for name, arr in small.items()}
    blocks = {}

    def fill(tmp):
        import h5py

        with h5py.File(tmp, "w") as f:
            for name, arr in small.items():
                f.create_dataset(name, data=arr)
            for name, (arr, dt) in big.items():
                arr = arr if hasattr(arr, "shape") else np.asarray(arr)  # (a compressed Ξ's arrays: read in slices)
                digests[name], per_block = _write_blocks(f, name, arr, dt, sliced=name in SLICED,
                                                         deflated=name in NEAR)
                if per_block is not None:
                    blocks[name] = per_block
            covers = {"attributes": sorted(attrs), "datasets": dict(sorted(digests.items()))}
            if blocks:  # (format 1.5) a reader that knows them verifies these instead, in parallel
                covers["blocks"] = dict(sorted(blocks.items()))
            for k, v in attrs.items():
                f.attrs[k] = v
            f.attrs["sha256_covers"] = json.dumps(covers, sort_keys=True)
            f.attrs["metadata_sha256"] = metadata_digest(attrs, covers)

    atomic_write(path, fill)


def _write_blocks(f, name, arr, dtype, *, sliced: bool = False, deflated: bool = False, block_bytes=8 << 20):
    """A dataset written a block of rows at a time: ``arr`` may be a strided view (Ξ from the native route)
    and ``dtype`` narrower than it without a full-size copy.  Returns the SHA-256 of the stored bytes and,
    for a dataset above :data:`~pmask.runtime.artifact.BLOCK_DIGEST_BYTES`, {"rows": R, "sha256": [the
    SHA-256 of each block of R rows]} (else None), computed on the same blocks.

    ``sliced`` (a dataset a reader may read in slices, unhashed: the far field's factors) is stored in
    ~1 MiB chunks with HDF5's Fletcher-32, which HDF5 checks on every read; the others are read whole and
    checked by their SHA-256, and are stored contiguous without it (it doubled the time to open a
    20,000-vertex compressed artifact: 0.58 s reading its near field with it, 0.23 s without, by hand).

    ``deflated`` (a compressed Ξ's near field): the same chunks through HDF5's shuffle and deflate
    (:data:`~pmask.runtime.artifact.NEAR_FILTERS`); the digests are of the values, as for every dataset."""
    h = hashlib.sha256()
    chunks = _chunks(arr.shape)
    if chunks is None:
        stored = np.asarray(arr, dtype)
        f.create_dataset(name, data=stored)
        update_array_digest(h, stored)
        return h.hexdigest(), None
    row_bytes = max(1, int(np.prod(arr.shape[1:])) * np.dtype(dtype).itemsize)
    per_block = None
    if arr.shape[0] * row_bytes > BLOCK_DIGEST_BYTES:
        step = digest_block_rows(arr.shape, np.dtype(dtype).itemsize)
        per_block = {"rows": int(step), "sha256": []}
    else:
        step = max(chunks[0], (block_bytes // row_bytes) // chunks[0] * chunks[0])
    if sliced:
        ds = f.create_dataset(name, shape=arr.shape, dtype=dtype, chunks=chunks, fletcher32=True)
    elif deflated:
        ds = f.create_dataset(name, shape=arr.shape, dtype=dtype, chunks=chunks, **NEAR_FILTERS)
    else:
        ds = f.create_dataset(name, shape=arr.shape, dtype=dtype)
    # a block's own digest on a second thread while this one stores it and feeds the whole-dataset digest
    # (hashlib releases the GIL): each byte is hashed twice, for 1.4 readers and for the block-wise check
    pool = ThreadPoolExecutor(1, thread_name_prefix="pmask-digest") if per_block is not None else None
    direct = deflated and arr.ndim == 1  # chunks deflated on two threads and written as stored
    zpool = ThreadPoolExecutor(2, thread_name_prefix="pmask-deflate") if direct else None
    try:
        for i0 in range(0, arr.shape[0], step):
            check_interrupt()  # Ctrl-C is taken here, between blocks (pmask.runtime.files)
            block = np.ascontiguousarray(arr[i0:i0 + step], dtype)
            own = pool.submit(array_digest, block) if pool is not None else None
            if direct:
                _write_deflated(ds, i0, block, chunks[0], zpool)
            else:
                ds[i0:i0 + step] = block
            update_array_digest(h, block)
            if own is not None:
                per_block["sha256"].append(own.result())
    finally:
        for p in (pool, zpool):
            if p is not None:
                p.shutdown(wait=True)
    return h.hexdigest(), per_block


def _write_deflated(ds, i0: int, block: np.ndarray, c: int, pool) -> None:
    """``ds[i0:i0 + len(block)] = block`` for a 1-D dataset stored as :data:`~pmask.runtime.artifact.NEAR_FILTERS`
    says, ``i0`` on a chunk's start: its chunks shuffled and deflated by ``pool``'s threads (zlib releases the
    GIL) and written as stored, where HDF5 runs its filters one chunk after another in this thread (the write
    stage at 20,000 vertices took 1.2 s plain and 9.2 s with HDF5 deflating, by hand; the bench page's large row
    gives it done so).  Read back by HDF5 (tested)."""
    assert i0 % c == 0, (i0, c)  # the blocks are whole chunks (_write_blocks' steps): a chunk is written whole
    jobs = [(s, pool.submit(deflate_chunk, block[s - i0:s - i0 + c], c)) for s in range(i0, i0 + len(block), c)]
    for s, job in jobs:
        ds.id.write_direct_chunk((s,), job.result())


def _chunks(shape):
    """Row-block chunks of about 1 MiB (Fletcher-32 needs chunked storage)."""
    if 0 in shape:
        return None
    cols = int(np.prod(shape[1:])) if len(shape) > 1 else 1
    rows = max(1, min(shape[0], (1 << 17) // max(cols, 1)))
    return (rows,) + tuple(shape[1:])
