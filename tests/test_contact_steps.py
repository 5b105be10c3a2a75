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
    """On a curved sheet (z = x²/(2R), R = 20 mm) the projection p = x + s N(x) along the interpolated normals
    (N = Σ b_k n_k, not normalised): Newton's method reproduces p to round-off down to 0.4 R (8 mm; two
    fixed-point steps, the form before, left 2-5 % of the depth at 2 mm), and p pressed below a mesh edge projects
    to the same point from the triangles on either side of it (the walk crossing an edge does not move it; with
    two fixed-point steps the two differed by up to 0.02 mm 4 mm deep on the kidney)."""
    R = 0.02
    c = Contacts(sheet(z=lambda x, y: x * x / (2 * R)), 1, engine="python", normal_radius=0.0)
    srf = c.surface
    for depth in (0.5e-3, 1e-3, 2e-3, 4e-3, 8e-3):
        x0 = np.array([4.1e-3, 3.7e-3, 4.1e-3 ** 2 / (2 * R)])
        n = np.array([-x0[0] / R, 0.0, 1.0])
        n /= np.linalg.norm(n)
        p = x0 - depth * n
        t, b0, b1, b2, s = tracking.locate(c, 0, *p)
        x = np.array(tracking.point(srf, t, b0, b1, b2))
        N = np.einsum("k,kc->c", [b0, b1, b2], np.asarray(srf._N)[list(srf._idx[t])])
        assert np.linalg.norm(x + s * N - p) <= 1e-15 + 1e-12 * depth
        assert s == pytest.approx(-depth, rel=0.05)
        # below the middle of each edge of t shared with a neighbour: both triangles project to that point
        VN, P = np.asarray(srf._N), np.asarray(srf._P)
        for nb in srf._nb[t]:
            if nb < 0:
                continue
            i, j = sorted(set(srf._idx[t]) & set(srf._idx[nb]))
            xe, Ne = 0.5 * (P[i] + P[j]), 0.5 * (VN[i] + VN[j])
            for tri in (t, nb):
                c0, c1, c2, se = tracking.project(srf, tri, *(xe - depth * Ne))
                assert np.linalg.norm(np.array(tracking.point(srf, tri, c0, c1, c2)) - xe) <= 1e-12 * depth
                assert se == pytest.approx(-depth, rel=1e-12)


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


def geo_of(K, N=(0.0, 0.0, 1.0), lam=1.0, k=None, g=(0.0, 0.0, 0.0), S=None, dlin=math.inf):
    """The law's inputs (law.GEO_K ...) for a vertex stiffness K: K̃ scaled to the normal stiffness k (by
    default the Schur complement 1/(Nᵀ K⁻¹ N) times λ, as the surface's k_j)."""
    K = list(np.ravel(K))
    Ki = law.inverse3(K)
    if k is None:
        k = lam / law.normal_compliance(*N, Ki)
    Kt, Kti = law.scaled(K, Ki, k, *N)
    return (*N, Kt, Kti, k, lam, g, [0.0] * 9 if S is None else list(np.ravel(S)), dlin)


def random_spd(rng):
    A = rng.standard_normal((3, 3))
    return A @ A.T + 3 * np.eye(3)


def test_the_law_stiffness_has_the_normal_stiffness_k(flat):
    """K̃ = c K with c = k Nᵀ K⁻¹ N: with the tangential directions free its stiffness along N is k exactly,
    1/(Nᵀ K̃⁻¹ N) = k, and it is symmetric positive definite like K."""
    rng = np.random.default_rng(7)
    for _ in range(20):
        K = random_spd(rng)
        N = rng.standard_normal(3)
        N /= np.linalg.norm(N)
        k = rng.uniform(10, 100)
        g = geo_of(K, tuple(N), k=k)
        Kt = np.reshape(g[law.GEO_K], (3, 3))
        assert 1.0 / (N @ np.linalg.solve(Kt, N)) == pytest.approx(k, rel=1e-13)
        np.testing.assert_allclose(np.reshape(g[law.GEO_KI], (3, 3)), np.linalg.inv(Kt), rtol=1e-11)
        assert np.linalg.eigvalsh(0.5 * (Kt + Kt.T)).min() > 0


