"""``pmask inspect SURFACE``: what a triangle surface holds before it is precomputed.

Shells (connected pieces) with their share of the area, defects (non-finite vertices, degenerate
triangles, boundary edges, non-manifold edges, inconsistently oriented edges, inward orientation), the
bounding box in the file's units, and the ``--edge-length`` that gives a chosen number of surface
vertices after remeshing: a closed triangulation with n vertices has about 2n triangles, each about
(√3/4) h² for edge length h, so n ≈ 2A / (√3 h²) for area A, times the 1.28 that gmsh's edges between half
and all of h add (:data:`pmask.precompute.meshing.GMSH_COUNT_FACTOR`, measured).
"""
from __future__ import annotations

import math
import numpy as np

from pmask.precompute.meshing import (DEBRIS_AREA_SHARE, GMSH_COUNT_FACTOR, MeshError, check_face_indices,
                                      edge_defects, is_cavity, pinched_vertices, read_mesh_file, shells, stl_damage,
                                      triangle_blocks)


def inspect_surface(path, units: str | None = None, targets=(500, 2000, 5000)) -> dict:
    """Facts about a surface file (in the file's own units)."""
    m = read_mesh_file(path)
    cells = {c.type: len(c.data) for c in m.cells}
    tris = triangle_blocks(m)
    if len(m.points) == 0 or not tris:
        raise MeshError(f"{path}: no triangles in this file (cell types: {sorted(cells) or 'none'}"
                        f"{stl_damage(path, '; ')})")
    check_face_indices(tris, len(m.points), path)
    raw = np.asarray(m.points, float).reshape(len(m.points), -1)[:, :3]
    finite = np.all(np.isfinite(raw), axis=1)
    pts, inverse = np.unique(np.where(finite[:, None], raw, np.nan), axis=0, return_inverse=True)
    T = inverse.ravel()[np.concatenate(tris).astype(np.int64)]
    out = {"file": str(path), "cells": cells, "vertices": int(len(pts)), "triangles": int(len(T)),
           "non_finite_vertices": int((~finite).sum())}
    degenerate = (T[:, 0] == T[:, 1]) | (T[:, 1] == T[:, 2]) | (T[:, 0] == T[:, 2])
    out["degenerate_triangles"] = int(degenerate.sum())
    T = T[~degenerate]
    out.update(edge_defects(T))
    out["pinched_vertices"] = int(len(pinched_vertices(T))) if len(T) else 0
    ok = np.all(np.isfinite(pts[T]), axis=(1, 2))
    tri_label, shell_area, shell_vol = shells(np.nan_to_num(pts), T[ok])
    shell_tris = np.bincount(tri_label, minlength=len(shell_area))
    order = np.argsort(-shell_area)
    total = float(shell_area.sum())
    out["shells"] = [{"triangles": int(shell_tris[k]), "area_share": float(shell_area[k] / total),
                      "volume": float(shell_vol[k])} for k in order if shell_tris[k]]
    main = int(order[0])  # cavities: inner shells facing inwards, meshed as the wall between (meshing.split_cavities)
    closed = not (out["boundary_edges"] or out["non_manifold_edges"] or out["inconsistent_edges"])
    cavity = [int(k) for k in order[1:] if closed and shell_tris[k] and shell_area[k] > DEBRIS_AREA_SHARE * total
              and is_cavity(np.nan_to_num(pts), T[ok], tri_label, main, k)]
    out["cavities"] = len(cavity)
    for rank, k in enumerate(order[:len(out["shells"])]):
        out["shells"][rank]["cavity"] = int(k) in cavity
    good = pts[np.all(np.isfinite(pts), axis=1)]
    lo, hi = good.min(axis=0), good.max(axis=0)
    out["bounding_box"] = [lo.tolist(), hi.tolist()]
    out["extent"] = float(np.linalg.norm(hi - lo))
    out["units"] = units or "m (not given)"
    main_area = float(shell_area[main] + shell_area[cavity].sum())  # the largest shell's, and its cavities' walls
    out["edge_length_for"] = {int(t): math.sqrt(GMSH_COUNT_FACTOR * 2.0 * main_area / (math.sqrt(3.0) * t))
                              for t in targets}
    return out


