"""The contact surface's Loop subdivision (pmask.runtime.contact.subdivision): invariants of the scheme and of its
map to the finite-element mesh, checked against geometry known independently (a plane, a sphere)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from pmask.runtime.contact import subdivision as sd
from pmask.runtime.geometry import triangle_normals


def param_points(s, P, T):
    """(m_f, 3, 3): each subdivided triangle's corners placed on the mesh by the map (Σ_k corners_k x_{v_k})."""
    return np.einsum("tkj,tjc->tkc", s.corners, P[T[s.parent]])


def test_a_plane_stays_a_plane_and_the_map_is_the_identity_there():
    """Loop's masks are affine combinations, so a flat patch (its open boundary kept as a crease, a straight
    B-spline) stays flat, and every subdivided vertex lies where the map puts it on the mesh (to round-off):
    on a plane the subdivision only re-spaces the vertices along it."""
    x, y = np.meshgrid(np.linspace(0, 1, 6), np.linspace(0, 1, 6))
    P = np.c_[x.ravel(), y.ravel(), np.zeros(36)]
    q = np.arange(36).reshape(6, 6)
    a, b, c, d = q[:-1, :-1].ravel(), q[:-1, 1:].ravel(), q[1:, :-1].ravel(), q[1:, 1:].ravel()
    T = np.concatenate([np.c_[a, b, d], np.c_[a, d, c]])
    s = sd.subdivide(P, T, 2)
    assert len(s.triangles) == 16 * len(T)
    assert np.abs(s.points[:, 2]).max() == 0.0
    assert s.points[:, :2].min() >= -1e-15 and s.points[:, :2].max() <= 1 + 1e-15  # the boundary does not move out
    # the boundary's corners (three crease edges? no: two, at right angles, so they are crease vertices; a
    # straight edge's vertices keep their place along it), and the map: a fine vertex's own mesh point is
    # within the subdivision's re-spacing of it (a fraction of an edge), on the same plane
    pp = param_points(s, P, T)
    assert np.abs(pp[..., 2]).max() == 0.0
    assert np.abs(pp - s.points[s.triangles]).max() <= 0.5 * 0.2


@pytest.fixture(scope="module")
def ball():
    m = trimesh.creation.icosphere(subdivisions=2, radius=0.02)
    return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)


def test_each_level_halves_the_angle_between_facets_and_vertex_normals(ball):
    """The property the contact law needs (the module docstring): the facets' normals approach the interpolated
    vertex normals, halving with each level (measured on an icosphere: 0.5 ± 0.1 a level); the limit surface
    passes through the mesh's vertices (on the ball) and between them stays closer to the ball than the flat
    facets do (their chordal error, the sagitta; measured 0.35 of it: Loop's surface of the mesh itself lay 2.3
    sagittas inside, hence the interpolating control points)."""
    P, T = ball
    angles = [sd.facet_angle(*(lambda s: (s.points, s.triangles))(sd.subdivide(P, T, L))) for L in range(4)]
    ratios = np.array(angles[1:]) / np.array(angles[:-1])
    assert np.all((ratios > 0.4) & (ratios < 0.6)), (angles, ratios)
    s = sd.subdivide(P, T, 3)
    r = np.linalg.norm(s.points, axis=1)
    edge = np.linalg.norm(P[T[:, 1]] - P[T[:, 0]], axis=1).mean()
    sagitta = edge ** 2 / (8 * 0.02)
    assert np.abs(r[:len(P)] - 0.02).max() <= 1e-13 * 0.02  # the iteration stops at 1e-13 of the size
    assert np.abs(r - 0.02).max() <= 0.5 * sagitta, (np.abs(r - 0.02).max(), sagitta)
    fn = triangle_normals(s.points, s.triangles)
    assert np.all(np.einsum("tc,tc->t", fn, s.points[s.triangles].mean(axis=1)) > 0)  # still outward


def test_the_map_to_the_mesh_is_continuous_and_inside_each_parent(ball):
    """A vertex shared by several subdivided triangles is put at the same mesh point by each (to round-off: the
    corners are dyadic fractions), inside its parent (barycentrics in [0, 1] summing to 1); and interpolating a
    per-vertex quantity of the mesh gives the value at that point."""
    P, T = ball
    s = sd.subdivide(P, T, 2)
    assert s.corners.min() >= 0 and s.corners.max() <= 1
    assert np.abs(s.corners.sum(axis=2) - 1).max() <= 1e-15
    pp = param_points(s, P, T).reshape(-1, 3)
    v = s.triangles.ravel()
    first = np.full((len(s.points), 3), np.nan)
    first[v] = pp  # the last writer wins; compare all against it
    assert np.abs(pp - first[v]).max() <= 1e-17
    q = s.interpolate(T, P)
    assert np.abs(q - first).max() <= 1e-17


def test_creases_are_kept_and_levels_follow_the_angle():
    """A cube's edges are creases (90°): its faces stay flat and its corners stay put, whatever the levels; the
    automatic choice adds no level to a mesh that is already flat away from its creases."""
    m = trimesh.creation.box(extents=(0.02, 0.02, 0.02))
    P, T = np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)
    s = sd.subdivide(P, T, 2)
    assert np.abs(np.abs(s.points).max(axis=1) - 0.01).max() <= 1e-15  # every vertex on a face of the cube
    for corner in P:
        assert np.min(np.linalg.norm(s.points - corner, axis=1)) == 0.0
    assert sd.choose_levels(P, T) == 0
    assert sd.facet_angle(P, T) == 0.0


