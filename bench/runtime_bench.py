"""Runtime benchmarks for `make bench`: the haptic step from C, through the binding and in the Python
engine, tight and in a paced 1 kHz loop, each beside its noise reference; several contacts; the
native servo thread beside a busy Python thread; deformation and how long it holds the GIL;
re-acquisition and batch K(x).

Every timing here is a measurement, not a test: nothing asserts a time.  References:

- C: the timer itself (two clock_gettime calls) and eq. 15 at the contact's own point (three 3x3 blocks
  blended: the issue's "physical limit" of a step), timed the same way in the same loop;
- Python: a trivial Python function taking the same probe list (the interpreter's floor), timed the same
  way in the same loop.
"""
from __future__ import annotations

import json
import math
import shutil
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
PACED_TICKS = 3000


def _stats(ts_us) -> dict:
    ts = np.asarray(ts_us, float)
    return {"median_us": float(np.median(ts)), "p99_us": float(np.percentile(ts, 99)),
            "p999_us": float(np.percentile(ts, 99.9)), "max_us": float(ts.max()), "n": int(len(ts))}


def gmsh_ellipsoid(n_target: int, axes=(0.055, 0.03, 0.02)):
    """A gmsh (frontal-Delaunay) surface mesh of an ellipsoid with about n_target vertices: the synthetic
    surfaces of the query benchmarks, with a mesher's valences (a UV sphere's pole fans are not)."""
    from pmask.precompute.meshing import gmsh_session

    a, b, c = axes
    p = 1.6075
    area = 4 * np.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3) ** (1 / p)
    h = np.sqrt(2 * area / (np.sqrt(3) * n_target))
    with gmsh_session("synthetic") as gmsh:
        s = gmsh.model.occ.addSphere(0, 0, 0, 1.0)
        gmsh.model.occ.dilate([(3, s)], 0, 0, 0, a, b, c)
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMin", h)
        gmsh.option.setNumber("Mesh.MeshSizeMax", h)
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
        gmsh.model.mesh.generate(2)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        _, _, tri = gmsh.model.mesh.getElements(2)
    order = np.argsort(tags)
    pts = coords.reshape(-1, 3)[order]
    tris = np.searchsorted(tags[order], np.concatenate(tri).reshape(-1, 3))
    used, inv = np.unique(tris, return_inverse=True)
    pts, tris = pts[used], inv.reshape(-1, 3)
    q = pts[tris]
    if np.einsum("ij,ij->i", np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]), q[:, 0]).sum() < 0:
        tris = tris[:, ::-1].copy()
    return pts, tris


def synthetic_stiffness(n: int):
    from pmask.runtime import SurfaceStiffness

    pts, tris = gmsh_ellipsoid(n)
    rng = np.random.default_rng(1)
    X = rng.standard_normal((len(pts), 3, 3)) * 10
    K = np.einsum("nij,nkj->nik", X, X) + 50 * np.eye(3)
    return SurfaceStiffness(pts, tris, K)

def equator_path(axes=(0.055, 0.03, 0.02), depth=0.0015, steps=20000, turns=2.0):
    """From 3 mm outside, in to ``depth`` over 100 steps, then round the equator ``turns`` times."""
    approach = np.column_stack([np.full(100, axes[0] + 0.003 - np.linspace(0, 0.003 + depth, 100)),
                                np.zeros(100), np.zeros(100)])
    th = np.linspace(0, 2 * np.pi * turns, steps)
    a, b = axes[0] - depth, axes[1] - depth
    return np.concatenate([approach, np.column_stack([a * np.cos(th), b * np.sin(th), np.zeros(steps)])])


def build_servo_bench(work: Path) -> Path | None:
    """Compile bench/servo_bench.c with the core, as a C application would."""
    from pmask.runtime import servo

    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        return None
    exe = work / "servo_bench"
    inc = servo.include_dir()
    subprocess.run([cc, "-std=c99", "-O2", "-ffp-contract=off", f"-I{inc}", str(HERE / "servo_bench.c"),
                    *map(str, servo.sources()), "-lm", "-lpthread", "-o", str(exe)], check=True)
    return exe


def write_trace(path: Path, probes: np.ndarray) -> Path:
    P = np.ascontiguousarray(probes, "<f8")
    with open(path, "wb") as f:
        f.write(struct.pack("<q", len(P)))
        f.write(P.tobytes())
    return path