def test_the_frictionless_law_is_the_normal_stiffness_times_depth(flat):
    """f = −k δ N for a full (coupled) SPD K, and the surface's own displacement is ū' = K̃⁻¹ f: no sideways
    push on the hand, and the tangential directions relaxed."""
    rng = np.random.default_rng(2)
    K = random_spd(rng)
    N = np.array([0.3, -0.2, 0.9])
    N /= np.linalg.norm(N)
    u = -1.5e-3 * N + [2e-4, 1e-4, 3e-5]
    geo = geo_of(K, tuple(N), 0.7, k=42.0)
    f, u2, sliding, delta = law.local_law(flat, ContactState(), geo, *u)
    assert delta == pytest.approx(-(N @ u))
    np.testing.assert_allclose(f, -42.0 * delta * N, rtol=1e-14)
    np.testing.assert_allclose(u2, np.reshape(geo[law.GEO_KI], (3, 3)) @ f, rtol=1e-12)
    assert N @ u2 == pytest.approx(-delta, rel=1e-12)  # the surface under the tool moves exactly δ along N
    assert sliding
    assert law.local_law(flat, ContactState(), geo, *(1e-3 * N))[3] == 0.0  # out of the body: no force


def test_friction_sticks_inside_the_cone_and_slides_on_its_edge():
    """Stuck: f = K̃ ū while its tangential part is within μ of its normal part; beyond, the force lies on the
    cone's edge exactly, between the stuck and the frictionless force (f = (1 − τ) f_stuck + τ f_free), and
    the slip it implies, s = ū − K̃⁻¹ f, dissipates: f · s ≥ 0 (random K, N and ū)."""
    c = Contacts(sheet(), 1, engine="python", friction=0.5, normal_radius=0.0)
    rng = np.random.default_rng(4)
    stuck = slid = 0
    for _ in range(200):
        K = random_spd(rng)
        N = rng.standard_normal(3)
        N /= np.linalg.norm(N)
        geo = geo_of(K, tuple(N))
        Kt = np.reshape(geo[law.GEO_K], (3, 3))
        u = -1e-3 * N + rng.uniform(-1.5e-3, 1.5e-3) * np.cross(N, rng.standard_normal(3))
        f, u2, sliding, delta = law.local_law(c, ContactState(), geo, *u)
        f = np.array(f)
        fs = Kt @ u
        phi = -(N @ f)
        ft = np.linalg.norm(f + phi * N)
        if not sliding:
            stuck += 1
            np.testing.assert_allclose(f, fs, rtol=1e-14)
            assert ft <= 0.5 * phi * (1 + 1e-12)
            continue
        slid += 1
        assert ft == pytest.approx(0.5 * phi, rel=1e-12)  # on the cone's edge
        ff = -geo[law.GEO_k] * delta * N
        tau = np.linalg.lstsq(np.column_stack([ff - fs]), f - fs, rcond=None)[0][0]
        assert 0.0 < tau <= 1.0
        np.testing.assert_allclose(f, (1 - tau) * fs + tau * ff, rtol=1e-9, atol=1e-12 * np.linalg.norm(fs))
        assert f @ (u - np.asarray(u2)) >= -1e-15 * np.linalg.norm(f) * np.linalg.norm(u)
    assert stuck > 20 and slid > 20  # both branches exercised


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
    geo = {0: geo_of(K1, N1, k=30.0), 1: geo_of(K2, N2, k=45.0)}
    C = 0.002 * np.array([[0.5, 0.1, 0.0], [0.1, 0.4, 0.05], [0.0, 0.05, 0.6]])
    cpl = {(0, 1): list(C.ravel()), (1, 0): list(C.T.ravel())}
    ubar = {0: (0.0, 0.0, -1e-3), 1: (0.0, -0.6e-3, -0.8e-3)}
    out, left, phis = coupling.normal_start([0, 1], geo, ubar, cpl)
    n1, n2 = np.array(N1), np.array(N2)
    M = np.array([[1 / 30.0, n1 @ C @ n2], [n2 @ C.T @ n1, 1 / 45.0]])  # the laws' own normal compliances 1/k
    phi = np.linalg.solve(M, [1e-3, 1e-3])
    np.testing.assert_allclose(out[0], -phi[0] * n1, rtol=1e-12)
    np.testing.assert_allclose(out[1], -phi[1] * n2, rtol=1e-12)
    np.testing.assert_allclose(phis, phi, rtol=1e-12)  # and the pair's φ themselves
    # a pair's start also gives what each contact leaves the other, ū_l − C_lk f_k (round-off: 1e-12 of ū)
    np.testing.assert_allclose(left[0], np.array(ubar[0]) - C @ (-phi[1] * n2), rtol=0, atol=1e-15)
    np.testing.assert_allclose(left[1], np.array(ubar[1]) - C.T @ (-phi[0] * n1), rtol=0, atol=1e-15)
    assert not np.allclose(left[0], ubar[0], rtol=0, atol=1e-5)  # the coupling moved it (|C f| = 5e-5 m here)


