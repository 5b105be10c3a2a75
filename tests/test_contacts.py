"""Several contacts coupled through the body: the capacitance solve against independent full finite-element
solves, a grasp in equilibrium with the support reactions, the haptic several-contact step, and the
displayed deformation meeting every contact."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import FullSystem, relerr
from pmask.pipeline.strokes import vertex_normal
from pmask.runtime import Contacts, HapticContact, Model, Status
from pmask.runtime.contact import tracking
from pmask.runtime.geometry import vertex_normals


@pytest.fixture(scope="module")
def model(kidney_small):
    return Model.load(kidney_small)


@pytest.fixture(scope="module")
def stiff(model):
    return model.stiffness("linear", 2 * model.mean_edge_length)


def contact_points(model, stiff, count, seed):
    """``count`` points inside touchable triangles, well apart, with random barycentrics."""
    rng = np.random.default_rng(seed)
    touch = np.flatnonzero(stiff.touchable & np.all(np.isin(model.triangles, model.contact[model.core]), axis=1))
    chosen = []
    while len(chosen) < count:
        t = int(rng.choice(touch))
        c = model.points[model.triangles[t]].mean(axis=0)
        if all(np.linalg.norm(c - model.points[model.triangles[u]].mean(axis=0)) > 0.015 for u in chosen):
            chosen.append(t)
    return [(t, rng.dirichlet([2.0, 2.0, 2.0])) for t in chosen]


def fe_displacements(model, stiff, points, forces):
    """Independent route (conftest.FullSystem): the masked tractions of every contact (ρ(x_l) = Σ_m φ_m(x_l) ρ^m,
    times f_l) on the whole tet mesh, solved by SuperLU with the support held; the surface's displacement."""
    tractions = np.zeros((len(model.points), 3, 1))
    row_of = {int(v): k for k, v in enumerate(model.contact[stiff.masks.centres])}
    for (t, b), f in zip(points, forces):
        for m_vertex, phi in zip(model.triangles[t], b):
            cols, rho = stiff.masks.row(row_of[int(m_vertex)])
            for j, w in zip(cols, rho):
                tractions[model.contact[j], :, 0] += phi * w * np.asarray(f)
    system = FullSystem.of(model.path)
    u, r = system.solve(tractions)
    return u[system.vi, :, 0], r


@pytest.mark.parametrize("count", [2, 3])
def test_several_masked_loads_against_a_full_finite_element_solve(model, stiff, count):
    """The capacitance solve: forces that impose displacements at 2 and 3 points at once; a full FE solve
    with those forces as masked tractions gives those displacements at the points (interpolated, eq. 16)
    and the same surface displacement field as eq. 16 from the ζ table, to 1e-8."""
    pts = contact_points(model, stiff, count, seed=count)
    rng = np.random.default_rng(10 + count)
    u_bar = rng.normal(0, 1e-3, (count, 3))
    f = stiff.coupled_forces(pts, u_bar)
    v_fe, _ = fe_displacements(model, stiff, pts, f)
    at = np.array([b @ v_fe[model.triangles[t]] for t, b in pts])
    assert relerr(at, u_bar) < 1e-8
    v = stiff.deformation_of([(t, b, fk) for (t, b), fk in zip(pts, f)])
    assert relerr(v[model.contact], v_fe[model.contact]) < 1e-8
    # and one load alone at a vertex is eq. 12: f = K_i ū with the unsymmetrised K_i
    i = 7
    vertex = model.contact[stiff.masks.centres[i]]
    t = int(np.flatnonzero(np.any(model.triangles == vertex, axis=1))[0])
    b = (model.triangles[t] == vertex).astype(float)
    np.testing.assert_allclose(stiff.coupled_forces([(t, b)], [u_bar[0]])[0], stiff.K_full[i] @ u_bar[0],
                               rtol=1e-10, atol=1e-12 * np.abs(stiff.K_full[i] @ u_bar[0]).max())