def c_bench(exe: Path, table: Path, trace: Path, n: int = 1, paced: int = PACED_TICKS, batch: int = 0,
            reacquire: int = 0, uncoupled: bool = False, ratio: int = 0, friction: float = 0.0,
            baseline: bool = False) -> dict:
    """servo_bench's JSON; ``baseline``: the core's SSE2 kernels where the CPU has AVX2
    (PMASK_DISABLE_CPU_FEATURES=AVX2)."""
    env = _bench_env(uncoupled, baseline)
    args = [str(exe), str(table), str(trace), str(n), "--paced", str(paced)]
    if friction:
        args += ["--friction", repr(float(friction))]
    if batch:
        args += ["--batch", str(batch)]
    if reacquire:
        args += ["--reacquire", str(reacquire)]
    if ratio:
        args += ["--ratio", str(ratio)]
    return json.loads(subprocess.run(args, check=True, capture_output=True, text=True, env=env).stdout)


def _bench_env(uncoupled: bool = False, baseline: bool = False) -> dict:
    import os

    env = {k: v for k, v in os.environ.items() if k not in ("PMASK_BENCH_UNCOUPLED", "PMASK_DISABLE_CPU_FEATURES")}
    if uncoupled:
        env["PMASK_BENCH_UNCOUPLED"] = "1"
    if baseline:
        env["PMASK_DISABLE_CPU_FEATURES"] = "AVX2"
    return env


def c_instructions(exe: Path, table: Path, trace: Path, n: int, ticks: int, uncoupled: bool = False,
                   baseline: bool = False) -> float:
    """Instructions a tick inside pm_servo_step over the whole trace, counted by valgrind's callgrind: a count
    that does not move with the machine's load, beside the timings that do (the docs quote it)."""
    import tempfile

    vg = shutil.which("valgrind")
    if vg is None:
        sys.exit("bench: valgrind is needed for the C step's instruction counts (make system-deps installs it)")
    with tempfile.TemporaryDirectory() as tmp:
        r = subprocess.run([vg, "--tool=callgrind", "--toggle-collect=pm_servo_step",
                            f"--callgrind-out-file={tmp}/cg.out", str(exe), str(table), str(trace), str(n),
                            "--paced", "0"], capture_output=True, text=True, env=_bench_env(uncoupled, baseline))
    found = [line.split(":")[-1] for line in r.stderr.splitlines() if "Collected :" in line]
    if r.returncode or not found:
        raise RuntimeError(f"callgrind failed ({r.returncode}): {r.stderr[-300:]}")
    return int(found[-1].replace(",", "")) / ticks


def python_loop(step, probes, paced: int = 0, reference=None) -> dict:
    """Time ``step(p)`` over ``probes`` (lists of floats: what a device driver hands over) back to back, and
    with ``paced`` > 0 in a 1 kHz loop paced by time.sleep on an absolute schedule, blocks of 500 ticks
    alternating with ``reference`` (the same loop around a trivial function)."""
    pc = time.perf_counter_ns
    plist = [list(map(float, p)) if np.ndim(p) == 1 else [list(map(float, q)) for q in p] for p in probes]
    for p in plist[:50]:
        step(p)
    ts = np.empty(len(plist))
    for k, p in enumerate(plist):
        t0 = pc()
        step(p)
        ts[k] = pc() - t0
    out = {"tight": _stats(ts / 1e3)}
    if reference is not None:
        tr = np.empty(len(plist))
        for k, p in enumerate(plist):
            t0 = pc()
            reference(p)
            tr[k] = pc() - t0
        out["reference_tight"] = _stats(tr / 1e3)
    if paced:
        T = 1e-3
        nxt = time.perf_counter()
        ts, tr, late, k = [], [], 0, 0
        while len(ts) < paced:
            for phase in (0, 1):
                for _ in range(500):
                    nxt += T
                    d = nxt - time.perf_counter()
                    if d > 0:
                        time.sleep(d)
                    p = plist[k % len(plist)]
                    t0 = pc()
                    if phase == 0:
                        step(p)
                        k += 1
                    elif reference is not None:
                        reference(p)
                    t1 = pc()
                    (ts if phase == 0 else tr).append((t1 - t0) / 1e3)
                    if phase == 0 and t1 / 1e9 > nxt + T:
                        late += 1
                    if time.perf_counter() > nxt + T:
                        nxt = time.perf_counter()
        out["paced"] = _stats(ts)
        out["late"] = late
        if reference is not None:
            out["reference_paced"] = _stats(tr)
    return out


def trivial(p):
    """The reference: a Python function that takes the probe and returns a force-sized tuple."""
    return (p[0], p[1], p[2]), 1


