"""Compressed Ξ against dense (issue #17): ratio, time, errors, workers, memory per worker.

Run by ``make bench`` (bench/run.py) or alone: ``python bench/compress_bench.py [OUT.json]``.  Every
figure comes from this run; the README quotes the latest.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

R_MAX = 0.01  # a 10 mm probe tip
#: the 50,000 row again with masks up to 5 mm (a 10 mm-wide tip): the exact near field holds every pair within
#: r_max, ∝ r_max² at a given mesh, so this is what a smaller tip buys (`make bench ONLY=organ-5mm`)
ORGAN_R_MAX = 0.005
TOL = 1e-4
#: P1 for the rows below but one: the element whose Ξ is stored once per symmetric pair.  P2, the default for
#: ν = 0.45 (what the large-organs guide's command runs), has its own row at LARGE (`make bench ONLY=organ-p2`)
ELEMENT = "P1"
#: the organ-scale kidney: 1.28 mm surface edges (20,427 contact vertices), the volume graded to 6 mm
LARGE = {"size": 0.00128, "interior": 0.006}
#: issue #27's 50,000 contact vertices (0.83 mm gave 47,467; edges scale the count as h⁻²): `make bench ONLY=organ`,
#: ~30-45 min on 2 cores
ORGAN = {"size": 0.00080, "interior": 0.006}


class PeakRSS:
    """Peak resident memory of this process and its children (the Dask workers), sampled every 0.1 s;
    per child process too."""

    def __init__(self):
        import psutil

        self.me = psutil.Process()
        self.peak, self.per, self._stop = 0, {}, threading.Event()
        self.t = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        while not self._stop.wait(0.1):
            total = 0
            for p in [self.me, *self.me.children(recursive=True)]:
                try:
                    r = p.memory_info().rss
                except Exception:
                    continue
                total += r
                self.per[p.pid] = max(self.per.get(p.pid, 0), r)
            self.peak = max(self.peak, total)

    def __enter__(self):
        self.t.start()
        return self

    def __exit__(self, *a):
        self._stop.set()
        self.t.join()


def setup(size):
    from pmask.pipeline import stages

    spec = stages.Spec(model="kidney", params={"size": size}, r_max=R_MAX, element=ELEMENT)
    mesh = stages.support_stage(spec, stages.mesh_stage(spec))
    surf = stages.surface_stage(spec, mesh)
    factor, _ = stages.factor_stage(spec, mesh, surf)
    return spec, mesh, surf, factor


def errors(size, work: Path) -> dict:
    """Dense and compressed artifacts of the same kidney through the whole pipeline; the runtime's errors."""
    from pmask.pipeline.stages import Spec, run
    from pmask.runtime import Model

    out = {}
    # "compressed": --compress alone, which compresses the dense Ξ where it fits (as here); _1, _2: the tiled route
    # from W on 1 and 2 Dask workers (--workers asks for it), the route of the sizes where the dense Ξ does not fit
    for name, kw in (("dense", {}), ("compressed", {"compress": TOL}), ("compressed_1", {"compress": TOL, "workers": 1}),
                     ("compressed_2", {"compress": TOL, "workers": 2})):
        p = work / f"{name}.h5"
        t0 = time.perf_counter()
        with PeakRSS() as m:
            s = run(Spec(model="kidney", params={"size": size}, r_max=R_MAX, element=ELEMENT, **kw), p, force=True)
        out[name] = {"greens_s": s["timings"]["greens"], "peak_rss_gib": m.peak / 2**30, "bytes": p.stat().st_size,
                     "whole_s": time.perf_counter() - t0}  # as a user waits: mesh to written artifact
        if kw:
            out[name]["stats"] = s["factor_stats"]["compress"]
    # the whole runs side by side (#27 item 6 asks the compressed route within 1.2x of dense where both fit)
    out["whole_ratio"] = {k: out[k]["whole_s"] / out["dense"]["whole_s"] for k in ("compressed", "compressed_2")}
    d, c = Model.load(work / "dense.h5"), Model.load(work / "compressed_2.h5")
    out["contact"] = len(d.contact)
    sd, sc = d.stiffness("linear", R_MAX), c.stiffness("linear", R_MAX)
    out["K_i_max_rel"] = float(np.abs(sc.K_full - sd.K_full).max() / np.abs(sd.K_full).max())
    rng = np.random.default_rng(0)
    inner = np.zeros(len(d.points), bool)
    inner[d.contact[d.core]] = True
    touch = np.flatnonzero(inner[d.triangles].all(axis=1))  # every corner has a mask (not next to the support)
    dev, cpl = [], []
    for _ in range(10):
        t = rng.choice(touch, 3, replace=False)
        b = rng.dirichlet(np.ones(3), 3)
        f = rng.normal(size=(3, 3))
        loads = list(zip(t, b, f))
        vd, vc = sd.deformation_of(loads), sc.deformation_of(loads)
        dev.append(float(np.linalg.norm(vc - vd) / np.linalg.norm(vd)))
        u = rng.normal(size=(3, 3)) * 1e-3
        fd, fc = sd.coupled_forces(list(zip(t, b)), u), sc.coupled_forces(list(zip(t, b)), u)
        cpl.append(float(np.linalg.norm(fc - fd) / np.linalg.norm(fd)))
    out["deformation_rel_max"], out["coupling_rel_max"] = max(dev), max(cpl)
    out["dense_Xi_bytes"] = 8 * (3 * len(d.contact)) ** 2
    out["compressed_stored_bytes"] = c.Xi.nbytes
    return out


def speed_reference(repeats: int = 7) -> float:
    """This machine's speed now (seconds): a 1024 x 1024 matrix product on one BLAS thread, the least of
    ``repeats``.  The GF stage is mostly such products (the sweep's and the tiles'), and a virtual machine's
    speed drifts over a day by more than a code change moves it (the 51,519-vertex run meshed in 25 s at one
    hour and 51 s at another, the same code), so each organ-scale run takes it before and after, the page gives
    it beside the run's times, and the refit (:func:`refit_numbers`) scales one run's times by the two runs'
    references."""
    from threadpoolctl import threadpool_limits

    rng = np.random.default_rng(0)
    A, B = rng.standard_normal((1024, 1024)), rng.standard_normal((1024, 1024))
    best = float("inf")
    with threadpool_limits(1, user_api="blas"):
        for _ in range(repeats):
            t0 = time.perf_counter()
            A @ B
            best = min(best, time.perf_counter() - t0)
    return best


