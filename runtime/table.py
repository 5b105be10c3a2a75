"""Runtime tables: everything the haptic step reads, in one file a C/C++ application can load.

A table is exported from an artifact for one mask and radius (``pmask export-table ARTIFACT --mask
linear --radius R -o FILE``, or :func:`export_table`); the native servo core
(``runtime/servo/core/``) and :meth:`pmask.runtime.contact.ContactSurface.from_table` read it.  It holds
the rendered per-vertex stiffness K_i (eq. 12 with the support blend and the region taper of
:mod:`pmask.runtime.stiffness`), so an application needs neither Ξ nor the masks.

Format 1.5, little-endian (1.1 added ``normal_stiffness``, ``shape`` and ``linear_depth``, which this version's
contact law needs, and a 1.0 table is refused with the advice to export it again; 1.2 the display surface; 1.3
the subdivided contact surface's map to the mesh, ``mesh_triangles``, ``parent`` and ``corners``; 1.4 a
compressed Ξ's own sections in place of the ζ table, ``xi_*`` and ``mask_*``; 1.5 the far field's factors in 16
bits as an artifact of format 1.8 stores them, with ``xi_U_scale`` and ``xi_V_scale``, and the exact pairs in
48-bit fixed point as format 1.7 stores them, ``xi_near_exact48``)::

    header (64 bytes)   "PMASKTBL", u32 major, u32 minor, u64 file size, u64 directory offset (64),
                        u32 section count, u32 CRC-32 of the header (this field zero) and the directory,
                        24 reserved zero bytes
    directory           per section 64 bytes: name (32, NUL-padded), u32 type (1 float64, 2 int64,
                        3 bytes), u32 CRC-32 of its data, u64 offset, u64 rows, u64 columns
    sections            each at an offset that is a multiple of 64

Sections (n_s vertices and n_t triangles of the contact surface, n_m vertices and n_mt triangles of the
finite-element mesh's surface under it, n_c contact vertices; the contact surface is the mesh's Loop subdivision
surface, :mod:`pmask.runtime.contact.subdivision`, or the mesh itself when ``parent`` is absent):

================= ============ ==========================================================================
points            n_s x 3      vertex positions [model units]; the first n_m the mesh's vertices where the contact
                               surface has them (rounded near creases: ContactSurface.mesh_points), where the
                               deformation is drawn
triangles         n_t x 3      vertex indices, counter-clockwise seen from outside
neighbours        n_t x 3      triangle across the edge opposite each vertex, -1 on an open edge
frames            n_t x 12     v0, duals a and b of the edges, unit normal (:func:`~pmask.runtime.geometry.triangle_frames`)
normals           n_s x 3      contact normals: the surface's own (on the mesh itself crease-blended)
stiffness         n_s x 9      rendered K_i [N/m], row-major
taper             n_s x 1      λ: 1 in the contact region, falling to 0 across the band beyond it
normal_stiffness  n_s x 1      k: the tapered normal stiffness [N/m] (:func:`~pmask.runtime.contact.surface.normal_stiffness`)
gradient          n_s x 3      ∇k per vertex (:func:`~pmask.runtime.contact.surface.normal_stiffness_gradient`)
shape             n_s x 9      the contact normals' shape operator S [1/model unit] (:func:`~pmask.runtime.contact.surface.shape_operators`)
linear_depth      n_s x 1      δ_lin: the depth past which the status is DEEP (:func:`~pmask.runtime.contact.surface.linear_depths`)
bounds            2 x 3        bounding box (lower, upper corner)
lengths           1 x 2        mean edge length, bounding-box diagonal
zeta              3n_c x 3n_c  optional: the ζ table (rows 3m..3m+2 = ζ_mᵀ), for coupled contacts and
                               the deformation of eq. 16
contact_row       n_m x 1      with zeta or xi_info: each mesh vertex's row block (contact vertex), -1 for none
xi_info           1 x 3        optional (1.4, a compressed artifact's table, in place of zeta): n_c, bytes of a
                               factor's value (4 or 8; 2: int16 words, 1.5), 1 when only the blocks on and above
                               the diagonal are stored
xi_*              ...          with xi_info: Ξ as :mod:`pmask.runtime.compressed` stores it (perm, leaves, scale,
                               dense_index, near_index, near_exact, near_mask, near_q (int16 bytes),
                               near_scale, lowrank_index, U and V (bytes)) and ``xi_owner`` (key, block,
                               flipped: the lookup of a pair of leaves' block), :func:`greens_sections`; with
                               16-bit factors (1.5) ``xi_U_scale`` and ``xi_V_scale``, float32 bytes: each
                               low-rank block's column scales, block after block (a value is its word times
                               its column's scale, in float32: :class:`pmask.runtime.compressed.Far16`);
                               optional (1.5) ``xi_near_exact48``: the exact pairs in 48-bit fixed point, 28
                               uint16 words a pair (:func:`pmask.runtime.compressed.pack_exact`), in place of
                               ``xi_near_exact``'s float64 (then empty)
mask_ptr          n_c+1 x 1    with xi_info: the core masks ρ^m by contact vertex m in compressed rows, ...
mask_cols         · x 1        ... their columns (contact vertices) ...
mask_weights      · x 1        ... and weights; the C core forms ζ_m(i) = Σ_j ρ^m_j Ξ_ij from them (eq. 13)
mesh_triangles    n_mt x 3     optional (1.3): the mesh's surface triangles, where ζ and the display live
parent            n_t x 1      with mesh_triangles: the mesh triangle each contact triangle lies in
corners           n_t x 9      with mesh_triangles: the barycentrics there of its corners (row-major, corner k
                               in columns 3k..3k+2): a point (t, b) is Σ_k b_k corners_k of triangle parent_t
display_points    n_d x 3      optional (1.2): the display surface at the scan's resolution (:mod:`pmask.runtime.display`)
display_triangles n_dt x 3     with display_points: its triangles
display_vertices  n_d x 3      with display_points: each display vertex's simulation triangle's vertices
display_bary      n_d x 3      with display_points: the barycentric weights of its closest point there
display_lift      n_d x 3      with display_points: the display vertex minus that closest point on the mesh drawn at
                               `points`' first n_m rows (rounded near creases: DisplaySurface.on)
meta              bytes        JSON: mask, radius, k_rigid, normal_radius, units, source artifact and digest
================= ============ ==========================================================================

The spatial index that restarts contact tracking is built by each reader at load (the Python engine a
uniform grid, :class:`~pmask.runtime.spatial.TriangleGrid`; the C core a bounding-volume hierarchy,
whose cost does not grow with the probe's depth); both return the same triangle.

A reader refuses a foreign file, a newer major version, a truncated or corrupt one (every section's
CRC-32 is checked) and stiffnesses that are not positive definite, with one line that says so; it
accepts a newer minor version and ignores sections it does not know.
"""
from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import numpy as np

