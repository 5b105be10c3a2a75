"""``--repair voxel``: a surface rebuilt from the solid it encloses, for inputs no mesh repair can mend.

The triangles are rasterised onto a grid of ``pitch`` (a third of the target edge length): every voxel a
triangle passes through is a shell voxel (the triangles are split until their edges are below half a
voxel, so their vertices mark every voxel they cross).  A morphological closing of the shell (dilate by
:data:`CLOSE_VOXELS`, fill the enclosed space with ``scipy.ndimage.binary_fill_holes``, erode back)
seals holes narrower than about ``2 CLOSE_VOXELS`` voxels, merges touching and intersecting shells into
one solid and ignores orientation altogether; the largest connected solid is kept (debris goes).

The voxels' own boundary would misplace the surface, by 0.6 voxel outwards on average and 0.4-0.85 by
direction (measured on spheres: the shell of a diagonal plane is thicker than an axis-aligned one's).  So the surface is taken where the
exact distance to the input's triangles (KD-tree over the split triangles' vertices) is
:data:`OFFSET_VOXELS` outside the solid, by marching cubes and Taubin smoothing as for label images
(:func:`pmask.precompute.segmentation.mask_surface`), and moved back along its normals by the same
distance: on spheres of 12-60 voxels radius the result lies within 0.07 voxel of the sphere (volume
within 0.6 %; ``tests/test_repair.py``).  The price is resolution: features thinner than about three
voxels vanish or come out thicker, and creases are rounded over a voxel or two.
"""
from __future__ import annotations

import logging

import numpy as np

from pmask.precompute.meshing import MeshError

log = logging.getLogger(__name__)

#: holes up to about twice this many voxels across are sealed by the closing
CLOSE_VOXELS = 2
#: the surface is extracted at this distance outside the input (in voxels) and moved back by it
OFFSET_VOXELS = 1.5
#: voxels per target edge length
VOXELS_PER_EDGE = 3
#: the grid may hold at most this many voxels (masks, labels, two float32 distance fields and the padded
#: copy marching cubes takes: ~20 bytes each, 4 GB at this bound)
MAX_VOXELS = 200_000_000


def voxel_repair(pts: np.ndarray, tris: np.ndarray, edge_length: float, name) -> tuple[np.ndarray, np.ndarray, dict]:
    """Rebuild the surface of the solid enclosed by ``(pts, tris)`` (any defects) at voxel size
    ``edge_length / VOXELS_PER_EDGE``; returns the new points and triangles and a report."""
    import trimesh
    from scipy import ndimage

    from pmask.precompute.segmentation import mask_surface

    used, tris = np.unique(np.asarray(tris, np.int64), return_inverse=True)  # unreferenced vertices mark nothing
    pts, tris = np.asarray(pts, float)[used], tris.reshape(-1, 3)
    pitch = edge_length / VOXELS_PER_EDGE
    lo = pts.min(axis=0) - (CLOSE_VOXELS + 2) * pitch
    shape = np.ceil((pts.max(axis=0) - lo) / pitch).astype(np.int64) + CLOSE_VOXELS + 3
    if np.prod(shape.astype(float)) > MAX_VOXELS:
        raise MeshError(f"{name}: --repair voxel at {1e3 * pitch:.3g} mm voxels needs a {shape[0]}x{shape[1]}x{shape[2]} "
                        "grid, too large for this machine; use a larger --edge-length or --repair meshfix")
    v, f = trimesh.remesh.subdivide_to_size(pts, tris, max_edge=0.5 * pitch, max_iter=20)
    shell = np.zeros(shape, bool)
    idx = np.floor((np.asarray(v) - lo) / pitch).astype(np.int64)
    shell[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    ball = ndimage.generate_binary_structure(3, 1)
    dilated = ndimage.binary_dilation(shell, ball, iterations=CLOSE_VOXELS)
    filled = ndimage.binary_fill_holes(dilated)
    if not np.any(filled & ~dilated):
        raise MeshError(f"{name}: --repair voxel: the surface encloses nothing once holes up to "
                        f"{2 * CLOSE_VOXELS * pitch * 1e3:.3g} mm are closed: its holes are wider, or the body is "
                        f"thinner than the {pitch * 1e3:.3g} mm voxels; close the holes in a mesh tool, use a smaller "
                        "--edge-length, or try --repair meshfix")
    solid = ndimage.binary_erosion(filled, ball, iterations=CLOSE_VOXELS, border_value=0) | (filled & shell)
    labels, n = ndimage.label(solid)
    sizes = np.bincount(labels.ravel())[1:]
    keep = int(np.argmax(sizes)) + 1
    solid = labels == keep
    affine = np.diag([pitch, pitch, pitch, 1.0])
    affine[:3, 3] = lo + 0.5 * pitch  # voxel (i, j, k) holds [lo + i pitch, lo + (i + 1) pitch): its centre
    # the surface at OFFSET_VOXELS outside the input, from exact (sampled) distances to its triangles over
    # the voxels outside the solid: unlike the voxels' own boundary it is the same in every direction
    # (the shell of a diagonal plane is thicker than an axis-aligned one's by up to a voxel)
    from scipy.spatial import cKDTree

    outside = ~solid
    near = outside & ndimage.binary_dilation(solid, ball, iterations=int(np.ceil(OFFSET_VOXELS)) + 2)
    idx_near = np.argwhere(near)
    dist = np.full(solid.shape, OFFSET_VOXELS + 3.0, np.float32)
    dist[solid] = 0.0
    kept = ndimage.binary_dilation(solid, ball, iterations=2)[idx[:, 0], idx[:, 1], idx[:, 2]]  # not the debris
    tree = cKDTree((np.asarray(v)[kept] - lo) / pitch - 0.5)  # sample points in voxel-centre coordinates
    dist[near] = tree.query(idx_near, workers=-1)[0]
    inward = OFFSET_VOXELS + 3.0 - dist  # increasing inwards, as mask_surface expects
    try:
        mesh, _ = mask_surface(solid, affine, field=inward, level=3.0)
        mesh.vertices = mesh.vertices - OFFSET_VOXELS * pitch * mesh.vertex_normals
    except MeshError as exc:
        raise MeshError(f"{name}: --repair voxel: {exc} of {1e3 * pitch:.3g} mm; use a smaller --edge-length "
                        "or --repair meshfix") from None
    report = {"route": "voxel", "voxel": pitch, "grid": [int(s) for s in shape], "solids": int(n),
              "dropped_voxels": int(sizes.sum() - sizes[keep - 1]), "before": {"triangles": int(len(tris))},
              "after": {"vertices": int(len(mesh.vertices)), "triangles": int(len(mesh.faces))}}
    log.warning("%s: --repair voxel: rebuilt from %.3g mm voxels (%d separate solids, the largest kept); %d -> %d "
                "triangles", name, 1e3 * pitch, n, len(tris), len(mesh.faces))
    return np.asarray(mesh.vertices), np.asarray(mesh.faces, np.int64), report
