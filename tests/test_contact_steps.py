"""Each step of the contact algorithm on its own (pmask.runtime.contact), against what it must compute:
geometry on a flat sheet where the answers are exact, the law against its formulas, the coupled solve
against numpy's, the output's terms one by one.  The engines' agreement over whole traces is
tests/test_servo.py's; the physics of whole contacts tests/test_haptics.py's."""
from __future__ import annotations

import math

import numpy as np
import pytest

from pmask.runtime import Contacts, Status
from pmask.runtime.contact import coupling, law, output, tracking
from pmask.runtime.contact.state import ContactState
from pmask.runtime.stiffness import SurfaceStiffness


def sheet(n=8, h=1e-3, K=None, z=None):
    """A flat n x n grid of squares (2 triangles each) in the plane z = 0 (or the height field z(x, y)),
    normals +z, uniform vertex stiffness K."""
    x, y = np.meshgrid(np.arange(n + 1) * h, np.arange(n + 1) * h, indexing="ij")
    P = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size) if z is None else z(x.ravel(), y.ravel())])
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    T = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    Kv = np.tile(np.diag([40.0, 50.0, 100.0]) if K is None else K, (len(P), 1, 1))
    return SurfaceStiffness(P, T, Kv)


@pytest.fixture(scope="module")
def flat():
    return Contacts(sheet(), 1, engine="python", normal_radius=0.0)


def test_projection_on_a_flat_sheet_is_the_orthogonal_one(flat):
    """With every normal +z the Phong projection is the orthogonal projection: barycentrics of (x, y) and the
    height z, exactly."""
    srf = flat.surface
    rng = np.random.default_rng(1)
    for _ in range(50):
        p = rng.uniform([0, 0, -3e-3], [8e-3, 8e-3, 3e-3])
        t, b0, b1, b2, s = tracking.locate(flat, 0, *p)
        assert min(b0, b1, b2) >= 0 and s == pytest.approx(p[2], abs=1e-15)
        x = tracking.point(srf, t, b0, b1, b2)
        np.testing.assert_allclose(x, [p[0], p[1], 0.0], atol=1e-15)


def test_projection_along_shaded_normals_inverts_the_map(flat):
    """On a curved sheet (z = x²/(2R), R = 20 mm) the projection p = x + s N(x) along interpolated normals:
    two fixed-point steps reproduce p to a small fraction of the depth at haptic depths (the contraction the
    docstring states: depth x normal variation / edge length)."""
    R = 0.02
    c = Contacts(sheet(z=lambda x, y: x * x / (2 * R)), 1, engine="python", normal_radius=0.0)
    srf = c.surface
    for depth in (0.5e-3, 1e-3, 2e-3):
        x0 = np.array([4.1e-3, 3.7e-3, 4.1e-3 ** 2 / (2 * R)])
        n = np.array([-x0[0] / R, 0.0, 1.0])
        n /= np.linalg.norm(n)
        p = x0 - depth * n
        t, b0, b1, b2, s = tracking.locate(c, 0, *p)
        x = np.array(tracking.point(srf, t, b0, b1, b2))
        N = np.array(tracking.normal(srf, t, b0, b1, b2))
        assert np.linalg.norm(x + s * N - p) <= 0.05 * depth
        assert s == pytest.approx(-depth, rel=0.05)


def test_the_proxy_moves_along_the_surface_by_at_most_its_limit(flat):
    """move_proxy: towards a target 5 mm away, 1 mm per call, crossing edges; on a plane the path is straight,
    so each call moves exactly 1 mm, and the last reaches the target."""
    st = ContactState()
    st.tri, st.b = tracking.locate(flat, 0, 1e-3, 1e-3, 0.0)[0], None
    t, b0, b1, b2, _ = tracking.locate(flat, 0, 1e-3, 1e-3, 0.0)
    st.tri, st.b = t, (b0, b1, b2)
    target = np.array([4e-3, 5e-3, 0.0])
    start = np.array(tracking.point(flat.surface, st.tri, *st.b))
    d0 = np.linalg.norm(target - start)
    for k in range(1, 8):
        tracking.move_proxy(flat, st, *target, 1e-3)
        x = np.array(tracking.point(flat.surface, st.tri, *st.b))
        assert np.linalg.norm(x - start) == pytest.approx(min(k * 1e-3, d0), abs=1e-12)
    np.testing.assert_allclose(x, target, atol=1e-12)


def geo_of(K, N=(0.0, 0.0, 1.0), lam=1.0):
    Ki = law.inverse3(list(np.ravel(K)))
    return (*N, list(np.ravel(K)), Ki, lam, (0.0, 0.0, 0.0))


