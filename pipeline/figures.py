"""The paper's Figure 6 for a model: vertex area, single-vertex and masked ‖K‖₂ maps (matplotlib)."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def figure6(model, out: Path, radius_factor: float = 2.0, numbers: dict | None = None) -> Path:
    """Three maps side by side, seen from +z and from −z, written as one PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.tri import Triangulation

    from pmask.pipeline.truth import vertex_norms
    from pmask.runtime.geometry import triangle_normals

    r = radius_factor * model.mean_edge_length
    verts = model.contact[model.core]
    fields = {"vertex area a [mm²]": np.full(len(model.points), np.nan),
              "single-vertex ‖K‖₂ [N/m]": np.full(len(model.points), np.nan),
              f"masked ‖K‖₂ [N/m] (cone, r = {radius_factor:g} × mean edge)": np.full(len(model.points), np.nan)}
    vals = [model.vertex_areas[verts] * 1e6, vertex_norms(model.stiffness("single")),
            vertex_norms(model.stiffness("linear", r))]
    for f, v in zip(fields.values(), vals):
        f[verts] = v
    normals = triangle_normals(model.points, model.triangles)
    fig, axes = plt.subplots(2, 3, figsize=(15, 7.2))
    for row, (sign, view) in enumerate(((1, "seen from +z"), (-1, "seen from −z"))):
        keep = sign * normals[:, 2] > 0
        tris = model.triangles[keep]
        for col, (title, f) in enumerate(fields.items()):
            ax = axes[row, col]
            ok = np.all(np.isfinite(f[tris]), axis=1)
            x, y = model.points[:, 0] * 1e3, sign * model.points[:, 1] * 1e3
            ax.triplot(Triangulation(x, y, tris), lw=0.15, color="0.6")
            tri = Triangulation(x, y, tris[ok])
            lo, hi = np.nanpercentile(f, [2, 98])
            pc = ax.tripcolor(tri, np.nan_to_num(f, nan=lo), shading="gouraud", cmap="RdYlBu_r", vmin=lo, vmax=hi)
            fig.colorbar(pc, ax=ax, shrink=0.8)
            ax.set_aspect("equal")
            ax.set_title(f"{title}\n{view}" if row == 0 else view, fontsize=9)
            ax.set_xlabel("x [mm]", fontsize=8)
    if numbers:
        s, m = numbers["single"], numbers["masked"]
        fig.suptitle(f"{Path(model.path).name}: rank correlation with a: single {s['rank_correlation_with_area']:.2f}, "
                     f"masked {m['rank_correlation_with_area']:.2f};  roughness: single {s['roughness']:.3f}, "
                     f"masked {m['roughness']:.3f}  (grey: fixed hilum)", fontsize=10)
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
