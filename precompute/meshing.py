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

log = logging.getLogger(__name__)


class MeshError(InputError):
    """Raised for geometry that cannot be meshed or used (says what to fix)."""


@contextlib.contextmanager
def gmsh_session(name: str = "pmask"):
    """Initialise gmsh quietly and reproducibly; always finalise."""
    import gmsh

    if gmsh.isInitialized():
        gmsh.finalize()
    gmsh.initialize(interruptible=False, readConfigFiles=False)
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


def check_surface(points: np.ndarray, triangles: np.ndarray, name: str = "surface") -> tuple[np.ndarray, np.ndarray]:
    """Refuse a triangle surface that cannot bound a solid; return it with duplicate vertices merged.

    Checks, each with a message that says what to fix: at least one triangle, no
    degenerate triangles, closed (every edge in two triangles), manifold (no edge in
    more than two), consistently oriented, and oriented outwards (positive volume).
    Self-intersections are found by gmsh when it meshes the volume.
    """
    if triangles is None or len(triangles) == 0:
        raise MeshError(f"{name}: no triangles; give a closed triangle surface (STL, OBJ, PLY, ...)")
    pts, inverse = np.unique(np.asarray(points, float), axis=0, return_inverse=True)
    tris = inverse.ravel()[np.asarray(triangles, np.int64)]
    bad = (tris[:, 0] == tris[:, 1]) | (tris[:, 1] == tris[:, 2]) | (tris[:, 0] == tris[:, 2])
    if np.any(bad):
        raise MeshError(f"{name}: {int(bad.sum())} degenerate triangles (repeated vertices); clean the surface")
    directed = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    undirected, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    if np.any(counts == 1):
        raise MeshError(f"{name}: the surface is open ({int(np.sum(counts == 1))} boundary edges); "
                        "close its holes (e.g. 'fill holes' in your segmentation or mesh tool)")
    if np.any(counts > 2):
        raise MeshError(f"{name}: the surface is not manifold ({int(np.sum(counts > 2))} edges shared by more "
                        "than two triangles); separate the touching parts")
    if len(np.unique(directed, axis=0)) != len(directed):
        raise MeshError(f"{name}: triangle orientation is inconsistent (some neighbours face opposite ways); "
                        "re-orient the triangles consistently (e.g. trimesh.repair.fix_winding)")
    p = pts[tris]
    volume = np.einsum("ij,ij->i", np.cross(p[:, 0], p[:, 1]), p[:, 2]).sum() / 6.0
    if volume < 0:
        raise MeshError(f"{name}: the surface is inverted (normals point inwards, volume {volume:.3g}); "
                        "flip the triangle orientation")
    return pts, tris


def remesh_surface(path: Path, *, edge_length: float, scale: float = 1.0, angle_deg: float = 40.0):
    """Remesh a (possibly very fine) triangle surface file to a target edge length.

    Follows gmsh tutorial t13: classify the triangles into patches, build a
    parametrisable geometry from them, then mesh it anew at ``edge_length``
    (in metres, after ``scale`` is applied).  Returns (points, tets) of the
    volume inside.
    """
    import warnings

    import meshio

    if not (np.isfinite(edge_length) and edge_length > 0):
        raise MeshError(f"the target edge length must be > 0, got {edge_length}")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # meshio's STL format sniffing overflows harmlessly
            m = meshio.read(path)
    except Exception as exc:  # meshio raises several types for unreadable files
        raise MeshError(f"{path}: cannot read this file as a triangle surface ({exc})") from exc
    blocks = [c.data for c in m.cells if c.type == "triangle"]
    pts, tris = check_surface(np.asarray(m.points, float)[:, :3] * scale,
                              np.concatenate(blocks) if blocks else None, str(path))
    with gmsh_session("remesh") as gmsh:
        s = gmsh.model.addDiscreteEntity(2)
        gmsh.model.mesh.addNodes(2, s, np.arange(1, len(pts) + 1), pts.ravel())
        gmsh.model.mesh.addElementsByType(s, 2, [], (tris + 1).ravel())
        gmsh.model.mesh.classifySurfaces(np.deg2rad(angle_deg), True, True, np.pi)
        gmsh.model.mesh.createGeometry()
        surfaces = [e[1] for e in gmsh.model.getEntities(2)]
        loop = gmsh.model.geo.addSurfaceLoop(surfaces)
        gmsh.model.geo.addVolume([loop])
        gmsh.model.geo.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMin", 0.5 * edge_length)
        gmsh.option.setNumber("Mesh.MeshSizeMax", edge_length)
        gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
        try:
            gmsh.model.mesh.generate(3)
        except Exception as exc:
            if "intersect" in str(exc):
                raise MeshError(f"{path}: the surface intersects itself (gmsh: {exc}); repair it so that no "
                                "triangles cross (e.g. remove overlapping parts)") from exc
            raise MeshError(f"{path}: gmsh could not remesh this surface ({exc}); "
                            "check that it is closed and not self-intersecting") from exc
        return tets_from_gmsh(gmsh)


def read_volume(path: Path, *, scale: float = 1.0):
    """Read a tetrahedral mesh (.msh, .vtu, ...) with meshio.

    Returns (points, tets, groups) where ``groups`` maps a physical group name
    to the boolean mask of the points its elements touch.
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
    vol = signed_volumes(points, tets)
    degenerate = np.abs(vol) <= 1e-12 * np.abs(vol).max()
    if np.any(degenerate):
        raise MeshError(f"{path}: {int(degenerate.sum())} tetrahedra have zero volume; repair or remesh the volume")
    n_neg = int(np.sum(vol < 0))
    if 0 < n_neg < len(vol):
        raise MeshError(f"{path}: {n_neg} of {len(vol)} tetrahedra are inverted (opposite orientation to the rest); "
                        "repair the mesh (e.g. re-export it from the mesher)")
    groups: dict[str, np.ndarray] = {}
    for name, sets in (m.cell_sets or {}).items():
        if name.startswith("gmsh:"):
            continue
        mask = np.zeros(len(points), bool)
        for cells, ids in zip(m.cells, sets):
            if ids is not None and len(ids):
                mask[np.asarray(cells.data)[ids].ravel()] = True
        groups[name] = mask
    points, tets, used = compact(points, tets)
    groups = {k: v[used] for k, v in groups.items()}
    return points, tets, groups
