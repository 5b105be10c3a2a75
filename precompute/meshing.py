"""Meshing with gmsh: model solids, volumes inside a given surface, user files.

Every function returns plain arrays: ``points`` (N, 3) float64 in metres and
``tets`` (M, 4) int64, positively oriented.  gmsh runs single-threaded with a
fixed random seed so that a pinned gmsh version gives the same mesh every time.
"""
from __future__ import annotations

import contextlib
import logging
from pathlib import Path

import numpy as np

from pmask.errors import InputError
from pmask.runtime.geometry import triangle_areas, unique_rows

log = logging.getLogger("pmask.precompute.meshing")  # also when run as the remesh worker (__main__)


class MeshError(InputError):
    """Raised for geometry that cannot be meshed or used (says what to fix)."""


@contextlib.contextmanager
def gmsh_session(name: str = "pmask"):
    """Initialise gmsh quietly and reproducibly; always finalise."""
    import gmsh

    if gmsh.isInitialized():
        gmsh.finalize()
    gmsh.initialize(interruptible=False, readConfigFiles=False)
    _ignore_sigpipe()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.Verbosity", 2)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.option.setNumber("Mesh.RandomSeed", 1)
        gmsh.option.setNumber("Mesh.Algorithm", 6)  # Frontal-Delaunay (2-D)
        gmsh.option.setNumber("Mesh.Algorithm3D", 1)  # Delaunay (3-D)
        gmsh.option.setNumber("Mesh.Optimize", 1)
        gmsh.model.add(name)
        yield gmsh
    finally:
        gmsh.finalize()


def _ignore_sigpipe() -> None:
    """gmsh's initialisation puts SIGPIPE back to its default action, which kills the process on a write to
    a closed socket or pipe (Python ignores it and raises BrokenPipeError instead): a viewer whose browser
    hung up after a precompute in the same process died silently (exit 141).  Restore Python's choice."""
    import signal
    import threading

    if hasattr(signal, "SIGPIPE") and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGPIPE, signal.SIG_IGN)


def tets_from_gmsh(gmsh, with_tags: bool = False):
    """Linear tetrahedra of the current gmsh model as (points, tets), nodes compacted.

    With ``with_tags`` also the gmsh node tag of every returned point.
    """
    tags, coords, _ = gmsh.model.mesh.getNodes()
    order = np.argsort(tags)
    tags = tags[order]
    coords = coords.reshape(-1, 3)[order]
    types, _, node_tags = gmsh.model.mesh.getElements(3)
    tets = [nt.reshape(-1, 4) for ty, nt in zip(types, node_tags) if ty == 4]
    if not tets:
        raise MeshError("gmsh produced no tetrahedra: is the surface closed and free of self-intersections?")
    tets = np.searchsorted(tags, np.concatenate(tets))
    points, tets, used = compact(coords, tets)
    return (points, tets, tags[used]) if with_tags else (points, tets)


def compact(points: np.ndarray, tets: np.ndarray):
    """Drop points no tetrahedron uses and orient every tetrahedron positively.

    Returns (points, tets, used) with ``used`` the kept indices of the input points.
    """
    used, inverse = np.unique(tets, return_inverse=True)
    points = np.ascontiguousarray(points[used], dtype=float)
    tets = inverse.reshape(-1, 4).astype(np.int64)
    vol = signed_volumes(points, tets)
    flip = vol < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    return points, tets, used


def signed_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volume of each tetrahedron (positive for right-handed vertex order)."""
    p = points[tets]
    return np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6.0


def enclosed_volume(points: np.ndarray, triangles: np.ndarray) -> float:
    """Signed volume enclosed by a closed triangle surface (divergence theorem; positive when outward)."""
    p = points[triangles]
    return float(np.einsum("ij,ij->i", np.cross(p[:, 0], p[:, 1]), p[:, 2]).sum() / 6.0)


def volume_inside_surface(points: np.ndarray, triangles: np.ndarray, *, size_factor: float = 1.0):
    """Tet-mesh the interior of a closed triangle surface, keeping it exactly.

    The surface becomes a discrete gmsh entity, so its vertices and triangles
    are the boundary of the volume mesh unchanged.  Interior element sizes are
    interpolated from the boundary (``Mesh.MeshSizeExtendFromBoundary``): the
    interior follows the surface resolution.
    """
    with gmsh_session("volume") as gmsh:
        gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 1)
        gmsh.option.setNumber("Mesh.MeshSizeFactor", float(size_factor))
        s = gmsh.model.addDiscreteEntity(2)
        node_tags = np.arange(1, len(points) + 1)
        gmsh.model.mesh.addNodes(2, s, node_tags, np.asarray(points, float).ravel())
        gmsh.model.mesh.addElementsByType(s, 2, [], (np.asarray(triangles) + 1).ravel())
        loop = gmsh.model.geo.addSurfaceLoop([s])
        gmsh.model.geo.addVolume([loop])
        gmsh.model.geo.synchronize()
        try:
            gmsh.model.mesh.generate(3)
        except Exception as exc:  # gmsh raises a bare Exception
            raise MeshError(f"gmsh could not mesh the interior of the surface ({exc}); "
                            "check that the surface is closed, manifold and not self-intersecting") from exc
        vol_points, tets = tets_from_gmsh(gmsh)
    return vol_points, tets


def edge_defects(tris: np.ndarray) -> dict:
    """Counts of the edges that keep a triangulation from bounding a solid: boundary edges (in one
    triangle: holes), non-manifold edges (in more than two) and inconsistently oriented edges (the same
    directed edge in two triangles)."""
    directed = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    _, counts = unique_rows(np.sort(directed, axis=1), return_counts=True)
    _, dcounts = unique_rows(directed, return_counts=True)
    return {"boundary_edges": int(np.sum(counts == 1)), "non_manifold_edges": int(np.sum(counts > 2)),
            "inconsistent_edges": int(np.sum(dcounts > 1))}


def shells(pts: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The connected pieces of a triangulation: each triangle's shell, and each shell's area and enclosed
    (signed) volume."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(pts)
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]]])
    n_comp, label = connected_components(coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)),
                                         directed=False)
    tri_label = label[tris[:, 0]]
    p = pts[tris]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    vol = np.einsum("ij,ij->i", np.cross(p[:, 0], p[:, 1]), p[:, 2]) / 6.0
    return (tri_label, np.bincount(tri_label, weights=area, minlength=n_comp),
            np.bincount(tri_label, weights=vol, minlength=n_comp))


def merge_duplicates(points: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The surface with coincident vertices merged (an STL repeats each vertex in every triangle)."""
    pts, inverse = np.unique(np.asarray(points, float), axis=0, return_inverse=True)
    return pts, inverse.ravel()[np.asarray(triangles, np.int64)]


def check_surface(points: np.ndarray, triangles: np.ndarray, name: str = "surface") -> tuple[np.ndarray, np.ndarray]:
    """Refuse a triangle surface that cannot bound a solid; return it with duplicate vertices merged.

    Checks, each with a message that says what to fix: at least one triangle, no
    degenerate triangles, closed (every edge in two triangles), manifold (no edge in
    more than two), consistently oriented, and oriented outwards (positive volume).
    Self-intersections are found by gmsh when it meshes the volume.
    """
    if triangles is None or len(triangles) == 0:
        raise MeshError(f"{name}: no triangles; give a closed triangle surface (STL, OBJ, PLY, ...)")
    pts, tris = merge_duplicates(points, triangles)
    bad = (tris[:, 0] == tris[:, 1]) | (tris[:, 1] == tris[:, 2]) | (tris[:, 0] == tris[:, 2])
    if np.any(bad):
        raise MeshError(f"{name}: {int(bad.sum())} degenerate triangles (repeated vertices); clean the surface")
    pts, tris = keep_main_shell(pts, tris, name)
    defects = edge_defects(tris)
    if defects["boundary_edges"]:
        raise MeshError(f"{name}: the surface is open ({defects['boundary_edges']} boundary edges); "
                        "close its holes (e.g. 'fill holes' in your segmentation or mesh tool), or try --repair")
    if defects["non_manifold_edges"]:
        raise MeshError(f"{name}: the surface is not manifold ({defects['non_manifold_edges']} edges shared by more "
                        "than two triangles); separate the touching parts, or try --repair")
    pinched = pinched_vertices(tris)
    if len(pinched):
        x = pts[pinched[0]]
        raise MeshError(f"{name}: {len(pinched)} vertices join parts of the surface that share no edge (shells "
                        f"touching at a point), e.g. at ({x[0]:.4g}, {x[1]:.4g}, {x[2]:.4g}); separate the parts, "
                        "or try --repair")
    if defects["inconsistent_edges"]:
        raise MeshError(f"{name}: triangle orientation is inconsistent (some neighbours face opposite ways); "
                        "re-orient the triangles consistently (e.g. trimesh.repair.fix_winding)")
    volume = enclosed_volume(pts, tris)
    if volume < 0:
        raise MeshError(f"{name}: the surface is inverted (normals point inwards, volume {volume:.3g}); "
                        "flip the triangle orientation")
    return pts, tris