def graphics_python(stop: threading.Event, counter: list, contacts) -> None:
    """A Python graphics thread at 60 Hz: each frame the displayed deformation (numpy, ~1 ms) and 3 ms of
    pure-Python work (building vertex buffers, a scene graph), holding the GIL most of that time."""
    T = 1.0 / 60.0
    nxt = time.perf_counter()
    while not stop.is_set():
        contacts.deformation()
        t_end = time.perf_counter() + 3e-3
        s = 0.0
        while time.perf_counter() < t_end:
            for i in range(200):
                s += i * 0.5
        counter[0] += 1
        nxt += T
        d = nxt - time.perf_counter()
        if d > 0:
            time.sleep(d)


def saturating_python(stop: threading.Event, counter: list, contacts) -> None:
    """Both cores saturated: numpy SVDs on the threaded BLAS and pure-Python loops, without a pause."""
    rng = np.random.default_rng(0)
    A = rng.standard_normal((200, 200))
    while not stop.is_set():
        np.linalg.svd(A)
        s = 0.0
        for i in range(20000):
            s += i * 0.5
        counter[0] += 1


def thread_bench(surface, probes, engine: str, seconds: float = 10.0, load: str | None = "graphics") -> dict:
    """The servo on its own thread at 1 kHz, its probes set from Python at ~200 Hz along the tour, with a
    Python thread beside it (``load``: 'graphics', 'saturating' or None): late ticks (a force not ready
    within its period, or skipped)."""
    from pmask.runtime import Contacts

    c = Contacts(surface, 1, engine=engine)
    stop, counter = threading.Event(), [0]
    target = {"graphics": graphics_python, "saturating": saturating_python}.get(load)
    busy = target is not None
    worker = threading.Thread(target=target, args=(stop, counter, c), daemon=True) if busy else None
    if busy:
        worker.start()
    c.start(1000.0)
    t_end = time.perf_counter() + seconds
    k = 0
    try:
        while time.perf_counter() < t_end:
            c.set_probes([list(map(float, probes[k % len(probes)]))])
            k += 5
            time.sleep(0.005)
    finally:
        c.stop()
        stop.set()
        if busy:
            worker.join()
    st = c.tick_stats()
    return {"engine": engine, "load": load or "none", "seconds": seconds, "busy_iterations": counter[0], "ticks": st["ticks"],
            "late": st["late"], "late_fraction": st["late"] / max(st["ticks"], 1),
            "max_lateness_us": 1e6 * st["max_lateness"], "step_max_us": 1e6 * st["step_max"]}


def deformation_bench(stiff, model, engine: str, repeats: int = 30) -> dict:
    """Contacts.deformation() for one contact on the top face, and the longest the GIL was held meanwhile
    (a Python thread records the gaps between its own loop iterations; sys.setswitchinterval(1e-4))."""
    from pmask.runtime import Contacts

    c = Contacts(stiff, 1, engine=engine, coupled=True)
    top = model.contact[model.core]
    i = top[np.argmax(model.points[top, 2])]
    for d in np.linspace(-1e-3, 1.5e-3, 60):
        c.step([model.points[i] - d * np.array([0.0, 0.0, 1.0])])
    c.deformation()
    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-4)
    gaps, stop = [0.0], threading.Event()

    def ticker():
        last = time.perf_counter()
        while not stop.is_set():
            t = time.perf_counter()
            gaps[0] = max(gaps[0], t - last)
            last = t

    ts = []
    th = threading.Thread(target=ticker, daemon=True)
    try:
        time.sleep(0.01)
        th.start()
        time.sleep(0.05)
        base = gaps[0]
        gaps[0] = 0.0
        time.sleep(0.05)
        idle_gap = gaps[0]  # the ticker's own gaps with nothing else running: the reference
        gaps[0] = 0.0
        for _ in range(repeats):
            t0 = time.perf_counter()
            c.deformation()
            ts.append(time.perf_counter() - t0)
            time.sleep(0.002)
        busy_gap = gaps[0]
    finally:
        stop.set()
        th.join()
        sys.setswitchinterval(old)
    del base
    return {"engine": engine, "median_ms": 1e3 * float(np.median(ts)), "max_ms": 1e3 * float(np.max(ts)),
            "gil_gap_ms": 1e3 * busy_gap, "idle_gap_ms": 1e3 * idle_gap}


#: "keeps the 1 ms tick": the step's 99th percentile within this share of the tick, the rest left to the device's
#: I/O and the application (a haptic loop that overruns one tick in a hundred is felt as a buzz)
TICK_SHARE = 0.5


