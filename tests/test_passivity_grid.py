"""The hands issue's passivity grid (#24 item 2) on the default kidney's upper face: closed circles at depth
2/4/6 mm, tilted 0/30/45° from the tangent plane, of radius 2.5/5 mm, both ways round, at 20 mm/s and 1 kHz;
the energy the body gives the hand over the third loop (the force the device holds times the probe's
motion), against the loop's peak stored energy."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from pmask.pipeline.strokes import vertex_normal
from pmask.runtime import HapticContact
from pmask.runtime.contact.state import TOUCHING

SPEED, RATE = 0.02, 1000.0


def loop_energy(stiff, probes, start, n, **options):
    """(energy given to the hand over probes[start:start + n], the largest stored energy there)."""
    h = HapticContact(stiff, **options)
    F, stored = np.zeros((len(probes), 3)), np.zeros(len(probes))
    for i, p in enumerate(probes):
        f, s = h.step(p)
        F[i] = f
        stored[i] = 0.5 * float(np.dot(-np.asarray(f), h.u_bar)) if s in TOUCHING else 0.0
    seg = slice(start - 1, start + n)
    return float(np.sum(F[seg][:-1] * np.diff(probes[seg], axis=0))), float(stored[seg].max())


@pytest.fixture(scope="module", params=["auto", 0], ids=["default", "mesh"])
def grid(request, model, stiff):
    """Every loop's (given with the controller off, given with it on, peak) as fractions of the peak, on the
    default contact surface (levels "auto": the mesh's Loop subdivision surface, two levels on this kidney) and on
    the mesh itself (levels=0)."""
    levels = request.param
    P = model.points
    free = model.contact[model.core]
    v = free[np.argmax(P[free, 2] - 0.2 * np.abs(P[free, 0] - 0.01))]  # the upper face, 10 mm off the middle
    srf = HapticContact(stiff, engine="python", levels=levels).surface
    assert srf.levels == (2 if levels == "auto" else 0)
    N = vertex_normal(srf, v)
    a = np.cross(N, [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(N, a)
    step = SPEED / RATE
    out = {}
    for depth, tilt, r, sense in itertools.product((0.002, 0.004, 0.006), (0, 30, 45), (0.0025, 0.005), (1, -1)):
        th = np.radians(tilt)
        e1 = np.cos(th) * a + np.sin(th) * N
        n = int(2 * np.pi * r / step)
        ang = sense * np.linspace(0.0, 2 * np.pi, n + 1)
        loop = P[v] - depth * N + r * (np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * b)
        approach = np.linspace(loop[0] + (depth + 0.003) * N, loop[0], int((depth + 0.003) / step))
        probes = np.vstack([approach, loop[1:], loop[1:], loop[1:]])
        start = len(approach) + 2 * n
        off, peak = loop_energy(stiff, probes, start, n, passivity=False, levels=levels)
        on, _ = loop_energy(stiff, probes, start, n, levels=levels)
        out[(depth, tilt, r, sense)] = (off / peak, on / peak)
    return levels, out


def test_the_law_is_passive_round_closed_loops_without_the_controller(grid):
    """With the passivity controller off, no loop gives the hand more than 1 % of its peak stored energy on the
    default contact surface (the issue's bound; measured 0.39 %, the 2 mm circle of 5 mm, untilted: the same circle
    the other way round takes 0.37 %, so what is left is the curl of a force that is not quite a gradient; with the
    zero-order hold's correction k N Nᵀ alone, which damped every loop a little, 0.22 % one way and −0.82 % the
    other) and 2 % on the mesh (measured 1.92 %, the 2 mm circle of 5 mm tilted 30°; it was 5.2 % on a 45° circle
    and ~5 % at depth before).

    On the mesh what remains is the flat triangles under interpolated normals, the proxy moving on facets while
    the force follows N, k δ (N − n_f)·dx over the part of a loop in contact (N and a facet's normal up to 9°
    apart on this mesh).  Measured by hand: adding the exact gradient of the energy on the facets,
    −φ (n_f / (n_f·N) − N), takes four loops (the worst two among them) within ±0.15 % (that term is nearly all of
    it), but it jumps at every edge: a 2 mm deep slide over the top changes the force by 4.1 mN in one tick
    against 0.07 mN without it, 60x.  Loop's subdivision surface halves the angle a level (2.95° after two), so
    the interpolated normal is the facets' to within it and the force stays continuous (the tour's bounds,
    tests/test_haptics.py, hold on it too)."""
    levels, loops = grid
    worst = max(loops.items(), key=lambda kv: kv[1][0])
    assert worst[1][0] <= (0.01 if levels else 0.02), worst
    assert len(loops) == 36


def test_the_controller_takes_little_where_the_law_is_passive(grid):
    """With the controller on it takes at most 2 % of a loop's peak energy beyond what the law itself dissipates
    on the default contact surface (the issue's bound; measured 0.75 %) and 2.5 % on the mesh (measured 2.19 %; it
    dragged 476-614 µJ over a rim slide before, when a new contact's first tick, the device holding no force yet,
    counted as energy the hand had not put in)."""
    levels, loops = grid
    took = {k: off - on for k, (off, on) in loops.items()}
    worst = max(took.items(), key=lambda kv: kv[1])
    assert worst[1] <= (0.02 if levels else 0.025), worst
