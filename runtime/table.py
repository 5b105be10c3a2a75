"""Runtime tables: everything the haptic step reads, in one file a C/C++ application can load.

A table is exported from an artifact for one mask and radius (``pmask export-table ARTIFACT --mask
linear --radius R -o FILE``, or :func:`export_table`); the native servo core
(``runtime/servo/core/``) and :meth:`pmask.runtime.contact.ContactSurface.from_table` read it.  It holds
the rendered per-vertex stiffness K_i (eq. 12 with the support blend and the region taper of
:mod:`pmask.runtime.stiffness`), so an application needs neither Ξ nor the masks.

Format 1.3, little-endian (1.1 added ``normal_stiffness``, ``shape`` and ``linear_depth``, which this version's
contact law needs, and a 1.0 table is refused with the advice to export it again; 1.2 the display surface; 1.3
the subdivided contact surface's map to the mesh, ``mesh_triangles``, ``parent`` and ``corners``)::

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
points            n_s x 3      vertex positions [model units]
triangles         n_t x 3      vertex indices, counter-clockwise seen from outside
neighbours        n_t x 3      triangle across the edge opposite each vertex, -1 on an open edge
frames            n_t x 12     v0, duals a and b of the edges, unit normal (:func:`~pmask.runtime.geometry.triangle_frames`)
normals           n_s x 3      contact normals (crease-blended, :func:`~pmask.runtime.geometry.contact_normals`)
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
contact_row       n_m x 1      with zeta: each mesh vertex's row block, -1 for none
mesh_triangles    n_mt x 3     optional (1.3): the mesh's surface triangles, where ζ and the display live
parent            n_t x 1      with mesh_triangles: the mesh triangle each contact triangle lies in
corners           n_t x 9      with mesh_triangles: the barycentrics there of its corners (row-major, corner k
                               in columns 3k..3k+2): a point (t, b) is Σ_k b_k corners_k of triangle parent_t
display_points    n_d x 3      optional (1.2): the display surface at the scan's resolution (:mod:`pmask.runtime.display`)
display_triangles n_dt x 3     with display_points: its triangles
display_vertices  n_d x 3      with display_points: each display vertex's simulation triangle's vertices
display_bary      n_d x 3      with display_points: the barycentric weights of its closest point there
display_lift      n_d x 3      with display_points: the display vertex minus that closest point
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
from pmask.runtime.files import atomic_write

MAGIC = b"PMASKTBL"
TABLE_MAJOR, TABLE_MINOR = 1, 3
HEADER, ENTRY, NAME = 64, 64, 32
F64, I64, BYTES = 1, 2, 3


class TableError(InputError):
    """A file that is not a runtime table this version reads (foreign, newer, truncated, corrupt)."""


def surface_sections(surface, zeta: bool = True, display=None) -> dict:
    """The sections of a table for a :class:`pmask.runtime.contact.ContactSurface` (without ``meta``), with a
    :class:`pmask.runtime.display.DisplaySurface` as the ``display_*`` sections (table 1.2)."""
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
    if display is not None:
        out.update({"display_points": display.points, "display_triangles": display.triangles,
                    "display_vertices": display.vertices, "display_bary": display.bary, "display_lift": display.lift})
    return out


def table_arrays(sections: dict, meta: dict) -> dict:
    """The sections as the native core borrows them (:func:`pmask.runtime.servo.load_table` of a dict, C
    ``pm_table_from_sections``): C-contiguous 2-D float64/int64 arrays (no copy when they already are) and the
    metadata as JSON bytes.  A viewer that rebuilds its 150 MB ζ table on every change of the mask radius
    hands it over this way instead of serialising it (:func:`table_bytes`) for the loader to copy again."""
    out = {}
    for name, value in sections.items():
        a = np.asarray(value)
        out[name] = np.ascontiguousarray(a, np.int64 if np.issubdtype(a.dtype, np.integer) else np.float64)
    out["meta"] = json.dumps(meta, sort_keys=True).encode()
    return out


def table_bytes(sections: dict, meta: dict) -> bytearray:
    """Serialise sections (name -> 2-D float64/int64 array) and the metadata into a table.  Each array is
    copied once, straight into its place (a viewer rebuilds a 150 MB table on every change of the mask
    radius: bytes of each array, then the whole, then a final bytes() made three copies)."""
    items = list(sections.items()) + [("meta", json.dumps(meta, sort_keys=True).encode())]
    n = len(items)
    offset = HEADER + n * ENTRY
    layout = []
    for name, value in items:
        if isinstance(value, bytes):
            kind, rows, cols, a, nbytes = BYTES, len(value), 1, value, len(value)
        else:
            a = np.asarray(value)
            if a.ndim != 2:
                raise ValueError(f"section {name} must be 2-D, got {a.shape}")
            kind = I64 if np.issubdtype(a.dtype, np.integer) else F64
            (rows, cols), nbytes = a.shape, 8 * a.size
        offset = -(-offset // 64) * 64
        layout.append((name, kind, rows, cols, a, offset, nbytes))
        offset += nbytes
    size = offset
    out = bytearray(size)
    view = memoryview(out)
    directory = []
    for name, kind, rows, cols, a, off, nbytes in layout:
        if kind == BYTES:
            out[off:off + nbytes] = a
        elif nbytes:
            np.frombuffer(out, "<i8" if kind == I64 else "<f8", a.size, off).reshape(a.shape)[...] = a
        directory.append(struct.pack("<32sIIQQQ", name.encode(), kind, zlib.crc32(view[off:off + nbytes]), off,
                                     rows, cols))
    head = struct.pack("<8sIIQQII24x", MAGIC, TABLE_MAJOR, TABLE_MINOR, size, HEADER, n, 0)
    d = b"".join(directory)
    crc = zlib.crc32(d, zlib.crc32(head))
    head = head[:36] + struct.pack("<I", crc) + head[40:]
    out[:HEADER] = head
    out[HEADER:HEADER + len(d)] = d
    view.release()
    return out


def write_table(path, surface, meta: dict, zeta: bool = True, display=None) -> Path:
    """Write a table for ``surface`` atomically (a killed export leaves no partial file)."""
    data = table_bytes(surface_sections(surface, zeta, display), meta)
    path = Path(path)
    if not path.parent.is_dir():
        raise InputError(f"the folder {path.parent} does not exist; create it or write the table elsewhere (-o)")
    return atomic_write(path, lambda tmp: Path(tmp).write_bytes(data))


def read_table(source) -> dict:
    """Read and check a table (a path or bytes): name -> array (2-D), ``meta`` -> dict.  Refuses what the
    native loader refuses, with the same reasons (:class:`TableError`)."""
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
    out = {}
    for i in range(n):
        name, kind, scrc, off, rows, cols = struct.unpack_from("<32sIIQQQ", buf, HEADER + i * ENTRY)
        name = name.rstrip(b"\0").decode("utf-8", "replace")
        item = 1 if kind == BYTES else 8
        nbytes = rows * cols * item
        if off % 8 or off > size or nbytes > size - off:
            raise TableError(f"{where}: corrupt runtime table: section '{name}' lies outside the file")
        data = buf[off:off + nbytes]
        if zlib.crc32(data) != scrc:
            raise TableError(f"{where}: corrupt runtime table: section '{name}' fails its checksum")
        if kind == BYTES:
            out[name] = data
        elif kind in (F64, I64):
            out[name] = np.frombuffer(data, "<f8" if kind == F64 else "<i8").reshape(rows, cols)
        # a type this version does not know: a newer minor's addition, ignored
    _check(out, where)
    try:
        out["meta"] = json.loads(out.get("meta", b"{}").decode())
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
    if "zeta" in t:
        Z = t["zeta"]
        if Z.dtype.kind != "f" or Z.shape[0] != Z.shape[1] or Z.shape[0] % 3:
            raise TableError(f"{where}: corrupt runtime table: the zeta table is not square")
        if not np.all(np.isfinite(Z)):
            raise TableError(f"{where}: corrupt runtime table: a non-finite number in the zeta table")
        row = t.get("contact_row")
        if row is None:
            raise TableError(f"{where}: not a complete runtime table: section 'contact_row' is missing (export it again)")
        if row.dtype.kind != "i" or row.shape != (nm, 1):
            raise TableError(f"{where}: corrupt runtime table: section 'contact_row' has the wrong type or shape {row.shape}")
        if row.min() < -1 or row.max() >= Z.shape[0] // 3:
            raise TableError(f"{where}: corrupt runtime table: a contact row is out of range")


def export_table(artifact, out, *, mask: str = "linear", radius: float | None = None, k_rigid: float | None = None,
                 normal_radius: float | None = None, zeta: bool = True, device=None, levels=0) -> Path:
    """Export a runtime table from an artifact: :meth:`pmask.runtime.Model.stiffness` for the mask and
    radius, the contact surface of :class:`pmask.runtime.contact.ContactSurface`, and (``zeta``) the ζ table
    for several coupled contacts and the deformation (3n_c x 3n_c doubles: 150 MB at the default
    kidney's 1,446 contact vertices).  radius : default :attr:`pmask.runtime.Model.default_radius`.  levels : the
    contact surface's subdivision (:class:`pmask.runtime.Contacts`; 0 the mesh, "auto" the automatic choice)."""
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
    return write_table(out, surface, meta, zeta, display=model.display())


def _version() -> str:
    from pmask import __version__

    return __version__