def test_at_rest_the_output_adds_only_the_energy_gradient_term():
    """output.render with no motion (no velocity terms, nothing for the controller to do): the force on the body
    is the law's plus ψ(δ) (I − δ_f S)⁻¹ ∇k and the user feels its negative, with ψ = ½ δ² until the
    penetration reaches δ_t = min(δ_lin, k / (8 |∇k|)), where the contact remembers δ* = δ_t and k* = k, then
    ψ = δ* δ − ½ δ*² while δ ≥ δ*; δ_f = min(δ, R/2) (R = 1/κ_max = 20 mm here).  The status is DEEP while
    δ ≥ δ_lin under the proxy."""
    c = Contacts(sheet(), 1, engine="python", normal_radius=0.0)
    st = c._states[0]
    S = np.diag([50.0, 20.0, 0.0])  # curvature radii 20 and 50 mm, on the tangent plane of N = z
    g = np.array([3.0, -2.0, 0.0])  # k = 100 N/m: k / (8 |∇k|) = 3.5 m, δ_lin binds
    f = (0.0, 0.0, -0.1)
    d0 = 5e-3
    # (δ, δ_lin under the proxy, status, ψ, δ_f): the third row reads another δ_lin (the proxy moved): δ* stays
    rows = ((1e-3, d0, Status.CONTACT, 0.5e-6, 1e-3), (7e-3, d0, Status.DEEP, d0 * 7e-3 - 0.5 * d0 * d0, 7e-3),
            (12e-3, 6.5e-3, Status.DEEP, d0 * 12e-3 - 0.5 * d0 * d0, 10e-3), (4e-3, d0, Status.CONTACT, 8e-6, 4e-3))
    for delta, here, status, psi, df in rows:
        geo = {0: geo_of(np.diag([40.0, 50.0, 100.0]), g=tuple(g), S=S, dlin=here)}
        u = (0.0, 0.0, -delta)
        output.render(c, c._states, [0], geo, {0: u}, {0: ((f, u, True, delta), u)})
        want = np.array(f) + psi * np.linalg.solve(np.eye(3) - df * S, g)
        np.testing.assert_allclose(st.body_force, want, rtol=1e-13)
        np.testing.assert_allclose(st.force, -np.array(st.body_force))
        assert st.status == status and st.depth == delta and st.frozen == (delta > d0)
        if st.frozen:
            assert st.frozen_depth == d0 and st.frozen_stiffness == pytest.approx(100.0)


