"""Half-space stand-in: a solid hemisphere loaded at the centre of its flat face.

The flat face is z = 0 (outward normal +z), the hemisphere of radius
``R = far * load_radius`` lies below it and is fixed on its curved far surface
(physical group ``far``).  A Distance + Threshold size field keeps the edge
length ``h_load`` within ``fine`` x r of the load point (the origin) and lets
it grow by ``grading`` per unit distance up to R / 5: a gentle, geometric
grading matters as much as h itself (measured: with sizes growing 0.44 per
unit distance the cone stiffness was 8 % high at h = r/8, with 0.2 it was
6 %).  The body is large enough (far >= 30) to act as a half-space: the far
support stiffens the centre by about 1 %.  The contact region is the disc of
radius ``0.25 h_load`` around the origin (the load vertex itself), widened by
r_max = 1.05 r so that masks up to the load radius are complete: Ξ stays small
(paper §2.3: Green's functions only where boundary values change) while the
volume mesh is large.
"""
from __future__ import annotations

import numpy as np

from pmask.errors import InputError

from pmask.meshes.common import ModelMesh
from pmask.precompute.meshing import gmsh_session, tets_from_gmsh

LOAD_RADIUS = 0.01  # m, the mask radius r the analytic checks use


def build(load_radius: float = LOAD_RADIUS, h_load: float | None = None, far: float = 30.0,
          E: float = 1.0e4, nu: float = 0.3, fine: float = 1.0, grading: float = 0.2) -> ModelMesh:
    """Mesh the hemisphere; ``h_load`` is the edge length within ``fine`` x r of the load point
    (default r/8); beyond, sizes grow by ``grading`` per unit distance up to R/5."""
    r = float(load_radius)
    h = float(h_load) if h_load is not None else r / 8
    if not (r > 0 and h > 0 and far >= 2 and fine > 0 and grading > 0):
        raise InputError("halfspace: load_radius, h_load, fine and grading must be > 0 and far >= 2")
    R = far * r
    with gmsh_session("halfspace") as gmsh:
        occ = gmsh.model.occ
        ball = occ.addSphere(0, 0, 0, R)
        box = occ.addBox(-2 * R, -2 * R, 0, 4 * R, 4 * R, 2 * R)
        out, _ = occ.cut([(3, ball)], [(3, box)])
        centre = occ.addPoint(0, 0, 0)
        occ.synchronize()
        vol = [t for d, t in out if d == 3]
        flat = [t for d, t in gmsh.model.getBoundary([(3, v) for v in vol], oriented=False)
                if gmsh.model.getBoundingBox(2, t)[2] > -1e-3 * R]
        curved = [t for d, t in gmsh.model.getBoundary([(3, v) for v in vol], oriented=False) if t not in flat]
        gmsh.model.mesh.embed(0, [centre], 2, flat[0])
        gmsh.model.addPhysicalGroup(2, curved, name="far")
        fd = gmsh.model.mesh.field.add("Distance")
        gmsh.model.mesh.field.setNumbers(fd, "PointsList", [centre])
        th = gmsh.model.mesh.field.add("Threshold")
        gmsh.model.mesh.field.setNumber(th, "InField", fd)
        gmsh.model.mesh.field.setNumber(th, "SizeMin", h)
        gmsh.model.mesh.field.setNumber(th, "SizeMax", R / 5)
        gmsh.model.mesh.field.setNumber(th, "DistMin", fine * r)
        gmsh.model.mesh.field.setNumber(th, "DistMax", fine * r + (R / 5 - h) / grading)
        gmsh.model.mesh.field.setAsBackgroundMesh(th)
        for opt in ("Mesh.MeshSizeFromPoints", "Mesh.MeshSizeFromCurvature", "Mesh.MeshSizeExtendFromBoundary"):
            gmsh.option.setNumber(opt, 0)
        gmsh.model.mesh.generate(3)
        far_tags = np.unique(np.concatenate(
            [gmsh.model.mesh.getNodes(2, s, includeBoundary=True)[0] for s in curved]))
        points, tets, tags = tets_from_gmsh(gmsh, with_tags=True)
    far_mask = np.isin(tags, far_tags) & (points[:, 2] < -1e-9 * R)  # the rim stays free
    return ModelMesh(points=points, tets=tets, fixed="group:far", contact=f"sphere:0,0,0,{0.25 * h!r}",
                     material={"E": float(E), "nu": float(nu)}, groups={"far": far_mask},
                     info={"load_radius_m": r, "h_load_m": h, "hemisphere_radius_m": R, "r_max_m": 1.05 * r},
                     )