def test_a_grasp_is_in_equilibrium_with_the_support_reactions(model, stiff):
    """Two jaws squeezing the kidney from above and below: the jaw forces and the support reactions (the
    precomputed reaction Green's functions applied to the same tractions) sum to zero force and moment."""
    top = np.argmax(model.points[model.contact[model.core], 2])
    bottom = np.argmin(model.points[model.contact[model.core], 2])
    pts = []
    for k in (top, bottom):
        v = model.contact[model.core][k]
        t = int(np.flatnonzero(np.any(model.triangles == v, axis=1))[0])
        pts.append((t, (model.triangles[t] == v).astype(float)))
    u_bar = np.array([[0, 0, -1e-3], [0, 0, 1e-3]])
    f = stiff.coupled_forces(pts, u_bar)
    R = model.reactions()
    assert R is not None
    traction = np.zeros(R.shape[1])
    row_of = {int(v): k for k, v in enumerate(model.contact[stiff.masks.centres])}
    for (t, b), fk in zip(pts, f):
        for m_vertex, phi in zip(model.triangles[t], b):
            cols, rho = stiff.masks.row(row_of[int(m_vertex)])
            for j, w in zip(cols, rho):
                traction[3 * j:3 * j + 3] += phi * w * fk
    react = (R @ traction).reshape(-1, 3)  # support forces on the fixed vertices
    xs = model.points
    scale = np.abs(f).sum()
    np.testing.assert_allclose(react.sum(axis=0) + f.sum(axis=0), 0.0, atol=1e-9 * scale)
    # moments: the tractions act over the masks, not at the contact points: take the nodal forces the element
    # makes of them (P2: the consistent load on corners and edge midpoints) from the independent route
    system = FullSystem.of(model.path)
    tractions = np.zeros((len(xs), 3, 1))
    tractions[model.contact, :, 0] = traction.reshape(-1, 3)
    F = system.loads(tractions)[:, 0].reshape(-1, 3)
    P = model.volume()[0]
    nodes = P if system.B is None else np.vstack([P, P[system.edges].mean(axis=1)])
    np.testing.assert_allclose(F.sum(axis=0), f.sum(axis=0), atol=1e-9 * scale)
    m_applied = np.cross(nodes, F).sum(axis=0)
    m_support = np.cross(xs[model.fixed], react).sum(axis=0)
    assert np.linalg.norm(m_applied + m_support) <= 1e-9 * scale * np.abs(xs).max()
    # the grasp squeezes: coupled, each jaw needs more force than alone (the other jaw's push is felt)
    alone = [np.linalg.norm(stiff.coupled_forces([p], [u])) for p, u in zip(pts, u_bar)]
    assert np.linalg.norm(f[0]) > 1.2 * alone[0] and np.linalg.norm(f[1]) > 1.2 * alone[1]


def test_contacts_that_cannot_move_are_one_line(model, stiff):
    """A point on a held vertex has no compliance, two coinciding points the same row twice: the several-contact
    solve is singular, and says which inputs to change instead of numpy's 'Singular matrix'."""
    from pmask.errors import InputError

    fixed = np.isin(model.triangles, model.fixed)
    t = int(np.flatnonzero(fixed.any(axis=1) & stiff.touchable)[0])
    b = np.where(fixed[t], 1.0, 0.0)
    b /= b.sum()
    with pytest.raises(InputError, match="support's held vertices"):
        stiff.coupled_forces([(t, b)], [[0.0, 0.0, -1e-3]])
    p = contact_points(model, stiff, 1, seed=4)[0]
    with pytest.raises(InputError, match="two points coincide"):
        stiff.coupled_forces([p, p], [[0.0, 0.0, -1e-3]] * 2)


def test_one_coupled_contact_is_the_single_contact(model, stiff):
    """s = 1 through the several-contact solver is the single contact, tick for tick."""
    p0 = model.points[model.contact[model.core]][np.argmax(model.points[model.contact[model.core], 2])]
    n = np.array([0.0, 0.0, 1.0])
    path = [p0 + (2e-3 - 4e-3 * k / 300) * n + 1e-3 * np.array([np.sin(k / 50), 0, 0]) for k in range(600)]
    a, b = HapticContact(stiff, engine="python"), Contacts(stiff, 1, engine="python")
    for p in path:
        fa, sa = a.step(p)
        (fb,), (sb,) = b.step([p])
        assert sa == sb and fa == fb


