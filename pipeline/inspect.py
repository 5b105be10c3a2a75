"""``pmask inspect SURFACE``: what a triangle surface holds before it is precomputed.

Shells (connected pieces) with their share of the area, defects (non-finite vertices, degenerate
triangles, boundary edges, non-manifold edges, inconsistently oriented edges, inward orientation), the
bounding box in the file's units, and the ``--edge-length`` that gives a chosen number of surface
vertices after remeshing: a closed triangulation with n vertices has about 2n triangles, each about
(√3/4) h² for edge length h, so h ≈ √(2A / (√3 n)) for area A.
"""
from __future__ import annotations

import math
import numpy as np

from pmask.precompute.meshing import MeshError


def inspect_surface(path, units: str | None = None, targets=(500, 2000, 5000)) -> dict:
    """Facts about a surface file (in the file's own units)."""
    import warnings

    import meshio
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            m = meshio.read(path)
    except Exception as exc:  # meshio raises several types for unreadable files
        raise MeshError(f"{path}: cannot read this file as a triangle surface ({exc})") from exc
    cells = {c.type: len(c.data) for c in m.cells}
    tris = [c.data for c in m.cells if c.type == "triangle"]
    tris += [c.data[:, [0, 1, 2]] for c in m.cells if c.type == "quad"]
    tris += [c.data[:, [0, 2, 3]] for c in m.cells if c.type == "quad"]
    if len(m.points) == 0 or not tris:
        raise MeshError(f"{path}: no triangles in this file (cell types: {sorted(cells) or 'none'})")
    raw = np.asarray(m.points, float).reshape(len(m.points), -1)[:, :3]
    finite = np.all(np.isfinite(raw), axis=1)
    pts, inverse = np.unique(np.where(finite[:, None], raw, np.nan), axis=0, return_inverse=True)
    T = inverse.ravel()[np.concatenate(tris).astype(np.int64)]
    out = {"file": str(path), "cells": cells, "vertices": int(len(pts)), "triangles": int(len(T)),
           "non_finite_vertices": int((~finite).sum())}
    degenerate = (T[:, 0] == T[:, 1]) | (T[:, 1] == T[:, 2]) | (T[:, 0] == T[:, 2])
    out["degenerate_triangles"] = int(degenerate.sum())
    T = T[~degenerate]
    directed = np.concatenate([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]])
    _, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    out["boundary_edges"] = int(np.sum(counts == 1))
    out["non_manifold_edges"] = int(np.sum(counts > 2))
    _, dcounts = np.unique(directed, axis=0, return_counts=True)
    out["inconsistent_edges"] = int(np.sum(dcounts > 1))
    n = len(pts)
    e = np.concatenate([T[:, [0, 1]], T[:, [1, 2]]])
    n_comp, label = connected_components(coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)),
                                         directed=False)
    ok = np.all(np.isfinite(pts[T]), axis=(1, 2))
    p = pts[T[ok]]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    vol = np.einsum("ij,ij->i", np.cross(p[:, 0], p[:, 1]), p[:, 2]) / 6.0
    lab = label[T[ok][:, 0]]
    shell_area = np.bincount(lab, weights=area, minlength=n_comp)
    shell_vol = np.bincount(lab, weights=vol, minlength=n_comp)
    shell_tris = np.bincount(lab, minlength=n_comp)
    order = np.argsort(-shell_area)
    total = float(shell_area.sum())
    out["shells"] = [{"triangles": int(shell_tris[k]), "area_share": float(shell_area[k] / total),
                      "volume": float(shell_vol[k])} for k in order if shell_tris[k]]
    good = pts[np.all(np.isfinite(pts), axis=1)]
    lo, hi = good.min(axis=0), good.max(axis=0)
    out["bounding_box"] = [lo.tolist(), hi.tolist()]
    out["extent"] = float(np.linalg.norm(hi - lo))
    out["units"] = units or "m (not given)"
    main_area = float(shell_area[order[0]])
    out["edge_length_for"] = {int(t): math.sqrt(2.0 * main_area / (math.sqrt(3.0) * t)) for t in targets}
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
               "inconsistently oriented edges": r["inconsistent_edges"]}
    found = {k: v for k, v in defects.items() if v}
    if shells and shells[0]["volume"] < 0 and not r["boundary_edges"]:
        found["largest shell oriented inwards"] = 1
    L.append("defects: " + (", ".join(f"{v} {k}" for k, v in found.items()) if found else "none"))
    small = shells[1:]
    if small and sum(s["area_share"] for s in small) <= 0.01:
        L.append(f"  the {len(small)} small shell(s) are debris: pmask precompute drops them (with a warning)")
    L.append("--edge-length for about " + ", ".join(f"{n} surface vertices: {h:.3g} {u}"
                                                    for n, h in r["edge_length_for"].items()))
    blocking = {k for k in found if k != "degenerate triangles"}
    if len(shells) > 1 and sum(s["area_share"] for s in shells[1:]) > 0.01:
        blocking.add("several bodies")
    L.append("ready for pmask precompute --surface" if not blocking
             else "not ready: " + ", ".join(sorted(blocking)) + " (repair it in your mesh tool first)")
    return "\n".join(L)
