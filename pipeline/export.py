"""ParaView export of an artifact's surface: areas, regions, stiffness norms, a deformation snapshot."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pmask.errors import InputError


def export_surface(model, out: Path, *, mask: str = "linear", radius: float | None = None,
                   contact_vertex: int | None = None, force=None) -> Path:
    """Write the surface (meshio: .vtu, .vtk, .xdmf, ...) with point data.

    vertex_area, fixed (1 on Λu), in_greens (1 where Ξ has rows), K_single_norm and
    K_masked_norm (‖K_i‖₂ [N/m], NaN where undefined), and with ``contact_vertex`` and
    ``force``: the displacement field of eq. 16 for that contact ("deformation", m).
    """
    import meshio

    from pmask.pipeline.truth import vertex_norms

    n = len(model.points)
    data = {"vertex_area": model.vertex_areas, "fixed": np.isin(np.arange(n), model.fixed).astype(np.int8),
            "in_greens": np.isin(np.arange(n), model.contact).astype(np.int8)}
    verts = model.contact[model.core]
    masked = model.stiffness(mask, radius)
    for name, stiff in (("K_single_norm", model.stiffness("single")), ("K_masked_norm", masked)):
        v = np.full(n, np.nan)
        v[verts] = vertex_norms(stiff)
        data[name] = v
    if contact_vertex is not None:
        if not 0 <= contact_vertex < n:
            raise InputError(f"contact vertex {contact_vertex} out of range [0, {n})")
        f = np.asarray(force if force is not None else [0.0, 0.0, -0.1], float)
        t = int(np.flatnonzero(np.any(model.triangles == contact_vertex, axis=1))[0])
        b = (model.triangles[t] == contact_vertex).astype(float)
        data["deformation"] = masked.deformation(t, b, f)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    meshio.write_points_cells(out, model.points, [("triangle", model.triangles)], point_data=data)
    return out