def test_the_coupling_blocks_are_the_symmetrised_compliance_kept_per_triangle_pair(model, stiff):
    """coupling_blocks sums C_lk from each pair's vertex-pair blocks, kept while both contacts stay on their
    triangles: equal to ½ (C_lk + C_klᵀ) of the definition (zeta_compliance, both orders) to round-off of
    nine-term sums in another order (1e-14 of the block), the reverse pair its transpose exactly, the kept
    blocks reused when only the barycentrics move and made anew when a triangle changes."""
    from pmask.runtime.contact import coupling

    c = Contacts(stiff, 3, engine="python")
    srf = c.surface
    for seed in range(40):
        pts = contact_points(model, stiff, 3, seed)
        for l, (t, b) in enumerate(pts):
            c._states[l].tri, c._states[l].b = t, tuple(b)
        kept = dict(c._pair_blocks)
        blocks = coupling.coupling_blocks(c, c._states, [0, 1, 2])
        for a in range(3):
            for b in range(a + 1, 3):
                (ta, ba), (tb, bb) = pts[a], pts[b]
                C = np.reshape(srf.compliance(ta, ba, tb, bb), (3, 3))
                Ct = np.reshape(srf.compliance(tb, bb, ta, ba), (3, 3))
                expect = 0.5 * (C + Ct.T)
                got = np.reshape(blocks[(a, b)], (3, 3))
                assert np.abs(got - expect).max() <= 1e-14 * np.abs(expect).max()
                assert blocks[(b, a)] == list(got.T.ravel())
                assert (c._pair_blocks[(a, b)] is kept.get((a, b))) == (kept.get((a, b), (None,))[:2] == (ta, tb))
        for l in range(3):  # the same triangles, other barycentrics: the kept blocks serve
            c._states[l].b = tuple(np.random.default_rng(seed + l).dirichlet([1.0, 1.0, 1.0]))
        before = {k: v for k, v in c._pair_blocks.items()}
        coupling.coupling_blocks(c, c._states, [0, 1, 2])
        assert all(c._pair_blocks[k] is before[k] for k in before)


def test_two_instruments_press_through_each_other(model, stiff):
    """Two probes on the top face 15 mm apart, pressed 2 mm: coupled, each feels the body yield under the
    other, so each force is smaller than alone; both are in contact and finite."""
    top = model.contact[model.core]
    i = top[np.argmax(model.points[top, 2])]
    p1 = model.points[i]
    p2 = p1 + np.array([0.015, 0.0, 0.0])
    p2[2] = model.points[top][np.argmin(np.linalg.norm(model.points[top][:, :2] - p2[:2], axis=1)), 2]
    n = np.array([0.0, 0.0, 1.0])
    coupled, alone = Contacts(stiff, 2), Contacts(stiff, 2, coupled=False)
    for d in np.linspace(-1e-3, 2e-3, 150):
        fc, sc = coupled.step([p1 - d * n, p2 - d * n])
        fa, sa = alone.step([p1 - d * n, p2 - d * n])
    assert sc == [Status.CONTACT, Status.CONTACT] == sa
    assert np.linalg.norm(fc[0]) < np.linalg.norm(fa[0]) and np.linalg.norm(fc[1]) < np.linalg.norm(fa[1])


def test_both_engines_run_the_subdivided_surface_and_map_contacts_to_the_mesh(model, stiff):
    """On the Loop subdivision surface (levels=2) two coupled contacts 12 mm apart press 3 mm and slide 3 mm: the native
    core (table 1.3, which maps each contact to its mesh triangle for ζ) gives the Python engine's forces to
    1e-12 N and its deformation to 1e-12 of its largest value; the proxies run on subdivided triangles (more of
    them than the mesh has); and the displayed surface meets each contact where the map puts it: the mesh's
    deformation interpolated at the contact's mesh point equals the contact's displacement ū' plus the contact
    point's offset from that mesh point (the limit surface's bulge over the flat triangle), so that the shown
    mesh reaches the displaced contact point (to 1e-8 of ū', as on the mesh: a wrong map would miss by the
    displacement's change over the gap, ~10 %)."""
    top = model.contact[model.core]
    i = top[np.argmax(model.points[top, 2])]
    n = vertex_normals(model.points, model.triangles)[i]
    starts = [model.points[i], model.points[i] + np.array([0.012, 0.0, -0.001])]
    path = [[s - min(d, 3e-3) * n + np.array([0.0, max(d - 3e-3, 0.0), 0.0]) for s in starts]
            for d in np.linspace(-1e-3, 6e-3, 700)]
    engines = {e: Contacts(stiff, 2, engine=e, levels=2) for e in ("python", "native")}
    forces = {e: np.array([c.step(p)[0] for p in path]) for e, c in engines.items()}
    np.testing.assert_allclose(forces["native"], forces["python"], rtol=0, atol=1e-12)
    srf = engines["python"].surface
    assert srf.levels == 2 and len(srf.T) == 16 * len(model.triangles)
    assert np.linalg.norm(forces["python"][-1], axis=1).min() > 0.01  # both still pressing
    v = {e: c.deformation() for e, c in engines.items()}
    assert v["python"].shape == (len(model.points), 3)
    np.testing.assert_allclose(v["native"], v["python"], rtol=0, atol=1e-12 * np.abs(v["python"]).max())
    c = engines["python"]
    for st in c.states:
        assert st.status == Status.CONTACT
        tm, *beta = srf.mesh_point(st.tri, *st.b)
        moved = np.asarray(beta) @ v["python"][model.triangles[tm]]
        under = np.asarray(beta) @ srf.mesh_points[model.triangles[tm]]  # the shown mesh's point, at rest
        offset = np.asarray(tracking.point(srf, st.tri, *st.b)) - under
        assert np.linalg.norm(offset) > 1e-3 * np.linalg.norm(st.u_bar)  # (it matters)
        assert np.linalg.norm(moved - st.u_bar - offset) <= 1e-8 * np.linalg.norm(st.u_bar)