def report(r: dict) -> str:
    """The inspection as lines for a terminal."""
    u = r["units"].split()[0]
    L = [f"{r['file']}: {r['vertices']} vertices, {r['triangles']} triangles ({', '.join(f'{v} {k}' for k, v in r['cells'].items())})"]
    lo, hi = np.array(r["bounding_box"][0]), np.array(r["bounding_box"][1])
    L.append(f"bounding box [{', '.join(f'{x:.4g}' for x in lo)}] .. [{', '.join(f'{x:.4g}' for x in hi)}] {u} "
             f"({r['extent']:.4g} {u} across)")
    if r["units"].endswith("(not given)") and r["extent"] > 2.0:
        L.append(f"  read as metres this is {r['extent']:.3g} m across: probably millimetres (--units mm)")
    shells = r["shells"]
    L.append(f"shells: {len(shells)}" + ("" if len(shells) == 1 else " (largest first: " + ", ".join(
        f"{s['triangles']} triangles {100 * s['area_share']:.2f} % of the area" for s in shells[:5])
        + (", ..." if len(shells) > 5 else "") + ")"))
    defects = {"non-finite vertices": r["non_finite_vertices"], "degenerate triangles": r["degenerate_triangles"],
               "boundary edges (holes)": r["boundary_edges"], "non-manifold edges": r["non_manifold_edges"],
               "inconsistently oriented edges": r["inconsistent_edges"],
               "vertices where shells touch": r["pinched_vertices"]}
    found = {k: v for k, v in defects.items() if v}
    if shells and shells[0]["volume"] < 0 and not r["boundary_edges"]:
        found["largest shell oriented inwards"] = 1
    L.append("defects: " + (", ".join(f"{v} {k}" for k, v in found.items()) if found else "none"))
    if r.get("cavities"):
        L.append(f"  {r['cavities']} shell(s) inside the largest face inwards: cavities; pmask precompute meshes the "
                 "wall between them (a hollow organ; each cavity's wall is group:cavity, group:cavity1, ...)")
    small = [s for s in shells[1:] if not s.get("cavity")]
    if small and sum(s["area_share"] for s in small) <= 0.01:
        L.append(f"  the {len(small)} small shell(s) are debris: pmask precompute drops them (with a warning)")
    L.append("--edge-length for about " + ", ".join(f"{n} surface vertices: {h:.3g} {u}"
                                                    for n, h in r["edge_length_for"].items()))
    blocking = {k for k in found if k != "degenerate triangles"}
    if sum(s["area_share"] for s in small) > 0.01:
        blocking.add("several bodies")
    L.append("ready for pmask precompute --surface" if not blocking else "not ready: " + ", ".join(sorted(blocking)))
    L += [f"  {line}" for line in repair_routes(blocking)]
    return "\n".join(L)


def repair_routes(blocking: set) -> list[str]:
    """The ``--repair`` routes for the defects found, each with what it does to the geometry."""
    if not blocking:
        return []
    if "non-finite vertices" in blocking:
        return ["no route repairs NaN or infinite coordinates: remove those vertices in your mesh tool"]
    out = []
    if "several bodies" in blocking:
        out.append("--repair voxel rebuilds the solid from voxels (edge length / 3): overlapping bodies become "
                   "one, separate ones stay separate and are refused; cut the file to one body for the others")
        out.append("--repair meshfix keeps the largest body only")
    else:
        out.append("--repair meshfix (MeshFix): closes holes, removes non-manifold parts and self-intersections; "
                   "keeps the largest shell and nearly all of its geometry")
        out.append("--repair voxel: rebuilds the solid from voxels (edge length / 3); works where MeshFix drops "
                   "much of the area (shared walls, shells that run into each other), loses detail thinner than "
                   "a voxel")
    out.append("both report what they changed (area kept, Hausdorff distance); or repair the file in your mesh tool")
    return out