def large(params: dict, work: Path, n_check: int = 8, r_max: float = R_MAX, element: str = ELEMENT) -> dict:
    """The organ-scale run: a kidney with ~20,000 contact vertices, compressed on 2 local workers through
    the whole pipeline (masks up to ``r_max``), peak RSS of the process tree; the dense route's refusal (and
    its Ξ's size); the compressed Ξ's columns of ``n_check`` random vertices against the same columns solved
    from the factor (native selected inversion per panel: another code path than the tiles' W store)."""
    from pmask.errors import ResourceError
    from pmask.pipeline import stages
    from pmask.precompute import compress, elements
    from pmask.runtime import Model
    from pmask.runtime.compressed import PAIR_WORDS

    spec = stages.Spec(model="kidney", params=params, r_max=r_max, compress=TOL, workers=2, element=element)
    p = work / "large.h5"
    before = speed_reference()
    with PeakRSS() as m:
        s = stages.run(spec, p, force=True)
    reference = [before, speed_reference()]
    out = {"params": params, "r_max_m": r_max, "greens_s": s["timings"]["greens"], "total_s": sum(s["timings"].values()),
           "timings": s["timings"], "peak_rss_gib": m.peak / 2**30,
           "peak_rss_per_process_gib": sorted((v / 2**30 for v in m.per.values()), reverse=True)[:4],
           "client_peak_rss_gib": m.per.get(os.getpid(), 0) / 2**30,  # this process: the pipeline's client
           "sweep_worker_peak_rss_gib": m.per.get(s["factor_stats"]["compress"].get("sweep_pid"), 0) / 2**30,
           "bytes": p.stat().st_size, "stats": s["factor_stats"]["compress"], "dofs": s["factor_stats"]["dofs"],
           "element": element, "speed_reference_s": reference}
    eager = []
    for _ in range(3):  # the near field read (and checked) at open, as every artifact was before
        t0 = time.perf_counter()
        Model.load(p, near_field="open")
        eager.append(time.perf_counter() - t0)
    out["open_near_field_s"], out["open_near_field_runs_s"] = float(np.median(eager)), eager
    opens = []
    for _ in range(5):  # the page cache warm after the write; five opens for their spread
        t0 = time.perf_counter()
        c = Model.load(p)  # far field left in the file above 512 MiB, near field read on demand above 256 MiB
        opens.append(time.perf_counter() - t0)
    out["open_s"], out["open_runs_s"] = float(np.median(opens)), opens
    out["far_field"] = type(c.Xi.U).__name__
    out["near_field"] = type(c.Xi.dense).__name__
    # every K_i in a process of its own (this one has run the pipeline and read the near field whole above, which
    # its heap keeps): open, form them all, and the process's peak RSS, what a user's application would see
    every = subprocess.run([sys.executable, __file__, "--every-k", str(p), repr(r_max)], check=True,
                           capture_output=True, text=True)
    out.update(json.loads(every.stdout.strip().splitlines()[-1]))
    n = len(c.contact)
    out["contact"] = n
    # the dense blocks (the pairs of leaves that hold a pair within r_max): format 1.6 stores those pairs exactly
    # (1.7: in fixed point, 56 bytes a pair) and the blocks' other pairs in 16 bits, split here
    out["near_bytes"] = int(c.Xi.near_nbytes)
    out["near_exact_bytes"] = int(c.Xi.dense.nbytes)
    out["near_16bit_bytes"] = int(c.Xi.near_nbytes - c.Xi.dense.nbytes)
    out["far_bytes"] = int(c.Xi.far_nbytes)  # (as stored: format 1.8's 16-bit words and scales)
    out["dense_Xi_bytes"] = 8 * (3 * n) ** 2
    # the least this format stores while it keeps every pair within r_max exact: those pairs' 3x3 blocks, once per
    # symmetric pair, at its bytes a pair (the leaf blocks' near field holds pairs up to r_max plus two leaves'
    # diagonals apart)
    from scipy.spatial import cKDTree

    Pc = c.points[c.contact]
    within = int(cKDTree(Pc).query_ball_point(Pc, r_max, return_length=True).sum())  # ordered pairs, i = j too
    out["exact_pair_bytes"] = 2 * PAIR_WORDS if c.Xi.fixed else 9 * c.Xi.dense.dtype.itemsize
    out["pairs_within_r_max_bytes"] = out["exact_pair_bytes"] * (within + n) // 2
    out["compressed_stored_bytes"] = c.Xi.nbytes
    out.update(disk_bytes(p))
    dense = stages.Spec(model="kidney", params=params, r_max=r_max, element=element)
    mesh = stages.support_stage(dense, stages.mesh_stage(dense))
    out["dense_need_gib"] = elements.get_element(element).memory_estimate(len(mesh.points), n)["total"] / 2**30
    try:
        stages.check_memory(elements.get_element(element), len(mesh.points), n, dense)
        out["dense_refused"] = None
    except ResourceError as exc:
        out["dense_refused"] = str(exc)
    surf = stages.surface_stage(dense, mesh)
    factor, _ = stages.factor_stage(dense, mesh, surf)
    rng = np.random.default_rng(1)
    pick = np.sort(rng.choice(n, n_check, replace=False))
    dcols = (3 * pick[:, None] + np.arange(3)).ravel()
    exact = compress.solved_columns(factor, dcols)
    E = np.zeros((3 * n, len(dcols)))
    E[dcols, np.arange(len(dcols))] = 1.0
    got = c.Xi.matvec(E)
    out["columns_checked"] = int(n_check)
    out["columns_rel_err"] = float(np.linalg.norm(got - exact) / np.linalg.norm(exact))
    P = c.points[c.contact]
    near = np.linalg.norm(P[:, None] - P[pick][None], axis=2) <= r_max  # (n, n_check)
    nm = np.repeat(np.repeat(near, 3, axis=0), 3, axis=1)
    out["near_max_abs_rel"] = float(np.abs(got - exact)[nm].max() / np.abs(exact).max())
    return out


def disk_bytes(path: Path) -> dict:
    """The compressed Ξ's bytes in the file (HDF5's storage sizes: the near field deflated,
    :data:`pmask.runtime.artifact.NEAR_FILTERS`), beside the values' bytes the rows give (what a reader holds)."""
    import h5py

    from pmask.runtime.artifact import NEAR

    with h5py.File(path, "r") as f:
        g = f["greens/hmatrix"]
        size = {f"greens/hmatrix/{k}": int(g[k].id.get_storage_size()) for k in g}
    near = sum(v for k, v in size.items() if k in NEAR)
    return {"disk_stored_bytes": sum(size.values()), "near_disk_bytes": near}


def haptic_step(dense: Path, compressed: Path, work: Path, repeats: int = 3) -> dict:
    """The C haptic step (one contact, the haptics issue's tour, tight) on the table of the organ-scale compressed
    artifact against the dense 3,882-vertex one's (the hands issue: ≤ 2x), alternated ``repeats`` times in this
    run: the median tick of each run, and the ratio of their medians."""
    import runtime_bench

    from pmask.pipeline.strokes import tour
    from pmask.runtime import Model
    from pmask.runtime.contact import ContactSurface
    from pmask.runtime.table import write_table

    exe = runtime_bench.build_servo_bench(work)
    trace = runtime_bench.write_trace(work / "tour.bin", tour()[0])
    tables, out = {}, {}
    for name, path in (("dense", dense), ("compressed", compressed)):
        m = Model.load(path)
        srf = ContactSurface(m.stiffness("linear", 2.0 * m.mean_edge_length))
        tables[name] = write_table(work / f"step_{name}.tbl", srf, {"bench": f"step {name}"}, zeta=False)
        out[f"{name}_vertices"] = len(m.points)
    runs = {name: [] for name in tables}
    for _ in range(repeats):
        for name, table in tables.items():
            runs[name].append(runtime_bench.c_bench(exe, table, trace, 1, paced=0)["tight"]["median_us"])
    out.update({f"{name}_median_us": r for name, r in runs.items()})
    out["ratio"] = float(np.median(runs["compressed"]) / np.median(runs["dense"]))
    return out