@pytest.mark.parametrize("levels", [0, "auto"], ids=["mesh", "default"])
def test_the_displayed_surface_meets_the_tool(model, stiff, levels):
    """The display deformation (eq. 16 with the display forces) moves the mesh's surface point under each
    contact to where the contact's displacement ū' takes the contact point (within 1 % of |ū'|; here to
    round-off), on the mesh and on the default contact surface (its subdivision surface), the mesh drawn where the
    contact surface has its vertices (``mesh_points``: near the hilum's lip the rounded surface's)."""
    top = model.contact[model.core]
    i = top[np.argmax(model.points[top, 2])]
    n = vertex_normals(model.points, model.triangles)[i]
    for count in (1, 2):
        c = Contacts(stiff, count, friction=0.5, levels=levels)
        starts = [model.points[i], model.points[i] + np.array([0.015, 0.0, -0.001])][:count]
        for d in np.linspace(-1e-3, 1.5e-3, 120):
            c.step([s - d * n + np.array([0.0, 2e-4 * d / 1.5e-3, 0.0]) for s in starts])
        v = c.deformation()
        for st in c.states:
            assert st.status == Status.CONTACT
            tm, *beta = c.surface.mesh_point(st.tri, *st.b)  # the contact's point on the mesh, where v lives
            shown = np.asarray(beta) @ (c.surface.mesh_points + v)[model.triangles[tm]]
            reached = np.asarray(tracking.point(c.surface, st.tri, *st.b)) + st.u_bar
            assert np.linalg.norm(shown - reached) <= 1e-8 * np.linalg.norm(st.u_bar)


def on_mesh(surface, where):
    """[(mesh triangle, barycentrics)] of contact-surface points [(triangle, barycentrics)]: where the full
    solve's loads and displacements sit (the contact surface is the mesh's subdivision surface)."""
    return [(tm, np.array(beta)) for tm, *beta in (surface.mesh_point(t, *b) for t, b in where)]


def fe_compliance(model, stiff, points):
    """The compliance (3s x 3s, symmetrised) between masked loads at ``points`` from full FE solves
    (conftest.FullSystem), interpolated at each point as eq. 16: the independent C of the coupled solve."""
    row_of = {int(v): k for k, v in enumerate(model.contact[stiff.masks.centres])}
    s = len(points)
    tractions = np.zeros((len(model.points), 3, 3 * s))
    for l, (t, b) in enumerate(points):
        for m_vertex, phi in zip(model.triangles[t], b):
            cols, rho = stiff.masks.row(row_of[int(m_vertex)])
            for j, w in zip(cols, rho):
                for a in range(3):
                    tractions[model.contact[j], a, 3 * l + a] += phi * w
    system = FullSystem.of(model.path)
    u, _ = system.solve(tractions)
    us = u[system.vi]
    C = np.vstack([np.einsum("i,iak->ak", b, us[model.triangles[t]]) for t, b in points])
    return 0.5 * (C + C.T)


