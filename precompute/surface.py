"""The boundary surface of a tetrahedral mesh."""
from __future__ import annotations

import numpy as np

from pmask.precompute.meshing import MeshError


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
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
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
    _, ecount = np.unique(e, axis=0, return_counts=True)
    if np.any(ecount != 2):
        raise MeshError(f"the boundary surface has {int(np.sum(ecount != 2))} edges not shared by exactly two "
                        "triangles (open or non-manifold boundary); remesh the volume")
    return surface_vertices, triangles