def test_a_non_manifold_edge_is_refused():
    P = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], float)
    T = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    with pytest.raises(ValueError, match="more than two"):
        sd.subdivide(P, T, 1)


def test_mesh_point_matches_the_map():
    """The per-tick map (plain Python) equals the arrays' map for points inside subdivided triangles."""
    m = trimesh.creation.icosphere(subdivisions=1, radius=1.0)
    P, T = np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)
    s = sd.subdivide(P, T, 2)
    rng = np.random.default_rng(0)
    parent, corners = s.parent.tolist(), [tuple(r) for r in s.corners.reshape(-1, 9).tolist()]
    for t in rng.integers(0, len(s.triangles), 50):
        b = rng.dirichlet(np.ones(3))
        tc, *beta = sd.mesh_point(parent, corners, int(t), *b)
        assert tc == s.parent[t]
        assert np.allclose(beta, b @ s.corners[t], rtol=0, atol=2e-16)  # the same sums in another order
        assert math.isclose(sum(beta), 1.0, abs_tol=1e-15)


def test_fields_carried_linearly_keep_the_vertices_values_and_stay_positive(ball):
    """K_i and λ ride on the subdivided surface by eq. 15 in the mesh triangle's barycentrics
    (Subdivided.interpolate): at the mesh's vertices (the first n_s subdivided vertices) they are the mesh's values
    exactly, the mesh's own coordinates carried so land where the map puts each subdivided triangle's corners
    (whichever triangle holds the vertex), values stay within the mesh's range (a taper stays in [0, 1]) and positive
    definite 3x3 blocks stay positive definite (convex combinations: random SPD blocks, eigenvalues 0.1-10)."""
    P, T = ball
    rng = np.random.default_rng(5)
    Q = np.linalg.qr(rng.normal(size=(len(P), 3, 3)))[0]
    K = np.einsum("vij,vj,vkj->vik", Q, rng.uniform(0.1, 10.0, (len(P), 3)), Q)
    step = (P[:, 2] > 0).astype(float)
    s = sd.subdivide(P, T, 2)
    fields = s.interpolate(T, np.hstack([K.reshape(-1, 9), step[:, None], P]))
    assert fields.shape == (len(s.points), 13)
    np.testing.assert_array_equal(fields[:len(P), :10], np.hstack([K.reshape(-1, 9), step[:, None]]))
    Kf = fields[:, :9].reshape(-1, 3, 3)
    assert np.linalg.eigvalsh(0.5 * (Kf + Kf.transpose(0, 2, 1)))[:, 0].min() >= 0.1 * (1 - 1e-12)
    assert fields[:, 9].min() >= 0.0 and fields[:, 9].max() <= 1.0 and 0.0 < fields[:, 9].mean() < 1.0
    # the mesh's coordinates carried so are where the map puts every corner of every subdivided triangle (one
    # place for a vertex, whichever of its triangles is asked: the carried field is continuous)
    np.testing.assert_allclose(fields[s.triangles, 10:], param_points(s, P, T), rtol=0, atol=1e-15)


def test_levels_a_user_asks_for_are_checked_in_one_line():
    """Levels outside 0-3, or more triangles than the contact surface's budget (400,000: its per-tick arrays grow
    4x a level), are refused with the numbers; 'auto' picks within the budget."""
    from pmask.errors import InputError
    from pmask.runtime import HapticContact
    from pmask.runtime.contact import ContactSurface
    from pmask.runtime.stiffness import SurfaceStiffness

    m = trimesh.creation.icosphere(subdivisions=5, radius=0.02)  # 20,480 triangles
    K = np.tile(np.eye(3) * 100.0, (len(m.vertices), 1, 1))
    ss = SurfaceStiffness(np.asarray(m.vertices), np.asarray(m.faces), K)
    with pytest.raises(InputError, match="at most 400,000 triangles"):
        ContactSurface(ss, levels=3)
    for bad in (-1, 4, 2.5, True, "two"):
        with pytest.raises(InputError, match="levels"):
            HapticContact(ss, levels=bad)
    assert ContactSurface(ss, levels=None).levels == 0  # fine enough already: 1.4° between facets and normals


def test_rounding_integrates_a_normal_field_back_to_its_surface():
    """round_creases moves vertices along given normals until they are the surface's own.  Given a unit sphere's
    normals and a cap of it bumped outwards along them (up to 0.075, vanishing at the cap's edge, where the heights
    are held at zero), it brings the cap back onto the sphere, the one surface with those normals that meets the
    rest: within 0.3 % of the bump (measured 0.23 %: the triangles' chords, 3° of arc here, against the sphere's
    tangent planes), so the contact surface's rounded crease has the blended normals it was fitted to."""
    s = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    P, T = np.asarray(s.vertices), np.asarray(s.faces)
    N = P / np.linalg.norm(P, axis=1, keepdims=True)
    free = P[:, 2] > 0.3
    z = np.clip((P[:, 2] - 0.3) / 0.7, 0.0, 1.0)
    bump = 0.05 * np.sin(np.pi * z) ** 2 * (1.0 + 0.5 * np.cos(3.0 * np.arctan2(P[:, 1], P[:, 0])))
    h = sd.round_creases(P + bump[:, None] * N, T, N, free)
    assert np.all(h[~free] == 0.0)
    back = P + (bump + h)[:, None] * N
    assert np.abs(np.linalg.norm(back, axis=1) - 1.0).max() <= 3e-3 * bump.max()
