"""The paper's Figure 6 for a model: vertex area, single-vertex and masked ‖K‖₂ maps (matplotlib)."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def _save(fig, out, tight: bool = True) -> Path:
    import matplotlib.pyplot as plt

    if tight:
        fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


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
            ax.set_ylabel("y [mm]" if sign > 0 else "−y [mm] (mirrored: seen from below)", fontsize=8)
    if numbers:
        s, m = numbers["single"], numbers["masked"]
        fig.suptitle(f"{Path(model.path).name}: rank correlation with a: single {s['rank_correlation_with_area']:.2f}, "
                     f"masked {m['rank_correlation_with_area']:.2f};  roughness: single {s['roughness']:.3f}, "
                     f"masked {m['roughness']:.3f}  (grey: the fixed support)", fontsize=10)
    out = _save(fig, out)
    return out


# ------------------------------------------------------------------ Figures 1 and 4 (the Loop ellipsoid family)
def vertex_pull(model, vertex: int, kind: str = "single", radius: float | None = None, force=None) -> np.ndarray:
    """Surface displacement (n_s, 3) under a force applied at surface ``vertex`` through a mask (eq. 11, 13):
    u_i = Σ_j Ξ_ij ρ_j f, with ρ = e_v / a_v for ``single`` (a point force).  Default force: a unit pull
    along the vertex's outward normal [N]."""
    from pmask.runtime.geometry import vertex_normals

    k = int(np.flatnonzero(model.contact == vertex)[0])
    if force is None:
        force = vertex_normals(model.points, model.triangles)[vertex]
    force = np.asarray(force, float)
    if kind == "single":
        idx, w = np.array([k]), np.array([1.0 / model.vertex_areas[vertex]])
    else:
        m = model.masks(kind, radius)
        idx, w = m.row(int(np.flatnonzero(m.centres == k)[0]))
    load = np.zeros(3 * len(model.contact))
    for j, wj in zip(idx, w):
        load[3 * j:3 * j + 3] = wj * force
    u = np.zeros((len(model.points), 3))
    u[model.contact] = (np.asarray(model.Xi, float) @ load).reshape(-1, 3)
    return u


def _deformed_panel(ax, model, u, scale, vertex, title, vmax):
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection
    import matplotlib.pyplot as plt

    from pmask.runtime.geometry import vertex_normals

    P = (model.points + scale * u) * 1e3
    mag = np.linalg.norm(u, axis=1)
    face = mag[model.triangles].mean(axis=1)
    cmap = plt.get_cmap("viridis")
    pc = Poly3DCollection(P[model.triangles], facecolors=cmap(np.clip(face / vmax, 0, 1)), edgecolors="0.25",
                          linewidths=0.15)
    ax.add_collection3d(pc)
    lo, hi = P.min(axis=0), P.max(axis=0)  # the deformed body fills its box: no empty margin around it
    pad = 0.04 * (hi - lo).max()
    ax.set_xlim(lo[0] - pad, hi[0] + pad); ax.set_ylim(lo[1] - pad, hi[1] + pad); ax.set_zlim(lo[2] - pad, hi[2] + pad)
    # look across the pull (perpendicular to the normal and the long axis): the pull shows in the outline
    n = vertex_normals(model.points, model.triangles)[vertex]
    d = np.cross(n, [1.0, 0.0, 0.0])
    d = d / np.linalg.norm(d) + 0.35 * n  # and a little from the pulled side
    d /= np.linalg.norm(d)
    ax.view_init(elev=float(np.degrees(np.arcsin(np.clip(d[2], -1, 1)))), azim=float(np.degrees(np.arctan2(d[1], d[0]))))
    ax.set_box_aspect(tuple(hi - lo + 2 * pad), zoom=1.25)
    ax.set_axis_off()
    ax.set_title(title, fontsize=9)


def _loop_models(work: Path):
    from pmask.pipeline.reference import REFERENCE_DIR, artifact_for, ensure_meshes
    from pmask.runtime import Model

    mesh_dir = REFERENCE_DIR / "meshes"
    ensure_meshes(mesh_dir)
    return [Model.load(artifact_for(f"loop{k}", mesh_dir, work)) for k in range(4)]