#: an organ read in metres is well under this across; a file this large without --units is probably in mm
MAX_EXTENT_WITHOUT_UNITS = 2.0  # m


def check_finite(points: np.ndarray, name) -> None:
    """Refuse NaN/inf coordinates before gmsh sees them (one inf vertex made a run grow to 24 GB)."""
    bad = ~np.all(np.isfinite(points), axis=1)
    if np.any(bad):
        raise MeshError(f"{name}: {int(bad.sum())} vertices have non-finite coordinates (NaN or inf; the first is "
                        f"vertex {int(np.flatnonzero(bad)[0])}); remove or repair them")


#: no organ a haptic simulator renders is smaller or (with a stated unit) larger than this across
MIN_EXTENT = 5e-3  # m
MAX_EXTENT = 1.0  # m


def check_extent(points: np.ndarray, units_given: bool, name, edge_length: float | None = None) -> None:
    """Refuse a size no organ has: a file in one unit read in another (points in metres, as read).

    Without --units the file is read in metres and more than 2 m across is probably millimetres; with a
    unit, under 5 mm or over 1 m across is probably the wrong unit.  ``edge_length`` (metres): an edge longer
    than half the body would leave no vertex inside it, which gmsh reports as a broken surface."""
    extent = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    if not units_given and extent > MAX_EXTENT_WITHOUT_UNITS:
        raise MeshError(f"{name}: read in metres the geometry is {extent:.3g} m across; if the file is in "
                        f"millimetres pass --units mm (selectors, --edge-length and --r-max are then in mm too), "
                        "or --units m if it really is that large")
    if units_given and extent > MAX_EXTENT:
        raise MeshError(f"{name}: in the unit given (--units) the geometry is {extent:.3g} m across, larger than any "
                        "organ: is the file in a smaller unit (a file in micrometres read as mm is 1000x too large)? "
                        "Pass the file's own unit with --units")
    if extent < MIN_EXTENT:
        raise MeshError(f"{name}: as read the geometry is only {1e3 * extent:.3g} mm across, smaller than any organ: "
                        "is the file in a larger unit than read (a file in metres read with --units mm is 1000x too "
                        "small)? Pass the file's own unit with --units")
    if edge_length is not None and edge_length > 0.5 * extent:
        raise MeshError(f"{name}: --edge-length is {1e3 * edge_length:.3g} mm, longer than half the body "
                        f"({1e3 * extent:.3g} mm across), so no vertex would lie inside it; choose about a tenth of "
                        "the body or less (pmask inspect suggests edge lengths for vertex counts; --edge-length is in "
                        "the --units unit)")


def remesh_bounded(path: Path, *, edge_length: float, scale: float = 1.0, units_given: bool = True,
                   timeout: float = 600.0, repair: str | None = None, xi_of_all: bool = False,
                   shell: int | None = None, inclusions=(), with_regions: bool = False, region_names=None,
                   angle_deg: float = 40.0):
    """:func:`remesh_surface` in a worker process (``python -m pmask.precompute.meshing``) that is stopped
    after ``timeout`` seconds or on Ctrl-C; returns (points, tets, geometry change).

    gmsh's surface classification can run for tens of minutes on some segmentations and defers Ctrl-C
    inside its C++ (and once printed "double free" on SIGTERM); a worker can always be killed, and the
    parent stays responsive.  A fresh interpreter rather than multiprocessing: spawn re-runs the caller's
    script in the child when it lacks a ``__main__`` guard, fork copies BLAS threads.

    ``inclusions``: closed surface files inside this one, meshed conformally as regions of their own
    (:func:`remesh_surface`); ``with_regions``: return (points, tets, change, regions) with regions
    {name: bool over tets}; ``angle_deg``: gmsh's feature angle (180: no feature edges, for a label image's
    surface, whose creases are its voxels')."""
    import json
    import subprocess
    import sys
    import tempfile

    job = {"path": str(path), "edge_length": edge_length, "scale": scale, "units_given": units_given,
           "repair": repair, "xi_of_all": xi_of_all, "timeout": timeout, "shell": shell,
           "inclusions": [str(q) for q in inclusions], "angle_deg": angle_deg}
    from pmask import interrupt

    interrupt.check()  # a Ctrl-C swallowed while the surface was read (trimesh's imports) stops it here
    with tempfile.TemporaryDirectory(prefix="pmask-remesh-") as tmp:
        out = Path(tmp) / "mesh.npz"
        job.update(save_surface_read(path, Path(tmp)))  # the surface as this process read it, not parsed again
        proc = subprocess.Popen([sys.executable, "-m", "pmask.precompute.meshing", json.dumps(job), str(out)],
                                stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                start_new_session=True)  # the terminal's Ctrl-C reaches us, and we stop it
        try:
            _, stderr = proc.communicate(timeout=timeout)  # gmsh's own chatter stays out of the console
        except subprocess.TimeoutExpired:
            raise MeshError(f"{path}: gmsh did not finish remeshing within {timeout:g} s (it can stall "
                            "classifying a surface with many sharp edges or a high genus); repair or simplify the "
                            "surface, try another --edge-length, or allow longer with --mesh-timeout") from None
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
        try:
            result = json.loads(out.with_suffix(".json").read_text())
        except (OSError, ValueError):
            last = (stderr or b"").decode(errors="replace").strip().splitlines()[-1:] or ["no message"]
            raise MeshError(f"{path}: gmsh crashed while remeshing this surface (exit code {proc.returncode}: "
                            f"{last[0][:200]}); "
                            "repair the surface (closed, manifold, not self-intersecting), "
                            + ("try another --repair route or " if repair and repair != "auto" else
                               "" if repair == "auto" else "try --repair or ")
                            + "another --edge-length") from None
        for message in result.get("warnings", []):
            log.warning("%s", message)
        if result["kind"] == "error":
            raise MeshError(result["message"])
        if result["kind"] == "bug":
            raise RuntimeError(f"remeshing failed inside pmask:\n{result['message']}")
        with np.load(out) as z:
            points, tets, label = z["points"], z["tets"], z["label"]
        if not with_regions:
            return points, tets, result["report"]
        names = list(region_names) if region_names is not None else inclusion_names(len(inclusions))
        return points, tets, result["report"], {name: label == k + 1 for k, name in enumerate(names)}


def inclusion_names(n: int) -> list[str]:
    """The regions ``--inclusion`` files become: "inclusion", or "inclusion1", "inclusion2", ... for several."""
    return ["inclusion"] if n == 1 else [f"inclusion{k + 1}" for k in range(n)]


def _worker(argv) -> int:
    """``python -m pmask.precompute.meshing JOB OUT``: one remesh, arrays to OUT (.npz) and the outcome
    (ok / error / bug, the report, the warnings) to OUT with the suffix .json."""
    import json
    import signal
    import traceback

    import os
    import threading
    import time

    job, out = json.loads(argv[0]), argv[1]
    if hasattr(signal, "SIGALRM"):  # if the parent is killed outright, do not outlive its time limit
        signal.alarm(int(job.get("timeout", 600)) + 30)
    parent = os.getppid()

    def orphaned():  # nor the parent by more than a second (a SIGKILL leaves no one to stop us)
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(1)
    threading.Thread(target=orphaned, daemon=True).start()
    warned = []  # this process's warnings, re-logged by the parent (the user's console is the parent's)
    handler = logging.Handler(logging.WARNING)
    handler.emit = lambda record: warned.append(record.getMessage())
    logging.getLogger("pmask").addHandler(handler)
    logging.getLogger("pmask").setLevel(logging.WARNING)
    try:
        _load_surface_read(job)
        report: dict = {}
        label = np.zeros(0, np.int64)
        points, tets, *rest = remesh_surface(Path(job["path"]), edge_length=job["edge_length"], scale=job["scale"],
                                             units_given=job["units_given"], report=report, repair=job["repair"],
                                             xi_of_all=job["xi_of_all"], shell=job.get("shell"),
                                             inclusions=[Path(q) for q in job.get("inclusions", [])],
                                             angle_deg=job.get("angle_deg", 40.0))
        label = rest[0] if rest else np.zeros(len(tets), np.int64)
        np.savez(out, points=points, tets=tets, label=label)
        result = {"kind": "ok", "report": report}
    except MeshError as exc:
        result = {"kind": "error", "message": str(exc)}
    except Exception:
        result = {"kind": "bug", "message": traceback.format_exc()}
    result["warnings"] = warned
    Path(out).with_suffix(".json").write_text(json.dumps(result))
    return 0


