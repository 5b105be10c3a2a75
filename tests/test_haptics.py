"""Haptic contact: the issue's passivity and continuity bounds on a scripted tour of the default kidney,
the contact law, never-raise and validation, several contacts against independent finite-element solves."""
from __future__ import annotations

import logging
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pmask.pipeline.strokes import region_edge_slide, rim_out_and_back, run_contact, tour, tour_metrics
from pmask.runtime import Contacts, Device, HapticContact, Model, Status
from pmask.runtime.geometry import vertex_normals

FRICTION = {"friction": 0.4, "dynamic_friction": 0.3}  # a typical instrument on wet tissue


@pytest.fixture(scope="module")
def the_tour():
    return tour()


def top_vertex(model):
    """A touchable free vertex on the upper face, with its outward normal."""
    cand = model.contact[model.core]
    i = cand[np.argmax(model.points[cand, 2] - 0.2 * np.abs(model.points[cand, 0]))]
    return model.points[i], vertex_normals(model.points, model.triangles)[i]


def press(h, p0, n, depths):
    return [h.step(p0 - d * n) for d in depths]


# ------------------------------------------------------------------------------------- the tour's bounds
@pytest.mark.parametrize("options", [{}, FRICTION, {"levels": 0}, {**FRICTION, "levels": 0}],
                         ids=["frictionless", "friction", "mesh", "mesh-friction"])
def test_tour_is_passive_continuous_and_the_proxy_keeps_up(stiff, the_tour, options):
    """The haptics issue's three bounds on its tour (press, over the top and round the pole, onto and across
    the hilum 5 mm deep and back, lift off, re-enter, circles and tilted circles at 1-4 mm, 12 mm deep at
    the pole), in the default settings (the contact surface: the mesh's subdivision surface) and on the mesh:

    - the energy the body gives the hand over every closed loop is <= 1 % of the loop's peak stored energy
      (a tick's work is the force the device holds times the probe's motion; the trapezoid rule too);
    - the largest force change per tick anywhere is <= 2x the largest on smooth free surface at the same
      speed (the tour's reference segments: slides over the top face, presses to 6 mm on four faces; the
      hands issue's bound, 3x before; measured 1.58x sliding back across the hilum 5 mm deep on the default
      surface, 1.55x on the mesh);
    - the proxy never moves more than twice the probe's own motion in one tick.

    One allowance, 12 mm deep at the pole (DEEP, 5 mm past the pole's focal depth of 7 mm): rocking there, the
    proxy moves by dead reckoning at twice the probe's tangential speed (the speed-up at half the radius of
    curvature) and the force turns with the normal across the pole's tip; with
    friction the stuck contact breaks away, its force falling while the anchor catches up (at most the tool's
    own motion a tick, measured 3.3x).  Bound 5x there (3.3x measured frictionless on the test session's kidney,
    4.2x with the projection of two fixed-point steps).

    On the subdivided surface (levels=2, with K carried by Loop's masks, by hand before): measured 1.51x and 1.06x
    (frictionless, friction), over the hilum; 2.9x and 3.3x 12 mm deep at the pole.
    """
    probes, segments = the_tour
    m = tour_metrics(run_contact(HapticContact(stiff, **options), probes), probes, segments)
    loops = [s for s in m["segments"] if s["loop"]]
    assert len(loops) >= 25
    for s in loops:
        assert s["given"] <= 0.01 and s["given_trapezoid"] <= 0.01, s
    for s in m["segments"]:
        assert s["ratio"] <= (5.0 if s["name"].startswith("12 mm deep") else 2.0), s
        assert s["proxy"] <= 2.0, s
    assert m["reference"] > 0