def _base_vertex(model) -> int:
    from pmask.meshes.loop import BASE_VERTEX

    return BASE_VERTEX  # Loop subdivision keeps the base surface's vertex order


def figure1(models, out: Path) -> tuple[Path, list[float]]:
    """Paper Figure 1: a unit vertex force (a pull along the normal, single-vertex mask) on three
    refinements of one body; the displacement at the loaded vertex grows without bound with refinement
    (a point load on an elastic solid is singular, u ~ 1/r).  Returns the PNG and those displacements [m/N]."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(13, 3.9))
    us = [vertex_pull(m, _base_vertex(m)) for m in models]
    peaks = [float(np.linalg.norm(u[_base_vertex(m)])) for m, u in zip(models, us)]
    scale = 0.008 / peaks[0]  # the coarsest pull drawn 8 mm long; the same exaggeration in every panel
    for k, (m, u, p) in enumerate(zip(models, us, peaks)):
        ax = fig.add_subplot(1, len(models), k + 1, projection="3d")
        _deformed_panel(ax, m, u, scale, _base_vertex(m),
                        f"{len(m.points)} vertices: |u| at the load = {p * 1e3:.2f} mm per N", peaks[0])
    fig.suptitle("Figure 1: a unit vertex force on three refinements of one body: the point load's displacement "
                 f"grows with refinement (same exaggeration {scale:.3g}x)", fontsize=10)
    _colour_bar(fig, peaks[0])
    out = _save(fig, out, tight=False)
    return out, peaks


def figure4(model, radius: float, out: Path) -> tuple[Path, dict]:
    """Paper Figure 4: the same pull through a single-vertex mask and through a multi-vertex (cone) mask on
    a once-refined mesh, exaggerated alike.  Returns the PNG and the displacement at the loaded vertex [m/N]."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    v = _base_vertex(model)
    us = {"single": vertex_pull(model, v), "linear": vertex_pull(model, v, "linear", radius)}
    peaks = {k: float(np.linalg.norm(u[v])) for k, u in us.items()}
    scale = 0.008 / peaks["linear"]
    vmax = max(peaks.values())
    fig = plt.figure(figsize=(9.5, 3.9))
    titles = {"single": f"single-vertex mask: {peaks['single'] * 1e3:.2f} mm per N at the load",
              "linear": f"cone mask, r = {radius * 1e3:.1f} mm: {peaks['linear'] * 1e3:.2f} mm per N"}
    for k, name in enumerate(us):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        _deformed_panel(ax, model, us[name], scale, v, titles[name], vmax)
    fig.suptitle(f"Figure 4: pulling deformations on a once-refined mesh ({len(model.points)} vertices), "
                 f"same force, same exaggeration {scale:.3g}x", fontsize=10)
    _colour_bar(fig, vmax)
    out = _save(fig, out, tight=False)
    return out, peaks


def _colour_bar(fig, vmax: float) -> None:
    """The panels' colour scale: |u| per newton of force [mm/N] from 0 to ``vmax`` [m/N] (clipped above)."""
    import matplotlib.pyplot as plt
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    fig.subplots_adjust(left=0.0, right=0.9, bottom=0.02, top=0.86, wspace=0.0)
    cax = fig.add_axes([0.92, 0.15, 0.012, 0.62])
    bar = fig.colorbar(ScalarMappable(Normalize(0.0, vmax * 1e3), plt.get_cmap("viridis")), cax=cax, extend="max")
    bar.set_label("|u| [mm per N]", fontsize=8)
    bar.ax.tick_params(labelsize=7)


def loop_figures(out_dir: Path, work: Path) -> dict:
    """Figures 1 and 4 on the Figure 5 family (stored meshes, artifacts in ``work``)."""
    models = _loop_models(Path(work))
    f1, peaks1 = figure1(models[1:], Path(out_dir) / "figure1_point_load.png")
    f4, peaks4 = figure4(models[1], models[0].mean_edge_length, Path(out_dir) / "figure4_masks.png")
    return {"figure1": f1, "figure1_peaks": peaks1, "figure4": f4, "figure4_peaks": peaks4}


