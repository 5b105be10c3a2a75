"""Scripted probe paths over the kidney and what they measure (used by the reference tables, the
examples and the benchmarks).

The stroke: the probe comes down 3 mm above the upper face at x = -45 mm, y = 12 mm, presses
1.5 mm below the (analytic ellipsoid) surface in 0.2 s, then slides at 35 mm/s to x = +45 mm
keeping that depth: 2.77 s of samples at 1 kHz.  The path crosses the large flat-face triangles and
the smaller ones towards both poles.  Two smoothness figures per run:

- ``rms_step``: RMS over the sliding phase of ‖f(k+1) − f(k)‖ [N per 1 ms step];
- ``roughness``: RMS of ‖f‖ minus its 301 ms moving average (10.5 mm of path, about two triangles of
  the kidney's flat face), over the mean ‖f‖: mesh artefacts are the part of the force that varies
  faster than the organ.
"""
from __future__ import annotations

import numpy as np

from pmask.meshes.kidney import SEMI_AXES
from pmask.runtime.contact.state import TOUCHING

RATE = 1000.0  # Hz
DEPTH = 1.5e-3  # m
Y0 = 0.012  # m
X0, X1 = -0.045, 0.045  # m
SPEED = 0.035  # m/s


def stroke_path() -> np.ndarray:
    """Probe positions (n, 3) of the scripted stroke, one per 1 ms tick."""
    a, b, c = SEMI_AXES

    def top(x):
        return c * np.sqrt(max(1 - (x / a) ** 2 - (Y0 / b) ** 2, 0.0))

    approach = [(X0, Y0, top(X0) + 3e-3 - (3e-3 + DEPTH) * k / 200) for k in range(200)]
    n_slide = int(round((X1 - X0) / SPEED * RATE))
    slide = [(x, Y0, top(x) - DEPTH) for x in np.linspace(X0, X1, n_slide)]
    return np.array(approach + slide)


def run_stroke(stiffness, path: np.ndarray, **contact_options):
    """Drive a HapticContact along ``path``; return forces on the user (n, 3) and statuses (n,)."""
    from pmask.runtime import HapticContact

    h = HapticContact(stiffness, **contact_options)
    forces = np.zeros((len(path), 3))
    status = np.zeros(len(path), dtype=int)
    for k, p in enumerate(path):
        f, s = h.step(p)
        forces[k], status[k] = f, s
    return forces, status