#: --repair meshfix warns when it drops more than this share of the input's area
REPAIR_AREA_WARN = 0.05


def repair_surface(pts: np.ndarray, tris: np.ndarray, name, warn: bool = True) -> tuple[np.ndarray, np.ndarray, dict]:
    """``--repair`` / ``--repair meshfix``: pymeshfix (Attene's MeshFix) keeps the largest shell, removes non-manifold parts and
    self-intersections, fills holes and orients the result outwards; returns it with what it changed."""
    try:
        import pymeshfix
    except ImportError:
        raise MeshError("--repair needs the repair extra (pymeshfix): pip install 'pmask[repair]'") from None
    upts, inverse = np.unique(pts, axis=0, return_inverse=True)
    t = inverse.ravel()[np.asarray(tris, np.int64)]
    t = t[(t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])]
    d = edge_defects(t)
    before = {"vertices": int(len(upts)), "triangles": int(len(t)), "boundary_edges": d["boundary_edges"],
              "non_manifold_edges": d["non_manifold_edges"], "inconsistent_edges": d["inconsistent_edges"]}
    tri_shell, area, _ = shells(upts, t)
    if np.count_nonzero(area) > 1:  # MeshFix keeps the shell with the most triangles: a finely triangulated ear
        # or debris over a coarse body would win; the report (and the docs) promise the largest by area
        used, keep = np.unique(t[tri_shell == np.argmax(area)], return_inverse=True)
        mf = pymeshfix.MeshFix(upts[used], keep.reshape(-1, 3))
    else:
        mf = pymeshfix.MeshFix(upts, t)
    mf.repair()
    out_p, out_t = np.asarray(mf.points, float), np.asarray(mf.faces, np.int64)
    if len(out_t) == 0:
        raise MeshError(f"{name}: MeshFix could not make a closed surface of this file (nothing was left); "
                        "mend it in a mesh tool")
    if enclosed_volume(out_p, out_t) < 0:
        out_t = out_t[:, ::-1]
    area_before = float(triangle_areas(upts, t).sum())
    area_after = float(triangle_areas(out_p, out_t).sum())
    fixed = {"before": before | {"area": area_before},
             "after": {"vertices": int(len(out_p)), "triangles": int(len(out_t)), "area": area_after},
             "changes": repair_changes(upts, t, out_p, out_t, before)}
    if warn and area_after < (1 - REPAIR_AREA_WARN) * area_before:
        log.warning("%s: --repair meshfix kept %.0f %% of the surface area: it drops all but the largest shell, and "
                    "shells that run into each other lose the smaller one; --repair voxel keeps their union",
                    name, 100 * area_after / area_before)
    if warn:
        log.warning("%s: --repair: %s", name, fixed["changes"])
    return out_p, out_t, fixed


def repair_changes(p_in, t_in, p_out, t_out, before: dict) -> str:
    """What a repair changed, and only that (a report of "holes filled" for a surface that had none misled
    users into looking for the holes): shells dropped, open and non-manifold edges gone, triangles and area."""
    n_shells = len(np.unique(shells(p_in, t_in)[0]))
    d = edge_defects(t_out)
    area_in, area_out = float(triangle_areas(p_in, t_in).sum()), float(triangle_areas(p_out, t_out).sum())
    parts = []
    if n_shells > 1:
        parts.append(f"kept the largest of {n_shells} shells")
    for key, what in (("boundary_edges", "open (boundary) edges"), ("non_manifold_edges", "non-manifold edges"),
                      ("inconsistent_edges", "inconsistently oriented edges")):
        if before.get(key, d[key]) != d[key]:
            parts.append(f"{what} {before[key]} -> {d[key]}")
    if len(t_out) != before["triangles"]:
        parts.append(f"triangles {before['triangles']} -> {len(t_out)}")
    if abs(area_out - area_in) > 1e-9 * area_in:
        parts.append(f"{100 * area_out / area_in:.1f} % of the area kept")
    return "; ".join(parts) if parts else "nothing needed changing (one closed, manifold shell)"


def pinched_vertices(tris: np.ndarray) -> np.ndarray:
    """Vertices whose triangles form more than one fan (a non-manifold vertex: two shells touching at a
    point, which edge counts cannot see).  The corners of a vertex are joined across the edges its
    triangles share; more than one group of corners is a pinch."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n_t = len(tris)
    corner = lambda t, k: 3 * t + k  # noqa: E731
    rows = []
    for k in range(3):  # edge (k, k+1) of each triangle: (triangle, its two corners, the edge's key)
        a, b = tris[:, k].astype(np.int64), tris[:, (k + 1) % 3].astype(np.int64)
        key = np.minimum(a, b) * (int(tris.max()) + 1) + np.maximum(a, b)
        rows.append(np.stack([np.arange(n_t), np.full(n_t, k), np.full(n_t, (k + 1) % 3), key], axis=1))
    e = np.concatenate(rows)
    e = e[np.argsort(e[:, 3], kind="stable")]
    same = e[1:, 3] == e[:-1, 3]  # consecutive rows on the same edge: join their corners
    t1, t2 = e[:-1][same], e[1:][same]
    # match corners by vertex: the corner of t2 that holds the same vertex as t1's corner
    src, dst = [], []
    for c1 in (1, 2):
        v1 = tris[t1[:, 0], t1[:, c1]]
        for c2 in (1, 2):
            m = tris[t2[:, 0], t2[:, c2]] == v1
            src.append(corner(t1[m, 0], t1[m, c1]))
            dst.append(corner(t2[m, 0], t2[m, c2]))
    src, dst = np.concatenate(src), np.concatenate(dst)
    g = coo_matrix((np.ones(len(src)), (src, dst)), shape=(3 * n_t, 3 * n_t))
    _, label = connected_components(g, directed=False)
    vertex = tris.ravel()
    pairs = unique_rows(np.stack([vertex, label], axis=1))
    fans = np.bincount(pairs[:, 0], minlength=int(vertex.max()) + 1)
    return np.flatnonzero(fans > 1)


#: pieces of a surface apart from its largest shell, up to this share of its area, are debris (segmentation
#: specks) and are dropped with a warning; more is a second body, refused
DEBRIS_AREA_SHARE = 0.01


def winding_numbers(p: np.ndarray, t: np.ndarray, x: np.ndarray, chunk: int = 2_000_000) -> np.ndarray:
    """The generalised winding number of the triangle surface (p, t) at points x (Jacobson, Kavan and
    Sorkine-Hornung 2013): Σ over triangles of the solid angle they subtend at x (Van Oosterom and Strackee's
    formula) over 4π.  1 inside a closed outward surface, 0 outside, and a graceful in-between near holes and
    overlaps, where a ray test flips."""
    tri = p[np.asarray(t, np.int64)]
    out = np.zeros(len(x))
    step = max(1, chunk // max(len(tri), 1))
    for s0 in range(0, len(x), step):
        q = x[s0:s0 + step, None, None, :]
        a, b, c = (tri[None, :, k, :] - q[:, :, 0, :] for k in range(3))
        la, lb, lc = (np.linalg.norm(v, axis=2) for v in (a, b, c))
        num = np.einsum("ijk,ijk->ij", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("ijk,ijk->ij", a, b) * lc + np.einsum("ijk,ijk->ij", b, c) * la
               + np.einsum("ijk,ijk->ij", c, a) * lb)
        out[s0:s0 + step] = 2.0 * np.arctan2(num, den).sum(axis=1) / (4.0 * np.pi)
    return out


def shells_overlap(pts, tris, tri_label, a: int, b: int, samples: int = 64) -> bool:
    """Whether shells a and b run into each other or one holds the other: some of either's vertices lie
    inside the other (winding number above ½), sampled."""
    rng = np.random.default_rng(0)
    for inner, outer in ((a, b), (b, a)):
        v = np.unique(tris[tri_label == inner])
        v = v if len(v) <= samples else rng.choice(v, samples, replace=False)
        if np.any(np.abs(winding_numbers(pts, tris[tri_label == outer], pts[v])) > 0.5):
            return True
    return False


class SeveralBodiesError(MeshError):
    """A surface of several bodies (not debris): which one is the organ is the user's choice (``--shell``)."""


class CavityError(SeveralBodiesError):
    """A closed shell inside the body facing inwards (a hollow organ's inner wall) where it cannot be meshed as
    a cavity: together with ``--inclusion``.  Every repair route would fill it, so ``--repair auto`` does
    not try them."""