def coupled_step(dense: Path, compressed: Path, repeats: int = 3) -> dict:
    """Two coupled jaws (``strokes.grasp_path``: 2.5 mm in, then slid 10 mm, μ = 0.3) in the native core through the
    Python binding, on the organ-scale compressed artifact and on the dense 3,882-vertex one (its ζ table),
    alternated ``repeats`` times in this run, each tick timed by the caller.  The compressed artifact both ways:
    "held", the default, Ξ's compressed sections handed to the core in memory (read once, when the first
    contacts are made: timed), from which it forms a pair of triangles' blocks itself; and "asked", as when they
    would not fit (:data:`pmask.runtime.servo.GREENS_MEMORY_SHARE` set to 0), the core asking the surface for
    the blocks when the jaws land on them: per run the requests and what they took (the first run's from a cold
    cache, the stiffness's bounded cache of ζ_m(i) blocks warm after it).  The median tick of each run."""
    from pmask.pipeline.strokes import grasp_path
    from pmask.runtime import Contacts, Model, servo
    from pmask.runtime.contact import ContactSurface

    md, mc = Model.load(dense), Model.load(compressed)
    sc = mc.stiffness("linear", 2.0 * mc.mean_edge_length)
    setups = {"dense": ContactSurface.of(md.stiffness("linear", 2.0 * md.mean_edge_length)),
              "held": ContactSurface.of(sc), "asked": ContactSurface(sc)}
    paths = {"dense": grasp_path(md, slide=0.01, press=400, hold=1000),
             "held": grasp_path(mc, slide=0.01, press=400, hold=1000)}
    paths["asked"] = paths["held"]
    out = {"dense_vertices": len(md.points), "compressed_vertices": len(mc.points),
           "held_greens_mib": mc.Xi.nbytes / 2**20}
    runs = {name: [] for name in setups}
    requests = []
    share = servo.GREENS_MEMORY_SHARE
    for _ in range(repeats):
        for name, srf in setups.items():
            asked = []
            pair_blocks = srf.pair_blocks

            def timed(ta, tb, pair_blocks=pair_blocks, asked=asked):
                t0 = time.perf_counter()
                blocks = pair_blocks(ta, tb)
                asked.append(time.perf_counter() - t0)
                return blocks

            srf.pair_blocks = timed  # what the servo made below asks
            servo.GREENS_MEMORY_SHARE = 0.0 if name == "asked" else share
            t0 = time.perf_counter()
            c = Contacts(srf, 2, friction=0.3, engine="native")
            if name == "held" and "held_load_s" not in out:
                out["held_load_s"] = time.perf_counter() - t0  # the sections read whole into the core
            servo.GREENS_MEMORY_SHARE = share
            ticks = np.empty(len(paths[name]))
            for k, probes in enumerate(paths[name]):
                t0 = time.perf_counter()
                c.step(probes)
                ticks[k] = time.perf_counter() - t0
            srf.__dict__.pop("pair_blocks", None)
            if name == "asked":
                requests.append(asked)
            elif asked:
                raise RuntimeError(f"the native core asked Python for blocks on the {name} route")
            runs[name].append(ticks)
    out.update({f"{name}_median_us": [float(np.median(t) * 1e6) for t in r] for name, r in runs.items()})
    out.update({f"{name}_max_ms": [float(t.max() * 1e3) for t in r] for name, r in runs.items()})
    out["ticks"] = len(runs["dense"][0])
    out["requests"] = [len(a) for a in requests]
    out["request_median_ms"] = [float(np.median(a) * 1e3) if a else None for a in requests]
    out["request_max_ms"] = [float(np.max(a) * 1e3) if a else None for a in requests]
    dense_median = np.median(np.concatenate(runs["dense"]))
    for name in ("held", "asked"):
        out[f"{name}_ratio"] = float(np.median(np.concatenate(runs[name])) / dense_median)
        # the native thread at 1 kHz beside a Python thread that holds the GIL (a pure-Python loop), the probes
        # set at the same pace: a tick that asks Python for blocks waits for the GIL
        c = Contacts(setups[name], 2, friction=0.3, engine="native")
        out[f"{name}_thread"] = beside_gil_holder(c, paths[name])
    return out


def beside_gil_holder(contacts, path) -> dict:
    """``contacts``' native thread at 1 kHz (set_probes, paced by the caller's clock) while another Python thread
    runs a pure-Python loop, holding the GIL but at its switch interval: the thread's ticks, late ticks and
    longest step."""
    done = threading.Event()

    def hold_gil():
        x = 0
        while not done.is_set():
            for i in range(100_000):
                x += i

    hog = threading.Thread(target=hold_gil, daemon=True)
    hog.start()
    contacts.start(1000.0)
    try:
        t0 = time.perf_counter()
        for k, probes in enumerate(path):
            contacts.set_probes(probes)
            while time.perf_counter() < t0 + (k + 1) * 1e-3:
                pass
        stats = contacts.tick_stats()
    finally:
        contacts.stop()
        done.set()
        hog.join()
    return {"ticks": int(stats["ticks"]), "late": int(stats["late"]), "step_max_ms": float(stats["step_max"]) * 1e3,
            "samples": len(path)}


def coupled_step_c(dense: Path, compressed: Path, work: Path, repeats: int = 3) -> dict:
    """The same two jaws in C (servo_bench, tight), on tables exported from each artifact: the dense one's with its
    ζ table, the organ-scale compressed one's with Ξ's compressed sections (table 1.4; 1.5 as the artifact stores
    them), from which the core forms a pair of triangles' blocks itself when the jaws land on them; alternated
    ``repeats`` times, each run a fresh process (a cold cache of blocks).  The median and the longest tick of each
    run, the empty timer's median beside them (the noise reference), the tables' sizes, and the ratio of the
    medians (the hands issue asks ≤ 2x)."""
    import runtime_bench

    from pmask.pipeline.strokes import grasp_path
    from pmask.runtime import Model
    from pmask.runtime.contact import ContactSurface
    from pmask.runtime.table import write_table

    exe = runtime_bench.build_servo_bench(work)
    tables, traces, out = {}, {}, {}
    for name, path in (("dense", dense), ("compressed", compressed)):
        m = Model.load(path)
        srf = ContactSurface.of(m.stiffness("linear", 2.0 * m.mean_edge_length))
        tables[name] = write_table(work / f"grasp_{name}.tbl", srf, {"bench": f"grasp {name}"}, zeta=True)
        P = grasp_path(m, slide=0.01, press=400, hold=1000)
        traces[name] = runtime_bench.write_trace(work / f"grasp_{name}.bin", np.reshape(P, (len(P), 6)))
        out[f"{name}_vertices"] = len(m.points)
        out[f"{name}_table_mib"] = tables[name].stat().st_size / 2**20
        del m, srf
    runs = {name: [] for name in tables}
    for _ in range(repeats):
        for name, table in tables.items():
            runs[name].append(runtime_bench.c_bench(exe, table, traces[name], 2, paced=0, friction=0.3))
    for name, r in runs.items():
        out[f"{name}_median_us"] = [x["tight"]["median_us"] for x in r]
        out[f"{name}_max_us"] = [x["tight"]["max_us"] for x in r]
        out[f"{name}_empty_us"] = [x["empty_tight"]["median_us"] for x in r]
        # (the first jaw's ticks with status CONTACT only: 2.5 mm deep may be DEEP, past δ_lin, on a fine mesh)
        out[f"{name}_contact_fraction"] = r[0]["contact_fraction"]
    out["ticks"] = runs["dense"][0]["ticks"]
    out["ratio"] = float(np.median(out["compressed_median_us"]) / np.median(out["dense_median_us"]))
    # the displayed deformation the C core computes on each table at the grasp's last tick (pm_servo_deformation
    # through the binding: the display forces, then the ζ table's rows or one product with Ξ's blocks)
    from pmask.runtime import Contacts

    for name, table in tables.items():
        c = Contacts(ContactSurface.from_table(table), 2, friction=0.3, engine="native")
        for probes in np.reshape(np.fromfile(traces[name], "<f8", offset=8), (-1, 2, 3)):
            c.step(probes.tolist())
        if not np.any(c.deformation()):
            raise RuntimeError(f"the grasp on the {name} table ends out of contact: nothing to time")
        ts = []
        for _ in range(20):
            t0 = time.perf_counter()
            c.deformation()
            ts.append(time.perf_counter() - t0)
        out[f"{name}_deformation_ms"] = float(np.median(ts) * 1e3)
        del c
    return out