def smoothness(forces: np.ndarray, status: np.ndarray, start: int = 200) -> dict:
    """Contact fraction, mean ‖f‖, RMS step and roughness of the sliding phase (from tick ``start``)."""
    f = forces[start:]
    ok = np.isin(status[start:], TOUCHING)
    mag = np.linalg.norm(f, axis=1)
    step = np.linalg.norm(np.diff(f, axis=0), axis=1)
    w = 301
    smooth = np.convolve(mag, np.ones(w) / w, mode="same")
    inner = slice(w // 2, len(mag) - w // 2)
    return {"contact_fraction": float(ok.mean()), "mean_force": float(mag.mean()),
            "rms_step": float(np.sqrt(np.mean(step ** 2))),
            "roughness": float(np.sqrt(np.mean((mag - smooth)[inner] ** 2)) / mag.mean())}


# ------------------------------------------------------------------------------------------ the tour
def kidney_sdf(p: np.ndarray) -> np.ndarray:
    """Approximate signed distance to the kidney's analytic surface (negative inside): the ellipsoid's
    first-order distance (F − 1)/‖∇F‖ intersected with the outside of the hilum ball."""
    from pmask.meshes.kidney import HILUM_CENTRE, HILUM_RADIUS

    p = np.atleast_2d(p)
    a = np.asarray(SEMI_AXES)
    F = np.sum((p / a) ** 2, axis=1)
    g = np.linalg.norm(2 * p / a ** 2, axis=1)
    d_ell = (F - 1.0) / np.maximum(g, 1e-12)
    d_ball = HILUM_RADIUS - np.linalg.norm(p - np.asarray(HILUM_CENTRE), axis=1)
    return np.maximum(d_ell, d_ball)


def level_curve(centre, e1, e2, angles, depth: float) -> np.ndarray:
    """Points at signed distance −depth below the kidney's surface on rays from ``centre`` in the plane
    spanned by e1, e2 (the body is star-shaped about a central point), by bisection on each ray."""
    centre, e1, e2 = (np.asarray(v, float) for v in (centre, e1, e2))
    dirs = np.cos(angles)[:, None] * e1 + np.sin(angles)[:, None] * e2
    lo = np.zeros(len(angles))
    hi = np.full(len(angles), 0.2)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        inside = kidney_sdf(centre + mid[:, None] * dirs) < -depth
        lo, hi = np.where(inside, mid, lo), np.where(inside, hi, mid)
    return centre + (0.5 * (lo + hi))[:, None] * dirs


def resample(curve: np.ndarray, spacing: float) -> np.ndarray:
    """The polyline ``curve`` at constant arc-length spacing (the probe at constant speed)."""
    seg = np.linalg.norm(np.diff(curve, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.arange(0.0, s[-1], spacing)
    return np.column_stack([np.interp(t, s, curve[:, k]) for k in range(3)])


def _line(a, b, spacing):
    n = max(2, int(np.ceil(np.linalg.norm(np.asarray(b) - a) / spacing)) + 1)
    return np.linspace(a, b, n)


def _surface_frame(point):
    """Outward unit normal of the analytic surface at (near) ``point`` and two tangents."""
    h = 1e-6
    g = np.array([(kidney_sdf(point + h * e) - kidney_sdf(point - h * e))[0] / (2 * h) for e in np.eye(3)])
    n = g / np.linalg.norm(g)
    t1 = np.cross(n, [0.0, 1.0, 0.0] if abs(n[1]) < 0.9 else [1.0, 0.0, 0.0])
    t1 /= np.linalg.norm(t1)
    return n, t1, np.cross(n, t1)


def circle(centre_on_surface, depth: float, radius: float = 2.5e-3, tilt_deg: float = 0.0, turns: int = 3,
           speed: float = 0.02, rate: float = RATE) -> np.ndarray:
    """``turns`` closed circles of ``radius`` at ``depth`` below a surface point, in the tangent plane
    tilted by ``tilt_deg`` about its first tangent (tilted: the depth varies by ±radius·sin(tilt))."""
    n, t1, t2 = _surface_frame(np.asarray(centre_on_surface, float))
    a = np.deg2rad(tilt_deg)
    u, v = t1, np.cos(a) * t2 + np.sin(a) * n
    c = np.asarray(centre_on_surface) - depth * n
    steps = int(round(2 * np.pi * radius / speed * rate))
    phi = np.linspace(0.0, 2 * np.pi * turns, steps * turns + 1)
    return c + radius * (np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * v)


def tour(speed: float = 0.02, rate: float = RATE) -> tuple[np.ndarray, list[dict]]:
    """The haptics issue's tour of the default kidney as probe samples at ``rate`` (m, model frame).

    Returns (probes (n, 3), segments): each segment a dict with ``name``, ``start``, ``stop`` (sample
    indices) and ``loop`` (True when the probe returns to where the segment began, so that the energy
    the body gives the hand over it must not be positive).  Segments: approach and press to 2 mm on the
    top face; slide over the top face and round the +x pole (2 mm); slide from the top face down the
    medial side onto the hilum (the fixed support) and across it (5 mm deep); lift off; re-enter;
    circles and circles tilted by 30 degrees at 1, 2, 3 and 4 mm, three turns each; lift off.
    """
    sp = speed / rate
    pieces, segments = [], []

    def add(name, pts, loop=False):
        pts = np.asarray(pts)
        if pieces and np.linalg.norm(pts[0] - pieces[-1][-1]) > 2 * sp:  # transit through the air, over the top
            a, b = pieces[-1][-1], pts[0]
            safe = SEMI_AXES[2] + 0.012
            hop = np.vstack([_line(a, [a[0], a[1], safe], sp), _line([a[0], a[1], safe], [b[0], b[1], safe], sp),
                             _line([b[0], b[1], safe], b, sp)])
            pieces.append(hop)
        start = sum(len(p) for p in pieces)
        pieces.append(pts)
        segments.append({"name": name, "start": start, "stop": start + len(pts), "loop": loop})

    top_centre = np.array([0.0, 0.004, 0.0])
    # press on the top face at x = -20 mm, y = 4 mm
    s0 = level_curve(top_centre, [1.0, 0, 0], [0, 0, 1.0], np.array([np.pi - 0.42]), 0.0)[0]
    n0, _, _ = _surface_frame(s0)
    add("approach", _line(s0 + 0.005 * n0, s0 + 0.0005 * n0, sp))
    add("press", _line(s0 + 0.0005 * n0, s0 - 0.002 * n0, 0.5 * sp))
    # over the top face and round the +x pole, 2 mm deep (plane y = 4 mm)
    ang = np.linspace(np.pi - 0.42, -0.6, 4000)
    curve = level_curve(top_centre, [1.0, 0, 0], [0, 0, 1.0], ang, 0.002)
    add("top face and pole", resample(np.vstack([s0 - 0.002 * n0, curve]), sp))
    # back over the pole to the top (so the slide is a closed loop in depth) and lift off
    add("back over the pole", resample(curve[::-1], sp))
    n1, _, _ = _surface_frame(level_curve(top_centre, [1.0, 0, 0], [0, 0, 1.0], np.array([np.pi - 0.42]), 0.0)[0])
    last = pieces[-1][-1]
    add("lift off", _line(last, last + 0.006 * n1, sp))
    # onto the hilum and across it, 5 mm deep: the plane x = 0, from the top face over the medial side
    centre_x0 = np.array([0.0, 0.004, 0.0])
    ang = np.linspace(np.pi / 2, -np.pi / 2, 5000)  # from the top (+z) over the hilum (-y) to the bottom
    curve = level_curve(centre_x0, [0, -1.0, 0], [0, 0, 1.0], ang, 0.005)  # angle 0: the hilum (-y)
    start = level_curve(centre_x0, [0, -1.0, 0], [0, 0, 1.0], np.array([np.pi / 2]), 0.0)[0]
    add("re-enter", _line(start + 0.004 * np.array([0, 0, 1.0]), curve[0], sp))
    add("onto and across the hilum", resample(curve, sp))
    add("back across the hilum", resample(curve[::-1], sp))
    last = pieces[-1][-1]
    add("lift off the top", _line(last, last + 0.006 * np.array([0, 0, 1.0]), sp))
    # circles on the top face (x = 10 mm, y = 0), in and out between them
    c_top = level_curve(np.array([0.01, 0.0, 0.0]), [0, 0, 1.0], [1.0, 0, 0], np.array([0.0]), 0.0)[0]
    nt, _, _ = _surface_frame(c_top)
    above = c_top + 0.004 * nt
    for tilt in (0.0, 30.0):
        for depth in (0.001, 0.002, 0.003, 0.004):
            ring = circle(c_top, depth, tilt_deg=tilt, speed=speed, rate=rate)
            add(f"in to {depth * 1e3:g} mm", _line(above, ring[0], sp))
            turn = (len(ring) - 1) // 3
            for k in range(3):  # each turn is a closed loop of its own
                add(f"circle {depth * 1e3:g} mm" + (f", tilted {tilt:g} deg" if tilt else "") + f", turn {k + 1}",
                    ring[k * turn:(k + 1) * turn + 1], loop=True)
            add("out", _line(ring[-1], above, sp))
    # deep at the +x pole (radius of curvature 7.3 mm in the x-z plane): press 12 mm, rock ±4 mm, come out
    tip = np.array([SEMI_AXES[0], 0.0, 0.0])
    down = _line(tip + [0.004, 0, 0], tip - [0.012, 0, 0], sp)
    rock = np.vstack([_line(down[-1], down[-1] + [0, 0, 0.004], sp), _line(down[-1] + [0, 0, 0.004],
                      down[-1] - [0, 0, 0.004], sp), _line(down[-1] - [0, 0, 0.004], down[-1], sp)])
    add("12 mm deep at the pole", np.vstack([down, rock, down[::-1]]), loop=True)
    # the references of continuity: the same motions at the same speed on smooth free surface, away from the
    # support and from creases: slides over the top face, and presses to 6 mm and back on the top face, the
    # lateral face, the +x pole and the free tissue next to the hilum (the stiffest free tissue)
    for depth in (0.002, 0.004, 0.006):
        ang = np.linspace(np.pi - 0.5, np.pi - 1.3, 1500)
        add(f"reference slide {depth * 1e3:g} mm", resample(level_curve(top_centre, [1.0, 0, 0], [0, 0, 1.0], ang,
                                                                       depth), sp))
    for name, centre, e1, e2, angle in (("top face", top_centre, [1.0, 0, 0], [0, 0, 1.0], np.pi - 0.42),
                                        ("lateral face", np.zeros(3), [0, 1.0, 0], [0, 0, 1.0], 0.0),
                                        ("pole", np.zeros(3), [1.0, 0, 0], [0, 1.0, 0], 0.0),
                                        ("next to the hilum", np.array([0.0, 0.004, 0.0]), [0, -1.0, 0], [0, 0, 1.0],
                                         0.75)):
        s0 = level_curve(centre, e1, e2, np.array([angle]), 0.0)[0]
        n0, _, _ = _surface_frame(s0)
        down = _line(s0 + 0.003 * n0, s0 - 0.006 * n0, sp)
        add(f"reference press, {name}", np.vstack([down, down[::-1]]))
    return np.vstack(pieces), segments


def run_contact(contact, probes: np.ndarray) -> dict:
    """Step a contact (:class:`pmask.runtime.HapticContact`) along ``probes``: the forces on the user,
    statuses, proxy points, penetrations and stored energies ½ f·ū' per tick."""
    n = len(probes)
    out = {"force": np.zeros((n, 3)), "status": np.zeros(n, int), "proxy": np.full((n, 3), np.nan),
           "depth": np.zeros(n), "stored": np.zeros(n)}
    for k, p in enumerate(probes):
        f, s = contact.step(p)
        out["force"][k], out["status"][k] = f, s
        x = contact.proxy
        if x is not None:
            out["proxy"][k] = x
        out["depth"][k] = contact.depth
        if s in TOUCHING:
            out["stored"][k] = 0.5 * float(np.dot(-np.asarray(f), contact.u_bar))
    return out


def tour_metrics(run: dict, probes: np.ndarray, segments: list[dict]) -> dict:
    """The haptics issue's three bounds on a tour, per segment.

    ``given``: the energy the body gives the hand over a closed loop, Σ f_user,k · (p_k+1 − p_k) (the
    force the device holds during each tick), over the loop's peak stored energy; ``given_trapezoid`` the
    same with the mean force of each tick.  ``max_step``: the largest ‖f_k+1 − f_k‖; ``ratio`` that over the
    reference, the largest on smooth free surface at the same speed (the ``reference`` segments).
    ``proxy``: the largest proxy motion per tick over the probe's, while in contact.
    """
    F, S, X = run["force"], run["status"], run["proxy"]
    dP = np.diff(probes, axis=0)
    zoh = np.einsum("ij,ij->i", F[:-1], dP)
    trap = np.einsum("ij,ij->i", 0.5 * (F[:-1] + F[1:]), dP)
    dF = np.linalg.norm(np.diff(F, axis=0), axis=1)
    dX = np.linalg.norm(np.diff(X, axis=0), axis=1)
    dp = np.linalg.norm(dP, axis=1)
    contact = (S == 1) | (S == 6)
    both = contact[1:] & contact[:-1]
    ref = max(dF[s["start"]:s["stop"] - 1].max() for s in segments if s["name"].startswith("reference"))
    out = {"reference": float(ref), "segments": []}
    for s in segments:
        i, j = s["start"], s["stop"]
        peak = float(run["stored"][i:j].max())
        prox = (np.maximum(dX[i:j - 1] - 1e-12, 0.0) / np.maximum(dp[i:j - 1], 1e-12))[both[i:j - 1]]
        out["segments"].append({
            "name": s["name"], "loop": s["loop"], "peak_stored": peak,
            "given": float(zoh[i:j - 1].sum()) / peak if peak > 0 else 0.0,
            "given_trapezoid": float(trap[i:j - 1].sum()) / peak if peak > 0 else 0.0,
            "max_step": float(dF[i:j - 1].max()), "ratio": float(dF[i:j - 1].max() / ref),
            "proxy": float(prox.max()) if len(prox) else 0.0})
    return out


def region_edge_slide(region_z: float = 0.0, depth: float = 0.002, speed: float = 0.02, rate: float = RATE,
                      parts: bool = False):
    """For an artifact precomputed with ``--contact "z>REGION_Z"`` (metres): press on the top face, slide
    down the lateral (+y) side across the region's edge at z = region_z and 10 mm beyond it, slide back and
    lift off: a closed loop that crosses the edge twice.  With ``parts``, also the sample ranges of the four
    pieces, {"press", "out", "back", "lift"}: slices."""
    end = np.arcsin(np.clip((region_z - 0.01) / SEMI_AXES[2], -1, 1))
    return _out_and_back(np.zeros(3), [0, 1.0, 0], np.pi / 2 - 0.3, end, depth, speed / rate, parts)


def rim_out_and_back(depth: float = 0.002, end: float = 0.0, speed: float = 0.02, rate: float = RATE,
                     parts: bool = False):
    """Press on the top face (x = 0, 13 mm off the middle towards the hilum), slide ``depth`` deep down the
    medial (−y) side, over the hilum's lip (the rim of its fixed support, at about 0.35 rad) into the hilum
    to the angle ``end`` (0: the hilum's middle; angles from −y towards +z about (0, 4 mm, 0)), slide back
    and lift off: the hands issue's out-and-back across the support rim, a closed path.  ``parts`` as in
    :func:`region_edge_slide`."""
    return _out_and_back(np.array([0.0, 0.004, 0.0]), [0, -1.0, 0], np.pi / 2 - 0.3, end, depth, speed / rate,
                         parts)


def _out_and_back(centre, e1, a0: float, a1: float, depth: float, sp: float, parts: bool):
    """Press to ``depth`` at angle a0 in the plane of e1 and +z through ``centre``, slide to a1 at that depth
    (:func:`level_curve`), slide back, lift off (3 mm above the surface at both ends)."""
    ang = np.linspace(a0, a1, 3000)
    curve = resample(level_curve(centre, e1, [0, 0, 1.0], ang, depth), sp)
    start = level_curve(centre, e1, [0, 0, 1.0], np.array([a0]), 0.0)[0]
    n0, _, _ = _surface_frame(start)
    press = _line(start + 0.003 * n0, curve[0], sp)
    probes = np.vstack([press, curve, curve[::-1], press[::-1]])
    if not parts:
        return probes
    a, b = len(press), len(press) + len(curve)
    return probes, {"press": slice(0, a), "out": slice(a, b), "back": slice(b, b + len(curve)),
                    "lift": slice(b + len(curve), len(probes))}


#: the hands issue's straight pushes into the surface: along the inward normal, and 30° and 45° off it towards
#: four azimuths (radians, about the normal)
PUSH_LINES = ((0, (0.0,)), (30, (0.0, 1.57, 3.14, 4.71)), (45, (0.0, 1.57, 3.14, 4.71)))


def vertex_normal(surface, v) -> np.ndarray:
    """The contact normal at mesh vertex v of a :class:`pmask.runtime.contact.ContactSurface` (the mesh's or its
    subdivision surface's: both keep the mesh's vertices, indices and positions)."""
    from pmask.runtime.contact import tracking

    t = int(np.flatnonzero(np.any(surface.T == v, axis=1))[0])
    return np.array(tracking.normal(surface, t, *(surface.T[t] == v).astype(float)))


def push_line(x, normal, tilt_deg: float, azimuth: float, depth: float = 0.015, speed: float = 0.01,
              rate: float = RATE) -> tuple[np.ndarray, np.ndarray]:
    """Probe positions of a straight push from 2 mm outside through the surface point x, ``tilt_deg`` off the
    inward normal −N towards ``azimuth``, ``depth`` along the line past x, at ``speed`` (the issue's 10 mm/s);
    and each one's distance along the line past x (negative outside)."""
    N = np.asarray(normal, float)
    a = np.cross(N, [1.0, 0.0, 0.0])
    if np.linalg.norm(a) < 0.3:
        a = np.cross(N, [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    t = np.radians(tilt_deg)
    line = -np.cos(t) * N + np.sin(t) * (np.cos(azimuth) * a + np.sin(azimuth) * np.cross(N, a))
    s = np.arange(-0.002, depth, speed / rate)
    return np.asarray(x, float) + s[:, None] * line, s


def depth_below(points, triangles):
    """A function of probe positions (m, 3) giving their distance to the undeformed surface (to a dense sampling of
    its triangles, 1/12 of an edge apart: ~0.25 mm on the default kidney)."""
    from scipy.spatial import cKDTree

    b = np.array([(i, j, 12 - i - j) for i in range(13) for j in range(13 - i)], float) / 12
    tree = cKDTree(np.einsum("sk,tkd->tsd", b, np.asarray(points)[np.asarray(triangles)]).reshape(-1, 3))
    return lambda probes: tree.query(probes)[0]


def push_metrics(force, status, depth, speed: float = 0.01, rate: float = RATE) -> dict:
    """What a straight push does over the stretch where the line goes deeper (from first contact to the deepest
    point of the line, the ticks where its depth below the surface grows by at least half the push's speed;
    ``depth`` signed, negative outside: :func:`depth_below` times the sign of :func:`push_line`'s distance):

    - ``released``: the contact ended on the way (it must not);
    - ``fall``: the largest fall of ‖F‖ below its largest value so far, relative (the issue: none);
    - ``fall_contact``: the largest fall of ‖F‖ from one tick to the next where both ticks are in contact short of
      the deep regime (status CONTACT or REGION_EDGE, δ < δ_lin);
    - ``deep``: the status said DEEP somewhere on the stretch; ``end``: the deepest tick; ``fall_at``: the tick of
      the largest fall (-1 when none)."""
    from pmask.runtime.contact.state import Status

    force, status, signed = np.asarray(force), np.asarray(status), np.asarray(depth, float)
    mag = np.linalg.norm(force, axis=1)
    run = np.maximum.accumulate(signed)
    back = np.flatnonzero((signed < run - 1e-4) & (run > 0))
    end = int(np.argmax(signed[:back[0]])) if len(back) else len(signed) - 1
    touching = np.isin(status, TOUCHING)
    first = int(np.flatnonzero(touching)[0]) if touching.any() else end
    i = np.arange(first + 1, end + 1)
    i = i[np.diff(signed)[i - 1] >= 0.5 * speed / rate]
    m = mag[i]
    best = np.maximum.accumulate(m) if len(m) else m
    shallow = np.isin(status, (Status.CONTACT, Status.REGION_EDGE))
    j = i[shallow[i] & shallow[i - 1]]
    falls = (best - m) / best
    return {"released": bool(not touching[first:end + 1].all()),
            "fall": float(np.max(falls)) if len(m) else 0.0,
            "fall_at": int(i[np.argmax(falls)]) if len(m) and np.max(falls) > 0.0 else -1,
            "fall_contact": float(np.max(1.0 - mag[j] / mag[j - 1])) if len(j) else 0.0,
            "deep": bool(np.any(status[first:end + 1] == Status.DEEP)), "end": end, "first": first}


def grasp_path(model, depth: float = 2.5e-3, slide: float = 3e-3, press: int = 400, hold: int = 300) -> np.ndarray:
    """Two jaws squeezing a model's middle from above and below, (press + hold, 2, 3) probe positions: from 2 mm
    outside to ``depth`` in along each jaw's vertex normal over ``press`` ticks, then held that deep while both
    slide ``slide`` along x over ``hold`` ticks (so that friction acts and the contacts cross triangles).  The
    jaws sit at the highest and lowest contact vertices within the middle 30 % of the model's x extent."""
    from pmask.runtime.geometry import vertex_normals

    P, free = model.points, model.contact[model.core]
    middle = free[np.abs(P[free, 0]) < 0.3 * np.abs(P[free, 0]).max()]
    n = vertex_normals(P, model.triangles)
    jaws = [(P[v], n[v]) for v in (middle[np.argmax(P[middle, 2])], middle[np.argmin(P[middle, 2])])]
    d = np.concatenate([np.linspace(-2e-3, depth, press), np.full(hold, depth)])
    x = np.concatenate([np.zeros(press), np.linspace(0.0, slide, hold)])
    return np.stack([p - d[:, None] * nv + x[:, None] * [1.0, 0.0, 0.0] for p, nv in jaws], axis=1)
