"""Supports defined by area (the soft-tissue issue, item 4): the fixed area is the same on every mesh of
the same geometry, because the mesh is fitted to the selector's boundary (pmask.precompute.supports)."""
import numpy as np
import pytest

from pmask.meshes import kidney
from pmask.pipeline.stages import Spec, support_stage, surface_stage
from pmask.precompute import selectors, supports
from pmask.runtime.geometry import triangle_areas

#: the kidney's lateral pole: the ellipsoid (55, 30, 20 mm) beyond x = 35 mm, far from the hilum's indentation
CAP_X = 0.035
SIZES = (0.006, 0.005, 0.004)  # three gmsh meshes of the same geometry (1,100-2,300 surface vertices)


def ellipsoid_cap_area(semi_axes, x0: float, n: int = 400) -> float:
    """∫ dΓ over the ellipsoid's part x ≥ x0, by Gauss-Legendre quadrature of |r_u × r_v| in the
    parametrisation x = a cos u, y = b sin u cos v, z = c sin u sin v (independent of any mesh)."""
    a, b, c = semi_axes
    u_max = np.arccos(x0 / a)
    gu, wu = np.polynomial.legendre.leggauss(n)
    gv, wv = np.polynomial.legendre.leggauss(2 * n)
    u, v = 0.5 * u_max * (gu + 1), np.pi * (gv + 1)
    U, V = np.meshgrid(u, v, indexing="ij")
    ru = np.stack([-a * np.sin(U), b * np.cos(U) * np.cos(V), c * np.cos(U) * np.sin(V)], -1)
    rv = np.stack([np.zeros_like(U), -b * np.sin(U) * np.sin(V), c * np.sin(U) * np.cos(V)], -1)
    return float(np.einsum("i,j,ij->", wu, wv, np.linalg.norm(np.cross(ru, rv), axis=-1)) * 0.5 * u_max * np.pi)


def held_area(size: float, selector: str, fit: bool = True) -> float:
    spec = Spec(model="kidney", fixed=selector)
    mesh = kidney.build(size)
    if fit:
        mesh = support_stage(spec, mesh)
        surf = surface_stage(spec, mesh)
        return float(triangle_areas(mesh.points[surf.vertices], surf.triangles)[surf.held].sum())
    from pmask.precompute.surface import boundary_surface

    vertices, triangles = boundary_surface(mesh.points, mesh.tets)
    held = supports.fixed_facets(selectors.select(selector, mesh.points[vertices]), triangles)
    return float(triangle_areas(mesh.points[vertices], triangles)[held].sum())


def test_fixed_area_is_the_same_on_three_remeshes():
    exact = ellipsoid_cap_area(kidney.SEMI_AXES, CAP_X)
    fitted = np.array([held_area(s, f"x>{CAP_X}") for s in SIZES])
    by_vertex = np.array([held_area(s, f"x>{CAP_X}", fit=False) for s in SIZES])
    # 1 %: the bound.  What is left is the piecewise-linear surface's own chord error on the
    # curved pole (the whole surface's area moves 0.2 % between these meshes)
    assert np.ptp(fitted) / exact < 0.01, fitted / exact
    assert np.all(np.abs(fitted / exact - 1) < 0.01), fitted / exact
    # what the fitting removes: whole triangles by vertex membership hold 8-15 % less, and differently per mesh
    assert np.all(by_vertex / exact < 0.95) and np.ptp(by_vertex) / exact > 0.03, by_vertex / exact


@pytest.mark.parametrize("selector", ["x>0.035", "z<-0.008", "sphere:0.05,0,0,0.02", "box:0.03,-1,-1,1,1,0|x<-0.05"])
def test_fitted_mesh_separates_held_and_free_facets(selector):
    """Invariants of the fitting: every tetrahedron keeps a positive volume, moved vertices stay on the
    surface edges they moved along (the enclosed volume changes by far less than an element's), and
    every surface triangle lies wholly inside the support (held) or wholly outside (free)."""
    spec = Spec(model="kidney", fixed=selector)
    mesh = kidney.build(0.006)
    fitted = support_stage(spec, mesh)
    report = fitted.info["support_fit"]
    assert report["moved"] > 0 and report["largest_move_per_edge"] <= 1.0
    p = fitted.points[fitted.tets]
    vol = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6
    p0 = mesh.points[mesh.tets]
    vol0 = np.einsum("ij,ij->i", np.cross(p0[:, 1] - p0[:, 0], p0[:, 2] - p0[:, 0]), p0[:, 3] - p0[:, 0]) / 6
    assert np.all(vol >= supports.KEEP_VOLUME * vol0 - 1e-18)
    assert abs(vol.sum() / vol0.sum() - 1) < 1e-3  # 0.1 %: a chord's sag over a few dozen rim edges
    surf = surface_stage(spec, fitted)
    centroids = fitted.points[surf.vertices][surf.triangles].mean(axis=1)
    inside = selectors.select(selector, centroids)
    # the centroid of a held facet is inside, of a free one outside; an unresolved edge (reported) may
    # leave at most one triangle on each side of it misplaced
    wrong = int(np.sum(inside != surf.held))
    assert wrong <= 2 * report["unresolved"], (wrong, report)


def test_group_supports_are_not_moved():
    mesh = kidney.build(0.006)
    assert support_stage(Spec(model="kidney"), mesh) is mesh  # group:hilum: facets of the geometry already
    assert not supports.conformable("group:hilum|z<0") and supports.conformable("z<0|sphere:0,0,0,1")