@pytest.mark.parametrize("options", [{}, FRICTION], ids=["frictionless", "friction"])
def test_crossing_the_edge_of_a_contact_region(kidney_top, options):
    """Across the edge of a --contact artifact the force fades out over r_max instead of dropping in one
    tick, and the loop out and back is passive.

    Frictionless, the largest force change per tick while crossing the edge band (REGION_EDGE) is at most 2x the
    largest over the same slide inside the region, 2 mm deep at the same speed (the hands issue's bound; measured
    1.4x; it was 7.7x when a contact frozen past δ* (law.py) unfroze at the band's first tick, a step of
    (k* − k)(δ − δ*)).  With friction the contact sticks again on the way back in, where λ and with it the
    friction cone grow, and a stuck contact dragged builds its force at the stuck stiffness times the speed,
    as a press does (3.9x the sliding slide's largest change, measured); the bound there is 3 % of the peak force a
    tick (the first assertion)."""
    m = Model.load(kidney_top)
    s = m.stiffness("linear", 2 * m.mean_edge_length)
    probes, parts = region_edge_slide(0.0, parts=True)
    r = run_contact(HapticContact(s, **options), probes)
    st = r["status"]
    assert {Status.CONTACT, Status.REGION_EDGE, Status.OUTSIDE_REGION} <= set(st.tolist())
    dF = np.linalg.norm(np.diff(r["force"], axis=0), axis=1)
    f = np.linalg.norm(r["force"], axis=1)
    # the force changes per tick by a small fraction of its largest value (pressing 2 mm takes ~100 ticks)
    assert dF.max() <= 0.03 * f.max()
    if not options:
        out = np.arange(parts["out"].start + 200, parts["out"].stop - 1)  # settled 4 mm after the press
        inside = out[(st[out] == Status.CONTACT) & (st[out + 1] == Status.CONTACT)]
        band = np.flatnonzero((st[:-1] == Status.REGION_EDGE) | (st[1:] == Status.REGION_EDGE))
        assert len(inside) > 500 and len(band) > 500
        assert dF[band].max() <= 2.0 * dF[inside].max(), (dF[band].max(), dF[inside].max())
    given = np.einsum("ij,ij->i", r["force"][:-1], np.diff(probes, axis=0)).sum()
    assert given <= 0.01 * r["stored"].max()


@pytest.mark.parametrize("levels", [0, "auto"], ids=["mesh", "default"])
def test_the_proxy_does_not_hop_where_the_depth_hovers_about_half_the_radius(stiff, the_tour, levels):
    """Sliding onto, across and back over the hilum 5 mm deep the contact is 7 mm below the surface, about half
    the radius of curvature there, where the proxy stops following the probe's projection and moves by dead
    reckoning (tracking.follow).  A switch between the two at R/2 made the proxy hop: every third tick a
    following tick pulled it back onto the projection the dead-reckoning ticks had drifted from, and the force
    changed in a sawtooth (on the subdivided surface the largest second difference of F per tick was 1.59x its
    largest first difference; with friction the slide's largest change per tick 1.37x the reference's, 1.14x
    with the blend).  Blended over 0.4-0.5 R (linalg3.reckoning) it is continuous in the state: ‖Δ²F‖ ≤ ‖ΔF‖ at
    its largest on the mesh (measured 0.81 and 0.78; a sawtooth's is up to twice), ≤ 1.2 ‖ΔF‖ on the default
    surface, whose lip is rounded (measured 0.80 and 1.04: the 1.04 is one tick 5.9 mm deep where the proxy passes
    a vertex beside a mesh edge, across which the linear K's gradient steps and ∇k, a per-vertex average, turns
    within two ticks; the tangential term it drives is a tenth of the force that deep; not a hop: the proxy's own
    second difference stays within 0.43 of its largest move there; with the proxy-offset term faded out only at
    the focal depth, not at 0.8 R, it was 1.21: linalg3.LAG_TO)."""
    probes, segments = the_tour
    F = run_contact(HapticContact(stiff, levels=levels), probes)["force"]
    dF = np.linalg.norm(np.diff(F, axis=0), axis=1)
    d2F = np.linalg.norm(F[2:] - 2 * F[1:-1] + F[:-2], axis=1)
    for s in segments:
        if s["name"].startswith(("onto and across the hilum", "back across the hilum")):
            i = np.arange(s["start"], s["stop"] - 2)
            assert d2F[i].max() <= (1.0 if levels == 0 else 1.2) * dF[i].max(), (s["name"], d2F[i].max() / dF[i].max())


def out_and_back_work(stiff, depth, end, **options):
    """(energy the body gives the hand over the whole out-and-back, the work done pressing in) for
    :func:`rim_out_and_back` (the force the device holds times the probe's motion, each tick)."""
    probes, parts = rim_out_and_back(depth, end, parts=True)
    F = run_contact(HapticContact(stiff, **options), probes)["force"]
    given = np.einsum("ij,ij->i", F[:-1], np.diff(probes, axis=0))
    return float(given.sum()), float(-given[:parts["press"].stop - 1].sum())