def eight_workers(size, work: Path) -> dict:
    """A simulated 8-worker cluster on this 2-core machine, each worker limited to 1 GiB: peak RSS per worker."""
    from distributed import Client, LocalCluster

    from pmask.precompute import compress

    _, mesh, surf, factor = setup(size)
    pts = mesh.points[surf.vertices[surf.regions.contact]]
    with Client(LocalCluster(n_workers=8, threads_per_worker=1, memory_limit="1GiB", dashboard_address="127.0.0.1:0",
                                scheduler_kwargs={"dashboard": False})) as cl:
        pids = set(cl.run(os.getpid).values())
        with PeakRSS() as m:
            t0 = time.perf_counter()
            _, st = compress.compressed_greens(factor, pts, R_MAX, store=work / "t8.h5", key="8", panel=128, client=cl)
            secs = time.perf_counter() - t0
    per = sorted(m.per[p] / 2**20 for p in pids if p in m.per)
    return {"workers": 8, "memory_limit_mib": 1024, "tiles": st["tiles"], "seconds": secs,
            "peak_rss_per_worker_mib": per, "factor_mib": compress.factor_bytes(factor) / 2**20,
            "tile_estimate_mib": st["tile_bytes"] / 2**20, "passes": st.get("passes"),
            "pass_estimate_mib": st.get("pass_bytes", 0) / 2**20}


def passes_side_by_side(params: dict, work: Path) -> dict:
    """The organ-scale kidney's tiles as passes (the route's default: at least ``PASSES_PER_THREAD`` a worker
    thread), as three passes a thread (the default before 2026-12-04) and one tile a task (``PASS_BYTES`` = 0:
    every pass a single tile, as before passes), on the same 2-worker LocalCluster in this one run, each run
    from its own W sweep (and the default's passes again, for the run's noise): the tiles' time (the GF stage less the
    sweep), how many times they read W's store, and whether all give the same arrays (they must, bit for bit: a pass
    shares reads, not arithmetic)."""
    import hashlib

    import numpy as np
    from distributed import Client, LocalCluster

    from pmask.pipeline import stages
    from pmask.precompute import compress

    spec = stages.Spec(model="kidney", params=params, r_max=R_MAX, element=ELEMENT)
    mesh = stages.support_stage(spec, stages.mesh_stage(spec))
    surf = stages.surface_stage(spec, mesh)
    factor, _ = stages.factor_stage(spec, mesh, surf)
    pts = mesh.points[surf.vertices[surf.regions.contact]]
    out, arrays = {"contact": len(pts)}, {}
    default, per_thread = compress.PASS_BYTES, compress.PASSES_PER_THREAD
    with Client(LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address="127.0.0.1:0",
                                scheduler_kwargs={"dashboard": False})) as cl:
        for label, budget, threads in (("passes", default, per_thread), ("three passes a thread", default, 3),
                                       ("one tile a task", 0, per_thread), ("passes again", default, per_thread)):
            compress.PASS_BYTES = budget  # (both read by the client only, where it cuts the passes)
            compress.PASSES_PER_THREAD = threads
            try:
                a, st = compress.compressed_greens(factor, pts, R_MAX, store=work / f"ab-{len(out)}.h5", key=label,
                                                   client=cl)
            finally:
                compress.PASS_BYTES, compress.PASSES_PER_THREAD = default, per_thread
            arrays[label] = {k: hashlib.sha256(np.ascontiguousarray(np.asarray(v))).hexdigest() for k, v in a.items()}
            out[label] = {"tiles_s": st["seconds"] - st["sweep_s"], "sweep_s": st["sweep_s"], "passes": st["passes"],
                          "W_reads": st["W_reads"], "tiles": st["tiles"]}
            print(label, out[label], flush=True)
    out["identical"] = all(other == arrays["passes"] for other in arrays.values())  # every array's SHA-256
    return out


def main(out: Path) -> dict:
    import tempfile

    from run import machine

    res = {"date": time.strftime("%Y-%m-%d %H:%M"), "r_max_m": R_MAX, "tolerance": TOL, "element": ELEMENT,
           "machine": machine()}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        res.update(kidney_rows(tmp))
        print(f"organ scale: kidney {LARGE} ...", flush=True)
        res["large"] = large(LARGE, tmp)
        print(json.dumps(res["large"], default=str)[:600], flush=True)
        print("the haptic step on the organ-scale compressed artifact ...", flush=True)
        # dense.h5 is the last errors() run's (3,882 contact vertices)
        res["haptic_step"] = haptic_step(tmp / "dense.h5", tmp / "large.h5", tmp)
        print(json.dumps(res["haptic_step"]), flush=True)
        print("two coupled contacts on the organ-scale compressed artifact ...", flush=True)
        res["coupled_step"] = coupled_step(tmp / "dense.h5", tmp / "large.h5")
        print(json.dumps(res["coupled_step"]), flush=True)
        print("two coupled contacts in C on the organ-scale compressed artifact's table ...", flush=True)
        res["coupled_step_c"] = coupled_step_c(tmp / "dense.h5", tmp / "large.h5", tmp)
        print(json.dumps(res["coupled_step_c"]), flush=True)
        print("passes against one tile a task at organ scale ...", flush=True)
        res["passes_ab"] = passes_side_by_side(LARGE, tmp)
        print("8 memory-limited workers ...", flush=True)
        res["eight_workers"] = eight_workers(0.005, tmp)
        print(json.dumps(res["eight_workers"]), flush=True)
    kept = json.loads(out.read_text()) if out.exists() else {}
    for key in (k for k in kept if k.startswith("organ") or k in ("large_p2", "read_model")):  # ONLY=organ..., reads
        res[key] = kept[key]
    res["refit"] = refit_numbers(res)
    out.write_text(json.dumps(res, indent=1, default=float))
    return res


def kidney_rows(work: Path) -> dict:
    """The dense-against-compressed rows (:func:`errors`) at the section's two kidney sizes, by key; the last
    leaves its dense artifact in ``work`` (dense.h5: the 3,882-vertex one, which the haptic steps compare with)."""
    rows = {}
    for size in (0.005, 0.003):
        print(f"dense vs compressed, kidney size {size} ...", flush=True)
        rows[f"kidney_{size}"] = errors(size, work)
        print(json.dumps(rows[f"kidney_{size}"], default=str)[:600], flush=True)
    return rows


def kidneys(out: Path) -> dict:
    """The dense-against-compressed rows alone (`make bench ONLY=compress-kidneys`, ~2 min), each with its own date
    and machine, stored beside the section's other results in ``out`` (kept as they were, with theirs)."""
    import tempfile

    from run import machine

    res = json.loads(out.read_text()) if out.exists() else {"r_max_m": R_MAX, "tolerance": TOL, "element": ELEMENT}
    with tempfile.TemporaryDirectory() as tmp:
        rows = kidney_rows(Path(tmp))
    for r in rows.values():
        r.update(date=time.strftime("%Y-%m-%d %H:%M"), machine=machine())
    res.update(rows)
    res.setdefault("date", r["date"])
    out.write_text(json.dumps(res, indent=1, default=float))
    return res


def grasp_in_c(out: Path) -> dict:
    """The same grasp in C alone (:func:`coupled_step_c`, `make bench ONLY=compress-c`, ~5 min on 2 cores): the
    organ-scale artifact (LARGE) and the 3,882-vertex dense kidney made afresh, their tables exported as this
    version writes them (table 1.5: the far field's 16-bit words, the exact pairs' 48-bit ones); stamped with its own date and machine and stored beside the
    section's other results in ``out`` (kept as they were, with theirs)."""
    import tempfile

    from run import machine

    from pmask.pipeline.stages import Spec, run

    res = json.loads(out.read_text()) if out.exists() else {"r_max_m": R_MAX, "tolerance": TOL, "element": ELEMENT}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        print("the dense kidney (size 0.003) and the organ-scale compressed one ...", flush=True)
        run(Spec(model="kidney", params={"size": 0.003}, r_max=R_MAX, element=ELEMENT), tmp / "dense.h5", force=True)
        run(Spec(model="kidney", params=LARGE, r_max=R_MAX, compress=TOL, workers=2, element=ELEMENT),
            tmp / "large.h5", force=True)
        print("two coupled contacts in C on the organ-scale compressed artifact's table ...", flush=True)
        c = coupled_step_c(tmp / "dense.h5", tmp / "large.h5", tmp)
    c.update(date=time.strftime("%Y-%m-%d %H:%M"), machine=machine())
    print(json.dumps(c, default=str), flush=True)
    res["coupled_step_c"] = c
    out.write_text(json.dumps(res, indent=1, default=float))
    return res