def test_a_grasp_with_friction_lies_between_the_sliding_and_the_stuck_solve(model, stiff):
    """The hands issue's item 4: two jaws squeeze the kidney's middle from above and below (2 mm outside to
    2.5 mm in, then held).  Against full FE solves at the jaws' contact points (the compliance C between their
    masked loads, conftest.FullSystem): frictionless, the normal forces solve Nᵀ C N φ = δ̄; with friction
    that holds (μ = 0.1, 0.3, 1, 10), the forces are the stuck solve f = C⁻¹ ū.  The law's forces (before the
    output's velocity and energy-gradient terms) meet them within 1 % (k(x) interpolates the vertices' normal
    stiffness where FE interpolates the compliance: measured 0.1 %); the grasp force never exceeds the larger
    of the two (it was 1.7x the frictionless at μ = 0.3 and 5.3x at μ = 1 when the cone was bounded by a
    normal force the tangential offset raised)."""
    from pmask.runtime.contact.tracking import normal, point

    free = model.contact[model.core]
    P = model.points
    middle = free[np.abs(P[free, 0]) < 0.3 * np.abs(P[free, 0]).max()]
    srf = Contacts(stiff, 2, engine="python").surface  # the jaws press where the contact surface has the vertices
    jaws = [(srf.mesh_points[v], vertex_normal(srf, v))
            for v in (middle[np.argmax(P[middle, 2])], middle[np.argmin(P[middle, 2])])]
    depth = np.concatenate([np.linspace(-2e-3, 2.5e-3, 600), np.full(100, 2.5e-3)])
    path = np.stack([p - depth[:, None] * nv for p, nv in jaws], axis=1)
    law_forces, where = {}, None
    for mu in (0.0, 0.1, 0.3, 1.0, 10.0):
        c = Contacts(stiff, 2, friction=mu, dynamic_friction=mu, engine="python")
        for probes in path:
            _, status = c.step(list(probes))
        assert all(s in (Status.CONTACT, Status.DEEP) for s in status), (mu, status)
        law_forces[mu] = np.array([st.law_force for st in c._states])
        if mu == 0.0:
            where = [(st.tri, np.array(st.b)) for st in c._states]
            srf = c.surface
            x = [np.array(point(srf, t, *b)) for t, b in where]
            N = [np.array(normal(srf, t, *b)) for t, b in where]
        else:
            assert not any(st.sliding for st in c._states)  # a squeeze without sideways motion holds
    C = fe_compliance(model, stiff, on_mesh(c.surface, where))
    ubar = np.concatenate([path[-1][l] - x[l] for l in range(2)])
    NN = np.zeros((6, 2))
    NN[0:3, 0], NN[3:6, 1] = N[0], N[1]
    phi_free = np.linalg.solve(NN.T @ C @ NN, -NN.T @ ubar)
    f_stuck = np.linalg.solve(C, ubar).reshape(2, 3)
    phi_law = -np.einsum("la,la->l", law_forces[0.0], np.array(N))
    np.testing.assert_allclose(phi_law, phi_free, rtol=0.01)
    for mu in (0.1, 0.3, 1.0, 10.0):
        f = law_forces[mu]
        assert np.linalg.norm(f - f_stuck) <= 0.01 * np.linalg.norm(f_stuck), (mu, f, f_stuck)
        phi = -np.einsum("la,la->l", f, np.array(N))
        assert np.all(phi <= 1.01 * np.maximum(phi_free, -np.einsum("la,la->l", f_stuck, np.array(N))))


@pytest.fixture(scope="module")
def halfspace_touchable(tmp_path_factory):
    """The P2 half-space (edges of 2.5 mm within 2 load radii, 10 load radii deep) with contact vertices
    within 5 mm of the load point: enough triangles for a cone of 5 mm (2 edge lengths) to sit anywhere."""
    from pmask.pipeline.stages import Spec, run

    out = tmp_path_factory.mktemp("hs_touch") / "halfspace.h5"
    run(Spec(model="halfspace", params={"h_load": 0.0025, "far": 10.0}, element="P2", contact="sphere:0,0,0,0.005"),
        out)
    return out


