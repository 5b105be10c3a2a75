"""Palpation block: a block of soft tissue with a stiffer spherical mass under its upper face (#26).

A 60 x 40 x 30 mm block (upper face z = 0), held on its lower face, with a ball of radius ``radius`` whose
centre is ``depth`` below the upper face, meshed conformally by gmsh (OCC fragment: the ball's surface an
interface inside the volume, its tetrahedra the region ``inclusion``, the rest ``tissue``).  Tissue
E = 10 kPa, ν = 0.45; the mass ``contrast`` times stiffer (default 10x), the same ν; ``--materials`` overrides
either.  Pressed from above, the stiffness over the mass rises: the palpation trainer's case.
"""
from __future__ import annotations

import numpy as np

from pmask.errors import InputError
from pmask.meshes.common import ModelMesh
from pmask.precompute.meshing import gmsh_session, tets_by_volume

BLOCK = (0.060, 0.040, 0.030)  # m: x, y, z extents; z from -0.030 to 0


def build(size: float = 0.004, depth: float = 0.010, radius: float = 0.005, contrast: float = 10.0) -> ModelMesh:
    """Mesh the block with largest edge ``size`` [m]; the mass's centre ``depth`` [m] below the upper face."""
    if not size > 0:
        raise InputError(f"palpation: size must be > 0 m, got {size}")
    if not (radius > 0 and depth - radius >= 0.5 * size and depth + radius <= BLOCK[2] - size):
        raise InputError(f"palpation: the mass (radius {radius} m, centre {depth} m deep) must lie inside the block "
                         f"below the upper face, at least half an element ({0.5 * size} m) under it, and clear of "
                         "the support")
    if not contrast > 0:
        raise InputError(f"palpation: contrast must be > 0, got {contrast}")
    with gmsh_session("palpation") as gmsh:
        occ = gmsh.model.occ
        block = occ.addBox(-BLOCK[0] / 2, -BLOCK[1] / 2, -BLOCK[2], *BLOCK)
        ball = occ.addSphere(0.0, 0.0, -depth, radius)
        occ.fragment([(3, block)], [(3, ball)])
        occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        gmsh.model.mesh.generate(3)
        volumes = [v for _, v in gmsh.model.getEntities(3)]
        boxes = [gmsh.model.getBoundingBox(3, v) for v in volumes]
        ball = [k for k, b in enumerate(boxes) if b[3] - b[0] < 2.5 * radius]  # the ball's box, not the block's
        points, tets, label = tets_by_volume(gmsh, volumes)
    inclusion = np.isin(label, ball)
    E, nu = 1.0e4, 0.45
    return ModelMesh(points=points, tets=tets, fixed=f"z<{-BLOCK[2] + 1e-6!r}",
                     material={"E": E, "nu": nu, "regions": {"inclusion": [contrast * E, nu]}},
                     regions={"inclusion": inclusion, "tissue": ~inclusion},
                     info={"block_m": list(BLOCK), "depth_m": depth, "radius_m": radius, "contrast": contrast,
                           "size_m": size})
