"""Haptic contact: contact life cycle, bad samples, passivity of the rendered stiffness, fuzzing."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pmask.runtime import HapticContact, Model, Status
from pmask.runtime.geometry import vertex_normals


@pytest.fixture(scope="module")
def model(kidney_small):
    return Model.load(kidney_small)


@pytest.fixture(scope="module")
def stiff(model):
    return model.stiffness("linear", 2 * model.mean_edge_length)


def top_vertex(model):
    """A touchable free vertex on the upper face, with its outward normal."""
    cand = model.contact[model.core]
    i = cand[np.argmax(model.points[cand, 2] - 0.2 * np.abs(model.points[cand, 0]))]
    return model.points[i], vertex_normals(model.points, model.triangles)[i]


def press(h, p0, n, depths):
    out = []
    for d in depths:
        out.append(h.step(p0 - d * n))
    return out


def test_contact_life_cycle(model, stiff):
    p0, n = top_vertex(model)
    h = HapticContact(stiff)
    res = press(h, p0, n, np.linspace(-2e-3, 1e-3, 31))
    status = [s for _, s in res]
    assert status[0] == Status.NO_CONTACT and status[-1] == Status.CONTACT
    first = status.index(Status.CONTACT)
    assert all(s == Status.NO_CONTACT for s in status[:first])
    f = np.array(res[-1][0])
    assert f @ n > 0  # the user is pushed back out
    K = stiff.at(h.triangle, h.bary)
    np.testing.assert_allclose(-f, K @ np.array(h.u_bar), rtol=1e-10)
    # the rendered force grows with depth (monotone for a symmetric positive definite K)
    mags = [np.linalg.norm(r[0]) for r in res[first:]]
    assert np.all(np.diff(mags) > 0)
    # leaving the body ends the contact
    f_out, s_out = h.step(p0 + 1e-3 * n)
    assert s_out == Status.NO_CONTACT and f_out == (0.0, 0.0, 0.0)


def test_starting_inside_is_not_a_contact(model, stiff):
    p0, n = top_vertex(model)
    h = HapticContact(stiff)
    assert h.step(p0 - 2e-3 * n)[1] == Status.NO_CONTACT
    assert h.step(p0 - 2.1e-3 * n)[1] == Status.NO_CONTACT
    assert h.step(p0 + 1e-3 * n)[1] == Status.NO_CONTACT
    assert h.step(p0 - 1e-3 * n)[1] == Status.CONTACT


def test_bad_samples_hold_the_last_force_decaying(model, stiff):
    p0, n = top_vertex(model)
    h = HapticContact(stiff, decay=0.5)
    press(h, p0, n, np.linspace(-1e-3, 1e-3, 21))
    good = np.array(h.force)
    assert h.status == Status.CONTACT and np.linalg.norm(good) > 0
    for k, bad in enumerate([(np.nan, 0, 0), (0, np.inf, 0), "xyz", None, (1, 2)], start=1):
        f, s = h.step(bad)
        assert s == Status.BAD_SAMPLE
        np.testing.assert_allclose(f, good * 0.5 ** k)
    # a good sample resumes the same contact
    f, s = h.step(p0 - 1e-3 * n)
    assert s == Status.CONTACT
    np.testing.assert_allclose(f, good, rtol=1e-9)


def test_implausible_jump_is_held_then_reset(model, stiff):
    p0, n = top_vertex(model)
    h = HapticContact(stiff, reset_after=3)
    press(h, p0, n, np.linspace(-1e-3, 1e-3, 21))
    far = p0 + np.array([0.0, 0.0, 0.05])
    statuses = [h.step(far)[1] for _ in range(5)]
    assert statuses[:3] == [Status.JUMP] * 3
    assert statuses[3] == Status.NO_CONTACT  # accepted after reset_after samples: tracking restarts


def test_sliding_stroke_force_is_continuous(model, stiff):
    """Halving the probe step halves the largest force change per step: no jumps in the force."""
    p0, n = top_vertex(model)
    t = np.cross(n, [1.0, 0.0, 0.0])
    t /= np.linalg.norm(t)

    def stroke(steps):
        h = HapticContact(stiff)
        press(h, p0, n, np.linspace(-1e-3, 1e-3, 40))
        fs = []
        for s in np.linspace(0, 8e-3, steps):
            f, st_ = h.step(p0 - 1e-3 * n + s * t)
            assert st_ == Status.CONTACT
            fs.append(f)
        return np.abs(np.diff(np.array(fs), axis=0)).max()

    coarse, fine = stroke(200), stroke(800)
    assert fine < 0.5 * coarse


@pytest.mark.parametrize("loop_plane_seed", [0])
def test_closed_stroke_work_symmetric_vs_full(model, loop_plane_seed):
    """A sticking contact driven round a closed loop: the full (non-symmetric) K does net work,
    the default symmetric one does none (below 1e-9 of the peak stored energy ½ūᵀKū)."""
    r = 2 * model.mean_edge_length
    full = model.stiffness("linear", r, symmetric=False)
    sym = model.stiffness("linear", r)
    p0, n = top_vertex(model)
    depth = 1e-3
    works, energies = {}, {}
    for name, s in (("full", full), ("sym", sym)):
        h = HapticContact(s, friction=1e6)
        press(h, p0, n, np.linspace(-1e-3, depth, 30))
        K = s.at(h.triangle, h.bary)
        skew = 0.5 * (K - K.T)
        w = np.array([skew[2, 1], skew[0, 2], skew[1, 0]])
        w = w / np.linalg.norm(w) if np.linalg.norm(w) > 0 else n
        e1 = np.cross(w, n if abs(w @ n) < 0.9 else [1.0, 0, 0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(w, e1)
        proxy = (h.triangle, h.bary)
        centre = p0 - depth * n
        W, prev_p, prev_f, peak = 0.0, None, None, 0.0
        for th in np.linspace(0, 2 * np.pi, 2001):
            p = centre + 0.5 * depth * (np.cos(th) * e1 + np.sin(th) * e2) - 0.5 * depth * np.cos(th) * 0
            f, st_ = h.step(p)
            assert st_ == Status.CONTACT
            fb = -np.array(f)  # force on the body
            if prev_p is not None:
                W += 0.5 * (fb + prev_f) @ (p - prev_p)
            u = np.array(h.u_bar)
            peak = max(peak, 0.5 * u @ K @ u)
            prev_p, prev_f = p, fb
        assert (h.triangle, h.bary) == proxy  # the contact stuck: the loop is closed in ū
        works[name], energies[name] = W, peak
    assert abs(works["sym"]) < abs(works["full"])
    assert abs(works["sym"]) < 1e-9 * energies["sym"]
    assert abs(works["full"]) > 1e-4 * energies["full"]


samples = st.one_of(
    st.tuples(*[st.floats(allow_nan=True, allow_infinity=True, width=64)] * 3),
    st.tuples(*[st.floats(-0.2, 0.2)] * 3),
    st.lists(st.floats(-0.1, 0.1), min_size=0, max_size=5),
    st.none(), st.text(max_size=3),
)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(samples, min_size=1, max_size=60))
def test_haptic_loop_never_raises_and_never_returns_nan(stiff, seq):
    h = HapticContact(stiff)
    for p in seq:
        f, s = h.step(p)
        assert isinstance(s, Status)
        assert len(f) == 3 and all(math.isfinite(c) for c in f)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.integers(0, 10**6), st.floats(0, 1), st.floats(0, 1))
def test_random_queries_are_finite_and_interpolate(stiff, t, u, v):
    touch = np.flatnonzero(stiff.touchable)
    t = int(touch[t % len(touch)])
    b = np.array([1 - u, u * (1 - v), u * v])
    b[0] = 1.0 - b[1] - b[2]
    K = stiff.at(t, b)
    assert np.all(np.isfinite(K))
    manual = sum(b[k] * stiff.K_vertex[stiff.triangles[t, k]] for k in range(3))
    np.testing.assert_allclose(K, manual, rtol=1e-12, atol=1e-12 * np.abs(manual).max())