from pmask.errors import InputError
from pmask.runtime.files import atomic_write, check_interrupt

MAGIC = b"PMASKTBL"
TABLE_MAJOR, TABLE_MINOR = 1, 5
HEADER, ENTRY, NAME = 64, 64, 32
F64, I64, BYTES = 1, 2, 3


class TableError(InputError):
    """A file that is not a runtime table this version reads (foreign, newer, truncated, corrupt)."""


def surface_sections(surface, zeta: bool = True, display=None) -> dict:
    """The sections of a table for a :class:`pmask.runtime.contact.ContactSurface` (without ``meta``), with a
    :class:`pmask.runtime.display.DisplaySurface` as the ``display_*`` sections (table 1.2).  ``zeta``: the ζ
    table, or for a compressed Ξ its own sections (:func:`greens_sections`, table 1.4)."""
    s = surface
    out = {
        "points": s.P, "triangles": s.T, "neighbours": s.neighbours, "frames": s.tri_geom,
        "normals": s.vertex_normals, "stiffness": s.K, "taper": s.taper[:, None],
        "normal_stiffness": s.normal_stiffness[:, None], "gradient": s.gradient, "shape": s.shape,
        "linear_depth": s.linear_depth[:, None],
        "bounds": np.stack([s.lo, s.hi]), "lengths": np.array([[s.mean_edge, s.diag]]),
    }
    if s.levels:
        out.update({"mesh_triangles": s.mesh_T, "parent": s.parent[:, None], "corners": s.corners})
    coupling = s.coupling() if zeta else None
    if coupling is not None:
        Zt, row = coupling
        out["zeta"] = Zt
        out["contact_row"] = np.asarray(row, np.int64)[:, None]
    elif zeta and s.compressed:
        out.update(greens_sections(s.stiffness))
        out["contact_row"] = np.asarray(s.stiffness._contact_row, np.int64)[:, None]
    if display is not None:
        display = display.on(s.mesh_points)  # laid onto the mesh where the contact surface has its vertices
        out.update({"display_points": display.points, "display_triangles": display.triangles,
                    "display_vertices": display.vertices, "display_bary": display.bary, "display_lift": display.lift})
    return out