@pytest.mark.parametrize("depth", [0.002, 0.004])
def test_out_and_back_across_the_support_rim(stiff, depth):
    """The hands issue's out-and-back across the support rim, frictionless with the controller off: from the top
    face down the medial side over the hilum's lip (the rim of its fixed support) into the hilum's middle and
    back, 2 and 4 mm deep at 20 mm/s, on the default contact surface, and the same short of the lip (to 0.5 rad).
    The issue's bound: |net work| ≤ 1 % of the work done pressing in (measured, over the lip 0.02 % and 0.06 %,
    short of it 0.09 % and 0.06 %; the slide into the hilum's stiffer tissue stores 5-13x what the press did).

    Three things each broke it (measured by hand): the lip a crease of the contact surface
    under normals blended across it (10.5 % and 30 %; the default surface is rounded there,
    :func:`pmask.runtime.contact.subdivision.round_creases`; the mesh, ``levels=0``, keeps it: 7.4 % and 20 %);
    the zero-order hold's correction with J = k N Nᵀ alone, which over-damps a slide whose depth and stiffness
    change along it (5.2 % at 2 mm: J is now the stored energy's Hessian, output.py); and 4 mm deep, where the
    slide turns DEEP and the proxy moves by dead reckoning off the probe's normal line, a force that left out how
    that offset changes the penetration as the proxy moves (4.6 %: output.py's proxy-offset term)."""
    for end in (0.5, 0.0):
        net, press_in = out_and_back_work(stiff, depth, end, passivity=False)
        assert press_in > 0
        assert abs(net) <= 0.01 * press_in, (end, net / press_in)


# ------------------------------------------------------------------------------------- the contact law
def test_contact_life_cycle_and_the_frictionless_force(model, stiff):
    """Pressing straight in: no force until the surface is crossed, then a force along the contact
    normal that grows with depth, with no sideways push from K's coupling (the old law gave 0.5-0.8 x the
    normal force sideways), and it fades to zero as the probe leaves."""
    p0, n = top_vertex(model)
    h = HapticContact(stiff)
    res = press(h, p0, n, np.linspace(-2e-3, 2e-3, 201))
    status = [s for _, s in res]
    assert status[0] == Status.NO_CONTACT and status[-1] == Status.CONTACT
    first = status.index(Status.CONTACT)
    f = np.array([r[0] for r in res[first:]])
    normal = f @ n
    assert np.all(np.diff(normal) > 0) and normal[-1] > 0  # pushes the user out, harder with depth
    sideways = np.linalg.norm(f - normal[:, None] * n, axis=1)
    assert sideways.max() <= 0.1 * normal.max()
    # k_n = 1/(nᵀK⁻¹n): the normal force per depth is the normal stiffness with the surface free to slide
    K = stiff.at(h.triangle, h.bary)
    k_n = 1.0 / (n @ np.linalg.solve(K, n))
    assert normal[-1] / h.depth == pytest.approx(k_n, rel=0.05)  # the contact normal is the averaged one
    out = press(h, p0, n, np.linspace(2e-3, -1e-3, 301))
    g = np.array([r[0] for r in out])
    assert out[-1][1] == Status.NO_CONTACT and np.all(g[-1] == 0)
    assert np.linalg.norm(np.diff(g, axis=0), axis=1).max() <= 0.02 * np.linalg.norm(g, axis=1).max()