def is_cavity(pts, tris, tri_label, outer: int, inner: int) -> bool:
    """Whether shell ``inner`` is a cavity of shell ``outer``: it faces inwards (negative enclosed volume)
    and lies inside (the generalised winding number of 64 of its vertices above ½): the inner wall of a
    bladder, a stomach or a heart chamber."""
    t_in = tris[tri_label == inner]
    if enclosed_volume(pts, t_in) >= 0:
        return False
    v = np.unique(t_in)
    v = v if len(v) <= 64 else np.random.default_rng(0).choice(v, 64, replace=False)
    return bool(np.all(winding_numbers(pts, tris[tri_label == outer], pts[v]) > 0.5))


def check_not_a_cavity(pts, tris, tri_label, per, outer: int, inner: int, name) -> None:
    """Refuse, naming it, a cavity where it reaches the surface checks (:func:`split_cavities` takes the
    cavities out before them on the route that meshes them): filling it silently, as the voxel route's union
    does, makes a stiffer organ than the hollow one."""
    if is_cavity(pts, tris, tri_label, outer, inner):
        rank = {k: r + 1 for r, k in enumerate(np.argsort(-per))}
        raise CavityError(f"{name}: shell {rank[inner]} ({100 * per[inner] / per.sum():.1f} % of the area) lies inside "
                          f"shell {rank[outer]} and faces inwards: a cavity, which pmask meshes, but not together "
                          "with --inclusion: precompute the hollow organ without --inclusion, or "
                          f"--shell {rank[outer]} takes the outer surface alone with the cavity filled, a stiffer "
                          "organ than the hollow one")


def split_cavities(points: np.ndarray, triangles: np.ndarray, name) -> tuple[np.ndarray, np.ndarray, list]:
    """A hollow organ's surface: (points, the triangles of every shell but the cavities, [each cavity's
    triangles, turned to face out of the cavity]), duplicates merged.  A cavity is a shell of more than
    debris's share of the area that lies inside the largest shell and faces inwards (:func:`is_cavity`); the
    body is then the volume between the walls (:func:`_remesh`), as a bladder's or a stomach's is."""
    pts, tris = merge_duplicates(points, triangles)
    if len(tris) == 0:
        return pts, tris, []
    tri_label, per, _ = shells(pts, tris)
    main = int(np.argmax(per))
    found = [int(k) for k in np.argsort(-per) if k != main and per[k] > DEBRIS_AREA_SHARE * per.sum()
             and is_cavity(pts, tris, tri_label, main, k)]
    return pts, tris[~np.isin(tri_label, found)], [tris[tri_label == k][:, ::-1] for k in found]


def shell_list(per: np.ndarray, tri_label: np.ndarray) -> str:
    """The shells largest first, as a refusal lists them: "1: 45.9 % of the area (2,560 triangles), ..."."""
    counts = np.bincount(tri_label, minlength=len(per))
    order = [k for k in np.argsort(-per) if counts[k]]
    return ", ".join(f"{r + 1}: {100 * per[k] / per.sum():.1f} % of the area ({counts[k]:,} triangles)"
                     for r, k in enumerate(order[:8])) + (", ..." if len(order) > 8 else "")


def select_shell(pts: np.ndarray, tris: np.ndarray, rank: int, name):
    """``--shell K``: the K-th largest shell by area (1 = the largest), before any check or repair."""
    t = np.asarray(tris, np.int64)
    tri_label, per, _ = shells(pts, t)
    counts = np.bincount(tri_label, minlength=len(per))
    order = [k for k in np.argsort(-per) if counts[k]]
    if not 1 <= rank <= len(order):
        raise MeshError(f"{name}: --shell {rank}, but the surface has {len(order)} shell(s): "
                        f"{shell_list(per, tri_label)}")
    return pts, t[tri_label == order[rank - 1]]


def keep_main_shell(pts: np.ndarray, tris: np.ndarray, name):
    """The largest connected shell; debris (the rest, ≤ 1 % of the area) dropped with a warning, a second
    body refused, listing the shells for ``--shell``.  A segmented heart exported for 3D printing had 77
    specks beside its main shell; a striatum came as 4 bodies."""
    tri_label, per, _ = shells(pts, tris)
    if len(per) == 1:
        return pts, tris
    main = int(np.argmax(per))
    rest = per.sum() - per[main]
    pieces = int(np.count_nonzero(np.bincount(tri_label, minlength=len(per)))) - 1
    if pieces and rest > DEBRIS_AREA_SHARE * per.sum():
        big = [k for k in np.argsort(-per) if k != main and per[k] > DEBRIS_AREA_SHARE * per.sum()]
        for k in big:
            check_not_a_cavity(pts, tris, tri_label, per, main, k, name)
        if any(shells_overlap(pts, tris, tri_label, main, k) for k in big):
            raise MeshError(f"{name}: the surface has {pieces + 1} shells that run into each other or lie one inside "
                            f"another (largest first: {shell_list(per, tri_label)}): the body is their union, which "
                            "--repair voxel builds (--repair auto tries it); --shell K takes one of them alone")
        raise SeveralBodiesError(f"{name}: the surface has {pieces + 1} separate shells and the smaller ones hold "
                                 f"{100 * rest / per.sum():.1f} % of the area (largest first: "
                                 f"{shell_list(per, tri_label)}); pmask models one body: choose it with --shell K "
                                 "(1 = the largest), or export the organ you want on its own")
    if pieces:  # (none: only vertices no triangle uses, dropped silently)
        log.warning("%s: dropped %d debris piece(s) apart from the main shell (%.2f %% of the area)", name, pieces,
                    100 * rest / per.sum())
    keep = tri_label == main
    used = np.unique(tris[keep])
    remap = np.full(len(pts), -1)
    remap[used] = np.arange(len(used))
    return pts[used], remap[tris[keep]]


def check_size_before_meshing(pts, tris, edge_length: float, name, xi_of_all: bool = True) -> None:
    """Refuse in seconds, before gmsh, an --edge-length whose Green's functions cannot fit in memory.

    A closed triangulation of area A at edge h has about n = 2A / (√3 h²) surface vertices (``pmask
    inspect``'s estimate, within 35 % after gmsh), and Ξ over all of them is (3n)² doubles; the volume
    it encloses, V, gets at least V / h³ vertices (gmsh, measured: 1,384 at h = 3 mm in a 20 mm sphere,
    where V / h³ = 1,241), whose sparse factor follows P1's fitted rule (:class:`~pmask.precompute.
    elements.Element.memory_estimate`; P2's is larger).  The bound uses 0.65 n and these lower
    bounds, so a refusal is never the estimate's error; the full check follows after meshing.
    With ``--contact`` (``xi_of_all`` false) only the factor counts."""
    from pmask.precompute.elements import P1
    from pmask.precompute.greens import available_memory

    area = float(triangle_areas(pts, tris).sum())
    volume = abs(enclosed_volume(pts, tris))
    n = 2.0 * area / (np.sqrt(3.0) * edge_length ** 2)
    n_volume = volume / edge_length ** 3
    avail = available_memory()
    need = P1().memory_estimate(n_volume, 0.65 * n if xi_of_all else 0)
    if avail is None or need["total"] <= avail:
        return
    if xi_of_all and need["Xi"] > avail:
        n_max = np.sqrt(avail / 8.0) / 3.0 / 0.65
        h_min = np.sqrt(2.0 * area / (np.sqrt(3.0) * n_max))
        raise MeshError(f"{name}: at --edge-length {edge_length:.3g} m the surface gets about {n:,.0f} vertices, "
                        f"whose dense Ξ alone would take ~{need['Xi'] / 2**30:.1f} GiB, more than the "
                        f"{avail / 2**30:.1f} GiB available: use an edge length of at least {h_min:.3g} m (in "
                        "metres; scale to your --units) or restrict Ξ with --contact")
    raise MeshError(f"{name}: at --edge-length {edge_length:.3g} m the solid gets at least {n_volume:,.0f} volume "
                    f"vertices, whose sparse factor{' and Ξ' if xi_of_all else ''} would take ~"
                    f"{need['total'] / 2**30:.1f} GiB, more than the {avail / 2**30:.1f} GiB available: use a larger "
                    "--edge-length (the factor grows like h^-4)")