#: rounds of the side-by-side comparison of two coupled contacts with one (servo_bench --ratio): each round
#: passes the whole trace through one, two coupled and two independent contacts in turn; the spread of the
#: rounds' ratios is printed beside their median
RATIO_ROUNDS = 41


def several_contacts(exe, table_path: Path, surface, model, work: Path, counts=(1, 2, 4, 8, 16, 32, 64)) -> dict:
    """s instruments on the upper face of the default kidney, pressing 0.5-1.5 mm and circling: per-tick cost
    in C (coupled and, for comparison, the s contacts independent), through the binding, and in Python (up to
    32: 64 would take minutes), each over the whole trace; 64 is the most one servo takes."""
    from pmask.runtime import Contacts

    top = model.contact[model.core]
    cand = top[model.points[top, 2] > 0.8 * model.points[top, 2].max()]
    chosen = [cand[np.argmax(model.points[cand, 2])]]
    while len(chosen) < max(counts):
        d = np.min(np.linalg.norm(model.points[cand][:, None] - model.points[chosen][None], axis=2), axis=1)
        chosen.append(cand[np.argmax(d)])
    ticks = 3000
    out = {}
    for s in counts:
        starts = model.points[chosen[:s]]
        # from 0.5 mm above to 1.5 mm deep and back, circling 1 mm
        P = np.array([[st + np.array([1e-3 * math.sin(0.01 * k + l), 1e-3 * math.cos(0.013 * k + l),
                                      5e-4 - 2e-3 * math.sin(math.pi * k / ticks)])
                       for l, st in enumerate(starts)] for k in range(ticks)])
        trace = write_trace(work / f"several_{s}.bin", P.reshape(ticks, -1))
        row = {"contacts": s}
        if exe is not None:
            c = c_bench(exe, table_path, trace, s, paced=0)
            row["c_tight"] = c["tight"]
            if s > 1:
                row["c_uncoupled_tight"] = c_bench(exe, table_path, trace, s, paced=0, uncoupled=True)["tight"]
            if s == 2:  # the hands issue's bound (≤ 2x one), side by side in one process
                r = c_bench(exe, table_path, trace, s, paced=0, ratio=RATIO_ROUNDS)
                row["c_kernel"] = r["kernel"]
                row["c_ratio"] = r["ratio"]
                # the SSE2 kernels beside, on the same machine (the same kernel again where the CPU has no AVX2)
                row["c_ratio_baseline"] = c_bench(exe, table_path, trace, s, paced=0, ratio=RATIO_ROUNDS,
                                                  baseline=True)["ratio"]
                one = write_trace(work / "several_2_first.bin", P[:, 0])
                counts = {"one": c_instructions(exe, table_path, one, 1, ticks),
                          "coupled": c_instructions(exe, table_path, trace, s, ticks),
                          "independent": c_instructions(exe, table_path, trace, s, ticks, uncoupled=True),
                          "coupled_baseline": c_instructions(exe, table_path, trace, s, ticks, baseline=True)}
                counts |= {f"{k}_over_one": counts[k] / counts["one"]
                           for k in ("coupled", "independent", "coupled_baseline")}
                row["c_instructions"] = counts
        nat = Contacts(surface, s, engine="native") if _native() else None
        if nat is not None:
            row["binding_tight"] = python_loop(nat.step, P)["tight"]  # the whole trace, as the others
            states = [nat.step(list(p))[1] for p in P[:ticks]]
            row["in_contact_fraction"] = float(np.mean([[x == 1 for x in r] for r in states]))
        if s <= 32:  # the whole trace, as the C (its first fifth is mostly the approach, out of contact)
            row["python_tight"] = python_loop(Contacts(surface, s, engine="python").step, P)["tight"]
        out[str(s)] = row
    return out


def tick_budget(several: dict) -> dict:
    """The most contacts (of those measured) each route keeps in the 1 ms tick: the step's p99 within
    :data:`TICK_SHARE` of it; "measured_up_to" when even the most measured does."""
    limit = 1e3 * TICK_SHARE
    out = {"share": TICK_SHARE, "limit_us": limit}
    for route, key in (("c", "c_tight"), ("binding", "binding_tight"), ("python", "python_tight")):
        rows = sorted((int(s), r[key]["p99_us"]) for s, r in several.items() if key in r)
        fits = [s for s, p99 in rows if p99 <= limit]
        out[route] = {"contacts": max(fits) if fits else 0, "measured_up_to": rows[-1][0] if rows else 0,
                      "p99_us": dict((str(s), p) for s, p in rows)}
    return out