def test_between_vertices_the_full_solve_ripples_with_the_mesh_and_the_law_does_not(halfspace_touchable):
    """On a half-space the stiffness of a cone of pressure does not depend on where its centre sits (the
    analytic k_n = π E r / (3 (1 − ν²)), FIELD-NOTES).  Full finite-element solves (conftest.FullSystem, P2) of
    the cone (r = 2 edge lengths) centred at vertices, edge midpoints and centroids of the triangles near the load
    point, its pressure sampled at the vertices as every mask is (aᵀρ = 1) and the displacement read from the
    quadratic field at the centre: at vertices they give the law's own k_j (within 0.5 %, K_j being symmetrised;
    measured 1e-5), between vertices they are stiffer, by 3.2-8.4 % (the sampled cone loses its peak between
    vertices: a mesh artefact; asserted ≥ 2 % everywhere and ≥ 5 % somewhere).  The law's k(x) (eq. 15) stays
    within 1.5 % of its vertex values (measured 0.9 %) and within 8 % of the analytic value (P2 at h = r/2 and
    a body 10 r deep; measured 3.3-6.5 %).  So between vertices it is the full solve, not the law, that departs
    from the continuum: the coupled tests below hold the law to it at vertices."""
    from pmask.runtime.contact.surface import at
    from pmask.runtime.contact.tracking import normal

    model = Model.load(halfspace_touchable)
    E, nu = model.attrs["material"]["E"], model.attrs["material"]["nu"]
    stiff = model.stiffness("linear", 2 * 0.0025)
    r = stiff.masks.radius
    P, T, contact = model.points, model.triangles, model.contact
    system = FullSystem.of(model.path)
    assert system.element == "P2"  # the quadratic read-out, exact for a linear field (u = x at every node)
    x = np.vstack([system.points, system.points[system.edges].mean(axis=1)]).reshape(-1, 1)
    np.testing.assert_allclose(system.value_at(x, system.vi[T[0]], [0.2, 0.3, 0.5]).ravel(),
                               np.array([0.2, 0.3, 0.5]) @ P[T[0]], rtol=0, atol=1e-15)
    near = np.flatnonzero(np.all(np.isin(T, contact[model.core]), axis=1))
    near = near[np.argsort(np.linalg.norm(P[T[near]].mean(axis=1), axis=1))][:8]
    where = {"vertex": [1.0, 0.0, 0.0], "edge": [0.5, 0.5, 0.0], "centroid": [1 / 3, 1 / 3, 1 / 3]}
    points = [(int(t), np.array(b)) for b in where.values() for t in near]
    tractions = np.zeros((len(P), 3, 3 * len(points)))
    a = system.areas[contact]
    for l, (t, b) in enumerate(points):
        cone = np.maximum(0.0, 1.0 - np.linalg.norm(P[contact] - b @ P[T[t]], axis=1) / r)
        for ax in range(3):
            tractions[contact, ax, 3 * l + ax] = cone / np.sum(a * cone)
    u, _ = system.field(tractions)
    srf = Contacts(stiff, 1, engine="python").surface
    fe, law = [], []
    for l, (t, b) in enumerate(points):
        N = np.array(normal(srf, t, *b))
        C = system.value_at(u[:, 3 * l:3 * l + 3], system.vi[T[t]], b)
        fe.append(1.0 / (N @ (0.5 * (C + C.T)) @ N))
        law.append(at(srf, t, *b)[2])
    k_n = np.pi * E * r / (3 * (1 - nu ** 2))
    fe, law = np.reshape(fe, (3, -1)) / k_n, np.reshape(law, (3, -1)) / k_n  # rows: vertex, edge, centroid
    np.testing.assert_allclose(law[0], fe[0], rtol=0.005)
    assert np.all(fe[1:] / fe[0] >= 1.02) and np.max(fe[1:] / fe[0]) >= 1.05, fe[1:] / fe[0]
    np.testing.assert_allclose(law[1:] / law[0], 1.0, atol=0.015)
    np.testing.assert_allclose(law, 1.0, atol=0.08)