def remesh_surface(path: Path, *, edge_length: float, scale: float = 1.0, angle_deg: float = 40.0,
                   units_given: bool = True, report: dict | None = None, repair: str | None = None,
                   xi_of_all: bool = False, shell: int | None = None, inclusions=()):
    """Remesh a (possibly very fine) triangle surface file to a target edge length.

    ``inclusions``: closed surface files (same units) that lie inside it, each meshed as a region of its own
    with its surface an interface inside the volume (conformal: the elements on both sides share its
    triangles); then returns (points, tets, label) with label 0 for the body and k for the k-th inclusion.

    Follows gmsh tutorial t13: classify the triangles into patches, build a
    parametrisable geometry from them, then mesh it anew at ``edge_length``
    (in metres, after ``scale`` is applied).  Returns (points, tets) of the
    volume inside.
    """
    if not (np.isfinite(edge_length) and edge_length > 0):
        raise MeshError(f"the target edge length must be > 0, got {edge_length}")
    raw, tris = read_surface_file(path, scale)
    check_extent(raw, units_given, path, edge_length)
    if shell is not None:
        raw, tris = select_shell(raw, tris, shell, path)
    if inclusions:
        if repair:
            raise MeshError(f"{path}: --inclusion needs a closed outer surface as it is: repair it first (pmask "
                            "precompute --repair writes nothing you can reuse; mend it in a mesh tool)")
        outer = check_surface(raw, tris, str(path))
        inner = [read_inclusion(q, scale, outer, edge_length) for q in inclusions]
        check_inclusions_apart(inner, [f"--inclusion {q}" for q in inclusions])
        check_size_before_meshing(*outer, edge_length, path, xi_of_all)
        points, tets, label = _remesh(*outer, path, edge_length, angle_deg, inclusions=inner)
        change = geometry_change(*outer, points, tets, edge_length)
        if report is not None:
            report.update(change)
        return points, tets, label
    if repair != "auto":
        return _remesh_route(raw, tris, repair, path, edge_length, angle_deg, report, xi_of_all)
    return _remesh_auto(raw, tris, path, edge_length, angle_deg, report, xi_of_all)


def read_inclusion(path: Path, scale: float, outer, edge_length: float):
    """An ``--inclusion`` surface, checked as a body of its own (closed, manifold, outward) and against the
    outer one: wholly inside it (a generalised winding number of its vertices), not touching it (half an
    edge length of tissue at least: an element between the two surfaces), and not thinner than an element
    (3 V / A, the radius of a ball, against half an edge length)."""
    raw, tris = read_surface_file(path, scale)
    pts, tris = check_surface(raw, tris, f"--inclusion {path}")
    return check_inner_surface(pts, tris, outer, edge_length, f"--inclusion {path}",
                               "an inclusion must lie wholly inside (same --units as the body)")


def check_inner_surface(pts, tris, outer, edge_length: float, what: str, advice: str):
    """A closed outward surface inside the body (an inclusion, or a cavity turned outwards) checked against
    the outer one (``outer``: (points, triangles)): wholly inside it (a generalised winding number of its
    vertices), not touching it (half an edge length of tissue at least: an element between the two surfaces),
    and not thinner than an element (3 V / A, the radius of a ball, against half an edge length)."""
    op, ot = outer
    rng = np.random.default_rng(0)
    sample = pts if len(pts) <= 2000 else pts[rng.choice(len(pts), 2000, replace=False)]
    outside = int(np.sum(winding_numbers(op, ot, sample) < 0.5))
    if outside:
        raise MeshError(f"{what}: it crosses the outer surface ({outside} of {len(sample)} sampled "
                        f"vertices lie outside the body): {advice}")
    gap = float(surface_distance(sample, op, ot).min())
    if gap < 0.5 * edge_length:
        raise MeshError(f"{what}: it touches the outer surface ({1e3 * gap:.3g} mm from it, less than "
                        f"half the {1e3 * edge_length:.3g} mm edge length): leave tissue between them, or use an "
                        f"--edge-length of at most {2e3 * gap:.3g} mm")
    thickness = 3.0 * enclosed_volume(pts, tris) / float(triangle_areas(pts, tris).sum())
    if thickness < 0.5 * edge_length:
        raise MeshError(f"{what}: it is thinner than an element (about {2e3 * thickness:.3g} mm across, "
                        f"for {1e3 * edge_length:.3g} mm edges): use an --edge-length of at most "
                        f"{2e3 * thickness:.3g} mm")
    return pts, tris


def check_inclusions_apart(inner, names, advice: str = "give each part of the tissue one material (separate "
                                                        "inclusions)") -> None:
    """Inclusions (or cavities) may not run into or hold each other: each region one material."""
    for a in range(len(inner)):
        for b in range(a + 1, len(inner)):
            for x, (p, t) in ((inner[a][0], inner[b]), (inner[b][0], inner[a])):
                if np.any(np.abs(winding_numbers(p, t, x[:500])) > 0.5):
                    raise MeshError(f"{names[a]} and {names[b]} overlap or one holds the other: {advice}")


#: ``--repair auto``'s order, measured over the corpus and the public scans (bench/repair_compare.py): as
#: it is; MeshFix, which keeps nearly all of the geometry when it keeps most of the area; the voxel route,
#: which keeps the union of shells that share walls or run into each other; MeshFix whatever area it keeps
AUTO_ROUTES = (None, "meshfix", "voxel", "meshfix-any-area")


def _remesh_auto(raw, tris, path, edge_length, angle_deg, report, xi_of_all):
    """``--repair auto``: the routes of :data:`AUTO_ROUTES` in turn until one gives a volume mesh; the report
    says which, what each before it ran into, and what the result did to the input's geometry (Hausdorff
    distance to the input surface as given, area and volume kept).  All failing, one line lists every
    route's reason: no advice that was already followed."""
    tried = []
    for route in AUTO_ROUTES:
        if route == "meshfix-any-area" and not any(r == "meshfix" and why.startswith("kept only") for r, why in tried):
            continue  # only where MeshFix worked but was passed over for the area it dropped
        sub = {} if report is not None else None
        try:
            if route == "meshfix":  # a MeshFix that drops much of the area is worse than the voxel route's union
                fixed_p, fixed_t, fixed = repair_surface(raw, tris, path, warn=False)
                kept = fixed["after"]["area"] / max(fixed["before"]["area"], 1e-300)
                if kept < 1 - REPAIR_AREA_WARN:
                    tried.append(("meshfix", f"kept only {100 * kept:.0f} % of the area (the largest shell)"))
                    continue
            out = _remesh_route(raw, tris, "meshfix" if route == "meshfix-any-area" else route, path, edge_length,
                                angle_deg, sub, xi_of_all)
        except SeveralBodiesError:
            raise  # which body is the organ is the user's to say (--shell), not a repair's to guess
        except MeshError as exc:
            tried.append((route or "as it is", _cause(str(exc).replace(f"{path}: ", ""))))
            continue
        points, tets = out
        if report is not None:
            report.update(sub)
            report["auto"] = {"route": route or "none", "tried": [f"{r}: {why}" for r, why in tried],
                              **input_change(raw, tris, points, tets, edge_length)}
        log.warning("%s: --repair auto: %s%s", path, f"route {route}" if route else "no repair needed",
                    "".join(f"; {r} was not used ({why})" for r, why in tried))
        return points, tets
    raise MeshError(f"{path}: --repair auto tried every route and none gave a solid: "
                    + "; ".join(f"{r}: {why}" for r, why in tried)
                    + ". What is left: a smaller --edge-length (thin parts need several elements across; the voxel "
                      "route's voxels follow it), or mending the file in a mesh tool")


def _cause(message: str) -> str:
    """A refusal without its advice to try a repair route (``--repair auto`` has tried them all)."""
    import re

    kept = []
    for part in message.split("; "):
        part = re.sub(r"^--repair \w+: ", "", part)
        part = re.sub(r",? or try --repair( \w+)?", "", part)
        if not re.search(r"\btry --repair", part):
            kept.append(part)
    return "; ".join(kept) if kept else message


def input_change(raw, tris, points, tets, edge_length: float) -> dict:
    """What a repaired, remeshed body did to the surface as given (which may be open, overlapping or carry
    debris): the symmetric Hausdorff distance between the two (:func:`geometry_change`'s sampling) and the
    share of the input's area the new surface has.  No volume: an open input encloses none."""
    from pmask.precompute.surface import boundary_surface

    t_in = np.asarray(tris, np.int64)
    d = geometry_change(raw, t_in, points, tets, edge_length, volume=False)
    v, t_out = boundary_surface(points, tets)
    area_in = float(triangle_areas(raw, t_in).sum())
    return {"hausdorff_to_input_m": d["hausdorff_m"],
            "area_kept": float(triangle_areas(points[v], t_out).sum()) / max(area_in, 1e-300)}