def organ_key(r_max: float, element: str = ELEMENT) -> str:
    """Where an organ run at ``r_max`` is kept in the results: "organ" at the section's R_MAX; the P2 run at
    LARGE, "large_p2"."""
    if element != ELEMENT:
        return f"large_{element.lower()}"
    return "organ" if r_max == R_MAX else f"organ_{r_max * 1e3:g}mm"


def organ(out: Path, r_max: float = R_MAX, element: str = ELEMENT) -> dict:
    """The organ-scale run at ORGAN (issue #27's 50,000 contact vertices) with masks up to ``r_max``, or with
    another element at LARGE (P2: the large-organs guide's own command), from a fresh work folder, stored beside
    the compressed-Ξ section's other results in ``out`` under :func:`organ_key` (its own date)."""
    import tempfile

    res = json.loads(out.read_text()) if out.exists() else {"r_max_m": R_MAX, "tolerance": TOL, "element": ELEMENT}
    params = ORGAN if element == ELEMENT else LARGE
    print(f"organ scale: kidney {params}, r_max {r_max} m, {element} ...", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        r = large(params, Path(tmp), r_max=r_max, element=element)
    from run import machine

    r["date"] = time.strftime("%Y-%m-%d %H:%M")
    r["machine"] = machine()
    res[organ_key(r_max, element)] = r
    res["refit"] = refit_numbers(res)
    print(json.dumps(r, default=str)[:600], flush=True)
    out.write_text(json.dumps(res, indent=1, default=float))
    return res


def rederive(out: Path) -> dict:
    """The results' derived entry (``refit``) computed again from the stored rows, nothing measured: after a change
    to :func:`refit_numbers` (``python bench/compress_bench.py --refit``, then ``python bench/report.py``)."""
    res = json.loads(out.read_text())
    res["refit"] = refit_numbers(res)
    out.write_text(json.dumps(res, indent=1, default=float))
    return res


def small_row(res: dict, g: dict) -> dict:
    """The 3,882-vertex row where it ran on the machine run ``g`` did (a row measured apart carries its own
    ``machine``), else nothing: times are not compared across machines."""
    small = res.get("kidney_0.003", {})
    where = lambda r: {k: (r.get("machine") or res.get("machine") or {}).get(k) for k in ("cpu", "cores")}  # noqa: E731
    return small if small and where(small) == where(g) else {}


def extrapolation(res: dict, sizes=(50_000, 100_000, 200_000)) -> str:
    """Where the organ-scale run's numbers go at larger n: a model, fitted to this run, not a measurement.
    The near field is every pair within r_max, so at a fixed r_max (mm) it grows like n² as the mesh refines
    (a mask covers ∝ n vertices); the far field like n log n; the GF stage's time with the slope measured
    between the 3,882- and the 20,427-vertex runs; N workers on a real scheduler divide the tiles' time by
    N/2 at best (the W sweep stays serial, on one worker)."""
    g = res["large"]
    small = small_row(res, g)
    n0 = g["contact"]
    slope = (np.log(g["greens_s"] / small["compressed_2"]["greens_s"]) / np.log(n0 / small["contact"])
             if small.get("compressed_2") else None)
    rows = []
    disk = g["disk_stored_bytes"] / g["compressed_stored_bytes"] if "disk_stored_bytes" in g else None
    for n in sizes:
        near = g["near_bytes"] * (n / n0) ** 2
        far = g["far_bytes"] * n * np.log(n) / (n0 * np.log(n0))
        t = f", GF stage ~{duration(g['greens_s'] * (n / n0) ** slope)} on 2 workers" if slope else ""
        rows.append(f"{n:,}: ~{(near + far) / 2**30:.1f} GiB stored ({near / 2**30:.1f} near, {far / 2**30:.1f} far"
                    + (f"; ~{disk * (near + far) / 2**30:.1f} in the file at this run's ratio" if disk else "")
                    + f"){t}")
    check = ""
    o = res.get("organ")
    if o and "near_bytes" in o:  # the model against the measured run at ~50,000
        n = o["contact"]
        near = g["near_bytes"] * (n / n0) ** 2
        far = g["far_bytes"] * n * np.log(n) / (n0 * np.log(n0))
        t = g["greens_s"] * (n / n0) ** slope if slope else None
        check = (f" Checked against the {n:,}-vertex run above: the model said {near / 2**30:.1f} GiB near and "
                 f"{far / 2**30:.2f} GiB far" + (f" and a GF stage of {t / 60:.0f} min" if t else "")
                 + f"; measured {o['near_bytes'] / 2**30:.1f}, {o['far_bytes'] / 2**30:.2f} GiB"
                 + f" and {o['greens_s'] / 60:.0f} min.")
    return ("**Extrapolated** (a model fitted to the organ-scale run, not measured; r_max fixed at "
            f"{1e3 * res['r_max_m']:.0f} mm, so the exact near field grows like n²"
            + (f"; time like n^{slope:.2f}, the slope measured from 3,882 to {n0:,} vertices" if slope else "")
            + "; N workers divide the tiles' time by at most N/2): " + "; ".join(rows) + "." + check
            + refit(res))


#: the sizes the refit goes to (refit_numbers)
REFIT_SIZES = (50_000, 100_000, 200_000)


def refit_numbers(res: dict, sizes=REFIT_SIZES) -> dict | None:
    """The refit below as numbers, kept in the results (``refit``) so that the guides can quote them: its
    exponents, and per size the values' bytes (near, far, total), the bytes in the file at the organ run's ratio
    of the two, and the W sweep's and the tiles' seconds on this machine's 2 workers."""
    g, o = res.get("large"), res.get("organ")
    if not (g and o and "near_bytes" in g and "near_bytes" in o):
        return None
    ln = np.log(o["contact"] / g["contact"])
    # the smaller run's times at the organ run's speed, where both took the speed reference (speed_reference)
    speed = (float(np.mean(o["speed_reference_s"]) / np.mean(g["speed_reference_s"]))
             if g.get("speed_reference_s") and o.get("speed_reference_s") else None)
    exp = {k: float(np.log(o[k] / g[k]) / ln) for k in ("near_bytes", "far_bytes")}
    exp["greens_s"] = float(np.log(o["greens_s"] / (g["greens_s"] * (speed or 1.0))) / ln)
    exp["sweep_s"] = float(np.log(o["stats"]["sweep_s"] / (g["stats"]["sweep_s"] * (speed or 1.0))) / ln)
    peaks = [k for k in ("client_peak_rss_gib", "sweep_worker_peak_rss_gib") if g.get(k) and o.get(k)]
    exp.update({k: float(np.log(o[k] / g[k]) / ln) for k in peaks})  # the processes' peaks (runs after #27's move)
    ratio = o["disk_stored_bytes"] / o["compressed_stored_bytes"] if "disk_stored_bytes" in o else None

    def at(value, key, n):
        return value * (n / o["contact"]) ** exp[key]

    out = {"exponents": exp, "from": [g["contact"], o["contact"]], "dates": [res.get("date", ""), o.get("date", "")],
           "speed": speed}
    for n in sizes:
        near, far = at(o["near_bytes"], "near_bytes", n), at(o["far_bytes"], "far_bytes", n)
        sweep = at(o["stats"]["sweep_s"], "sweep_s", n)
        out[str(n)] = {"near_bytes": near, "far_bytes": far, "stored_bytes": near + far,
                       "disk_bytes": None if ratio is None else ratio * (near + far),
                       "sweep_s": sweep, "tiles_s": at(o["greens_s"], "greens_s", n) - sweep,
                       **{k: at(o[k], k, n) for k in peaks}}
    return out


def duration(seconds: float) -> str:
    """A modelled time as a reader takes it in: minutes below an hour (an extrapolation's "0.0 h" said nothing),
    else hours to a tenth."""
    return f"{seconds / 60:.0f} min" if seconds < 3600 else f"{seconds / 3600:.1f} h"


def refit(res: dict, sizes=REFIT_SIZES, workers=(2, 16, 64)) -> str:
    """The extrapolation again, each quantity a power of n through the two largest runs at the same r_max (the
    organ-scale run and the 50,000 row): what the measured growth says, still a model.  The W sweep runs on
    one worker (serial whatever the workers); the rest of the GF stage is the tiles', which N workers on a real
    scheduler divide by at most N/2 (this machine's 2 workers); their I/O of W's store is assumed to scale with
    them (a shared filesystem that does not is slower)."""
    r = refit_numbers(res, sizes)
    if r is None:
        return ""
    exp, (n_g, n_o) = r["exponents"], r["from"]
    rows = []
    for n in sizes:
        x = r[str(n)]
        times = ", ".join(f"{duration(x['sweep_s'] + x['tiles_s'] * 2 / w)} on {w}" for w in workers)
        disk = (f", ~{x['disk_bytes'] / 2**30:.2f} in the file at the {n_o:,}-vertex run's ratio"
                if x["disk_bytes"] is not None else "")
        peaks = (f"; peak RSS of the client ~{x['client_peak_rss_gib']:.2f} GiB, of the worker that factorises and "
                 f"sweeps ~{x['sweep_worker_peak_rss_gib']:.2f} GiB" if "sweep_worker_peak_rss_gib" in x else "")
        rows.append(f"{n:,}: ~{x['stored_bytes'] / 2**30:.2f} GiB stored ({x['near_bytes'] / 2**30:.2f} near, "
                    f"{x['far_bytes'] / 2**30:.2f} far{disk}), GF stage ~{times} workers{peaks}")
    speed = (f"the first run's times scaled by the runs' speed references, x{r['speed']:.2f}" if r.get("speed")
             else "no speed reference in the first run (it predates them): the time exponents carry any change in "
                  "the machine's speed between the runs")
    return (f" Refitted through the {n_g:,}- and {n_o:,}-vertex runs (measured {r['dates'][0]} and "
            f"{r['dates'][1]}; {speed}; each quantity a power of n: "
            f"near field n^{exp['near_bytes']:.2f}, far field n^{exp['far_bytes']:.2f}, GF stage "
            f"n^{exp['greens_s']:.2f} of which the W sweep (one worker) n^{exp['sweep_s']:.2f}; N workers divide "
            f"the rest "
            f"by at most N/2): " + "; ".join(rows) + ".")


def exact_floor(g: dict) -> int:
    """The bytes of the pairs within r_max, which the format keeping them exact stores (``exact_pair_bytes`` a
    pair: 56 in fixed point, format 1.7; 72 in float64 before): ``pairs_within_r_max_bytes`` counts each unordered
    pair (i = j included) once, which a symmetric Ξ stores; a non-symmetric one (P2) stores both ways, every pair
    but i = j twice."""
    once = int(g["pairs_within_r_max_bytes"])
    return once if g["stats"].get("symmetric") else 2 * once - int(g.get("exact_pair_bytes", 72)) * int(g["contact"])


def organ_paragraph(g: dict, res: dict, title: str) -> str:
    """The paragraph of an organ-scale run (``large``)."""
    st = g["stats"]
    memory = (f" Memory models (what the run checked before each phase): W sweep {st['sweep_peak_bytes'] / 2**30:.2f} "
              f"GiB at its peak in {st.get('sweep_batches', 1)} batch(es), assembly {st['assembly_bytes'] / 2**30:.2f} GiB."
              if "sweep_peak_bytes" in st and "assembly_bytes" in st else "")
    small = small_row(res, g)
    per_flop = (small.get("dense", {}).get("greens_s", 0.0) / small["compressed_2"]["stats"]["gram_flops"]
                if small.get("compressed_2", {}).get("stats", {}).get("gram_flops") else None)
    est = (f"~{per_flop * st['gram_flops'] / 60:.0f} min by its " + ("syrk" if st.get("symmetric") else "gemm")
           + " flops" if per_flop else "not estimated")
    return (f"**{title}**: kidney ({g.get('element', 'P1')}) with {g['params']['size'] * 1e3:.2f} mm surface edges, "
              f"volume graded to "
              f"{g['params']['interior'] * 1e3:.0f} mm ({g['contact']:,} contact vertices, {g['dofs']:,} dofs), "
              f"compressed on 2 local workers through `pmask precompute`: whole run {g['total_s'] / 60:.1f} min "
              + (f"(the machine's speed reference, a one-thread 1024² matrix product, "
                 f"{1e3 * g['speed_reference_s'][0]:.0f} ms before the run and {1e3 * g['speed_reference_s'][1]:.0f} "
                 "ms after; "
                 if g.get("speed_reference_s") else "(")
              + f"GF stage {g['greens_s'] / 60:.1f} min: W sweep {st['sweep_s']:.0f} s, {st['tiles']} tiles"
              + (f" in {st['passes']} passes over W (each within {st['pass_bytes'] / 2**30:.2f} GiB by the memory "
                 f"model), which read W's store {st['W_reads']:.1f} times in all" if "passes" in st else "")
              + (f", {st['sketched']:,} far blocks or pieces from their sketches, {st['formed_again']:,} of them formed "
                 "after all" if "sketched" in st else "") + "), "
              f"**peak RSS {g['peak_rss_gib']:.2f} GiB** (process tree; largest processes "
              f"{', '.join(f'{x:.2f}' for x in g['peak_rss_per_process_gib'][:3])} GiB"
              + (f"; the client {g['client_peak_rss_gib']:.2f} GiB, the worker that factorised and swept W "
                 f"{g['sweep_worker_peak_rss_gib']:.2f} GiB" if g.get("sweep_worker_peak_rss_gib") else "")
              + "), W's store "
              f"{st['W_bytes'] / 2**30:.2f} GiB on disk. Stored {g['compressed_stored_bytes'] / 2**30:.2f} GiB "
              + (f"of values, **{g['disk_stored_bytes'] / 2**30:.2f} GiB in the file** (the near field deflated: "
                 f"{g['near_disk_bytes'] / g['near_bytes']:.2f} of its bytes) " if "disk_stored_bytes" in g else "")
              + (f"(near field {g['near_bytes'] / 2**30:.2f}"
                 + (f" (its pairs within r_max exactly {g['near_exact_bytes'] / 2**30:.2f}, its other pairs in 16 bits "
                    f"with their scales and mask {g['near_16bit_bytes'] / 2**30:.2f})"
                    if "near_exact_bytes" in g else "")
                 + f", far field {g['far_bytes'] / 2**30:.2f}"
                 + (f" in 16 bits ({st['far_rank3k_blocks']:,} of its blocks at rank 3k, the largest rounding "
                    f"{st['far_rounding_max']:.1e} of a block)" if "far_rank3k_blocks" in st else "")
                 + (f"; the pairs within r_max alone, which the format stores exactly "
                    f"({int(g.get('exact_pair_bytes', 72))} bytes a pair), are {exact_floor(g) / 2**30:.2f} GiB"
                    + ("" if st.get("symmetric") else " (both ways: Ξ is not symmetric)")
                    + ((" (the exact part holds those within a diagonal leaf block both ways)"
                        if st.get("symmetric") else "")
                       if "near_exact_bytes" in g else
                       ": the leaf blocks hold pairs up to r_max plus two leaves' diagonals apart")
                    if "pairs_within_r_max_bytes" in g else "") + ") "
                 if "near_bytes" in g else "")
              + f"against a dense {g['dense_Xi_bytes'] / 2**30:.1f} GiB: {g['dense_Xi_bytes'] / g['compressed_stored_bytes']:.1f}x, "
              f"max rank {st['max_rank']}" + (", stored once per symmetric pair of blocks" if st.get("symmetric") else "")
              + (f"; {st['merged_blocks']:,} blocks wider than a panel merged from {st['merged_pieces']:,} pieces "
                 f"in {st['merge_s']:.1f} s" if "merged_blocks" in st else "")
              + (f". Opened in {g['open_s']:.2f} s (median of {len(g.get('open_runs_s', [0]))}, "
                 f"{min(g.get('open_runs_s', [g['open_s']])):.2f}–{max(g.get('open_runs_s', [g['open_s']])):.2f} s; "
                 f"`Model.load`, page cache warm, far field "
                 + ("left in the file" if g.get("far_field") == "FileArray" else "read into memory and checked")
                 + (f", near field read when first needed; {g['open_near_field_s']:.2f} s reading and checking it at "
                    f"open, median of {len(g['open_near_field_runs_s'])})"
                    if g.get("near_field") == "BlocksOnDemand" else ", near field read and checked)")
                 + f", every K_i in {g['all_K_s']:.1f} s"
                 + (", reading and checking the near field as it goes" if g.get("near_field") == "BlocksOnDemand"
                    else "")
                 + (f" ({g['near_block_reads']:,} reads of its {g['near_blocks']:,} blocks, at most "
                    f"{g['near_held_limit'] / 2**30:.1f} GiB of them held)" if g.get("near_held_limit") else "")
                 + (f" (a process that opens it and forms them: peak RSS {g['all_K_peak_rss_gib']:.2f} GiB)"
                    if "all_K_peak_rss_gib" in g
                    else "") if "open_s" in g else "") + ". Dense: " + (f"does not fit (needs ~{g['dense_need_gib']:.0f} GiB; without --compress `pmask precompute` "
                                              "takes the compressed route for it, with a warning)"
                                           if g["dense_refused"] else "would run") + f", estimated {est} if it "
              f"fitted (scaled from the 3,882-vertex dense run). {g['columns_checked']} random vertices' columns "
              f"against the factor's own solve: {g['columns_rel_err']:.1e} relative, near field "
              f"{g['near_max_abs_rel']:.0e}."
        + memory)


def markdown(res: dict) -> str:
    """The README's table of this bench."""
    kidneys = sorted(k for k in res if k.startswith("kidney_"))
    when = res[kidneys[0]] if kidneys and res[kidneys[0]].get("date") else res  # (rows measured apart carry their own)
    L = [f"**Compressed Ξ** (kidney, {res.get('element', 'P1')}, r_max = {1e3 * res['r_max_m']:.0f} mm, "
         f"tolerance {res['tolerance']:g}; "
         f"{when['date']}" + (f", {when['machine']['cpu']}, {when['machine']['cores']} cores" if when.get("machine") else "")
         + "):", "",
         "| contact vertices | dense Ξ | compressed | ratio | GF stage dense / from dense / tiles on 1 worker / 2 "
         "workers | whole run dense / from dense / tiles on 2 workers (each ÷ dense) | "
         "peak RSS dense / 2 workers | K_i | deformation | 3 coupled contacts |", "|---|---|---|---|---|---|---|---|---|---|"]
    for key in kidneys:
        r = res[key]
        first = r.get("compressed")  # (rows measured before --compress compressed the dense Ξ where it fits: none)
        L.append(f"| {r['contact']:,} | {r['dense_Xi_bytes'] / 2**20:.0f} MiB | {r['compressed_stored_bytes'] / 2**20:.0f} MiB "
                 f"| {r['dense_Xi_bytes'] / r['compressed_stored_bytes']:.1f}x | {r['dense']['greens_s']:.1f} / "
                 + (f"{first['greens_s']:.1f} / " if first else "– / ")
                 + f"{r['compressed_1']['greens_s']:.1f} / {r['compressed_2']['greens_s']:.1f} s | "
                 + (f"{r['dense']['whole_s']:.1f} / " + (f"{first['whole_s']:.1f} / " if first else "– / ")
                    + f"{r['compressed_2']['whole_s']:.1f} s ("
                    + (f"{first['whole_s'] / r['dense']['whole_s']:.2f}x, " if first else "")
                    + f"{r['compressed_2']['whole_s'] / r['dense']['whole_s']:.2f}x) | " if "whole_s" in r["dense"] else "– | ")
                 + f"{r['dense']['peak_rss_gib']:.2f} / {r['compressed_2']['peak_rss_gib']:.2f} GiB | "
                 f"{r['K_i_max_rel']:.1e} | {r['deformation_rel_max']:.1e} | {r['coupling_rel_max']:.1e} |")
    g = res.get("large")
    if when is not res and res.get("machine"):  # the table measured apart (`ONLY=compress-kidneys`)
        L += ["", f"The rest of this section: `make bench ONLY=compress` of {res['date']}, {res['machine']['cpu']}, "
                  f"{res['machine']['cores']} cores, unless a paragraph names its own run."]
    if g:
        L += ["", organ_paragraph(g, res, "Organ scale")]
    if res.get("organ"):
        o = res["organ"]
        m = o.get("machine")
        where = (f", {m['cpu']}, {m['cores']} cores" if m else ", on a machine this page did not record")
        L += ["", organ_paragraph(o, res, f"Issue #27's 50,000 (measured {o.get('date', '')}{where})")]
    for key in sorted(k for k in res if k.startswith("organ_")):  # the same organ with a smaller r_max
        o = res[key]
        m = o.get("machine")
        where = (f", {m['cpu']}, {m['cores']} cores" if m else ", on a machine this page did not record")
        L += ["", organ_paragraph(o, res, f"The same 50,000 with masks up to r_max = {o['r_max_m'] * 1e3:g} mm "
                                          f"(measured {o.get('date', '')}{where})")]
    if res.get("large_p2"):
        o = res["large_p2"]
        m = o.get("machine")
        where = (f", {m['cpu']}, {m['cores']} cores" if m else ", on a machine this page did not record")
        L += ["", organ_paragraph(o, res, f"The organ-scale kidney with P2, the element `--element auto` takes "
                                          f"for ν = 0.45 (the large-organs guide's command; measured "
                                          f"{o.get('date', '')}{where}, `make bench ONLY=organ-p2`)")]
    h = res.get("haptic_step")
    if g and h:
        L += ["", f"The haptic step in C (one contact, the haptics issue's tour, tight; the native core on the "
                  f"artifact's exported table) on the organ-scale compressed artifact ({h['compressed_vertices']:,} "
                  f"surface vertices): median tick {', '.join(f'{x:.3f}' for x in h['compressed_median_us'])} µs "
                  f"against {', '.join(f'{x:.3f}' for x in h['dense_median_us'])} µs on the dense "
                  f"{h['dense_vertices']:,}-vertex one, alternated in this run: {h['ratio']:.2f}x (the hands issue "
                  f"asks ≤ 2x)."]
    c = res.get("coupled_step")
    if g and c and "held_median_us" in c:
        L += ["", f"Two coupled jaws in the native core (a grasp 2.5 mm deep slid 10 mm, μ = 0.3, {c['ticks']:,} ticks, "
                  f"each timed through the Python binding) on the organ-scale compressed artifact, by default "
                  f"with Ξ's compressed sections held by the core ({c['held_greens_mib']:,.0f} MiB, read in "
                  f"{c['held_load_s']:.1f} s when the first contacts are made), which forms a pair of triangles' "
                  f"blocks itself when the jaws land on them: median tick "
                  f"{', '.join(f'{x:.2f}' for x in c['held_median_us'])} µs (longest "
                  f"{', '.join(f'{x:.2f}' for x in c['held_max_ms'])} ms) against "
                  f"{', '.join(f'{x:.2f}' for x in c['dense_median_us'])} µs (longest "
                  f"{', '.join(f'{x:.2f}' for x in c['dense_max_ms'])} ms) on the dense "
                  f"{c['dense_vertices']:,}-vertex one's ζ table, alternated in this run ({c['held_ratio']:.2f}x).  "
                  f"Where the sections would not fit (past half the memory available) the core asks the surface "
                  f"for the blocks instead, a tick that asks taking the GIL: median tick "
                  f"{', '.join(f'{x:.2f}' for x in c['asked_median_us'])} µs ({c['asked_ratio']:.2f}x); "
                  f"{c['requests'][0]} requests for blocks per run, taking a median "
                  f"{c['request_median_ms'][0]:.3f} ms and at most {c['request_max_ms'][0]:.1f} ms from a cold cache "
                  f"(the longest tick {c['asked_max_ms'][0]:.1f} ms: a tick that asks is late by that much), "
                  f"at most {max(c['request_max_ms'][1:] or [0.0]):.2f} ms once the stiffness's cache of blocks is "
                  f"warm."]
        if "held_thread" in c:
            h, a = c["held_thread"], c["asked_thread"]
            L[-1] += (f"  The native thread at 1 kHz beside a Python thread holding the GIL (a pure-Python loop; the "
                      f"{h['samples']:,} samples set at the same pace): with the sections held, {h['late']} late "
                      f"ticks of {h['ticks']:,}, the longest step {h['step_max_ms']:.2f} ms; asking Python for "
                      f"blocks, {a['late']:,} late of {a['ticks']:,}, the longest step {a['step_max_ms']:.1f} ms "
                      f"(the ticks that ask wait for the GIL; with the sections held no step waits, and its late "
                      f"ticks are the scheduler's: the servo, the pacing loop and the GIL holder spin on the "
                      f"run's {res['machine']['cores']} cores).")
    c = res.get("coupled_step_c")
    if g and c:
        m = c.get("machine")
        apart = (f"measured apart, {c['date']}, {m['cpu']}, {m['cores']} cores, `make bench ONLY=compress-c`; "
                 if m else "")
        L += ["", f"The same grasp in C ({apart}`servo_bench`, tight, μ = 0.3, a fresh process each run) on the tables "
                  f"`pmask export-table` writes: the organ-scale compressed artifact's ({c['compressed_table_mib']:,.0f} "
                  f"MiB, Ξ's compressed sections in place of the ζ table; the core forms a pair of triangles' blocks "
                  f"when the jaws land on them) and the dense {c['dense_vertices']:,}-vertex one's "
                  f"({c['dense_table_mib']:,.0f} MiB with its ζ table): median tick "
                  f"{', '.join(f'{x:.3f}' for x in c['compressed_median_us'])} µs against "
                  f"{', '.join(f'{x:.3f}' for x in c['dense_median_us'])} µs, alternated in this run "
                  f"({c['ratio']:.2f}x; the hands issue asks ≤ 2x); the longest tick "
                  f"{', '.join(f'{x / 1e3:.2f}' for x in c['compressed_max_us'])} ms against "
                  f"{', '.join(f'{x / 1e3:.2f}' for x in c['dense_max_us'])} ms (the ticks that form blocks are "
                  f"among the compressed table's; the dense one's longest show the machine's own hiccups of that "
                  f"size); the empty timer {np.median(c['compressed_empty_us'] + c['dense_empty_us']):.3f} µs.  "
                  f"The displayed deformation the C core computes at the grasp's last tick (`pm_servo_deformation` "
                  f"through the binding, median of 20): {c['compressed_deformation_ms']:.2f} ms from Ξ's compressed "
                  f"sections against {c['dense_deformation_ms']:.2f} ms from the dense one's ζ table."]
    if g and "near_bytes" in g:
        L += ["", extrapolation(res)]
    ab = res.get("passes_ab")
    if ab:
        p, one, again = ab["passes"], ab["one tile a task"], ab["passes again"]
        three = ab.get("three passes a thread")  # (a run before 2026-12-04 has no such row)
        runs = [p] + ([three] if three else []) + [one, again]  # (in the sentence's order)
        L += ["", f"Passes against one tile a task, side by side in this run ({ab['contact']:,} contact vertices, "
                  f"2 local workers, each run from its own W sweep): the tiles took {p['tiles_s']:.0f} s in "
                  f"{p['passes']} passes, reading W's store {p['W_reads']:.1f} times, "
                  + (f"against {three['tiles_s']:.0f} s in {three['passes']} passes (three a worker thread), reading "
                     f"it {three['W_reads']:.1f} times ({p['tiles_s'] / three['tiles_s']:.2f}x), and "
                     if three else "against ")
                  + f"{one['tiles_s']:.0f} s "
                  f"one tile a task ({one['tiles']} tasks), reading it {one['W_reads']:.1f} times "
                  f"({p['tiles_s'] / one['tiles_s']:.2f}x); the passes again {again['tiles_s']:.0f} s (the run's "
                  "noise); "
                  f"the sweeps {', '.join(format(r['sweep_s'], '.0f') for r in runs)} s; the arrays "
                  + ("identical bit for bit." if ab["identical"] else "**not identical**.")]
    e = res["eight_workers"]
    L += ["", f"8 simulated workers (LocalCluster, 1 GiB each, on 2 cores), {e['tiles']} tiles of the default kidney "
              f"in {e['seconds']:.1f} s: peak RSS per worker {min(e['peak_rss_per_worker_mib']):.0f}–"
              f"{max(e['peak_rss_per_worker_mib']):.0f} MiB (a tile estimated "
              f"{e['tile_estimate_mib']:.0f} MiB" + (f"; {e['passes']} passes over W, each estimated at most "
                                                       f"{e['pass_estimate_mib']:.0f} MiB" if e.get("passes") else "")
              + ")."]
    return "\n".join(L)


def every_k(path: str, r_max: float) -> dict:
    """Open a compressed artifact and form every K_i (the near field only, read on demand above 256 MiB, at most
    ``Model.NEAR_FIELD_HELD`` of it held): the time, and this process's peak RSS (the kernel's VmHWM: the
    interpreter, numpy and the model included; not ru_maxrss, which a process started by fork and exec inherits
    from its parent: it gave the bench process's 3.4 GiB), for a process that does nothing else."""
    from pmask.runtime import Model

    c = Model.load(path)
    t0 = time.perf_counter()
    c.stiffness("linear", r_max).K_full
    out = {"all_K_s": time.perf_counter() - t0}
    with open("/proc/self/status") as f:
        hwm = next(int(line.split()[1]) for line in f if line.startswith("VmHWM:"))  # kB
    out["all_K_peak_rss_gib"] = hwm * 1024 / 2**30
    if type(c.Xi.dense).__name__ == "BlocksOnDemand":  # held up to the budget, the rest read again as needed
        d = c.Xi.dense
        out.update(near_blocks=len(d._read), near_block_reads=int(d.reads), near_held_limit=d.budget)
    return out


if __name__ == "__main__":
    if sys.argv[1:2] == ["--every-k"]:
        print(json.dumps(every_k(sys.argv[2], float(sys.argv[3]))))
    elif sys.argv[1:2] == ["--refit"]:
        rederive(Path(__file__).parent / "compress_results.json")
    else:
        main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).parent / "compress_results.json")