def test_past_the_increment_depth_the_law_keeps_the_stiffness_where_it_began():
    """With δ* = 2 mm and k* = 60 N/m remembered and k = 80 N/m under the proxy: the frictionless normal force
    is k δ* + k* (δ − δ*) and the surface's own displacement K̃⁻¹ f scaled by k δ / φ (the law's stiffness
    scaled to the secant φ / δ); shallower than δ* the linear law; δ_t = min(δ_lin, k / (8 √2 |∇k|))."""
    c = Contacts(sheet(), 1, engine="python", normal_radius=0.0)
    st = ContactState()
    st.frozen, st.frozen_depth, st.frozen_stiffness = True, 2e-3, 60.0
    geo = geo_of(np.diag([40.0, 50.0, 100.0]), k=80.0)
    f, u2, sliding, delta = law.local_law(c, st, geo, 1e-4, 0.0, -3e-3)
    phi = 80.0 * 2e-3 + 60.0 * 1e-3
    np.testing.assert_allclose(f, (0.0, 0.0, -phi), rtol=1e-14)
    np.testing.assert_allclose(u2, np.reshape(geo[law.GEO_KI], (3, 3)) @ f * (80.0 * 3e-3 / phi), rtol=1e-13)
    f, _, _, _ = law.local_law(c, st, geo, 0.0, 0.0, -1.5e-3)  # shallower than δ*: the linear law
    np.testing.assert_allclose(f, (0.0, 0.0, -80.0 * 1.5e-3), rtol=1e-14)
    assert law.increment_depth(5e-3, 80.0, 3e3, 4e3, 0.0) == pytest.approx(80.0 / (8 * math.sqrt(2)) / 5e3)
    assert law.increment_depth(5e-3, 80.0, 3.0, 4.0, 0.0) == 5e-3


def test_a_frozen_contact_fades_out_with_the_region_instead_of_stepping():
    """Past δ* in a contact region's edge band (λ = 0.4 under the proxy, ∇λ = (0, 30, 0) /m): the increments'
    stiffness is tapered as k is, φ = k δ* + λ k* (δ − δ*), the contact stays frozen (it used to unfreeze there
    in one tick: a step of (k* − k)(δ − δ*)), and the force's tangential part is the gradient of the energy
    k (δ* δ − ½ δ*²) + ½ λ k* (δ − δ*)² along the surface: (δ* δ − ½ δ*²) ∇k + ½ k* (δ − δ*)² ∇λ (flat, S = 0)."""
    flat = sheet()
    gl = np.array([0.0, 30.0, 0.0])
    taper = 0.25 + flat.points @ gl  # λ = 0.4 at y = 5 mm, 0.25-0.49 over the sheet
    c = Contacts(SurfaceStiffness(flat.points, flat.triangles, flat.K_vertex, taper=taper), 1, engine="python",
                 normal_radius=0.0)
    st = c._states[0]
    st.tri = int(np.flatnonzero(np.all(np.abs(flat.points[flat.triangles, 1] - 5.5e-3) < 1e-3, axis=1))[0])
    st.frozen, st.frozen_depth, st.frozen_stiffness = True, 2e-3, 60.0
    lam, k, gk = 0.4, 32.0, np.array([5.0, 0.0, 0.0])
    geo = geo_of(np.diag([40.0, 50.0, 100.0]), lam=lam, k=k, g=tuple(gk))
    delta = 3e-3
    u = (0.0, 0.0, -delta)
    f, u2, sliding, d = law.local_law(c, st, geo, *u)
    phi = k * 2e-3 + lam * 60.0 * 1e-3
    np.testing.assert_allclose(f, (0.0, 0.0, -phi), rtol=1e-14)
    output.render(c, c._states, [0], {0: geo}, {0: u}, {0: ((f, u2, sliding, d), u)})
    assert st.frozen and st.status == Status.REGION_EDGE
    want = np.array(f) + (2e-3 * delta - 0.5 * 2e-3 ** 2) * gk + 0.5 * 60.0 * 1e-3 ** 2 * gl
    np.testing.assert_allclose(st.body_force, want, rtol=1e-13)  # at rest: no velocity terms
    output.render(c, c._states, [0], {0: geo}, {0: (0.0, 0.0, -1.5e-3)}, {0: ((f, u2, sliding, 1.5e-3), u)})
    assert not st.frozen  # shallower than δ*: the linear law again