def _remesh_route(raw, tris, repair, path, edge_length, angle_deg, report, xi_of_all):
    """One route: repair (None, "meshfix" or "voxel"), the surface checks, gmsh; (points, tets)."""
    if repair:
        if repair == "voxel":
            from pmask.precompute.voxel import voxel_repair

            raw, tris, fixed = voxel_repair(raw, tris, edge_length, path)
        else:
            raw, tris, fixed = repair_surface(raw, tris, path)
        if report is not None:
            report["repair"] = fixed
    cavities, inner = [], []
    if not repair:  # a hollow organ as it is: its cavities are meshed as such (a repair route would fill them)
        raw, tris, inner = split_cavities(raw, tris, path)
    try:
        pts, tris = check_surface(raw, tris, str(path))
    except MeshError as exc:
        if not repair or isinstance(exc, SeveralBodiesError):
            raise
        # never advise the route that has just run (a printed heart was told "try --repair" after it)
        other = "voxel" if repair != "voxel" else "meshfix"
        raise MeshError(f"{_cause(str(exc))}; this is after --repair {repair}: try --repair {other}, or mend the "
                        "file in a mesh tool") from None
    if inner:
        names = [f"{path}: cavity {k + 1}" for k in range(len(inner))]
        cavities = [check_inner_surface(*check_surface(raw, t, name), (pts, tris), edge_length, name,
                                        "its wall runs into the outer surface; mend the file in a mesh tool")
                    for t, name in zip(inner, names)]
        check_inclusions_apart(cavities, names, "mend the file in a mesh tool")
        log.info("%s: %d cavit%s inside the outer surface: the body is the volume between the walls", path,
                 len(cavities), "y" if len(cavities) == 1 else "ies")
    whole = join_surfaces((pts, tris), *[(p, t[:, ::-1]) for p, t in cavities])  # the walls as the body's surface
    check_size_before_meshing(*whole, edge_length, path, xi_of_all)
    try:
        points, tets = _remesh_with_fallback(pts, tris, path, edge_length, angle_deg, cavities, whole)
    except MeshError as exc:
        if repair == "meshfix" or repair is True:
            raise MeshError(f"{_cause(str(exc))}; this is after --repair meshfix: try --repair voxel or a smaller "
                            "--edge-length") from None
        if repair != "voxel":
            raise
        # the voxel route's surface folds where the body is thinner than about three voxels (the bunny's ears
        # at 2.5 mm edges): say so, instead of the generic advice to try --repair
        from pmask.precompute.voxel import VOXELS_PER_EDGE

        raise MeshError(f"{str(exc).split('; ')[0]}; after --repair voxel this means parts thinner than about three "
                        f"voxels ({3e3 * edge_length / VOXELS_PER_EDGE:.3g} mm) folded: try --repair meshfix "
                        "or a smaller --edge-length") from None
    change = geometry_change(*whole, points, tets, edge_length)
    change["edge_length"] = edge_length_report(*whole, points, tets, edge_length)
    if cavities:
        change["cavities"] = len(cavities)
    if report is not None:
        report.update(change)
    if abs(change["volume_change"]) > VOLUME_CHANGE_WARN or change["hausdorff_m"] > HAUSDORFF_WARN * edge_length:
        log.warning("%s: the remesh moved the surface by up to %.3g mm and changed the volume by %+.1f %%; a smaller "
                    "--edge-length keeps more of the geometry", path, 1e3 * change["hausdorff_m"],
                    100 * change["volume_change"])
    return points, tets


#: gmsh's surface edges fall between 0.5 and 1 of --edge-length: the vertex count is this many times the
#: equilateral estimate 2A / (√3 h²) (measured on remeshed balls: 1.27 and 1.28 at 10 and 7 edges per
#: radius; coarser, curvature adds vertices); pmask inspect's suggestions use it
GMSH_COUNT_FACTOR = 1.28
#: --edge-length honoured: more surface vertices than this times that estimate, or an edge shorter than this
#: share of the target, means the feature edges ruled the mesh
EDGE_COUNT_SLACK, EDGE_SHORTEST = 1.3, 0.3


def expected_surface_vertices(area: float, edge_length: float) -> float:
    """The surface vertices a remesh at ``edge_length`` gives a surface of ``area``: GMSH_COUNT_FACTOR x 2A/(√3 h²)."""
    return GMSH_COUNT_FACTOR * 2.0 * area / (np.sqrt(3.0) * edge_length ** 2)


def edge_length_report(pts, tris, points, tets, edge_length: float) -> dict:
    """How well a remesh honoured ``edge_length``: its surface vertices against the estimate from the input's
    area (:func:`expected_surface_vertices`, pmask inspect's), and its shortest surface edge against h."""
    from pmask.precompute.surface import boundary_surface

    v, t = boundary_surface(points, tets)
    p = points[v]
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    shortest = float(np.linalg.norm(p[e[:, 0]] - p[e[:, 1]], axis=1).min())
    estimate = expected_surface_vertices(float(triangle_areas(pts, tris).sum()), edge_length)
    return {"surface_vertices": int(len(v)), "estimate": estimate, "count_ratio": len(v) / max(estimate, 1e-300),
            "shortest_edge_ratio": shortest / edge_length}


def join_surfaces(*parts) -> tuple[np.ndarray, np.ndarray]:
    """Several triangle surfaces (points, triangles) as one."""
    offsets = np.cumsum([0] + [len(p) for p, _ in parts])
    return (np.vstack([p for p, _ in parts]),
            np.vstack([np.asarray(t, np.int64) + o for (_, t), o in zip(parts, offsets)]))


def _remesh_with_fallback(pts, tris, path, edge_length, angle_deg, cavities=(), whole=None):
    """:func:`_remesh`, again without feature edges where they made the surface unparametrisable or ruled
    the mesh; ``cavities`` (outward (points, triangles) each) are left empty inside the body, ``whole`` being
    the body's surface with their walls (the outer surface alone without cavities)."""
    whole = whole if whole is not None else (pts, tris)
    remesh = lambda angle: _remesh(pts, tris, path, edge_length, angle, cavities=cavities)  # noqa: E731
    try:
        out = remesh(angle_deg)
    except MeshError as exc:
        if angle_deg >= 180.0 or "parametriz" not in str(exc) and "Invalid boundary mesh" not in str(exc):
            raise
        # real organ surfaces have many edges sharper than 40°: classified as features, they cut the surface
        # into patches gmsh cannot parametrise; without feature edges those surfaces remesh (measured on a
        # lung, an XCAT liver and the bunny), at the price of rounding real creases, so this is the fallback
        log.warning("%s: classifying at %g° gave patches gmsh cannot parametrise; retrying without feature edges",
                    path, angle_deg)
        return remesh(180.0)
    if angle_deg >= 180.0:
        return out
    # the feature edges may also rule the mesh without failing: a staircase of voxel faces or a lung's many
    # sharp edges kept as curves gave 2.2x the vertices --edge-length asks for and 0.055 mm edges at 10 mm;
    # then the surface is remeshed without feature edges, which honours the length
    got = edge_length_report(*whole, *out, edge_length)
    if got["count_ratio"] <= EDGE_COUNT_SLACK and got["shortest_edge_ratio"] >= EDGE_SHORTEST:
        return out
    log.warning("%s: with the edges sharper than %g° kept as features the mesh has %.1fx the surface vertices "
                "--edge-length asks for and edges down to %.2g of it; remeshing without feature edges (real creases "
                "are rounded)", path, angle_deg, got["count_ratio"], got["shortest_edge_ratio"])
    try:
        return remesh(180.0)
    except MeshError:
        return out  # the feature-edge mesh is valid, only finer than asked


def surface_distance(x: np.ndarray, p: np.ndarray, t: np.ndarray, candidates: int = 16) -> np.ndarray:
    """Distance from each point of ``x`` to the triangle surface (p, t): the exact distance (trimesh's
    vectorised closest point on a triangle) to each of the ``candidates`` triangles whose centroids are
    nearest, the smallest of them."""
    from scipy.spatial import cKDTree
    from trimesh.triangles import closest_point

    k = min(candidates, len(t))
    _, idx = cKDTree(p[t].mean(axis=1)).query(x, k=k)
    idx = idx.reshape(len(x), k)
    out = np.empty(len(x))
    for s0 in range(0, len(x), 20_000):  # bounded memory: 20,000 x k triangle-point pairs at a time
        s1 = min(s0 + 20_000, len(x))
        q = np.repeat(x[s0:s1], k, axis=0)
        c = closest_point(p[t[idx[s0:s1].ravel()]], q)
        out[s0:s1] = np.linalg.norm(c - q, axis=1).reshape(s1 - s0, k).min(axis=1)
    return out