def _native() -> bool:
    from pmask.runtime import servo

    return servo.available()


def surface_bench(name: str, surface, probes: np.ndarray, exe, work: Path, *, reacquire: int = 2000) -> dict:
    """One surface: C (tight, paced, batch, re-acquisition), binding and Python engine."""
    from pmask.runtime import HapticContact
    from pmask.runtime.table import write_table

    table = write_table(work / f"{name}.tbl", surface, {"bench": name}, zeta=False)
    trace = write_trace(work / f"{name}.bin", probes)
    row = {"surface_vertices": len(surface.P), "triangles": len(surface.T)}
    if exe is not None:
        row["c"] = c_bench(exe, table, trace, 1, batch=1_000_000, reacquire=reacquire)
    short = probes[:20000]
    if _native():
        h = HapticContact(surface, engine="native")
        row["binding"] = python_loop(h.step, short, paced=PACED_TICKS, reference=trivial)
    h = HapticContact(surface, engine="python")
    row["python"] = python_loop(h.step, probes[:5000], paced=PACED_TICKS, reference=trivial)
    # the Python grid's scan: what re-acquisition cost before the spatial index
    rng = np.random.default_rng(5)
    pts = probes[rng.integers(0, len(probes), 20)]
    t0 = time.perf_counter()
    for p in pts:
        surface.grid.nearest_scan(p)
    row["scan_ms"] = 1e3 * (time.perf_counter() - t0) / len(pts)
    t0 = time.perf_counter()
    for p in pts:
        surface.grid.nearest(p)
    row["python_grid_ms"] = 1e3 * (time.perf_counter() - t0) / len(pts)
    return row


#: free vertices drawn at random (seeded) for the deep pushes; the test (tests/test_deep.py) draws 20 of them
DEEP_SITES = 80


def deep_pushes(model, stiff, levels="auto", n_sites: int = DEEP_SITES) -> dict:
    """The hands issue's straight pushes (:data:`pmask.pipeline.strokes.PUSH_LINES`, to 15 mm at 10 mm/s) at
    ``n_sites`` random free vertices: how many lines reach the deep regime, how many lose force while going
    deeper (the issue: none) and by how much, short of it and in it (:func:`pmask.pipeline.strokes.push_metrics`),
    and on how many the deep hold acts (past δ_lin, :mod:`pmask.runtime.contact.output`) with its largest factor:
    the Python engine, whose state shows it (the native one sends the same forces, tests/test_deep.py).
    Physics, not speed; here because it steps the haptic engine a few hundred thousand times."""
    from pmask.pipeline.strokes import PUSH_LINES, depth_below, push_line, push_metrics, vertex_normal
    from pmask.runtime import HapticContact

    srf = HapticContact(stiff, levels=levels, engine="python").surface
    P = srf.mesh_points  # each line through the contact surface's point at the vertex (rounded near creases)
    below = depth_below(P, model.triangles)
    sites = np.random.default_rng(1).choice(model.contact[model.core], n_sites, replace=False)
    out = {"levels": srf.levels, "default": levels == "auto", "sites": int(n_sites), "lines": 0, "deep_lines": 0,
           "released": 0, "falls": [], "held": [],
           "fall_contact_max": 0.0, "vertices": len(P), "element": str(model.attrs.get("element", "P1"))}
    for v in sites:
        N = vertex_normal(srf, v)
        for tilt, azimuths in PUSH_LINES:
            for az in azimuths:
                probes, s = push_line(P[v], N, tilt, az)
                h = HapticContact(stiff, levels=levels, engine="python")  # the hold's factor is visible here
                steps, scale = [], 1.0
                for p in probes:
                    steps.append(h.step(p))
                    scale = max(scale, h._state().hold_scale)
                status = np.array([int(st) for _, st in steps])
                depth = below(probes) * np.sign(s)
                m = push_metrics(np.array([f for f, _ in steps]), status, depth)
                out["lines"] += 1
                out["deep_lines"] += m["deep"]
                out["released"] += m["released"]
                out["fall_contact_max"] = max(out["fall_contact_max"], m["fall_contact"])
                if scale > 1.0 + 1e-9:
                    out["held"].append({"vertex": int(v), "tilt": tilt, "azimuth": az, "scale": scale})
                if m["fall"] > 1e-12:
                    k = m["fall_at"]
                    out["falls"].append({"vertex": int(v), "tilt": tilt, "azimuth": az, "fall": m["fall"],
                                         "depth_mm": 1e3 * float(depth[k]), "status": int(status[k]),
                                         "to_support_mm": 1e3 * float(np.linalg.norm(P[model.fixed] - P[v],
                                                                                     axis=1).min())})
    return out