def test_a_deep_contact_moves_with_the_probe_along_the_surface():
    """Deeper than half the radius of curvature (dead reckoning): on a flat sheet (R infinite) the proxy
    follows the projection at any depth; on a sphere of radius R = 10 mm, 8 mm deep, it moves by
    (I − δ_f S)⁻¹ P Δp = 2 P Δp (δ_f = R/2), so a press along the normal leaves it where it is."""
    c = Contacts(sheet(), 1, engine="python", normal_radius=0.0)
    st = c._states[0]
    st.tri, st.b, st.depth = 10, (0.2, 0.3, 0.5), 8e-3
    st.move = (1e-4, -5e-5, -2e-4)
    st.target = (10, 0.1, 0.4, 0.5)  # the projection: followed (flat: never focal)
    tracking.follow(c, st)
    assert st.tri == 10 and st.b == pytest.approx((0.1, 0.4, 0.5), abs=1e-12)
    from pmask.runtime.contact import linalg3
    S = [100.0, 0, 0, 0, 100.0, 0, 0, 0, 0.0]  # R = 10 mm
    assert linalg3.largest_curvature(S) == pytest.approx(100.0)
    assert linalg3.tracking_depth(S, 8e-3) == pytest.approx(5e-3) and linalg3.tracking_depth(S, 3e-3) == 3e-3
    np.testing.assert_allclose(linalg3.speed_up(S, 5e-3), np.diag([2.0, 2.0, 1.0]).ravel(), rtol=1e-14)


@pytest.mark.parametrize("seed", range(8))
def test_the_frictionless_start_solves_the_complementarity_problem(seed):
    """coupling.normal_start against the conditions that define the coupled frictionless contact (an LCP):
    φ ≥ 0; A φ = δ̄ where φ > 0; w = δ̄ − A φ ≤ 0 where φ = 0 (a released contact is not pushed into), for 3-8
    contacts with random normals, stiffnesses and couplings, some too shallow to press once the others dent
    the surface.  To 1e-12 of δ̄ (Gaussian elimination on at most 8 unknowns: round-off ~1e-15).  Clipping
    the all-pressing solve at zero, as the start did before, fails them whenever a contact is carried away."""
    rng = np.random.default_rng(seed)
    s = int(rng.integers(3, 9))
    N = rng.normal(size=(s, 3))
    N /= np.linalg.norm(N, axis=1)[:, None]
    k = rng.uniform(50.0, 400.0, s)
    # a compliance between the contacts: SPD with strong coupling (a patch of one body)
    G = rng.normal(size=(3 * s, 3 * s))
    C = 1e-3 * (0.3 * G @ G.T / (3 * s) + np.kron(np.full((s, s), 0.8), np.eye(3)) + 0.2 * np.eye(3 * s))
    geo = [[*N[l], *[None] * (law.GEO_k - 3), float(k[l])] for l in range(s)]  # only N and k are read
    coupling_blocks = {(l, m): list(C[3 * l:3 * l + 3, 3 * m:3 * m + 3].ravel()) for l in range(s) for m in range(s)
                       if l != m}
    depth = rng.uniform(-0.5e-3, 2e-3, s)
    ubar = [tuple(-depth[l] * N[l]) for l in range(s)]
    out, _, _ = coupling.normal_start(list(range(s)), geo, ubar, coupling_blocks)
    phi = np.array([-np.dot(out[l], N[l]) for l in range(s)])
    A = np.diag(1.0 / k) + np.array([[0.0 if l == m else N[l] @ C[3 * l:3 * l + 3, 3 * m:3 * m + 3] @ N[m]
                                      for m in range(s)] for l in range(s)])
    delta = depth.copy()
    w = delta - A @ phi
    tol = 1e-12 * np.abs(delta).max()
    assert np.all(phi >= 0.0)
    assert np.all(np.abs(w[phi > 0]) <= tol), (w, phi)
    assert np.all(w[phi == 0] <= tol), (w, phi)