def test_between_vertices_the_full_solve_is_stiffer_than_the_law_on_the_kidney(model, stiff):
    """The test above on the coarse kidney (P2, masks of 2 mean edge lengths), at 24 random points inside
    triangles and 12 at vertices, with two full finite-element loads (conftest.FullSystem): (A) as eq. 16 does,
    the vertices' masks spread by the barycentrics and read by the same linear interpolation (the coupled tests'
    reference), and (D) the cone centred at the point, read from the quadratic P2 field there.  Their normal
    compliances NᵀCN (N the law's contact normal) agree within 5 % (measured 3.8 %).  The law's k(x) meets them
    at vertices (within 0.5 %; measured 0.05 %), and between vertices they are stiffer than it by up to 16 %
    (measured 0.84-0.99 of A, never softer): more than on the half-space, this mesh being coarser and less
    regular, the same artefact of a cone sampled between vertices."""
    from pmask.runtime.contact.surface import at
    from pmask.runtime.contact.tracking import normal

    P, T, contact = model.points, model.triangles, model.contact
    system = FullSystem.of(model.path)
    assert system.element == "P2"  # the quadratic read-out
    a, r = system.areas, stiff.masks.radius
    row_of = {int(v): k for k, v in enumerate(contact[stiff.masks.centres])}
    inside = [p for seed in range(8) for p in contact_points(model, stiff, 3, seed=100 + seed)]
    points = inside + [(t, np.eye(3)[i % 3]) for i, (t, _) in enumerate(inside[:12])]
    s = len(points)
    tractions = np.zeros((len(P), 3, 6 * s))
    for l, (t, b) in enumerate(points):
        d = np.linalg.norm(P[contact] - b @ P[T[t]], axis=1) / r
        cone = np.maximum(0.0, 1.0 - d)  # the 'linear' profile the masks use
        for ax in range(3):
            tractions[contact, ax, 3 * l + ax] = cone / np.sum(a[contact] * cone)
            for m_vertex, phi in zip(T[t], b):
                cols, rho = stiff.masks.row(row_of[int(m_vertex)])
                np.add.at(tractions[:, ax, 3 * (s + l) + ax], contact[cols], phi * rho)
    u, _ = system.field(tractions)
    srf = Contacts(stiff, 1, engine="python", levels=0).surface  # eq. 15 over the mesh's own triangles
    ratios = []
    for l, (t, b) in enumerate(points):
        N = np.array(normal(srf, t, *b))
        C_D = system.value_at(u[:, 3 * l:3 * l + 3], system.vi[T[t]], b)
        C_A = np.einsum("i,iak->ak", b, u[:3 * system.N].reshape(system.N, 3, -1)[system.vi[T[t]], :,
                                                                                   3 * (s + l):3 * (s + l) + 3])
        k = at(srf, t, *b)[2]
        ratios.append((k * (N @ C_A @ N), k * (N @ C_D @ N)))
    law_A, law_D = np.array(ratios).T
    mid = np.arange(s) < len(inside)
    np.testing.assert_allclose(law_D / law_A, 1.0, atol=0.05)
    np.testing.assert_allclose(law_A[~mid], 1.0, atol=0.005)
    assert 0.82 <= law_A[mid].min() and law_A[mid].max() <= 1.0, (law_A[mid].min(), law_A[mid].max())


@pytest.mark.parametrize("count", [2, 3])
def test_frictionless_pairs_and_triples_meet_the_full_solve(model, stiff, count):
    """The hands issue's item 4: two and three instruments pressed 1.5 mm along their normals, frictionless and
    coupled, at vertices: each normal force meets the coupled normal problem with the full finite-element
    compliance between the contact points (Nᵀ C N φ = δ̄ with no contact pulling, solved by active sets) within
    5 % (the issue's bound; measured 0.08 % for the pair, 0.7 % for the triple; the third force of a triple was
    25 % off before).  Inside triangles the full solve is stiffer than each contact's own eq. 15 stiffness, by
    up to 16 % on this mesh (the two tests above: a cone sampled between vertices, an artefact of the mesh the
    law does not have), and a triple there was 9 % off (the contacts' mutual compliances, from ζ, are the full
    solve's exactly)."""
    from pmask.runtime.contact.tracking import normal, point

    pts = [(t, np.eye(3)[np.argmax(b)]) for t, b in contact_points(model, stiff, count, seed=20 + count)]
    n = vertex_normals(model.points, model.triangles)
    starts = [b @ model.points[model.triangles[t]] for t, b in pts]
    dirs = [b @ n[model.triangles[t]] for t, b in pts]
    dirs = [d / np.linalg.norm(d) for d in dirs]
    c = Contacts(stiff, count, engine="python")
    for depth in np.concatenate([np.linspace(-1e-3, 1.5e-3, 500), np.full(100, 1.5e-3)]):
        _, status = c.step([s - depth * d for s, d in zip(starts, dirs)])
    assert all(s in (Status.CONTACT, Status.DEEP) for s in status), status
    where = [(st.tri, np.array(st.b)) for st in c._states]
    x = [np.array(point(c.surface, t, *b)) for t, b in where]
    N = [np.array(normal(c.surface, t, *b)) for t, b in where]
    probes = [s - 1.5e-3 * d for s, d in zip(starts, dirs)]
    ubar = np.concatenate([p - xl for p, xl in zip(probes, x)])
    C = fe_compliance(model, stiff, on_mesh(c.surface, where))
    NN = np.zeros((3 * count, count))
    for l in range(count):
        NN[3 * l:3 * l + 3, l] = N[l]
    A, r = NN.T @ C @ NN, -NN.T @ ubar
    active = np.ones(count, bool)  # no contact pulls (the LCP): drop those the solve makes pull, solve again
    while True:
        phi_fe = np.zeros(count)
        phi_fe[active] = np.linalg.solve(A[np.ix_(active, active)], r[active])
        if np.all(phi_fe >= 0):
            break
        active &= phi_fe > 0
    phi = -np.einsum("la,la->l", np.array([st.law_force for st in c._states]), np.array(N))
    np.testing.assert_allclose(phi, phi_fe, rtol=0.05, atol=1e-6 * phi_fe.max())