#: the remesh is reported in every case and warned about beyond these (a coarse --edge-length cut an
#: ellipsoid's poles by 7 % of its size and its volume by 10.6 %)
VOLUME_CHANGE_WARN = 0.02
HAUSDORFF_WARN = 0.5  # x the edge length


def geometry_change(p_in, t_in, points, tets, edge_length: float, seed: int = 0, volume: bool = True) -> dict:
    """How far the remeshed boundary lies from the input surface: the symmetric Hausdorff distance, as the
    largest exact point-to-surface distance over area-uniform samples of each surface (~edge/10 apart, so
    it is short of the true one by at most about that spacing), and the relative change of the volume."""
    from pmask.precompute.surface import boundary_surface

    v, t_out = boundary_surface(points, tets)
    p_out = points[v]
    spacing = 0.1 * edge_length
    rng = np.random.default_rng(seed)

    def sample(p, t):
        tri = p[t]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        n = int(min(200_000, max(1000, area.sum() / spacing ** 2)))
        k = rng.choice(len(t), n, p=area / area.sum())
        a, b = rng.random(n), rng.random(n)
        flip = a + b > 1
        a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
        return np.vstack([p, tri[k, 0] + a[:, None] * (tri[k, 1] - tri[k, 0]) + b[:, None] * (tri[k, 2] - tri[k, 0])])

    d1 = surface_distance(sample(p_out, t_out), p_in, t_in).max()
    d2 = surface_distance(sample(p_in, t_in), p_out, t_out).max()
    if not volume:  # an open or overlapping input encloses no volume to compare with
        return {"hausdorff_m": float(max(d1, d2)), "sample_spacing_m": spacing}
    vol_in = enclosed_volume(p_in, t_in)
    vol_out = float(np.abs(signed_volumes(points, tets)).sum())
    return {"hausdorff_m": float(max(d1, d2)), "volume_change": vol_out / vol_in - 1.0, "sample_spacing_m": spacing}


def _remesh(pts, tris, path, edge_length, angle_deg, inclusions=(), cavities=()):
    """gmsh: classify and parametrise the surface(s), mesh the volume.  With ``inclusions`` (closed surfaces
    inside, (points, tris) each) the body is the volume between the outer loop and theirs and each inclusion a
    volume of its own on the same surface mesh; returns (points, tets, label) then, label 0 the body.
    ``cavities`` (closed surfaces inside, facing out of the cavity) are holes in the body: its volume lies
    between the outer loop and theirs, and nothing is meshed inside them (gmsh tutorial t2's volume with a
    hole: a volume of several surface loops, the first the outer)."""
    with gmsh_session("remesh") as gmsh:
        parts = [(pts, tris), *inclusions, *cavities]
        offset = 0
        for p, t in parts:
            s = gmsh.model.addDiscreteEntity(2)
            gmsh.model.mesh.addNodes(2, s, np.arange(offset + 1, offset + len(p) + 1), p.ravel())
            gmsh.model.mesh.addElementsByType(s, 2, [], (np.asarray(t) + 1 + offset).ravel())
            offset += len(p)
        gmsh.model.mesh.classifySurfaces(np.deg2rad(angle_deg), True, True, np.pi)
        try:
            gmsh.model.mesh.createGeometry()
        except Exception as exc:  # gmsh raises a bare Exception ("Wrong topology of boundary mesh for parametrization")
            raise MeshError(f"{path}: gmsh could not build a parametrisable geometry from this surface ({exc}); "
                            "repair or smooth it, or try another --edge-length") from exc
        surfaces = [e[1] for e in gmsh.model.getEntities(2)]
        if len(parts) == 1:
            loop = gmsh.model.geo.addSurfaceLoop(surfaces)
            gmsh.model.geo.addVolume([loop])
        else:  # which input each classified patch came from: the one its nodes lie on
            owner = {}
            for s in surfaces:
                x = gmsh.model.mesh.getNodes(2, s, includeBoundary=True)[1].reshape(-1, 3)[:8]
                owner[s] = int(np.argmin([surface_distance(x, p, np.asarray(t)).max() for p, t in parts]))
            loops = [gmsh.model.geo.addSurfaceLoop([s for s in surfaces if owner[s] == k]) for k in range(len(parts))]
            volumes = [gmsh.model.geo.addVolume(loops)] + [gmsh.model.geo.addVolume([lp])
                                                           for lp in loops[1:1 + len(inclusions)]]
        gmsh.model.geo.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMin", 0.5 * edge_length)
        gmsh.option.setNumber("Mesh.MeshSizeMax", edge_length)
        gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
        try:
            gmsh.model.mesh.generate(3)
        except Exception as exc:
            if "intersect" in str(exc):
                raise MeshError(f"{path}: the surface intersects itself (gmsh: {exc}); repair it so that no "
                                "triangles cross (e.g. remove overlapping parts), or try --repair") from exc
            raise MeshError(f"{path}: gmsh could not remesh this surface ({exc}); "
                            "check that it is closed and not self-intersecting") from exc
        if len(parts) == 1:
            return tets_from_gmsh(gmsh)
        if not inclusions:  # the body alone (a cavity's own surface mesh has nodes no tetrahedron outside uses)
            return tets_by_volume(gmsh, volumes)[:2]
        return tets_by_volume(gmsh, volumes)


def tets_by_volume(gmsh, volumes):
    """(points, tets, label) of the current gmsh model, label k for the tets of ``volumes[k]``."""
    tags, coords, _ = gmsh.model.mesh.getNodes()
    order = np.argsort(tags)
    tags, coords = tags[order], coords.reshape(-1, 3)[order]
    tets, label = [], []
    for k, v in enumerate(volumes):
        types, _, nodes = gmsh.model.mesh.getElements(3, v)
        t = [nt.reshape(-1, 4) for ty, nt in zip(types, nodes) if ty == 4]
        if not t:
            raise MeshError("gmsh produced no tetrahedra in an inclusion or the body around it: is it thicker "
                            "than an element and free of self-intersections?")
        tets.append(np.searchsorted(tags, np.concatenate(t)))
        label.append(np.full(len(tets[-1]), k, np.int64))
    points, tets, _ = compact(coords, np.vstack(tets))
    return points, tets, np.concatenate(label)


def stl_damage(path, lead: str = "") -> str:
    """What is wrong with a damaged STL file, from its size and header ("" when nothing is found)."""
    path = Path(path)
    if path.suffix.lower() != ".stl" or not path.is_file():
        return ""
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(84)
    if head[:5].lower() == b"solid" and b"\0" not in head[:80]:
        return f"{lead}an ASCII STL that ends early or is malformed: re-export it"
    if size < 84:
        return f"{lead}an STL of {size} bytes, shorter than a binary STL's 84-byte header: truncated, re-export it"
    n = int.from_bytes(head[80:84], "little")
    if 84 + 50 * n != size:
        return (f"{lead}a binary STL whose header counts {n} triangles ({84 + 50 * n} bytes) in a file of {size} "
                "bytes: truncated or miscounted, re-export it")
    return ""


def read_mesh_file(path):
    """meshio.read with one clear line for a file it cannot read (its STL reader prints and exits)."""
    import contextlib
    import io
    import warnings

    import meshio

    try:
        quiet = io.StringIO()  # meshio's STL reader prints its failure before exiting
        with warnings.catch_warnings(), contextlib.redirect_stdout(quiet), contextlib.redirect_stderr(quiet):
            warnings.simplefilter("ignore", RuntimeWarning)  # meshio's STL format sniffing overflows harmlessly
            return meshio.read(path)
    except (Exception, SystemExit) as exc:  # meshio raises several types for unreadable files, and SystemExit
        why = stl_damage(path) or (str(exc) if str(exc) not in ("", "1") else type(exc).__name__)
        raise MeshError(f"{path}: cannot read this file as a triangle surface ({why})") from None


def triangle_blocks(m) -> list:
    """A meshio mesh's triangles, its quadrilaterals (OBJ, PLY exports) as two triangles each."""
    quads = [c.data for c in m.cells if c.type == "quad"]
    return ([c.data for c in m.cells if c.type == "triangle"] + [q[:, [0, 1, 2]] for q in quads]
            + [q[:, [0, 2, 3]] for q in quads])


#: the last surface :func:`read_surface_file` parsed, (points as in the file, triangles) by the file's suffix
#: and the digest of its bytes: a run reads its ``--surface`` for the checks, the remesh and the display
#: surface, and meshio parsed a 327,680-triangle ASCII STL (98 MB) in 7-13 s each time, where its digest took
#: 0.09-0.19 s (SHA-256, by hand)
_READ: dict = {}


