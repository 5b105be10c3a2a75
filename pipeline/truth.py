r"""Verification numbers: the paper's Figure 5 and 6, and analytic half-space stiffness.

Half-space, axisymmetric traction profile p(s) on a disc of radius r (Boussinesq
for the normal, Cerruti for the tangential load), centre stiffness:

.. math::  k_n = \frac{E \int_0^r 2\pi s\, p\, ds}{2 (1-\nu^2) \int_0^r p\, ds}, \qquad
           \frac{k_t}{k_n} = \frac{2 (1-\nu)}{2-\nu}

cone: :math:`k_n = \pi E r / (3(1-\nu^2))`, uniform disc: :math:`\pi E r / (2(1-\nu^2))`.
"""
from __future__ import annotations

import numpy as np

from pmask.runtime.geometry import one_rings
from pmask.runtime.masks import PROFILES


def analytic_centre_stiffness(kind: str, E: float, nu: float, r: float) -> tuple[float, float]:
    """(k_n, k_t) at the centre of a mask of radius r on an elastic half-space."""
    if kind == "single":
        return 0.0, 0.0  # a point load has an unbounded centre displacement
    s = np.linspace(0.0, r, 200001)[:-1]
    p = PROFILES[kind](s / r)
    ds = s[1] - s[0]
    kn = E * np.sum(2 * np.pi * s * p) * ds / (2 * (1 - nu ** 2) * np.sum(p) * ds)
    return float(kn), float(kn * 2 * (1 - nu) / (2 - nu))


def centre_stiffness(model, kind: str, radius: float, normal=(0.0, 0.0, 1.0)) -> dict:
    """k_n = nᵀKn and k_t = mean tangential diagonal of the (full) K at the first touchable vertex."""
    stiff = model.stiffness(kind, radius, symmetric=False)
    K = stiff.K_full[0]
    n = np.asarray(normal, float)
    t1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(n, t1)
    kn = float(n @ K @ n)
    kt = float(0.5 * (t1 @ K @ t1 + t2 @ K @ t2))
    return {"kn": kn, "kt": kt, "ratio": kt / kn}


def vertex_norms(stiffness) -> np.ndarray:
    """‖K_i‖₂ of the (unsymmetrised) vertex stiffness of every touchable contact vertex."""
    return np.linalg.norm(stiffness.K_full, ord=2, axis=(1, 2))


def rank_correlation(x: np.ndarray, y: np.ndarray) -> float:
    """Spearman rank correlation (ties broken by order; values here are continuous)."""
    rx = np.argsort(np.argsort(x)).astype(float)
    ry = np.argsort(np.argsort(y)).astype(float)
    return float(np.corrcoef(rx, ry)[0, 1])


def roughness(values: np.ndarray, vertices: np.ndarray, n_surface: int, triangles: np.ndarray) -> float:
    """Mean over ``vertices`` of |v_i − mean of v_j over i's one-ring| / v_i (one-ring within ``vertices``)."""
    full = np.full(n_surface, np.nan)
    full[vertices] = values
    rings = one_rings(n_surface, triangles)
    out = []
    for i in vertices:
        ring = rings[i][np.isfinite(full[rings[i]])]
        if len(ring):
            out.append(abs(full[i] - full[ring].mean()) / full[i])
    return float(np.mean(out))


def normal_stiffness(stiffness, normals) -> np.ndarray:
    """k_n = 1 / (nᵀ K_i⁻¹ n) of every touchable contact vertex: the stiffness a frictionless contact renders."""
    verts = stiffness.model.contact[stiffness.masks.centres]
    K = stiffness.K_vertex[verts]
    n = normals[verts]
    return 1.0 / np.einsum("vi,vij,vj->v", n, np.linalg.inv(K), n)


def figure6_numbers(model, radius_factor: float = 2.0) -> dict:
    """What the Figure 6 pictures show, per stiffness: correlation of ‖K_i‖₂ with a, roughness of ‖K_i‖₂,
    and the roughness of the normal stiffness k_n that the frictionless contact renders."""
    from pmask.runtime.geometry import vertex_normals

    verts = model.contact[model.core]
    a = model.vertex_areas[verts]
    normals = vertex_normals(model.points, model.triangles)
    out = {"radius": radius_factor * model.mean_edge_length}
    for name, stiff in (("single", model.stiffness("single")),
                        ("masked", model.stiffness("linear", radius_factor * model.mean_edge_length))):
        k = vertex_norms(stiff)
        out[name] = {"rank_correlation_with_area": rank_correlation(k, a),
                     "roughness": roughness(k, verts, len(model.points), model.triangles),
                     "normal_roughness": roughness(normal_stiffness(stiff, normals), verts, len(model.points),
                                                   model.triangles),
                     "median_norm": float(np.median(k))}
    return out


def figure5_row(model, base_position, radius: float) -> dict:
    """Single and masked ‖K‖₂ at the free vertex nearest ``base_position``."""
    pts = model.points[model.contact]
    k = int(np.argmin(np.linalg.norm(pts - np.asarray(base_position), axis=1)))
    core = np.flatnonzero(model.core)
    row = int(np.searchsorted(core, k))
    single = model.stiffness("single", symmetric=False).K_full[row]
    masked = model.stiffness("linear", radius, symmetric=False)
    return {"vertices": len(model.points), "mean_edge": model.mean_edge_length,
            "single": float(np.linalg.norm(single, 2)), "masked": float(np.linalg.norm(masked.K_full[row], 2)),
            "mask_size": int(np.diff(masked.masks.indptr)[row])}


def observed_rate(values, hs) -> list[float]:
    """Convergence rates log(e_k/e_{k+1}) / log(h_k/h_{k+1}) of successive differences."""
    v = np.asarray(values, float)
    d = np.abs(np.diff(v))
    return [float(np.log(d[k] / d[k + 1]) / np.log(hs[k + 1] / hs[k + 2])) if d[k + 1] > 0 else float("inf")
            for k in range(len(d) - 1)]