def test_a_contact_the_other_carries_away_is_released_exactly_in_both_engines(model, stiff):
    """Two instruments a mesh edge apart on the upper face: one pressed 3 mm, the other only 0.2 mm, so the
    first one's dent carries the surface away from the second.  The coupled normal problem is then a
    complementarity problem with the second contact released; the frictionless start solves it exactly
    (Murty's pivoting, coupling.normal_start) where it used to clip a solve that made the second one pull and
    leave the rest to 40-60 Gauss-Seidel sweeps.  Against full FE solves at the contact points (the same
    active-set solve as the test above), the full solve releases the second contact too, the law gives it no
    force, and the first one's force meets the full solve within 5 % (the bound above); the native core's
    forces are the Python's to 1e-12 N over the whole press (the pivoting path of both)."""
    from pmask.runtime.contact.tracking import normal, point

    free = model.contact[model.core]
    T = model.triangles
    srf = Contacts(stiff, 2, engine="python").surface
    P = srf.mesh_points  # where the contact surface has the mesh's vertices (rounded near the hilum's lip)
    a = free[np.argmax(P[free, 2])]
    ring = np.unique(T[np.any(T == a, axis=1)])
    b = max((v for v in ring if v != a and v in set(free.tolist())), key=lambda v: P[v, 2])
    n = {v: vertex_normal(srf, v) for v in (a, b)}
    deep, shallow = 3e-3, 2e-4
    ramp = np.concatenate([np.linspace(-1e-3, 1.0, 400), np.ones(100)])
    path = [[P[a] - min(deep, max(x * deep, -1e-3)) * n[a], P[b] - min(shallow, max(x * deep, -1e-3)) * n[b]]
            for x in ramp]
    engines = {e: Contacts(stiff, 2, engine=e) for e in ("python", "native")}
    forces = {e: np.array([c.step([list(p) for p in probes])[0] for probes in path]) for e, c in engines.items()}
    np.testing.assert_allclose(forces["native"], forces["python"], rtol=0, atol=1e-12)
    c = engines["python"]
    where = [(st.tri, np.array(st.b)) for st in c._states]
    x = [np.array(point(c.surface, t, *bb)) for t, bb in where]
    N = [np.array(normal(c.surface, t, *bb)) for t, bb in where]
    ubar = np.concatenate([np.asarray(p) - xl for p, xl in zip(path[-1], x)])
    assert all(np.dot(ubar[3 * l:3 * l + 3], N[l]) < 0 for l in range(2))  # both probes below the undeformed surface
    C = fe_compliance(model, stiff, on_mesh(c.surface, where))
    NN = np.zeros((6, 2))
    NN[0:3, 0], NN[3:6, 1] = N[0], N[1]
    A, r = NN.T @ C @ NN, -NN.T @ ubar
    active = np.ones(2, bool)
    while True:
        phi_fe = np.zeros(2)
        phi_fe[active] = np.linalg.solve(A[np.ix_(active, active)], r[active])
        if np.all(phi_fe >= 0):
            break
        active &= phi_fe > 0
    assert list(active) == [True, False], phi_fe  # the full solve carries the shallow contact away
    phi = -np.einsum("la,la->l", np.array([st.law_force for st in c._states]), np.array(N))
    assert phi[1] == 0.0 and phi[0] > 0.0, phi
    np.testing.assert_allclose(phi[0], phi_fe[0], rtol=0.05)