@pytest.mark.parametrize("levels", [0, "auto"])
@pytest.mark.parametrize("engine", ["python", "native"])
def test_a_jump_out_of_contact_is_tracked_where_it_lands(model, stiff, levels, engine):
    """A probe parked above the body that jumps (a mouse across the viewer's page, a device's reset) to just
    outside the bottom face and presses in touches the bottom face where it presses: tracking restarts from the
    spatial grid after a jump out of contact.  It walked from where the probe had been; from the body's far
    side the walk found a projection there, read the probe as deep inside and began the contact on the wrong
    side (measured before, on the subdivided surface, whose walk covers a quarter of the mesh's distance a tick: the
    viewer's test pressed the small kidney's bottom face 1 mm deep and got a contact 46 mm deep on its top face;
    this test fails on both engines' subdivided surface without the restart)."""
    from pmask.runtime import servo

    if engine == "native" and not servo.available():
        pytest.skip("the native core is not built")
    P, T = model.points, model.triangles
    core = set(model.contact[model.core].tolist())
    tris = [i for i, tri in enumerate(T) if core.issuperset(tri.tolist())]
    t = min(tris, key=lambda i: P[T[i]].mean(axis=0)[2])  # a core triangle on the bottom face
    c, h = P[T[t]].mean(axis=0), model.mean_edge_length
    n = np.cross(P[T[t][1]] - P[T[t][0]], P[T[t][2]] - P[T[t][0]])
    n = n / np.linalg.norm(n) * (1.0 if n[2] < 0 else -1.0)  # outward: down
    lo, hi = P.min(axis=0), P.max(axis=0)
    diag = float(np.linalg.norm(hi - lo))
    h_ = HapticContact(stiff, engine=engine, levels=levels, max_jump=2.0 * diag)
    assert h_.step(hi + 0.25 * diag)[1] == Status.NO_CONTACT  # parked above, as the viewer parks a lifted probe
    for s in np.linspace(1.5, -0.2, 30):
        f, status = h_.step(c + s * h * n)
    assert status in (Status.CONTACT, Status.DEEP)
    # where it pressed (the interpolated normal's projection wanders from the centroid by ~depth x angle), 0.2 edges
    # deep
    assert np.linalg.norm(np.asarray(h_.proxy) - c) <= 0.25 * h and h_.depth <= 0.3 * h, (h_.proxy, c, h_.depth)


def test_starting_inside_is_not_a_contact(model, stiff):
    p0, n = top_vertex(model)
    h = HapticContact(stiff)
    assert h.step(p0 - 2e-3 * n)[1] == Status.NO_CONTACT
    assert h.step(p0 - 2.1e-3 * n)[1] == Status.NO_CONTACT
    assert h.step(p0 + 1e-3 * n)[1] == Status.NO_CONTACT
    assert h.step(p0 - 1e-3 * n)[1] == Status.CONTACT


def test_a_sticking_contact_stores_what_it_is_given(model, stiff):
    """With friction that never slips, the contact is a spring (½ k_n δ² + ½ k_t |w|²): driving the probe
    round a closed loop (0.5 mm, tilted) returns the work put in.  Not exactly: k_n and k_t are taken at the
    proxy, which follows the probe (measured: 0.6 % of the stored energy per loop), hence the issue's 1 %."""
    p0, n = top_vertex(model)
    h = HapticContact(stiff, friction=1e6)
    press(h, p0, n, np.linspace(-1e-3, 2e-3, 150))
    e1 = np.cross(n, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    centre = p0 - 2e-3 * n
    path = [centre + 0.5e-3 * (np.cos(t) * e1 + np.sin(t) * (e2 + n) / np.sqrt(2)) - 0.5e-3 * e1
            for t in np.linspace(0, 2 * np.pi, 2001)]
    F = np.array([h.step(p)[0] for p in path])
    assert not h.sliding
    given = np.einsum("ij,ij->i", F[:-1], np.diff(path, axis=0)).sum()
    stored = 0.5 * np.dot(-np.array(h.force), h.u_bar)
    assert given <= 0.01 * stored


def test_a_tool_tip_rests_on_the_surface(model, stiff):
    """A spherical tip of radius r_tool touches when its centre is r_tool above the surface."""
    p0, n = top_vertex(model)
    r = 1.5e-3
    h = HapticContact(stiff, tool_radius=r)
    assert press(h, p0, n, [-5e-3, -r - 1e-4])[-1][1] == Status.NO_CONTACT
    f, s = press(h, p0, n, np.linspace(-r - 1e-4, -r + 5e-4, 20))[-1]
    assert s == Status.CONTACT and h.depth == pytest.approx(5e-4, rel=0.05)


def test_viscous_damping_resists_motion(model, stiff):
    p0, n = top_vertex(model)
    forces = {}
    for b in (0.0, 2.0):
        h = HapticContact(stiff, damping=b, passivity=False)
        forces[b] = press(h, p0, n, np.linspace(-1e-3, 1.5e-3, 126))[-1][0]  # pressing in at 20 mm/s
    assert forces[2.0] @ n > forces[0.0] @ n  # more resistance while moving in


# ------------------------------------------------------------------------------------- safety
class Raises:
    def __float__(self):
        raise RuntimeError("a bad driver value")


samples = st.one_of(
    st.tuples(*[st.floats(allow_nan=True, allow_infinity=True, width=64)] * 3),
    st.tuples(*[st.floats(-0.2, 0.2)] * 3),
    st.lists(st.floats(-0.1, 0.1), min_size=0, max_size=5),
    st.just([10 ** 400, 0, 0]), st.just([Raises(), 0.0, 0.0]), st.just(Raises()),
    st.none(), st.text(max_size=3),
)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(samples, min_size=1, max_size=60))
def test_the_step_never_raises_and_never_returns_nan(surface, seq):
    h = HapticContact(surface)
    for p in seq:
        f, s = h.step(p)
        assert isinstance(s, Status) and s != Status.INTERNAL_ERROR
        assert len(f) == 3 and all(math.isfinite(c) for c in f)


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.integers(1, 4), st.lists(st.lists(samples, min_size=4, max_size=4), min_size=1, max_size=30),
       st.booleans())