def file_digest(path) -> str:
    """The SHA-256 of a file's bytes (hex): an input's identity in the stage keys, and a parse's here."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _file_key(path) -> str:
    return f"{Path(path).suffix.lower()} {file_digest(path)}"  # the suffix too: it picks meshio's reader


def read_surface_file(path, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A triangle surface file as (points in metres, triangles), its face indices and coordinates checked:
    one line for a file without triangles, an index past the vertices, or a non-finite coordinate.  A file
    whose bytes are those of the last one parsed is not parsed again."""
    try:
        key = _file_key(path)
    except OSError:
        key = None  # the reader says what is wrong with the path
    if key in _READ:
        raw, tris = _READ[key]
        return raw * scale, tris.copy()
    raw, tris = _parse_surface_file(path)
    if key is not None:
        _READ.clear()  # one file kept: a run has one --surface (its inclusions are small)
        _READ[key] = (raw, tris)
    return raw * scale, tris.copy()


def save_surface_read(path, folder: Path) -> dict:
    """The job entry that hands :func:`read_surface_file`'s last read of ``path`` to a remesh worker (the file
    as parsed, in an .npz in ``folder``), so that it does not parse the file again; {} when it was not read."""
    try:
        key = _file_key(path)
    except OSError:
        return {}
    if key not in _READ:
        return {}
    raw, tris = _READ[key]
    np.savez(folder / "surface.npz", points=raw, triangles=tris)
    return {"surface_read": str(folder / "surface.npz"), "surface_key": key}


def _load_surface_read(job: dict) -> None:
    """A remesh worker's side of :func:`save_surface_read`: the parent's read, for the same unchanged file."""
    if "surface_read" in job:
        with np.load(job["surface_read"]) as z:
            _READ.clear()
            _READ[job["surface_key"]] = (z["points"], z["triangles"])


def _parse_surface_file(path) -> tuple[np.ndarray, np.ndarray]:
    """:func:`read_surface_file`'s parse: (points as in the file, triangles)."""
    m = read_mesh_file(path)
    blocks = triangle_blocks(m)
    if len(m.points) == 0 or not blocks:
        raise MeshError(f"{path}: no triangles in this file (cell types: {sorted({c.type for c in m.cells}) or 'none'}"
                        f"{stl_damage(path, '; ')}); give a closed triangle surface (STL, OBJ, PLY, ...)")
    check_face_indices(blocks, len(m.points), path)
    raw = np.asarray(m.points, float).reshape(len(m.points), -1)[:, :3]
    check_finite(raw, path)
    return raw, np.concatenate(blocks).astype(np.int64)


def check_face_indices(blocks, n_points: int, path) -> None:
    """Every face's vertex index within the file's vertices (an OBJ face naming a missing vertex)."""
    for b in blocks:
        b = np.asarray(b)
        if b.size and (b.min() < 0 or b.max() >= n_points):
            bad = int(b.max()) if b.max() >= n_points else int(b.min())
            raise MeshError(f"{path}: a face refers to vertex {bad + 1} (counting from 1), but the file has "
                            f"{n_points} vertices: the file is damaged or truncated; re-export it")


def read_volume(path: Path, *, scale: float = 1.0, with_regions: bool = False):
    """Read a tetrahedral mesh (.msh, .vtu, ...) with meshio.

    Returns (points, tets, groups) where ``groups`` maps a physical group name
    to the boolean mask of the points its elements touch; ``with_regions`` adds
    the physical volumes as boolean masks over the tetrahedra.
    """
    import meshio

    try:
        m = meshio.read(path)
    except Exception as exc:
        raise MeshError(f"{path}: cannot read this file as a volume mesh ({exc})") from exc
    blocks = [c.data for c in m.cells if c.type == "tetra"]
    if not blocks:
        raise MeshError(f"{path}: the file has no tetrahedra (cell types: "
                        f"{sorted({c.type for c in m.cells})}); --volume needs a linear tet mesh")
    tets = np.concatenate(blocks).astype(np.int64)
    points = np.asarray(m.points, float)[:, :3] * scale
    check_finite(points, path)
    vol = signed_volumes(points, tets)
    degenerate = np.abs(vol) <= 1e-12 * np.abs(vol).max()
    if np.any(degenerate):
        raise MeshError(f"{path}: {int(degenerate.sum())} tetrahedra have zero volume; repair or remesh the volume")
    n_neg = int(np.sum(vol < 0))
    if 0 < n_neg < len(vol):
        raise MeshError(f"{path}: {n_neg} of {len(vol)} tetrahedra are inverted (opposite orientation to the rest); "
                        "repair the mesh (e.g. re-export it from the mesher)")
    groups: dict[str, np.ndarray] = {}
    regions: dict[str, np.ndarray] = {}  # physical volumes: masks over the tetrahedra (materials by region)
    offsets = np.cumsum([0] + [len(c.data) if c.type == "tetra" else 0 for c in m.cells])
    for name, sets in (m.cell_sets or {}).items():
        if name.startswith("gmsh:"):
            continue
        mask = np.zeros(len(points), bool)
        tmask = np.zeros(len(tets), bool)
        for k, (cells, ids) in enumerate(zip(m.cells, sets)):
            if ids is not None and len(ids):
                mask[np.asarray(cells.data)[ids].ravel()] = True
                if cells.type == "tetra":
                    tmask[offsets[k] + np.asarray(ids, np.int64)] = True
        groups[name] = mask
        if tmask.any():
            regions[name] = tmask
    points, tets, used = compact(points, tets)
    groups = {k: v[used] for k, v in groups.items()}
    check_volume_quality(points, tets, path)
    if with_regions:
        return points, tets, groups, regions
    return points, tets, groups


#: a user's tet mesh is warned about beyond these: edge lengths spread more than this factor (5th to 95th
#: percentile), or tetrahedra flatter than this radius ratio (3 r_in / r_circ: 1 regular, 0 flat)
EDGE_SPREAD_WARN = 20.0
RADIUS_RATIO_WARN = 0.05


def volume_quality(points: np.ndarray, tets: np.ndarray) -> dict:
    """Edge-length spread and the worst radius ratio 3 r_in / r_circ of a tetrahedral mesh."""
    p = points[tets]
    pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    edges = np.stack([np.linalg.norm(p[:, i] - p[:, j], axis=1) for i, j in pairs], axis=1)
    vol = np.abs(signed_volumes(points, tets))
    faces = [(1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2)]
    area = sum(0.5 * np.linalg.norm(np.cross(p[:, b] - p[:, a], p[:, c] - p[:, a]), axis=1) for a, b, c in faces)
    r_in = 3.0 * vol / area
    # circumradius: R = sqrt((aA+bB+cC)(aA+bB-cC)(aA-bB+cC)(-aA+bB+cC)) / (24 V), products of opposite edges
    a, b, c = edges[:, 0] * edges[:, 5], edges[:, 1] * edges[:, 4], edges[:, 2] * edges[:, 3]
    prod = np.clip((a + b + c) * (a + b - c) * (a - b + c) * (-a + b + c), 0.0, None)
    r_circ = np.sqrt(prod) / (24.0 * np.maximum(vol, 1e-300))
    ratio = 3.0 * r_in / np.maximum(r_circ, 1e-300)
    lo, hi = np.percentile(edges, [5, 95])
    return {"edge_p5": float(lo), "edge_p95": float(hi), "edge_spread": float(hi / lo),
            "worst_radius_ratio": float(ratio.min()), "flat_tets": int(np.sum(ratio < RADIUS_RATIO_WARN))}


def check_volume_quality(points, tets, name) -> dict:
    """Warn about a --volume mesh whose elements will make the Green's functions poor (a mesh with 0.4-61 mm
    edges passed silently and gave K_i asymmetries up to 99 %)."""
    q = volume_quality(points, tets)
    if q["edge_spread"] > EDGE_SPREAD_WARN or q["flat_tets"]:
        log.warning("%s: a poor volume mesh for Green's functions: edge lengths from %.3g to %.3g mm (5th-95th "
                    "percentile, x%.0f), %d tetrahedra flatter than radius ratio %g (worst %.3g); remesh it more "
                    "evenly (or give the surface with --surface and --edge-length)", name, 1e3 * q["edge_p5"],
                    1e3 * q["edge_p95"], q["edge_spread"], q["flat_tets"], RADIUS_RATIO_WARN,
                    q["worst_radius_ratio"])
    return q


if __name__ == "__main__":
    import sys

    # run the importable module's worker, not this __main__ copy's: otherwise a MeshError raised by a module
    # that imports pmask.precompute.meshing (the voxel repair, label images) is another class than the one
    # caught here, and a user's mistake would be reported as our bug
    from pmask.precompute import meshing

    sys.exit(meshing._worker(sys.argv[1:]))