def run(kidneys: dict, synthetic, work: Path) -> dict:
    """kidneys: {surface vertices: artifact path}; synthetic: callable n -> SurfaceStiffness."""
    from pmask.pipeline.strokes import tour
    from pmask.runtime import Model
    from pmask.runtime.contact import ContactSurface
    from pmask.runtime.table import write_table

    exe = build_servo_bench(work) if _native() else None
    res = {"surfaces": {}}
    tour_probes, _ = tour()
    default = None
    for nv, path in sorted(kidneys.items()):
        print(f"  haptics on kidney {nv} ...", flush=True)
        m = Model.load(path)
        stiff = m.stiffness("linear", 2.0 * m.mean_edge_length)
        srf = ContactSurface(stiff)  # the default contact surface (levels "auto")
        res["surfaces"][f"kidney_{len(m.points)}"] = dict(surface_bench(f"kidney_{nv}", srf, tour_probes, exe, work),
                                                          synthetic=False, levels=srf.levels)
        res["surfaces"][f"kidney_{len(m.points)}"]["deformation"] = [deformation_bench(stiff, m, e)
                                                                     for e in ("native", "python") if e == "python" or _native()]
        if default is None or abs(len(m.points) - 1543) < abs(len(default[0].points) - 1543):
            default = (m, stiff, srf)
    m, stiff, _ = default  # the same kidney on the mesh's own triangles (levels=0), beside the default's row
    print(f"  haptics on kidney {len(m.points)}, mesh ...", flush=True)
    mesh = ContactSurface(stiff, levels=0)
    res["surfaces"][f"kidney_{len(m.points)}_mesh"] = dict(
        surface_bench(f"kidney_{len(m.points)}_mesh", mesh, tour_probes, exe, work), synthetic=False, levels=0,
        mesh=True)
    eq = equator_path()
    for n in (500, 5000, 50000, 164000):
        print(f"  haptics on synthetic {n} ...", flush=True)
        srf = ContactSurface(synthetic(n), levels=0)  # the mesh as it is: the rows measure the step against n
        res["surfaces"][f"synthetic_{len(srf.P)}"] = dict(surface_bench(f"synthetic_{n}", srf, eq, exe, work),
                                                          synthetic=True)
    m, stiff, srf = default
    print(f"  deep pushes at {DEEP_SITES} random sites, default surface and mesh ...", flush=True)
    res["deep"] = [deep_pushes(m, stiff, levels) for levels in ("auto", 0)]
    print("  several contacts ...", flush=True)
    srf.coupling()
    table = write_table(work / "kidney_default_zeta.tbl", srf, {"bench": "several"}, zeta=True)
    res["several"] = several_contacts(exe, table, srf, m, work)
    res["several_tick"] = tick_budget(res["several"])
    print("  servo thread beside a busy Python thread ...", flush=True)
    engines = ("native", "python") if _native() else ("python",)
    res["thread"] = []
    for load in (None, "graphics", "saturating"):  # three runs each, interleaved: this VM's stalls come in bursts
        runs = {e: [] for e in engines}
        for _ in range(3):
            for e in engines:
                runs[e].append(thread_bench(srf, tour_probes, e, load=load))
        for e in engines:
            r = runs[e]
            res["thread"].append({"engine": e, "load": load or "none", "seconds": sum(x["seconds"] for x in r),
                                  "ticks": sum(x["ticks"] for x in r), "late": sum(x["late"] for x in r),
                                  "late_fraction": sum(x["late"] for x in r) / max(sum(x["ticks"] for x in r), 1),
                                  "late_fractions": [x["late_fraction"] for x in r],
                                  "max_lateness_us": max(x["max_lateness_us"] for x in r),
                                  "step_max_us": max(x["step_max_us"] for x in r)})
    return res


