"""Support (Λu), free (Λp) and contact sets on the surface."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pmask.errors import InputError


class RegionError(InputError):
    """A fixed or contact region that cannot be used (says what to change)."""


@dataclass
class Regions:
    """Surface index sets: ``free`` (Λp), ``fixed`` (Λu), ``contact`` ⊆ free (rows/columns of Ξ),
    and ``core`` (bool over contact): vertices a probe may touch, whose masks up to r_max are complete."""

    free: np.ndarray
    fixed: np.ndarray
    contact: np.ndarray
    core: np.ndarray


def surface_regions(points: np.ndarray, fixed_mask: np.ndarray, contact_mask: np.ndarray | None,
                    r_max: float, *, fixed_selector: str = "", contact_selector: str = "") -> Regions:
    """Split the surface into fixed and free vertices; widen the contact region by ``r_max``.

    ``fixed_mask`` and ``contact_mask`` are boolean over the surface vertices.
    Without a contact region every free vertex is a contact vertex.
    """
    n = len(points)
    fixed = np.flatnonzero(fixed_mask)
    if len(fixed) == 0:
        raise RegionError(f"the fixed-region selector '{fixed_selector}' matches no surface vertex; "
                          "choose a region that touches the surface (see 'pmask precompute --help')")
    if len(fixed) == n:
        raise RegionError(f"the fixed-region selector '{fixed_selector}' matches every surface vertex, "
                          "so nothing is free to touch; choose a smaller support region")
    centred = points[fixed] - points[fixed].mean(axis=0)
    if len(fixed) < 3 or np.linalg.svd(centred, compute_uv=False)[1] <= 1e-9 * np.abs(centred).max():
        raise RegionError(f"the fixed region '{fixed_selector}' has {len(fixed)} vertices on a line or fewer "
                          "than three: it cannot hold the body against rotation; choose a larger support region")
    free = np.flatnonzero(~fixed_mask)
    if contact_mask is None:
        return Regions(free=free, fixed=fixed, contact=free, core=np.ones(len(free), bool))
    core_vertices = free[contact_mask[free]]
    if len(core_vertices) == 0:
        raise RegionError(f"the contact-region selector '{contact_selector}' matches no free surface vertex")
    if not (np.isfinite(r_max) and r_max > 0):
        raise RegionError(f"r_max must be a finite length > 0, got {r_max}")
    from scipy.spatial import cKDTree

    near = cKDTree(points[core_vertices]).query(points[free], distance_upper_bound=r_max)[0]
    contact = free[np.isfinite(near)]
    core = np.isin(contact, core_vertices)
    return Regions(free=free, fixed=fixed, contact=contact, core=core)


def without(reg: Regions, drop: np.ndarray) -> Regions:
    """``reg`` with the surface vertices where ``drop`` (bool over the surface) taken out of the contact set
    (a hollow body's cavity walls: no mask reaches through the wall, no probe touches them)."""
    keep = ~np.asarray(drop, bool)[reg.contact]
    if not keep[reg.core].any():
        raise RegionError("the contact region lies wholly on a cavity's wall: select the wall itself with "
                          "--contact group:cavity (or the outer surface with a geometric selector)")
    return Regions(free=reg.free, fixed=reg.fixed, contact=reg.contact[keep], core=reg.core[keep])