def greens_sections(stiffness) -> dict:
    r"""A compressed artifact's Green's functions as table sections (format 1.4, module docstring): Ξ's
    H-matrix as the artifact stores it (:mod:`pmask.runtime.compressed`: the exact near field pair by pair with its
    16-bit neighbours, the far field's low-rank factors (from a format 1.8 artifact its 16-bit words and their
    scales, from 1.7 the exact pairs' 48-bit words: table 1.5), the lookup of a pair's block) and the core masks ρ^m by
    contact vertex, from which the C core forms ζ_m(i) = Σ_j ρ^m_j Ξ_ij (eq. 13) for the vertices a pair of
    coupled contacts touches, as :meth:`pmask.runtime.stiffness.Stiffness.zeta_block` does.  A dense block of a
    format ≤ 1.5 artifact (stored whole) is written pair by pair, every pair exact.  Everything is read whole:
    the table holds all of it (about the artifact's stored bytes)."""
    Xi = stiffness.model.Xi
    n = Xi.n
    whole = lambda a, dt: np.ascontiguousarray(np.asarray(a[:] if len(a) else np.zeros(0)), dt)  # noqa: E731
    di = Xi.dense_index.copy()
    exact48 = {}
    if Xi.packed:
        ni, exact = Xi.near_index, (np.zeros(0) if Xi.fixed else whole(Xi.dense, np.float64))
        if Xi.fixed:  # (format 1.7: the exact pairs' 48-bit words as the artifact stores them, table 1.5: 56 bytes
            exact48 = {"xi_near_exact48": whole(Xi.dense, np.uint16).astype("<u2", copy=False)}  # a pair, not 72)
        mask, q, qscale = Xi.near_mask, whole(Xi.near_q, np.int16), Xi.near_scale
    else:  # whole blocks (format <= 1.5): every pair exact, in pair order
        pairs = (di[:, 1] - di[:, 0]) * (di[:, 3] - di[:, 2])
        nbytes = -(-pairs // 8)
        exact = np.concatenate([Xi.dense_block(b).reshape(m, 3, -1, 3).transpose(0, 2, 1, 3).ravel()
                                for b, m in enumerate(di[:, 1] - di[:, 0])] or [np.zeros(0)])
        di[:, 4] = np.concatenate([[0], np.cumsum(9 * pairs)[:-1]]) if len(di) else di[:, 4]
        ni = np.zeros((len(di), 3), np.int64)
        ni[:, 1] = np.concatenate([[0], np.cumsum(nbytes)[:-1]]) if len(di) else 0
        ni[:, 2] = np.concatenate([[0], np.cumsum(3 * (di[:, 3] - di[:, 2]))[:-1]]) if len(di) else 0
        mask = np.concatenate([np.packbits(np.ones(k, bool)) for k in pairs] or [np.zeros(0, np.uint8)])
        q, qscale = np.zeros(0, np.int16), np.zeros(int(np.sum(3 * (di[:, 3] - di[:, 2]))))
    scales = {}
    if Xi.far_scales is not None:  # (format 1.8: the words as the artifact stores them, table 1.5: half the bytes)
        from pmask.runtime.compressed import Far16, far_words_of

        U, V = (np.ascontiguousarray(a.words[:], np.int16) if isinstance(a, Far16)  # (left in the file: its words)
                else far_words_of(a, sc, Xi.lowrank_index, w)  # (decoded at open: the same words back)
                for a, sc, w in ((Xi.U, Xi.far_scales[0], 5), (Xi.V, Xi.far_scales[1], 6)))
        scales = {"xi_U_scale": np.asarray(Xi.far_scales[0], "<f4"), "xi_V_scale": np.asarray(Xi.far_scales[1], "<f4")}
    else:
        U, V = whole(Xi.U, Xi.U.dtype), whole(Xi.V, Xi.V.dtype)
        if U.dtype not in (np.float32, np.float64) or V.dtype != U.dtype:
            raise InputError("the compressed Green's functions' factors are neither float32 nor float64; recompute "
                             "the artifact (pmask precompute --force)")
    masks = stiffness.masks
    lens = np.zeros(n, np.int64)
    lens[masks.centres] = np.diff(masks.indptr)
    ptr = np.concatenate([[0], np.cumsum(lens)])
    order = np.argsort(masks.centres, kind="stable")  # the masks in contact order
    cols = np.concatenate([masks.indices[masks.indptr[k]:masks.indptr[k + 1]] for k in order] or [np.zeros(0)])
    w = np.concatenate([masks.values[masks.indptr[k]:masks.indptr[k + 1]] for k in order] or [np.zeros(0)])
    col = lambda a, dt: np.ascontiguousarray(np.asarray(a, dt).reshape(-1, 1))  # noqa: E731
    return {
        "xi_info": np.array([[n, U.dtype.itemsize, int(Xi.symmetric)]], np.int64),
        "xi_perm": col(Xi.perm, np.int64), "xi_leaves": col(Xi.leaves, np.int64),
        "xi_scale": col(Xi.scale if Xi.symmetric else np.zeros(0), np.float64),
        "xi_dense_index": np.asarray(di, np.int64).reshape(-1, 5),
        "xi_near_index": np.asarray(ni, np.int64).reshape(-1, 3),
        "xi_near_exact": col(exact, np.float64), "xi_near_mask": np.asarray(mask, np.uint8),
        "xi_near_q": np.asarray(q, "<i2"), "xi_near_scale": col(qscale, np.float64),
        "xi_lowrank_index": np.asarray(Xi.lowrank_index, np.int64).reshape(-1, 7),
        "xi_U": U.astype(U.dtype.newbyteorder("<"), copy=False),  # (no copy on a little-endian host)
        "xi_V": V.astype(V.dtype.newbyteorder("<"), copy=False),
        "xi_owner": np.stack([Xi._key, Xi._block, Xi._flip.astype(np.int64)], axis=1).astype(np.int64),
        "mask_ptr": col(ptr, np.int64), "mask_cols": col(cols, np.int64), "mask_weights": col(w, np.float64),
        **scales, **exact48,
    }


def table_arrays(sections: dict, meta: dict) -> dict:
    """The sections as the native core borrows them (:func:`pmask.runtime.servo.load_table` of a dict, C
    ``pm_table_from_sections``): C-contiguous 2-D float64/int64 arrays (no copy when they already are), a
    compressed Ξ's byte sections (:data:`GREENS`) as their raw bytes (a uint8 view, little-endian as
    :func:`greens_sections` makes them) and the metadata as JSON bytes.  A viewer that rebuilds its 150 MB ζ table
    on every change of the mask radius hands it over this way instead of serialising it (:func:`table_bytes`) for
    the loader to copy again."""
    out = {}
    for name, value in sections.items():
        if _is_bytes(name, value):
            out[name] = _raw(value)
        else:
            a = np.asarray(value)
            out[name] = np.ascontiguousarray(a, np.int64 if np.issubdtype(a.dtype, np.integer) else np.float64)
    out["meta"] = json.dumps(meta, sort_keys=True).encode()
    return out


def _is_bytes(name: str, value) -> bool:
    """Whether a section is raw bytes: given as bytes (the metadata, a table's own byte sections), or one the
    format names bytes (:data:`GREENS`: 16-bit pairs, the factors in float32, float64 or 16 bits, and
    :data:`FAR16`: their scales, :data:`EXACT48`: the exact pairs' fixed point)."""
    return (isinstance(value, (bytes, bytearray, memoryview)) or name in FAR16 or name == EXACT48
            or GREENS.get(name, ("",))[0] == "b")


def _raw(value) -> np.ndarray:
    """A section's bytes as a flat uint8 view (a copy only where an array is not contiguous)."""
    if isinstance(value, (bytes, bytearray, memoryview)):
        return np.frombuffer(value, np.uint8)
    return np.ascontiguousarray(value).view(np.uint8).reshape(-1)


def _layout(sections: dict, meta: dict) -> tuple[list, int]:
    """Where each section goes in a table: [(name, kind, rows, cols, its little-endian bytes (uint8 view or
    bytes), offset, nbytes)] in order, each 64-byte aligned after the header and directory, and the table's
    size.  Only a section not yet contiguous little-endian 8-byte values is copied (rare: an int32 array)."""
    items = list(sections.items()) + [("meta", json.dumps(meta, sort_keys=True).encode())]
    offset = HEADER + len(items) * ENTRY
    layout = []
    for name, value in items:
        if _is_bytes(name, value) or isinstance(value, np.ndarray) and value.dtype.itemsize != 8:
            raw = _raw(value)  # (any array not of 8-byte items goes as its raw bytes: int16, float32, uint8)
            kind, rows, cols = BYTES, raw.size, 1
        else:
            a = np.asarray(value)
            if a.ndim != 2:
                raise ValueError(f"section {name} must be 2-D, got {a.shape}")
            kind = I64 if np.issubdtype(a.dtype, np.integer) else F64
            rows, cols = a.shape
            raw = np.ascontiguousarray(a, "<i8" if kind == I64 else "<f8").view(np.uint8).reshape(-1)
        offset = -(-offset // 64) * 64
        layout.append((name, kind, rows, cols, raw, offset, len(raw)))
        offset += len(raw)
    return layout, offset


def _head(layout: list, size: int, crcs: list) -> bytes:
    """The header and directory of a table laid out by :func:`_layout`, given each section's CRC-32."""
    directory = b"".join(struct.pack("<32sIIQQQ", name.encode(), kind, crc, off, rows, cols)
                         for (name, kind, rows, cols, _, off, _), crc in zip(layout, crcs))
    head = struct.pack("<8sIIQQII24x", MAGIC, TABLE_MAJOR, TABLE_MINOR, size, HEADER, len(layout), 0)
    crc = zlib.crc32(directory, zlib.crc32(head))
    return head[:36] + struct.pack("<I", crc) + head[40:] + directory


def table_bytes(sections: dict, meta: dict) -> bytearray:
    """Serialise sections (name -> 2-D float64/int64 array, or raw bytes) and the metadata into a table in
    memory.  Each array is copied once, straight into its place (a viewer rebuilds a 150 MB table on every change
    of the mask radius: bytes of each array, then the whole, then a final bytes() made three copies);
    :func:`write_table` writes a file without holding the whole."""
    layout, size = _layout(sections, meta)
    out = bytearray(size)
    for *_, raw, off, nbytes in layout:
        out[off:off + nbytes] = memoryview(raw)
    head = _head(layout, size, [zlib.crc32(raw) for *_, raw, _, _ in layout])
    out[:len(head)] = head
    return out


#: the bytes written (and checksummed) at a time by :func:`write_table`
WRITE_CHUNK = 64 << 20


def write_table(path, surface, meta: dict, zeta: bool = True, display=None) -> Path:
    """Write a table for ``surface`` atomically (a killed export leaves no partial file), a section at a time
    straight from its array: the export of a large organ's compressed Ξ holds its sections once, not the
    sections and the table's bytes (3 GB each at 47,000 vertices)."""
    path = Path(path)
    if not path.parent.is_dir():
        raise InputError(f"the folder {path.parent} does not exist; create it or write the table elsewhere (-o)")
    layout, size = _layout(surface_sections(surface, zeta, display), meta)

    def write(tmp):
        crcs = []
        with open(tmp, "wb") as f:
            f.truncate(size)  # (the gaps between sections: zeros, as table_bytes leaves them)
            for *_, raw, off, nbytes in layout:
                f.seek(off)
                view, crc = memoryview(raw), 0
                for k in range(0, nbytes, WRITE_CHUNK):
                    chunk = view[k:k + WRITE_CHUNK]
                    f.write(chunk)
                    crc = zlib.crc32(chunk, crc)
                crcs.append(crc)
                check_interrupt()
            f.seek(0)
            f.write(_head(layout, size, crcs))

    return atomic_write(path, write)


def read_table(source) -> dict:
    """Read and check a table (a path or bytes): name -> array (2-D) or bytes (a memoryview: every section a view
    of the file's bytes, read once), ``meta`` -> dict, and with a
    compressed Ξ's sections (1.4) ``greens`` -> :class:`pmask.runtime.compressed.MaskedXi` over them.  Refuses what
    the native loader refuses, with the same reasons (:class:`TableError`)."""
    if isinstance(source, (bytes, bytearray, memoryview)):
        buf, where = bytes(source), "the runtime table"
    else:
        where = str(source)
        try:
            buf = Path(source).read_bytes()
        except OSError as exc:
            raise TableError(f"cannot read the runtime table {where}: {exc.strerror or exc}") from None
    if len(buf) < HEADER or buf[:8] != MAGIC:
        raise TableError(f"{where} is not a pmask runtime table (no PMASKTBL header); write one with "
                         "`pmask export-table ARTIFACT -o FILE`")
    magic, major, minor, size, dir_off, n, crc = struct.unpack_from("<8sIIQQII", buf)
    if major > TABLE_MAJOR or major == 0:
        raise TableError(f"{where}: runtime table format {major}.{minor} is not one this version reads "
                         f"({TABLE_MAJOR}.x): export the table with this version of pmask, or update pmask")
    if size != len(buf):
        raise TableError(f"{where}: corrupt runtime table: truncated or padded (the header says {size} bytes, "
                         f"there are {len(buf)})")
    if dir_off != HEADER or n > 4096 or HEADER + n * ENTRY > size:
        raise TableError(f"{where}: corrupt runtime table: bad section directory")
    head = buf[:36] + b"\0\0\0\0" + buf[40:HEADER]
    if zlib.crc32(buf[HEADER:HEADER + n * ENTRY], zlib.crc32(head)) != crc:
        raise TableError(f"{where}: corrupt runtime table: the header's checksum does not match")
    out, whole = {}, memoryview(buf)  # the sections are views of the file's bytes, not copies
    for i in range(n):
        name, kind, scrc, off, rows, cols = struct.unpack_from("<32sIIQQQ", buf, HEADER + i * ENTRY)
        name = name.rstrip(b"\0").decode("utf-8", "replace")
        item = 1 if kind == BYTES else 8
        nbytes = rows * cols * item
        if off % 8 or off > size or nbytes > size - off:
            raise TableError(f"{where}: corrupt runtime table: section '{name}' lies outside the file")
        data = whole[off:off + nbytes]
        if zlib.crc32(data) != scrc:
            raise TableError(f"{where}: corrupt runtime table: section '{name}' fails its checksum")
        if kind == BYTES:
            out[name] = data
        elif kind in (F64, I64):
            out[name] = np.frombuffer(data, "<f8" if kind == F64 else "<i8").reshape(rows, cols)
        # a type this version does not know: a newer minor's addition, ignored
    _check(out, where)
    try:
        out["meta"] = json.loads(bytes(out.get("meta", b"{}")).decode())
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise TableError(f"{where}: corrupt runtime table: its metadata is not JSON") from None
    return out


#: (rows, columns) of each required section; 'v' n_s, 't' n_t, None any
_SHAPES = {"points": (None, 3), "triangles": (None, 3), "neighbours": ("t", 3), "frames": ("t", 12),
           "normals": ("v", 3), "stiffness": ("v", 9), "taper": ("v", 1), "normal_stiffness": ("v", 1),
           "gradient": ("v", 3), "shape": ("v", 9), "linear_depth": ("v", 1), "bounds": (2, 3), "lengths": (1, 2)}
_INTS = {"triangles", "neighbours", "contact_row", "mesh_triangles", "parent"}


def _check(t: dict, where: str) -> None:
    for name in _SHAPES:
        if name not in t:
            raise TableError(f"{where}: not a complete runtime table: section '{name}' is missing (a table from an "
                             "older pmask, or a damaged one: export it again with `pmask export-table`)")
    nv, nt = len(t["points"]), len(t["triangles"])
    for name, (r, c) in _SHAPES.items():
        a = t[name]
        rows = {"v": nv, "t": nt}.get(r, r)
        if (name in _INTS) != (a.dtype.kind == "i") or (rows is not None and a.shape[0] != rows) or a.shape[1] != c:
            raise TableError(f"{where}: corrupt runtime table: section '{name}' has the wrong type or shape {a.shape}")
    if nv < 3 or nt < 1:
        raise TableError(f"{where}: runtime table without a surface ({nv} vertices, {nt} triangles)")
    T, nb = t["triangles"], t["neighbours"]
    if T.min() < 0 or T.max() >= nv or nb.min() < -1 or nb.max() >= nt:
        raise TableError(f"{where}: corrupt runtime table: a triangle or neighbour index is out of range")
    floats = [k for k in _SHAPES if k not in _INTS]
    if not all(np.all(np.isfinite(t[k])) for k in floats):
        raise TableError(f"{where}: corrupt runtime table: a non-finite number")
    lam = t["taper"][:, 0]
    if lam.min() < 0 or lam.max() > 1:
        raise TableError(f"{where}: corrupt runtime table: taper outside [0, 1] at vertex "
                         f"{int(np.flatnonzero((lam < 0) | (lam > 1))[0])}")
    k, dlin = t["normal_stiffness"][:, 0], t["linear_depth"][:, 0]
    if k.min() < 0 or dlin.min() <= 0:
        raise TableError(f"{where}: corrupt runtime table: a negative normal stiffness or a linear depth that is not "
                         "positive")
    K = t["stiffness"].reshape(-1, 3, 3)
    bad = np.flatnonzero(~(np.linalg.eigvalsh(0.5 * (K + K.transpose(0, 2, 1)))[:, 0] > 0))
    if len(bad):
        raise TableError(f"{where}: runtime table: the stiffness at surface vertex {int(bad[0])} is not positive "
                         "definite (a corrupt or hand-edited table; export it again from a checked artifact)")
    nm = nv
    if "parent" in t or "mesh_triangles" in t or "corners" in t:
        mt, par, cor = (t.get(k) for k in ("mesh_triangles", "parent", "corners"))
        if mt is None or par is None or cor is None:
            raise TableError(f"{where}: not a complete runtime table: 'mesh_triangles', 'parent' and 'corners' go "
                             "together (export it again)")
        if (mt.dtype.kind != "i" or mt.ndim != 2 or mt.shape[1] != 3 or len(mt) < 1 or par.dtype.kind != "i"
                or par.shape != (nt, 1) or cor.dtype.kind != "f" or cor.shape != (nt, 9)):
            raise TableError(f"{where}: corrupt runtime table: the contact surface's map to the mesh has the wrong "
                             "type or shape")
        if mt.min() < 0 or par.min() < 0 or par.max() >= len(mt):
            raise TableError(f"{where}: corrupt runtime table: a mesh triangle index is out of range")
        if not (np.all(np.isfinite(cor)) and cor.min() >= 0 and cor.max() <= 1
                and np.all(np.abs(cor.reshape(-1, 3, 3).sum(axis=2) - 1.0) <= 1e-8)):
            raise TableError(f"{where}: corrupt runtime table: the corners' barycentrics are not in [0, 1] "
                             "summing to 1")
        nm = int(mt.max()) + 1
    nc = None
    if "zeta" in t:
        Z = t["zeta"]
        if Z.dtype.kind != "f" or Z.shape[0] != Z.shape[1] or Z.shape[0] % 3:
            raise TableError(f"{where}: corrupt runtime table: the zeta table is not square")
        if not np.all(np.isfinite(Z)):
            raise TableError(f"{where}: corrupt runtime table: a non-finite number in the zeta table")
        nc = Z.shape[0] // 3
    elif "xi_info" in t:
        t["greens"] = table_greens(t, where)
        nc = t["greens"].Xi.n
    if nc is not None:
        row = t.get("contact_row")
        if row is None:
            raise TableError(f"{where}: not a complete runtime table: section 'contact_row' is missing (export it again)")
        if row.dtype.kind != "i" or row.shape != (nm, 1):
            raise TableError(f"{where}: corrupt runtime table: section 'contact_row' has the wrong type or shape {row.shape}")
        if row.min() < -1 or row.max() >= nc:
            raise TableError(f"{where}: corrupt runtime table: a contact row is out of range")


#: the compressed Green's functions' sections (table 1.4) in the order both loaders check them: (type, columns);
#: 'b' raw bytes
GREENS = {"xi_info": ("i", 3), "xi_leaves": ("i", 1), "xi_scale": ("f", 1), "xi_dense_index": ("i", 5),
          "xi_near_index": ("i", 3), "xi_near_exact": ("f", 1), "xi_near_mask": ("b", 1), "xi_near_q": ("b", 1),
          "xi_near_scale": ("f", 1), "xi_lowrank_index": ("i", 7), "xi_U": ("b", 1), "xi_V": ("b", 1),
          "xi_owner": ("i", 3), "mask_ptr": ("i", 1), "mask_cols": ("i", 1), "mask_weights": ("f", 1),
          "xi_perm": ("i", 1)}
#: with 16-bit factors (xi_info's item 2, table 1.5): their column scales, float32 bytes
FAR16 = ("xi_U_scale", "xi_V_scale")
#: optional (table 1.5): the exact pairs in 48-bit fixed point (:func:`pmask.runtime.compressed.pack_exact`'s uint16
#: words, 28 a pair), xi_near_exact then empty
EXACT48 = "xi_near_exact48"


def table_greens(t: dict, where: str = "the runtime table"):
    """A table's compressed Green's functions (:func:`greens_sections`) as a
    :class:`pmask.runtime.compressed.MaskedXi`, checked as the C loader checks them (``core/greens.c``: the same
    checks in the same order, the same line when one fails)."""
    from pmask.runtime.compressed import (_ONES, EXACT_EXPONENTS, PAIR_WORDS, CompressedXi, Far16, MaskedXi,
                                          exponents_valid, unpack_exact)

    def bad(what):
        return TableError(f"{where}: corrupt runtime table: the compressed Green's functions {what} (export it again)")

    for name, (kind, cols) in GREENS.items():
        a = t.get(name)
        if a is None:
            raise TableError(f"{where}: not a complete runtime table: section '{name}' is missing (a table from an "
                             "older pmask, or a damaged one: export it again with `pmask export-table`)")
        if kind == "b" and not isinstance(a, (bytes, bytearray, memoryview)) or kind != "b" and (
                not isinstance(a, np.ndarray) or a.dtype.kind != kind or a.shape[1] != cols):
            raise TableError(f"{where}: corrupt runtime table: section '{name}' has the wrong type or shape")
        if name == "xi_info":
            if a.shape[0] != 1:
                raise TableError(f"{where}: corrupt runtime table: section '{name}' has the wrong type or shape")
            n, item, symmetric = (int(x) for x in a[0])
            if n < 1 or item not in (2, 4, 8) or symmetric not in (0, 1):
                raise bad("have a bad header")
    rows = {"xi_scale": n if symmetric else 0, "xi_near_index": len(t["xi_dense_index"]), "mask_ptr": n + 1,
            "mask_weights": len(t["mask_cols"]), "xi_perm": n}
    for name, r in rows.items():
        if len(t[name]) != r:
            raise TableError(f"{where}: corrupt runtime table: section '{name}' has the wrong type or shape")
    for name in FAR16:
        a = t.get(name)
        if a is not None and not isinstance(a, (bytes, bytearray, memoryview)):
            raise TableError(f"{where}: corrupt runtime table: section '{name}' has the wrong type or shape")
        if item == 2 and a is None:
            raise TableError(f"{where}: not a complete runtime table: section '{name}' is missing (a damaged table: "
                             "export it again with `pmask export-table`)")
    if len(t["xi_U"]) % item or len(t["xi_V"]) % item:
        raise bad("have a bad header")
    perm, leaves = t["xi_perm"][:, 0], t["xi_leaves"][:, 0]
    if perm.min() < 0 or perm.max() >= n or len(np.unique(perm)) != n:
        raise bad("do not order their vertices")
    if len(leaves) < 2 or leaves[0] != 0 or leaves[-1] != n or np.any(np.diff(leaves) <= 0):
        raise bad("do not cluster their vertices")
    di, ni, li = t["xi_dense_index"], t["xi_near_index"], t["xi_lowrank_index"]
    box = np.vstack([di[:, :4], li[:, :4]])
    if len(box) and (box[:, [0, 2]].min() < 0 or box[:, [1, 3]].max() > n or np.any(box[:, [1, 3]] <= box[:, [0, 2]])):
        raise bad("have a block outside their vertices")
    U, V = (np.frombuffer(t[k], {2: "<i2", 4: "<f4", 8: "<f8"}[item]) for k in ("xi_U", "xi_V"))
    mask, exact, qscale = np.frombuffer(t["xi_near_mask"], np.uint8), t["xi_near_exact"][:, 0], t["xi_near_scale"][:, 0]
    nexact, words48 = len(exact), t.get(EXACT48)
    if words48 is not None:  # (table 1.5: the exact pairs in fixed point, xi_near_exact empty)
        if not isinstance(words48, (bytes, bytearray, memoryview)):
            raise TableError(f"{where}: corrupt runtime table: section '{EXACT48}' has the wrong type or shape")
        if nexact or len(words48) % (2 * PAIR_WORDS):
            raise bad("have a bad header")
        words48 = np.frombuffer(words48, "<u2")
        nexact = len(words48) // PAIR_WORDS * 9
    pairs = (di[:, 1] - di[:, 0]) * (di[:, 3] - di[:, 2])
    nbytes = -(-pairs // 8)
    ok = not len(di) or (di[:, 4].min() >= 0 and ni.min() >= 0 and np.all(ni[:, 1] <= len(mask) - nbytes))
    if ok and len(di):
        before = np.concatenate([[0], np.cumsum(_ONES[mask])])
        e = before[ni[:, 1] + nbytes] - before[ni[:, 1]]
        ok = (np.all(e <= pairs) and np.all(di[:, 4] <= nexact - 9 * e)
              and np.all(ni[:, 0] <= len(t["xi_near_q"]) // 2 - 9 * (pairs - e))
              and np.all(ni[:, 2] <= len(qscale) - 3 * (di[:, 3] - di[:, 2])))
    m, w, k = 3 * (li[:, 1] - li[:, 0]), 3 * (li[:, 3] - li[:, 2]), li[:, 4]
    if not ok or (len(li) and (k.min() < 0 or li[:, 5:].min() < 0 or np.any(li[:, 5] + m * k > len(U))
                                or np.any(li[:, 6] + w * k > len(V)))):
        raise bad("do not match their index")
    if item == 2:  # (table 1.5: the words times their columns' scales, decoded as the artifact's reader does)
        su, sv = (np.frombuffer(t[name], "<f4") if len(t[name]) % 4 == 0 else None for name in FAR16)
        if su is None or sv is None or len(su) != int(k.sum()) or len(sv) != int(k.sum()):
            raise bad("do not match their index")
        with np.errstate(over="ignore", invalid="ignore"):  # (a huge scale: refused as non-finite below)
            U, V = Far16(U, su, li, 5)[:], Far16(V, sv, li, 6)[:]
    scale = t["xi_scale"][:, 0]
    if words48 is not None:  # every pair's exponent one a float64 has, every value finite (as the C core checks)
        e48 = words48[PAIR_WORDS - 1::PAIR_WORDS].view("<i2")
        if not exponents_valid(e48):
            raise bad("hold an exponent no float64 has")
        # a value m 2^(e - 46), |m| ≤ 2^47, is below 2^1023 where e < 1023: only the pairs at e = 1023 can overflow
        # (-2^47 there is -2^1024), so only they are decoded (decoding all took 0.46 s of the 20,427-vertex
        # organ's 1.3 s load, by hand)
        top = np.flatnonzero(e48 == EXACT_EXPONENTS[1])
        with np.errstate(over="ignore"):
            if len(top) and not np.all(np.isfinite(unpack_exact(words48.reshape(-1, PAIR_WORDS)[top]))):
                raise bad("hold a non-finite number")
        exact = words48  # (CompressedXi reads uint16 words as fixed point: format 1.7's reader)
    values = [qscale, t["mask_weights"], U, V] + ([exact] if words48 is None else [])
    if not all(np.all(np.isfinite(a)) for a in values):
        raise bad("hold a non-finite number")
    if symmetric and not np.all(scale > 0):
        raise bad("have a scale that is not positive")
    ptr, cols, weights = t["mask_ptr"][:, 0], t["mask_cols"][:, 0], t["mask_weights"][:, 0]
    if ptr[0] != 0 or ptr[-1] != len(cols) or np.any(np.diff(ptr) < 0) or (len(cols) and (cols.min() < 0
                                                                                         or cols.max() >= n)):
        raise bad("have masks that do not match")
    try:
        Xi = CompressedXi(perm, leaves, di, exact, li, U, V, tolerance=0.0,  # (the export's is in the metadata)
                          scale=scale if symmetric else None, near_index=ni, near_mask=mask,
                          near_q=np.frombuffer(t["xi_near_q"], "<i2"), near_scale=qscale)
    except InputError:  # (the blocks do not tile the pairs: no lookup can match them)
        raise bad("have a block lookup that does not match their blocks") from None
    owner = t["xi_owner"]
    if not (np.array_equal(owner[:, 0], Xi._key) and np.array_equal(owner[:, 1], Xi._block)
            and np.array_equal(owner[:, 2], Xi._flip)):
        raise bad("have a block lookup that does not match their blocks")
    return MaskedXi(Xi, lambda c: (cols[ptr[c]:ptr[c + 1]], weights[ptr[c]:ptr[c + 1]]))


def export_table(artifact, out, *, mask: str = "linear", radius: float | None = None, k_rigid: float | None = None,
                 normal_radius: float | None = None, zeta: bool = True, device=None, levels="auto") -> Path:
    """Export a runtime table from an artifact: :meth:`pmask.runtime.Model.stiffness` for the mask and
    radius, the contact surface of :class:`pmask.runtime.contact.ContactSurface`, and (``zeta``) the ζ table
    for several coupled contacts and the deformation (3n_c x 3n_c doubles: 150 MB at the default
    kidney's 1,446 contact vertices), or for a compressed artifact Ξ's own sections and the masks
    (:func:`greens_sections`: about the artifact's stored bytes).  radius : default
    :attr:`pmask.runtime.Model.default_radius`.  levels : the
    contact surface's subdivision (:class:`pmask.runtime.Contacts`; "auto", the default, the automatic choice,
    0 the mesh)."""
    from pmask.runtime.contact import ContactSurface
    from pmask.runtime.model import Model

    model = artifact if isinstance(artifact, Model) else Model.load(artifact)
    stiff = model.stiffness(mask, radius, k_rigid=k_rigid, device=device)
    surface = ContactSurface(stiff, normal_radius, None if levels == "auto" else int(levels))
    meta = {"format": f"{TABLE_MAJOR}.{TABLE_MINOR}", "mask": stiff.masks.kind, "radius": stiff.masks.radius,
            "k_rigid": stiff.k_rigid, "symmetric": stiff.symmetric, "support_blend": stiff.support_blend,
            "normal_radius": surface.normal_radius, "levels": surface.levels,
            "units": {"length": "model units (as the artifact)", "stiffness": "N/m"},
            "source": str(getattr(model, "path", "")), "source_digest": str(model.attrs.get("metadata_sha256", "")),
            "pmask_version": _version()}
    if zeta and surface.compressed:  # (table 1.4: what a user computes from it is within this of the dense Ξ's)
        meta["greens"] = {"form": "hmatrix", "tolerance": model.Xi.tolerance}
    return write_table(out, surface, meta, zeta, display=model.display())


def _version() -> str:
    from pmask import __version__

    return __version__