def test_the_several_contact_step_never_raises_and_never_returns_nan(surface, n, seq, friction):
    h = Contacts(surface, n, **(FRICTION if friction else {}))
    for row in seq:
        forces, statuses = h.step(row[:n])
        assert len(forces) == n and all(isinstance(s, Status) and s != Status.INTERNAL_ERROR for s in statuses)
        assert all(math.isfinite(c) for f in forces for c in f)


def test_a_probe_far_outside_says_so(model, stiff, caplog):
    """A probe given in mm to a model in metres is 1000x outside: the status says so, and a warning once."""
    p0, _ = top_vertex(model)
    h = HapticContact(stiff)
    with caplog.at_level(logging.WARNING):
        statuses = [h.step(p0 * 1000.0)[1] for _ in range(3)]
    assert statuses == [Status.FAR_OUTSIDE] * 3
    assert sum("same length unit" in r.message for r in caplog.records) == 1


@pytest.mark.parametrize("option,value", [("max_jump", -1.0), ("max_jump", float("nan")), ("max_jump", 0.0),
                                          ("decay", 1.0), ("decay", -0.1), ("friction", -0.2),
                                          ("friction", float("inf")), ("damping", float("nan")),
                                          ("tool_radius", 10.0), ("reset_after", 0), ("proxy_speed", 0.5),
                                          ("device", "phantom"), ("engine", "gpu")])
def test_constructor_parameters_are_validated(stiff, option, value):
    with pytest.raises(ValueError, match=option):
        HapticContact(stiff, **{option: value})


def test_the_default_support_stiffness_respects_the_device(model):
    """k_rigid defaults to at most half the sampled-data bound 2 b / T of the device, and the report says so."""
    for device in (Device(), Device(damping=0.05), Device(damping=2.0, rate=2000.0)):
        s = model.stiffness("linear", 2 * model.mean_edge_length, device=device)
        bound = 2 * device.damping * device.rate
        assert s.report()["stable_stiffness"] == pytest.approx(bound)
        assert s.k_rigid <= 0.5 * bound + 1e-12


def test_float32_barycentrics_are_accepted(stiff):
    t = int(np.flatnonzero(stiff.touchable)[0])
    b = np.array([0.2, 0.3, 0.5], np.float32) + np.float32(3e-8)  # sum off by ~1e-7, as float32 math gives
    K = stiff.at(t, b)
    np.testing.assert_allclose(K, stiff.at(t, [0.2, 0.3, 0.5]), rtol=1e-6)


def test_green_functions_that_are_not_positive_definite_are_refused(kidney_small, tmp_path):
    """A sign-flipped Ξ (which the checksums refuse too) loaded without verification: the stiffness is
    refused by name of the vertices, whatever the checksums say."""
    import shutil

    import h5py

    from pmask.runtime.stiffness import StiffnessError

    p = tmp_path / "flipped.h5"
    shutil.copy(kidney_small, p)
    with h5py.File(p, "r+") as f:
        f["greens/Xi"][...] = -f["greens/Xi"][()]
    m = Model.load(p, verify=False)
    with pytest.raises(StiffnessError, match=r"not positive definite at \d+ of \d+ surface vertices \(\d+.*"
                                             r"cannot come from an elastic body"):  # the artifact named, not the mask
        m.stiffness("linear", 2 * m.mean_edge_length)
