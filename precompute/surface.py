"""The boundary surface of a tetrahedral mesh."""
from __future__ import annotations

import numpy as np

from pmask.precompute.meshing import MeshError
from pmask.runtime.geometry import unique_rows


def boundary_surface(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boundary triangles of a positively oriented tet mesh.

    Returns ``(surface_vertices, triangles)``: the volume indices of the
    boundary vertices (sorted) and the boundary triangles as indices into
    ``surface_vertices``, ordered counter-clockwise seen from outside.
    Raises :class:`MeshError` when a face is shared by more than two tets
    (a non-manifold volume) or the boundary is not a closed 2-manifold.
    """
    # faces opposite each vertex, ordered so that the normal points out of the tet
    faces = np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]])
    key = np.sort(faces, axis=1)
    _, inverse, counts = unique_rows(key, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    if np.any(counts > 2):
        raise MeshError(f"{int(np.sum(counts > 2))} faces are shared by more than two tetrahedra: "
                        "the volume mesh is not manifold; remesh it")
    tris = faces[counts[inverse] == 1]
    if len(tris) == 0:
        raise MeshError("the volume mesh has no boundary faces")
    surface_vertices, local = np.unique(tris, return_inverse=True)
    triangles = local.reshape(-1, 3)
    # every boundary edge must be shared by exactly two boundary triangles
    e = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    _, ecount = unique_rows(e, return_counts=True)
    if np.any(ecount != 2):
        raise MeshError(f"the boundary surface has {int(np.sum(ecount != 2))} edges not shared by exactly two "
                        "triangles (open or non-manifold boundary); remesh the volume")
    return surface_vertices, triangles


def cavity_names(n: int) -> list[str]:
    """The groups a hollow body's cavity walls become: "cavity", or "cavity1", "cavity2", ... (largest first)."""
    return ["cavity"] if n == 1 else [f"cavity{k + 1}" for k in range(n)]


def cavity_walls(points: np.ndarray, triangles: np.ndarray) -> list[np.ndarray]:
    """The walls of a hollow body's cavities (a bladder's or a stomach's lumen), as bool masks over the
    surface vertices, largest first: the connected pieces of the boundary surface other than the outer one
    (the largest by area) whose bounding box lies inside the outer one's.  A single tetrahedral body's
    boundary pieces are its outer surface and the walls of its holes; [] for a solid body."""
    from pmask.runtime.geometry import surface_pieces, triangle_areas

    label = surface_pieces(len(points), triangles)
    if np.all(label == label[0]):
        return []
    area = np.bincount(label[triangles[:, 0]], triangle_areas(points, triangles), minlength=len(points))
    outer = int(np.argmax(area))
    lo, hi = points[label == outer].min(axis=0), points[label == outer].max(axis=0)
    walls = [k for k in np.argsort(-area) if k != outer and area[k] > 0
             and np.all(points[label == k].min(axis=0) >= lo) and np.all(points[label == k].max(axis=0) <= hi)]
    return [label == k for k in walls]
