"""The hands issue's deep presses (#24 item 1) on the default kidney: along straight pushes into the surface,
normal and 30° and 45° off it, at the pole, the flat top, the lateral face, the hilum's lip (the kidney's one
saddle, next to the support) and the support rim, pushing harder never feels softer; a normal push on a
smooth convex part keeps its force within 10° of the contact normal at first contact; past δ_lin the
status says DEEP and there the force keeps growing.  At random sites it never falls, short of δ_lin or past it
(past it the force is held where the law's own would fall, and the hold only takes energy out)."""
from __future__ import annotations

import numpy as np
import pytest

from pmask.pipeline.strokes import PUSH_LINES, depth_below, push_line, push_metrics, vertex_normal
from pmask.runtime import HapticContact, Status


@pytest.fixture(scope="module")
def kidney(model, stiff):
    """Sites (the contact surface's point at a mesh vertex, contact normal there), and the depth of points below the
    undeformed surface (:func:`pmask.pipeline.strokes.depth_below`; the mesh drawn where the contact surface has
    its vertices, which near the hilum's lip is rounded)."""
    free = model.contact[model.core]
    srf = HapticContact(stiff, engine="python").surface
    P = srf.mesh_points
    fixed = np.asarray(model.fixed)
    to_support = np.linalg.norm(P[free][:, None] - P[fixed][None], axis=2).min(axis=1)
    lateral = free[np.abs(P[free, 0]) < 0.005]
    curv = np.linalg.eigvalsh(np.asarray(srf._S).reshape(-1, 3, 3))[:, 0]  # the smaller principal curvature
    sites = {"pole": free[np.argmax(P[free, 0])], "top": free[np.argmax(P[free, 2])],
             "lateral face": lateral[np.argmax(P[lateral, 1])], "support rim": free[np.argmin(to_support)],
             "hilum's lip": free[np.argmin(curv[free])]}
    normals = {name: (P[v], vertex_normal(srf, v)) for name, v in sites.items()}
    return normals, depth_below(P, model.triangles)


def push(stiff, x, N, tilt, azimuth, below):
    """A straight push (:func:`pmask.pipeline.strokes.push_line`): forces, statuses and the signed depth below
    the undeformed surface per tick."""
    probes, s = push_line(x, N, tilt, azimuth)
    h = HapticContact(stiff)
    out = [h.step(p) for p in probes]
    F = np.array([f for f, _ in out])
    status = np.array([int(st) for _, st in out])
    return F, status, below(probes) * np.sign(s)


@pytest.mark.parametrize("site", ["pole", "top", "lateral face", "hilum's lip", "support rim"])
def test_pushing_harder_never_feels_softer(stiff, kidney, site):
    """Over the stretch of each push where the line goes deeper (its depth grows by at least half the push's
    speed, up to the deepest point of the line, ≤ 15 mm; :func:`pmask.pipeline.strokes.push_metrics`): the
    contact never ends and |F| never falls below its largest value so far, beyond round-off (measured: not at
    all, on every line; it fell by 27 % at the pole before, and by 0.94 % on a 30° line at the lateral face with
    an earlier form of the deep law, whose increments followed k(x) as the contact slid towards softer tissue);
    for a normal push F stays within 10° of the contact normal at first contact (the issue asks it on smooth
    convex parts; the law's bound, atan(2 FROZEN_CHANGE) = 10.0°, holds at every site: measured 6.2° at the pole,
    5.6° at the top, 8.9° at the lateral face, 9.1° at the hilum's lip, 9.6° at the support rim, pushed through the
    contact surface's point there (through the mesh's vertex, off the surface where it is rounded, the rim gave
    12.0°; 6.1°, 6.9°, 9.1°, 7.3° and 9.2° while the lip was a crease); it turned 45-65°
    at the pole before, and 12.3° at the lateral face and 12.6° at the rim with FROZEN_CHANGE 1/8 once the
    projection was exact); and past δ_lin the status is DEEP.  These five sites hold it past δ_lin too; other
    sites do not (the next test)."""
    normals, below = kidney
    x, N = normals[site]
    for tilt, azimuths in PUSH_LINES:
        for az in azimuths:
            F, status, depth = push(stiff, x, N, tilt, az, below)
            m = push_metrics(F, status, depth)
            assert not m["released"], (site, tilt, az)
            assert m["fall"] <= 1e-12, (site, tilt, az, m["fall"])
            if tilt == 0:
                end, first = m["end"], m["first"]
                assert depth[end] > 0.01 and Status.DEEP in status, (site, depth[end])
                on = np.arange(first + 5, end + 1)
                mag = np.linalg.norm(F[on], axis=1)
                angle = np.degrees(np.arccos(np.clip(F[on] @ N / mag, -1.0, 1.0)))
                assert angle.max() <= 10.0, (site, angle.max())