# ------------------------------------------------------------------ an organ with a mass
def mass_figure(model, out: Path, radius_factor: float = 2.0, force: float = 0.2) -> tuple[Path, dict]:
    """The same press, over the stiffest region (a mass) and over the point mirrored across the body's centre
    in x: the surface displacement seen from above, on one colour scale, each with its indentation.  A push of
    ``force`` [N] into the surface through the cone mask (eq. 11, 13: u = Σ_j Ξ_ij ρ_j f).  Returns the PNG and
    its numbers (indentation over the mass and mirrored, their ratio)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.tri import Triangulation

    from pmask.runtime.artifact import MATERIALS, VOLUME, read_artifact
    from pmask.runtime.geometry import vertex_normals

    regions = model.attrs.get("material", {}).get("regions") or []
    if not regions:
        raise ValueError(f"{model.path}: no material regions: no mass to show")
    a = read_artifact(model.path, datasets=VOLUME + MATERIALS, verify=False)
    label = a["volume/material_region"]
    stiffest = int(np.argmax([r["E"] for r in regions]))
    vp, vt = a["volume/points"], a["volume/tets"]
    e = vp[vt[:, 1:]] - vp[vt[:, :1]]
    vol = np.abs(np.linalg.det(e)) / 6.0
    inside = label == stiffest
    centre = (vp[vt[inside]].mean(axis=1) * vol[inside, None]).sum(axis=0) / vol[inside].sum()
    P = model.points
    core = model.contact[model.core]
    over = int(core[np.argmin(np.linalg.norm(P[core] - centre, axis=1))])
    mirror_at = P[over].copy()
    mirror_at[0] = 2.0 * P[core, 0].mean() - mirror_at[0]
    mirror = int(core[np.argmin(np.linalg.norm(P[core] - mirror_at, axis=1))])
    n = vertex_normals(P, model.triangles)
    r = radius_factor * model.mean_edge_length
    u = {v: vertex_pull(model, v, "linear", r, force=-force * n[v]) for v in (over, mirror)}
    dent = {v: float(-u[v][v] @ n[v]) for v in (over, mirror)}
    vmax = max(float(np.linalg.norm(x, axis=1).max()) for x in u.values()) * 1e3
    up = n[model.triangles].mean(axis=1)[:, 2] > 0
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.6), layout="constrained")
    for ax, v, what in ((axes[0], over, f"over the {regions[stiffest]['name']}"), (axes[1], mirror, "mirrored")):
        tri = Triangulation(P[:, 0] * 1e3, P[:, 1] * 1e3, model.triangles[up])
        pc = ax.tripcolor(tri, np.linalg.norm(u[v], axis=1) * 1e3, shading="gouraud", cmap="viridis", vmin=0, vmax=vmax)
        ax.plot(*(P[v, :2] * 1e3), "w+", ms=12, mew=2)
        ax.set_aspect("equal")
        ax.set_xlabel("x [mm]")
        ax.set_ylabel("y [mm]")
        ax.set_title(f"{force:g} N pressed {what}: indentation {dent[v] * 1e3:.2f} mm "
                     f"({force / dent[v]:.0f} N/m)", fontsize=9)
    fig.colorbar(pc, ax=axes, shrink=0.85, label="surface displacement [mm]")
    fig.suptitle(f"{Path(model.path).name}: {regions[stiffest]['name']} E = {regions[stiffest]['E']:g} Pa in tissue "
                 f"E = {model.attrs['material']['E']:g} Pa, seen from +z (cone mask, r = {radius_factor:g} × mean edge)",
                 fontsize=10)
    numbers = {"region": regions[stiffest]["name"], "force_N": force, "indentation_over_mm": 1e3 * dent[over],
               "indentation_mirrored_mm": 1e3 * dent[mirror], "ratio": dent[over] / dent[mirror],
               "vertex_over": over, "vertex_mirrored": mirror}
    return _save(fig, out, tight=False), numbers


# ------------------------------------------------------------------ a scan pressed by a probe
def scan_figure(model, out: Path, depth: float | None = None) -> tuple[Path, dict]:
    """The artifact's display surface (the scan at its own resolution, :mod:`pmask.runtime.display`) pressed by
    a probe: a single contact driven from outside into the flattest upward-facing free vertex to ``depth``
    (default 1.5 mean edges), the servo's deformation carried to the scan and laid onto it at the contact; two
    views, the scan coloured by its displacement.  Returns the PNG and its numbers (the distance from the
    probe to the pressed scan beside the simulation surface's own, the displacement at the contact)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from pmask.precompute.meshing import surface_distance
    from pmask.runtime import HapticContact
    from pmask.runtime.geometry import vertex_normals

    ds = model.display()
    if ds is None:
        raise ValueError(f"{model.path}: no display surface (precomputed from a model, a --volume mesh or with "
                         "--no-display)")
    stiff = model.stiffness("linear", model.default_radius)
    h = HapticContact(stiff)
    P, n = model.points, vertex_normals(model.points, model.triangles)
    core = model.contact[model.core]
    up = core[n[core, 2] > 0.9]
    up = up if len(up) else core
    v = int(up[np.argmin(np.linalg.norm(P[up, :2] - P[core, :2].mean(axis=0), axis=1))])  # the top, mid-body
    depth = 2.0 * model.mean_edge_length if depth is None else depth
    for s in np.linspace(-1.0, depth / model.mean_edge_length, 400):
        _, status = h.step(P[v] - s * model.mean_edge_length * n[v])
    probe = P[v] - depth * n[v]
    u = h.deformation()
    proxy = np.asarray(h.proxy)
    x = ds.deform(u, [proxy], stiff.masks.radius)
    mag = np.linalg.norm(x - ds.points, axis=1)
    numbers = {"status": str(status.name), "depth_mm": 1e3 * depth, "display_triangles": int(len(ds.triangles)),
               "simulation_vertices": int(len(P)),
               "probe_to_scan_mm": 1e3 * float(surface_distance(probe[None], x, ds.triangles)[0]),
               "probe_to_simulation_mm": 1e3 * float(surface_distance(probe[None], P + u, model.triangles)[0]),
               "largest_displacement_mm": 1e3 * float(mag.max())}
    fig = plt.figure(figsize=(12, 5.2), layout="constrained")
    cmap = plt.get_cmap("viridis")
    face = mag[ds.triangles].mean(axis=1)
    lo, hi = x.min(axis=0) * 1e3, x.max(axis=0) * 1e3
    for k, (elev, azim, title) in enumerate(((20, -60, "the scan pressed"), (75, -90, "from above"))):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        ax.add_collection3d(Poly3DCollection(x[ds.triangles] * 1e3, facecolors=cmap(face / max(mag.max(), 1e-30)),
                                             linewidths=0, shade=True, lightsource=matplotlib.colors.LightSource(
                                                 azdeg=225, altdeg=45)))
        tool = np.array([probe, probe + 6.0 * model.mean_edge_length * n[v]]) * 1e3  # the tool's shaft, in red
        ax.plot(*tool.T, color="red", lw=2.5)
        ax.set_xlim(lo[0], hi[0]); ax.set_ylim(lo[1], hi[1]); ax.set_zlim(lo[2], hi[2])
        ax.set_box_aspect(tuple(hi - lo))
        ax.view_init(elev=elev, azim=azim)
        ax.set_axis_off()
        ax.set_title(title, fontsize=9)
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(0, 1e3 * mag.max()))
    fig.colorbar(sm, ax=fig.axes, shrink=0.7, label="displacement of the scan [mm]")
    fig.suptitle(f"{Path(model.path).name}: the scan ({len(ds.triangles):,} triangles) carried by the "
                 f"{len(P):,}-vertex simulation surface, a probe (red) pressed {1e3 * depth:.1f} mm in; the scan lies "
                 f"{numbers['probe_to_scan_mm']:.2f} mm from it", fontsize=10)
    return _save(fig, out, tight=False), numbers