# ------------------------------------------------------------------------------------------ report
def markdown(res: dict) -> str:
    from pmask.runtime.contact.state import Status

    L = ["**The haptic step** (µs per tick, one instrument; tight = back to back over the probe trace, paced = in a "
         "1 kHz loop on an absolute schedule as a device loop runs it; the kidneys run the haptics issue's tour, "
         "the synthetic gmsh ellipsoids (random SPD K_i) a press and two turns round the equator)", "",
         "| surface | vertices | C tight median / p99.9 | C paced median / p99.9 | C reference paced (eq. 15 at the point / timer) | "
         "binding tight | binding paced | Python paced reference | Python engine paced | re-acquisition C median / p99 | "
         "Python scan | C batch M K(x)/s (memory floor) |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in res["surfaces"].items():
        c = r.get("c")
        b = r.get("binding")
        p = r["python"]
        label = ("synthetic" if r["synthetic"] else "kidney, mesh (`levels=0`)" if r.get("mesh") else
                 f"kidney (default surface: `levels={r['levels']}`)" if "levels" in r else "kidney")
        if c:
            cc = (f"{c['tight']['median_us']:.2f} / {c['tight']['p999_us']:.2f} | {c['paced']['median_us']:.2f} / "
                  f"{c['paced']['p999_us']:.2f} | {c['blend_paced']['median_us']:.2f} / {c['empty_paced']['median_us']:.2f}")
            re = f"{c['reacquire']['median_us']:.1f} / {c['reacquire']['p99_us']:.1f}" if c.get("reacquire") else "—"
            batch = f"{c['batch_per_s'] / 1e6:.0f} ({c['batch_floor_per_s'] / 1e6:.0f})"
        else:
            cc, re, batch = "— | — | —", "—", "—"
        bb = (f"{b['tight']['median_us']:.2f} | {b['paced']['median_us']:.2f}" if b else "— | —")
        L.append(f"| {label} | {r['surface_vertices']} | {cc} | {bb} | {p['reference_paced']['median_us']:.2f} | "
                 f"{p['paced']['median_us']:.1f} | {re} | {r['scan_ms']:.2f} ms | {batch} |")
    L += ["", "**Several instruments** (default kidney, coupled through the ζ table; µs per tick, tight)", "",
          "| s | C coupled median / p99 | C, s independent contacts | binding median / p99 | Python engine median / p99 | share of ticks in contact |",
          "|---|---|---|---|---|---|"]
    for s, r in res["several"].items():
        c = r.get("c_tight")
        u = r.get("c_uncoupled_tight")
        py = r.get("python_tight")
        pys = f"{py['median_us']:.1f} / {py['p99_us']:.1f}" if py else "—"
        L.append(f"| {s} | {c['median_us']:.2f} / {c['p99_us']:.2f} | "
                 f"{(str(round(u['median_us'], 2))) if u else '—'} | "
                 f"{r['binding_tight']['median_us']:.2f} / {r['binding_tight']['p99_us']:.2f} | {pys} | "
                 f"{r.get('in_contact_fraction', float('nan')):.2f} |" if c else f"| {s} | — | — | — | — | — |")
    rt = res["several"].get("2", {}).get("c_ratio")
    if rt:
        L += ["", f"Side by side in one process ({rt['rounds']} rounds, each the whole trace through one contact, two "
                  f"coupled and two independent ones in turn, the least of a few passes each; the mean tick): one "
                  f"{rt['one_us']:.3f} µs, two coupled {rt['coupled_us']:.3f} µs, two independent "
                  f"{rt['independent_us']:.3f} µs; two coupled against one "
                  f"{rt['coupled_over_one']['median']:.2f}x (median of the rounds, "
                  f"{rt['coupled_over_one']['min']:.2f}–{rt['coupled_over_one']['max']:.2f}x), two independent "
                  f"{rt['independent_over_one']['median']:.2f}x "
                  f"({rt['independent_over_one']['min']:.2f}–{rt['independent_over_one']['max']:.2f}x), with the "
                  f"core's {res['several']['2'].get('c_kernel', 'baseline')} kernels."]
        rb = res["several"]["2"].get("c_ratio_baseline")
        if rb:
            L += ["", f"The same with the baseline (SSE2) kernels (PMASK_DISABLE_CPU_FEATURES=AVX2), side by side "
                      f"in a second process: two coupled against one {rb['coupled_over_one']['median']:.2f}x "
                      f"({rb['coupled_over_one']['min']:.2f}–{rb['coupled_over_one']['max']:.2f}x), two independent "
                      f"{rb['independent_over_one']['median']:.2f}x."]
        ins = res["several"]["2"].get("c_instructions")
        if ins:
            L += ["", f"Instructions a tick inside `pm_servo_step` (valgrind's callgrind, the whole trace; a count "
                      f"the machine's load does not move): one {ins['one']:,.0f}, two coupled {ins['coupled']:,.0f} "
                      f"({ins['coupled_over_one']:.3f}x one), two independent {ins['independent']:,.0f} "
                      f"({ins['independent_over_one']:.3f}x), two coupled with the baseline kernels "
                      f"{ins['coupled_baseline']:,.0f} ({ins['coupled_baseline_over_one']:.3f}x)."]
    tick = res.get("several_tick")
    if tick:
        def kept(route):
            t = tick[route]
            return f"{t['contacts']}" + (" (all measured)" if t["contacts"] == t["measured_up_to"] else "")
        L += ["", f"Contacts each route keeps in the 1 ms tick (the step's p99 within {tick['limit_us']:.0f} µs, "
                  f"half the tick; the rest is the device's and the application's): C core {kept('c')}, the native "
                  f"engine from Python {kept('binding')}, the Python engine {kept('python')}."]
    deep = res.get("deep")
    if deep:
        L += ["", f"**Deep pushes at random sites** (the {deep[0]['vertices']:,}-vertex kidney, {deep[0]['element']} as "
                  f"this bench precomputes it (the tests' default kidney is P2), {deep[0]['sites']} free vertices drawn "
                  "at random, "
                  "the hands issue's nine straight pushes at each (through the contact surface's point there, "
                  "along the inward normal, 30° and 45° off it towards four azimuths) to 15 mm at 10 mm/s, over the "
                  "stretch where the line goes deeper; "
                  "physics, not speed: `pmask.pipeline.strokes.push_metrics`)", "",
              "| contact surface | lines | reaching DEEP | contact ended | largest fall tick to tick short of DEEP | "
              "lines where \\|F\\| falls | their falls at a DEEP tick | largest fall (depth below the surface, "
              "distance of the site from the support) | lines where the deep hold acts (its largest factor) |",
              "|---|---|---|---|---|---|---|---|---|"]
        for d in deep:
            f = d["falls"]
            w = max(f, key=lambda x: x["fall"]) if f else None
            worst = (f"{100 * w['fall']:.2g} % ({w['depth_mm']:.1f} mm, {w['to_support_mm']:.0f} mm); the others "
                     + ", ".join(f"{100 * x['fall']:.2g}" for x in sorted(f, key=lambda x: -x["fall"])[1:]) + " %"
                     if w else "none")
            label = (f"default (`levels={d['levels']}`)" if d.get("default") else
                     f"subdivided (`levels={d['levels']}`)" if d["levels"] else "mesh (`levels=0`)")
            deep_ticks = sum(x["status"] == Status.DEEP for x in f)
            held = d.get("held")
            hold = "—" if held is None else f"{len(held)} ({max(x['scale'] for x in held):.3g})" if held else "0"
            L.append(f"| {label} | {d['lines']} | {d['deep_lines']} | {d['released']} | {d['fall_contact_max']:.1g} | "
                     f"{len(f)} | {deep_ticks} | {worst} | {hold} |")
    L += ["", "**Servo thread at 1 kHz** (probes set from Python at 200 Hz along the tour; beside it nothing, a "
              "Python graphics thread at 60 Hz (the displayed deformation and 3 ms of pure Python per frame), or "
              "a Python thread saturating both cores (SVDs on the threaded BLAS and Python loops))", "",
          "| beside it | engine | ticks (3 runs of 10 s) | late | late share | per run | largest lateness µs | longest step µs |",
          "|---|---|---|---|---|---|---|---|"]
    for t in res["thread"]:
        per = ", ".join(f"{100 * x:.2f} %" for x in t["late_fractions"])
        L.append(f"| {t['load']} | {t['engine']} | {t['ticks']} | {t['late']} | {100 * t['late_fraction']:.3f} % | {per} | "
                 f"{t['max_lateness_us']:.0f} | {t['step_max_us']:.0f} |")
    L += ["", "**Deformation for display** (whole surface, one contact, eq. 16 with the display forces; longest "
              "time a Python thread waited for the GIL meanwhile, beside the same thread's gaps with nothing running)",
          "", "| surface vertices | engine | median ms | max ms | longest GIL wait ms | idle reference ms |",
          "|---|---|---|---|---|---|"]
    for name, r in res["surfaces"].items():
        for d in r.get("deformation", []):
            L.append(f"| {r['surface_vertices']} | {d['engine']} | {d['median_ms']:.3f} | {d['max_ms']:.3f} | "
                     f"{d['gil_gap_ms']:.3f} | {d['idle_gap_ms']:.3f} |")
    return "\n".join(L) + "\n"
