"""Liver with a mass: a liver-sized lobe held on its flat posterior face, with a stiffer tumour under the
anterior surface (#26, the palpation trainer's organ).

The lobe is an ellipsoid of semi-axes 75 x 50 x 40 mm with the part below z = -15 mm cut off (the flat bare
area where a liver lies on the diaphragm, fixed: ``z<-0.0149``).  The mass is a ball of radius ``radius``
whose centre lies ``depth`` below the upper surface, above the lobe's centre line at ``x = offset``, meshed
conformally by gmsh (OCC fragment: the ball's surface an interface inside the volume; regions ``mass`` and
``tissue``).  Tissue E = 5 kPa, ν = 0.45 (soft liver parenchyma); the mass ``contrast`` times stiffer (default
5x, a common ratio for hepatic tumours), the same ν; ``--materials mass:E:nu`` overrides it.  Stiffness and
deformation over the mass: ``pmask figures liver`` and ``examples/palpation.py``.
"""
from __future__ import annotations

import numpy as np

from pmask.errors import InputError
from pmask.meshes.common import ModelMesh
from pmask.precompute.meshing import gmsh_session, tets_by_volume

AXES = (0.075, 0.050, 0.040)  # m: semi-axes of the lobe
CUT = -0.015  # m: the flat posterior face (the support) at this z


def build(size: float = 0.005, depth: float = 0.020, radius: float = 0.010, offset: float = 0.020,
          contrast: float = 5.0) -> ModelMesh:
    """Mesh the lobe with largest edge ``size`` [m]; the mass's centre ``depth`` [m] under the upper surface
    at x = ``offset`` [m]."""
    if not size > 0:
        raise InputError(f"liver: size must be > 0 m, got {size}")
    if not abs(offset) < 0.6 * AXES[0]:
        raise InputError(f"liver: offset must lie within ±{0.6 * AXES[0]} m of the centre, got {offset}")
    top = AXES[2] * np.sqrt(max(0.0, 1.0 - (offset / AXES[0]) ** 2))  # the upper surface above the mass
    centre = top - depth
    if not (radius > 0 and depth - radius >= 0.5 * size and centre - radius >= CUT + size):
        raise InputError(f"liver: the mass (radius {radius} m, centre {depth} m deep) must lie inside the lobe, at "
                         f"least half an element ({0.5 * size} m) under its surface and clear of the support")
    if not contrast > 0:
        raise InputError(f"liver: contrast must be > 0, got {contrast}")
    with gmsh_session("liver") as gmsh:
        occ = gmsh.model.occ
        lobe = occ.addSphere(0.0, 0.0, 0.0, 1.0)
        occ.dilate([(3, lobe)], 0.0, 0.0, 0.0, *AXES)
        below = occ.addBox(-1.0, -1.0, -1.0, 2.0, 2.0, 1.0 + CUT)
        (body, *_), _ = occ.cut([(3, lobe)], [(3, below)])
        ball = occ.addSphere(offset, 0.0, centre, radius)
        occ.fragment([body], [(3, ball)])
        occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        gmsh.option.setNumber("Mesh.MeshSizeMin", 0.3 * size)
        gmsh.model.mesh.generate(3)
        volumes = [v for _, v in gmsh.model.getEntities(3)]
        boxes = [gmsh.model.getBoundingBox(3, v) for v in volumes]
        ball = [k for k, b in enumerate(boxes) if b[3] - b[0] < 2.5 * radius]  # the ball's box, not the lobe's
        points, tets, label = tets_by_volume(gmsh, volumes)
    mass = np.isin(label, ball)
    E, nu = 5.0e3, 0.45
    return ModelMesh(points=points, tets=tets, fixed=f"z<{CUT + 1e-4!r}",
                     material={"E": E, "nu": nu, "regions": {"mass": [contrast * E, nu]}},
                     regions={"mass": mass, "tissue": ~mass},
                     info={"semi_axes_m": list(AXES), "cut_z_m": CUT, "mass_centre_m": [offset, 0.0, centre],
                           "radius_m": radius, "contrast": contrast, "size_m": size})
