"""The hands issue's deep presses (#24 item 1) on the default kidney: along straight pushes into the surface,
normal and 30° and 45° off it, at the pole, the flat top, the lateral face, the hilum's lip (the kidney's one
saddle, next to the support) and the support rim, pushing harder never feels softer; a normal push on a
smooth convex part keeps its force within 10° of the contact normal at first contact; past δ_lin the
status says DEEP and there the force keeps growing.  At random sites it never falls short of δ_lin; past it, it
does on a few lines in a hundred (the haptics bench counts them: the issue's "never softer" is not met there)."""
from __future__ import annotations

import numpy as np
import pytest

from pmask.pipeline.strokes import PUSH_LINES, depth_below, push_line, push_metrics, vertex_normal
from pmask.runtime import HapticContact, Status


@pytest.fixture(scope="module")
def kidney(model, stiff):
    """Sites (vertex, contact normal there), and the depth of points below the undeformed surface
    (:func:`pmask.pipeline.strokes.depth_below`)."""
    P = model.points
    free = model.contact[model.core]
    srf = HapticContact(stiff, engine="python").surface
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
    convex parts; the law's bound, atan(2 FROZEN_CHANGE) = 10.0°, holds at every site: measured 6.1° at the pole,
    6.9° at the top, 9.1° at the lateral face, 7.3° at the hilum's lip, 9.2° at the support rim; it turned 45-65°
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


def test_at_random_sites_pushing_harder_never_feels_softer_short_of_the_deep_regime(model, stiff, kidney):
    """The same nine lines at 20 free vertices drawn at random (seeded): the contact never ends, and while it is
    short of the deep regime (status CONTACT, δ < δ_lin) |F| never falls from one tick to the next as the line
    goes deeper, beyond round-off (measured: not at all).  Past δ_lin (DEEP) it can: where a frozen contact
    slides obliquely into stiffer tissue its tangential term outgrows the freezing's bound and then shrinks faster
    than the normal part grows as ∇k weakens, or where the proxy moves by dead reckoning beside the support the
    penetration itself stops growing (both traced by hand: the haptics guide's "Pressing deep"); how often and
    by how much is measured at 80 random sites by the haptics bench (which that guide cites), not asserted
    here."""
    _, below = kidney
    P = model.points
    srf = HapticContact(stiff, engine="python").surface
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
                deep += m["deep"]
    assert deep > 0  # the lines do reach the deep regime, so the bound above is short of it, not vacuous