def test_the_frictionless_law_is_the_normal_stiffness_times_depth(flat):
    """f = −λ k_n δ N with k_n = 1/(Nᵀ K⁻¹ N) for a full (coupled) SPD K, and ū' = −δ N: no sideways push."""
    rng = np.random.default_rng(2)
    A = rng.standard_normal((3, 3))
    K = A @ A.T + 3 * np.eye(3)
    N = np.array([0.3, -0.2, 0.9])
    N /= np.linalg.norm(N)
    u = -1.5e-3 * N + [2e-4, 1e-4, 3e-5]
    f, u2, sliding, delta = law.local_law(flat, ContactState(), geo_of(K, N, 0.7), *u)
    kn = 1.0 / (N @ np.linalg.solve(K, N))
    assert delta == pytest.approx(-(N @ u))
    np.testing.assert_allclose(f, -0.7 * kn * delta * N, rtol=1e-14)
    np.testing.assert_allclose(u2, -delta * N, rtol=1e-14)
    assert sliding
    assert law.local_law(flat, ContactState(), geo_of(K, N), *(1e-3 * N))[3] == 0.0  # out of the body: no force


def test_friction_sticks_inside_the_cone_and_slides_on_its_edge():
    """The tangential spring k_t = 2λ/(tr K⁻¹ − Nᵀ K⁻¹ N) holds while |k_t w| ≤ μ λ k_n δ; beyond, the force
    lies on the cone's edge (its tangential part exactly μ times the normal force).  Forces on the body: along
    the displacement the tool imposes."""
    c = Contacts(sheet(), 1, engine="python", friction=0.5, normal_radius=0.0)
    K = np.diag([40.0, 50.0, 100.0])
    geo = geo_of(K)
    kt = 2.0 / (1 / 40 + 1 / 50)
    small = (1e-5, 0.0, -1e-3)  # |k_t w| = 0.00044 N < 0.5 * 0.1 N
    f, u2, sliding, delta = law.local_law(c, ContactState(), geo, *small)
    assert not sliding and f[0] == pytest.approx(kt * 1e-5) and f[2] == pytest.approx(-0.1)
    big = (2e-3, 1e-3, -1e-3)
    f, u2, sliding, delta = law.local_law(c, ContactState(), geo, *big)
    assert sliding and math.hypot(f[0], f[1]) == pytest.approx(-0.5 * f[2], rel=1e-14)
    assert math.atan2(f[1], f[0]) == pytest.approx(math.atan2(1e-3, 2e-3))


def test_the_coupled_normal_start_solves_the_delassus_system():
    """normal_start: the normal forces with every contact pressing solve A φ = δ̄ (numpy's answer); solve_spd
    is Gaussian elimination (numpy's answer on a random SPD matrix)."""
    rng = np.random.default_rng(3)
    A = rng.standard_normal((5, 5))
    A = A @ A.T + 5 * np.eye(5)
    r = rng.standard_normal(5)
    np.testing.assert_allclose(coupling.solve_spd([list(row) for row in A], list(r)), np.linalg.solve(A, r), rtol=1e-12)
    assert coupling.solve_spd([[1.0, 2.0], [2.0, 1.0]], [1.0, 1.0]) is None  # not positive definite
    K1, K2 = np.diag([40.0, 50.0, 100.0]), np.diag([60.0, 60.0, 80.0])
    N1, N2 = (0.0, 0.0, 1.0), (0.0, 0.6, 0.8)
    geo = {0: geo_of(K1, N1), 1: geo_of(K2, N2)}
    C = 0.002 * np.array([[0.5, 0.1, 0.0], [0.1, 0.4, 0.05], [0.0, 0.05, 0.6]])
    cpl = {(0, 1): list(C.ravel()), (1, 0): list(C.T.ravel())}
    ubar = {0: (0.0, 0.0, -1e-3), 1: (0.0, -0.6e-3, -0.8e-3)}
    out = coupling.normal_start([0, 1], geo, ubar, cpl)
    n1, n2 = np.array(N1), np.array(N2)
    M = np.array([[n1 @ np.linalg.solve(K1, n1), n1 @ C @ n2], [n2 @ C.T @ n1, n2 @ np.linalg.solve(K2, n2)]])
    phi = np.linalg.solve(M, [1e-3, 1e-3])
    np.testing.assert_allclose(out[0], -phi[0] * n1, rtol=1e-12)
    np.testing.assert_allclose(out[1], -phi[1] * n2, rtol=1e-12)


def test_at_rest_the_output_adds_only_the_energy_gradient_term():
    """output.render with no motion (no velocity terms, nothing for the controller to do): the force on the body
    is the law's plus ½ δ² ∇k_n, and the user feels its negative."""
    c = Contacts(sheet(), 1, engine="python", normal_radius=0.0)
    st = c._states[0]
    geo = {0: (0.0, 0.0, 1.0, [40.0, 0, 0, 0, 50.0, 0, 0, 0, 100.0], law.inverse3([40.0, 0, 0, 0, 50.0, 0, 0, 0, 100.0]),
               1.0, (3.0, -2.0, 0.0))}
    f = (0.0, 0.0, -0.1)
    result = {0: ((f, (0.0, 0.0, -1e-3), True, 1e-3), (0.0, 0.0, -1e-3))}
    output.render(c, c._states, [0], geo, {0: (0.0, 0.0, -1e-3)}, result)
    np.testing.assert_allclose(st.body_force, (0.5e-6 * 3.0, -0.5e-6 * 2.0, -0.1), rtol=1e-14)
    np.testing.assert_allclose(st.force, -np.array(st.body_force))
    assert st.status == Status.CONTACT and st.depth == 1e-3