def test_at_random_sites_pushing_harder_never_feels_softer(model, stiff, kidney):
    """The same nine lines at 20 free vertices drawn at random (seeded): the contact never ends, and |F| never
    falls as the line goes deeper, beyond round-off: neither short of the deep regime (status CONTACT, δ < δ_lin,
    from one tick to the next) nor past δ_lin (DEEP, below its largest value so far).  Past δ_lin the law's own
    |F| can fall: where a frozen contact slides obliquely into stiffer tissue its tangential term outgrows the
    freezing's bound and then shrinks faster than the normal part grows as ∇k weakens, or where the proxy moves
    by dead reckoning beside the support the penetration itself stops growing (both traced by hand: the haptics
    guide's "Pressing deep").  There the force is held (:mod:`pmask.runtime.contact.output`; the next test shows
    what it costs)."""
    _, below = kidney
    srf = HapticContact(stiff, engine="python").surface
    P = srf.mesh_points
    sites = np.random.default_rng(1).choice(model.contact[model.core], 20, replace=False)
    deep = 0
    for v in sites:
        N = vertex_normal(srf, v)
        for tilt, azimuths in PUSH_LINES:
            for az in azimuths:
                F, status, depth = push(stiff, P[v], N, tilt, az, below)
                m = push_metrics(F, status, depth)
                assert not m["released"], (v, tilt, az)
                assert m["fall_contact"] <= 1e-12, (v, tilt, az, m["fall_contact"])
                assert m["fall"] <= 1e-12, (v, tilt, az, m["fall"])
                deep += m["deep"]
    assert deep > 0  # the lines do reach the deep regime, so the bound above covers it, not vacuous


def test_the_deep_hold_only_takes_energy_out(model, stiff):
    """Past δ_lin, while δ grows and the hand does work against the force, the force's magnitude is held at
    least at the last tick's (the factor hs on it returns to 1 over ten ticks otherwise): it only resists the
    motion, so it can only take energy out.  In and straight back out along the 30° lines (azimuths 0 and 4.71) at
    the random sites, controller off: on every line the hand gets back at most what it put in (net ≤ 1 % of the
    press's work, the issue's bound for closed loops; measured at most +0.06 %, on a line where the law's own round
    trip is not exact and the hold barely acts), and on every line where the hold acts its own share of the work,
    Σ (1 − 1/hs) f·Δp over the ticks (the force sent is hs times the law's), takes energy out: ≤ 1e-6 of the
    press's work (measured −6.7 % to +1.6e-7; the +1.6e-7 is a line where hs − 1 reached 3e-4 and, during its
    ten-tick release, the probe moved along the force: the release gives back a little of what the hold held).  The
    hold does act here (its factor reached 1.54: the law's own |F| fell to 0.65 of its
    largest past δ_lin, beyond the line's deepest point).  The native engine holds the same force, to round-off."""
    srf = HapticContact(stiff, engine="python").surface
    P = srf.mesh_points
    sites = np.random.default_rng(1).choice(model.contact[model.core], 20, replace=False)
    held, most = [], (1.0, None)
    for v in sites:
        N = vertex_normal(srf, v)
        for az in (0.0, 4.71):
            probes, _ = push_line(P[v], N, 30, az)
            path = np.vstack([probes, probes[::-1]])
            h = HapticContact(stiff, engine="python", passivity=False)
            F, scale = [], []
            for p in path:
                F.append(h.step(p)[0])
                scale.append(h._state().hold_scale)
            F, scale = np.array(F), np.array(scale)
            given = np.einsum("ij,ij->i", F[:-1], np.diff(path, axis=0))
            press = -given[:len(probes) - 1].sum()
            net = given.sum()
            assert press > 0 and net <= 0.01 * press, (v, az, net / press)
            if scale.max() > 1.0 + 1e-9:
                held.append(float(((1.0 - 1.0 / scale[:-1]) * given).sum() / press))
                if scale.max() > most[0]:
                    most = (scale.max(), path, F)
    assert most[0] > 1.05, most[0]  # the hold acts on these lines
    assert max(held) <= 1e-6, held  # and where it acts, it takes energy out
    _, path, F = most
    native = HapticContact(stiff, engine="native", passivity=False)
    Fn = np.array([native.step(p)[0] for p in path])
    assert np.abs(Fn - F).max() <= 1e-12 * np.abs(F).max()
