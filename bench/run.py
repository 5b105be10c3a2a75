"""`make bench`: precompute and runtime measured side by side in one run.

Writes bench/results.json and the docs' benchmark page (docs/generated/benchmarks.md, bench/report.py).
Benchmarks are measurements, not tests: nothing here asserts a time.
"""
from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent

#: kidney size parameter -> about 500, 1,500 and 4,000 free surface vertices
SIZES = (0.0085, 0.005, 0.003)
#: precompute runs per size (each in a fresh process); the row shown is the run with the median
#: Green's-function stage.  A 2-second stage on this shared 2-core VM moves by +-30 % from run to
#: run, the 30-second baseline averages that noise out within itself.
REPEATS = {0.0085: 3, 0.005: 3, 0.003: 3}

def sh(args, **kw) -> str:
    return subprocess.run(args, check=True, capture_output=True, text=True, **kw).stdout

def precompute(size: float, out: Path, *flags, backend: str | None = None) -> dict:
    env = dict(os.environ, **({"PMASK_CHOLMOD": backend} if backend else {}))
    line = sh([sys.executable, str(HERE / "precompute_case.py"), str(size), str(out), *flags],
              env=env).strip().splitlines()[-1]
    return json.loads(line)

def drop_page_cache() -> bool:
    try:
        os.sync()
        with open("/proc/sys/vm/drop_caches", "w") as f:
            f.write("3\n")
        return True
    except OSError:
        return False

LOAD_SNIPPET = """
import json, sys, time
t0 = time.perf_counter()
from pmask.runtime import Model
t1 = time.perf_counter()
m = Model.load(sys.argv[1])
t2 = time.perf_counter()
s = m.stiffness("linear", 2.0 * m.mean_edge_length)
t3 = time.perf_counter()
import numpy as np
t = int(np.flatnonzero(s.touchable)[len(s.touchable) // 2])
ts = []
for _ in range(20):
    a = time.perf_counter(); s.deformation(t, [0.2, 0.3, 0.5], [0.0, 0.0, -0.05]); ts.append(time.perf_counter() - a)
print(json.dumps({"import_s": t1 - t0, "load_s": t2 - t1, "vertex_stiffness_s": t3 - t2,
                  "deformation_s": float(np.median(ts)), "n_contact": int(len(m.contact))}))
"""

def load_bench(path: Path) -> dict:
    """Fresh processes: once after dropping the page cache (if allowed), then the median of three warm."""
    def once():
        return json.loads(sh([sys.executable, "-c", LOAD_SNIPPET, str(path)], cwd=ROOT).strip().splitlines()[-1])

    out = {}
    if drop_page_cache():
        out["cold"] = once()
    warm = [once() for _ in range(3)]
    out["warm"] = {k: float(np.median([w[k] for w in warm])) for k in warm[0]}
    return out


CHECK_SNIPPET = """
import json, sys, time
from pmask.runtime.artifact import read_artifact
ts = {}
for verify in (False, True, False, True):
    t0 = time.perf_counter(); read_artifact(sys.argv[1], verify=verify); ts.setdefault(verify, []).append(time.perf_counter() - t0)
print(json.dumps({"load_unverified_s": min(ts[False]), "load_verified_s": min(ts[True])}))
"""


def check_cost(path: Path) -> dict:
    """What the metadata checksum costs at load (Fletcher-32 is checked by HDF5 on every read either way)."""
    return json.loads(sh([sys.executable, "-c", CHECK_SNIPPET, str(path)], cwd=ROOT).strip().splitlines()[-1])

def batch_bench(stiff, n=1_000_000) -> dict:
    rng = np.random.default_rng(2)
    t = rng.integers(0, stiff.n_triangles, n)
    b = rng.random((n, 3))
    b /= b.sum(axis=1, keepdims=True)
    runs = []
    for _ in range(3):  # the first run also pays for first-touch page faults of its 216 MB result
        t0 = time.perf_counter()
        K = stiff.at_batch(t, b)
        runs.append(time.perf_counter() - t0)
        assert np.all(np.isfinite(K))
        del K
    return {"queries": n, "seconds": min(runs), "first_run_s": runs[0], "queries_per_s": n / min(runs)}

def section_only(section: str) -> None:
    """`make bench ONLY=haptics` (or ONLY=viewer): one section alone, on kidneys precomputed afresh at the
    three sizes (one run each: the precompute rows are not replaced), written into the stored results beside
    the other sections with its own date, which the page states.  For a change to the contact law, the servo
    or the viewer, whose numbers must not wait for the whole hour-long bench."""
    from pmask.runtime import Model

    stored = HERE / "results.json"
    res = json.loads(stored.read_text())
    work = Path(tempfile.mkdtemp(prefix="pmask-bench-"))
    arts = []
    for size in SIZES if section != "display" else ():
        print(f"precompute kidney size={size} ...", flush=True)
        precompute(size, work / f"kidney_{size}.h5")
        arts.append(work / f"kidney_{size}.h5")
    print(f"{section} ...", flush=True)
    if section == "display":
        import display_bench

        res["display"] = display_bench.run(work)
    elif section == "haptics":
        import runtime_bench

        res["haptics"] = runtime_bench.run({len(Model.load(p).points): p for p in arts},
                                           runtime_bench.synthetic_stiffness, work)
    else:
        import viewer_bench

        res["viewer"] = viewer_bench.run({n: p for n, p in ((len(Model.load(p).points), p) for p in arts) if n > 1000})
    res[section]["date"] = time.strftime("%Y-%m-%d %H:%M:%S")
    res[section]["machine"] = machine()
    import shutil

    shutil.rmtree(work, ignore_errors=True)
    stored.write_text(json.dumps(res, indent=2))
    import report

    print(f"wrote {report.write(res, report.stored()[1])}")


def main() -> None:
    if "--only" in sys.argv:
        part = sys.argv[sys.argv.index("--only") + 1:][:1]
        if part == ["compress"]:  # the compressed-Ξ section (its own results file and date), ~15 min
            import compress_bench
            import report

            compress = compress_bench.main(HERE / "compress_results.json")
            print(f"wrote {report.write(report.stored()[0], compress)}")
            return None
        if part == ["compress-kidneys"]:  # that section's dense-against-compressed rows alone, ~2 min
            import compress_bench
            import report

            compress = compress_bench.kidneys(HERE / "compress_results.json")
            print(f"wrote {report.write(report.stored()[0], compress)}")
            return None
        if part == ["compress-c"]:  # that section's grasp in C on the organ-scale table alone, ~5 min
            import compress_bench
            import report

            compress = compress_bench.grasp_in_c(HERE / "compress_results.json")
            print(f"wrote {report.write(report.stored()[0], compress)}")
            return None
        if part in (["organ"], ["organ-5mm"], ["organ-p2"]):  # issue #27's 50,000-vertex organ (r_max 10 or 5 mm),
            # ~30-45 min; or the 20,000-vertex one with P2
            import compress_bench
            import report

            r_max = compress_bench.ORGAN_R_MAX if part == ["organ-5mm"] else compress_bench.R_MAX
            element = "P2" if part == ["organ-p2"] else compress_bench.ELEMENT
            compress = compress_bench.organ(HERE / "compress_results.json", r_max, element)
            print(f"wrote {report.write(report.stored()[0], compress)}")
            return None
        if part == ["reads"]:  # the read model of W's store at the two organ-scale kidneys, ~10 min
            import read_model
            import report

            compress = read_model.main(HERE / "compress_results.json")
            print(f"wrote {report.write(report.stored()[0], compress)}")
            return None
        if part not in (["haptics"], ["viewer"], ["display"]):
            sys.exit("bench: --only takes 'haptics', 'viewer', 'display', 'compress', 'compress-kidneys', 'compress-c', 'organ', 'organ-5mm', 'organ-p2' or 'reads' (the other sections "
                     "run as one: `make bench`)")
        return section_only(part[0])

    work = Path(tempfile.mkdtemp(prefix="pmask-bench-"))
    res = {"machine": machine(),
           "date": time.strftime("%Y-%m-%d %H:%M:%S"), "precompute": [], "runtime": {}}
    arts = {}
    for size in SIZES:
        runs = []
        for k in range(REPEATS[size]):
            flags = ["--baseline"] if size >= 0.005 and k == 0 else []
            print(f"precompute kidney size={size} ({k + 1}/{REPEATS[size]}) ...", flush=True)
            runs.append(precompute(size, work / f"kidney_{size}.h5", *flags))
        gf = [r["timings"]["factor"] + r["timings"]["greens"] for r in runs]
        r = dict(runs[int(np.argsort(gf)[len(gf) // 2])])
        r["baseline"] = runs[0].get("baseline")
        r["gf_runs_s"] = gf
        res["precompute"].append(r)
        arts[r["free"]] = work / f"kidney_{size}.h5"
    print("pip-only CHOLMOD (cvxopt) at the default size ...", flush=True)
    res["cvxopt_default"] = precompute(0.005, work / "kidney_cvxopt.h5", backend="cvxopt")
    print("P2 at the default size and at ~3,900 free vertices ...", flush=True)
    res["p2"] = [precompute(size, work / f"kidney_p2_{size}.h5", "--p2") for size in (0.005, 0.003)]
    print("remesh of a 327,680-triangle surface ...", flush=True)
    res["remesh_300k"] = remesh_bench(work)
    print("repair routes over the corpus ...", flush=True)
    import repair_compare

    res["repair_routes"] = repair_compare.run()
    print("compressed Ξ against dense, workers ...", flush=True)
    import compress_bench

    compressed = compress_bench.main(HERE / "compress_results.json")  # (its own file: the page's last section)
    print("float32 ...", flush=True)
    r32 = precompute(0.005, work / "kidney_f32.h5", "--float32")
    res["float32"] = float32_effect(work / "kidney_0.005.h5", work / "kidney_f32.h5", r32)
    # scaling exponents
    free = np.array([r["free"] for r in res["precompute"]])
    dofs = np.array([r["dofs"] for r in res["precompute"]])
    tot = np.array([sum(r["timings"].values()) for r in res["precompute"]])
    res["scaling"] = {"time_vs_free_exponent": float(np.polyfit(np.log(free), np.log(tot), 1)[0]),
                      "time_vs_condensed_dofs_exponent": float(np.polyfit(np.log(dofs), np.log(tot), 1)[0])}
    # runtime: load + K_i and batch K(x) from numpy on the real kidneys; then the haptic step (runtime_bench)
    from pmask.runtime import Model

    import runtime_bench

    for n_free, path in sorted(arts.items()):
        print(f"runtime kidney {n_free} ...", flush=True)
        m = Model.load(path)
        stiff = m.stiffness("linear", 2.0 * m.mean_edge_length)
        res["runtime"][f"kidney_{len(m.points)}"] = {
            "surface_vertices": len(m.points), "synthetic": False, "load": load_bench(path), "batch": batch_bench(stiff)}
    print("haptics ...", flush=True)
    res["haptics"] = runtime_bench.run({len(Model.load(p).points): p for p in arts.values()},
                                       runtime_bench.synthetic_stiffness, work)
    res["haptics"].update(date=res["date"], machine=res["machine"])  # (the guides name where the rounds ran)
    import viewer_bench

    res["viewer"] = viewer_bench.run({n: p for n, p in ((len(Model.load(p).points), p) for p in arts.values()) if n > 1000})
    res["check_cost"] = check_cost(work / "kidney_0.005.h5")
    import display_bench

    res["display"] = display_bench.run(work)
    res["display"]["date"] = res["date"]
    import shutil

    shutil.rmtree(work, ignore_errors=True)
    (HERE / "results.json").write_text(json.dumps(res, indent=2))
    import report

    print(f"wrote {report.write(res, compressed)}")


REMESH_SNIPPET = """
import json, sys, time
from pathlib import Path
t0 = time.perf_counter()
import meshio
m = meshio.read(sys.argv[1])
t1 = time.perf_counter()
from pmask.precompute.meshing import remesh_bounded
points, tets, change = remesh_bounded(Path(sys.argv[1]), edge_length=0.002, scale=1e-3, timeout=600)
t2 = time.perf_counter()
print(json.dumps({"read_s": t1 - t0, "remesh_s": t2 - t1, "triangles_in": int(len(m.cells[0].data)),
                  "volume_vertices": int(len(points)), "tets": int(len(tets)), "hausdorff_mm": 1e3 * change["hausdorff_m"],
                  "volume_change": change["volume_change"]}))
"""


def remesh_bench(work: Path, runs: int = 2) -> dict:
    """The real-inputs issue's target: a 327,680-triangle sphere (20 mm, the corpus's largest case) remeshed
    to 2 mm in a fresh process, the way `pmask precompute --surface` does it (checks, the bounded gmsh
    worker, the Hausdorff distance); reading the STL alone beside it as the noise reference."""
    import meshio

    from pmask.pipeline.corpus import corpus

    v, f = corpus()["over 300,000 triangles"]
    stl = work / "sphere327k.stl"
    meshio.write_points_cells(stl, v, [("triangle", f)])
    out = [json.loads(sh([sys.executable, "-c", REMESH_SNIPPET, str(stl)], cwd=ROOT).strip().splitlines()[-1])
           for _ in range(runs)]
    return {"runs": out, "remesh_s": [r["remesh_s"] for r in out], "read_s": [r["read_s"] for r in out]}


def float32_effect(p64: Path, p32: Path, r32: dict) -> dict:
    from pmask.runtime import Model

    out = {}
    for name, p in (("float64", p64), ("float32", p32)):
        t0 = time.perf_counter()
        m = Model.load(p)
        out[f"{name}_load_s"] = time.perf_counter() - t0
        out[f"{name}_bytes"] = p.stat().st_size
        out[f"{name}_K"] = m.stiffness("linear", 2.0 * m.mean_edge_length).K_full
        single = m.stiffness("single").K_full
        out[f"{name}_K_single"] = single
    rel = np.linalg.norm(out["float32_K"] - out["float64_K"], axis=(1, 2)) / np.linalg.norm(out["float64_K"], axis=(1, 2))
    rel1 = (np.linalg.norm(out["float32_K_single"] - out["float64_K_single"], axis=(1, 2))
            / np.linalg.norm(out["float64_K_single"], axis=(1, 2)))
    return {"bytes_float64": out["float64_bytes"], "bytes_float32": out["float32_bytes"],
            "load_s_float64": out["float64_load_s"], "load_s_float32": out["float32_load_s"],
            "K_rel_error_max": float(rel.max()), "K_rel_error_median": float(np.median(rel)),
            "K_single_rel_error_max": float(rel1.max())}

def machine() -> dict:
    """What the numbers were measured on (a partial route records its own: the page says when it differs)."""
    return {"platform": platform.platform(), "cpu": _cpu(), "cores": os.cpu_count(), "memory_gib": _mem_gib(),
            "python": platform.python_version()}


def where(res: dict, section: dict) -> str:
    """'the same machine' when a section measured on its own ran where the rest did, else which machine."""
    m, own = res["machine"], section.get("machine")
    if own is None:
        return "a machine this page did not record"
    if all(own.get(k) == m.get(k) for k in ("cpu", "cores", "memory_gib")):
        return "the same machine"
    return (f"another machine ({own['cpu']}, {own['cores']} cores, {own['memory_gib']} GiB; compare its rows with "
            "each other, not with the sections above)")


def _cpu() -> str:
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()

def _mem_gib() -> float:
    try:
        return round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)
    except (ValueError, OSError):
        return float("nan")

def markdown(res: dict) -> str:
    m = res["machine"]
    L = [f"Measured {res['date']} on {m['cpu']}, {m['cores']} cores, {m['memory_gib']} GiB, "
         f"Python {m['python']} (`make bench`).", ""]
    L += ["**Precompute, kidney** (seconds; Green's-function (GF) stage = from the assembled stiffness to Ξ and "
          "the reactions: sparse Cholesky of K_FF (`factor`) + selected inversion of its surface block (`greens`); "
          "each row is the run with the median GF stage of the runs in the last column, each in a fresh process)", "",
          "| free vertices | volume dofs | mesh | assemble | factor | greens | checkpoint | write | total | GF stage | "
          "dense floor | GF / dense floor | fill floor | peak RSS GiB | artifact MiB | GF stage of every run |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["precompute"]:
        t = r["timings"]
        gf = t["factor"] + t["greens"]
        L.append(f"| {r['free']} | {3 * r['volume_vertices']} | {t['mesh']:.2f} | {t['assemble']:.2f} | "
                 f"{t['factor']:.2f} | {t['greens']:.2f} | {t.get('checkpoint', 0):.2f} | {t['write']:.2f} | "
                 f"{sum(t.values()):.2f} | {gf:.2f} | "
                 f"{r['dense_floor_s']:.2f} | {gf / r['dense_floor_s']:.2f} | {r.get('fill_floor_s', float('nan')):.2f} | "
                 f"{r['peak_rss_gib']:.2f} | "
                 f"{r['size_bytes'] / 2**20:.0f} | {', '.join(f'{x:.2f}' for x in r['gf_runs_s'])} |")
    L += ["", "**Baseline, same matrices**: scipy `splu` (defaults) on K_FF, one solve per column "
          "(GF stage = splu factor + solves; the whole run adds the same mesh, assembly, regions and write as ours)",
          "", "| free vertices | splu factor | column solves | baseline GF stage | ours | ratio GF | "
          "baseline whole run | ours whole run | ratio whole | max rel. diff vs Ξ |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["precompute"]:
        b = r.get("baseline")
        if not b:
            continue
        t = r["timings"]
        ours = t["factor"] + t["greens"]
        base = b["factor_s"] + b["solve_s"]
        whole_b = base + t["mesh"] + t["assemble"] + t["regions"] + t["write"]  # the baseline writes no checkpoint
        whole = sum(t.values())
        L.append(f"| {r['free']} | {b['factor_s']:.2f} | {b['solve_s']:.2f} | {base:.2f} | {ours:.2f} | "
                 f"{base / ours:.1f}x | {whole_b:.2f} | {whole:.2f} | {whole_b / whole:.1f}x | "
                 f"{b['max_rel_diff_vs_Xi']:.1e} |")
    for r in res["precompute"]:
        fs = r.get("factor_stats") or {}
        g = fs.get("greens_s")
        if r.get("baseline") and g and "solve_s" in g:  # the native route's own timers
            t = r["timings"]
            inside = fs["analyse_s"] + fs["numeric_s"] + sum(g[k] for k in (
                "setup_s", "solve_s", "prefault_wait_s", "syrk_s", "permute_s", "reactions_s"))
            n = 3 * r["free"]
            L += ["", f"Inside that GF stage ({r['free']} free vertices, {n} dofs in Ξ, {fs['dofs']} dofs in K_FF): "
                      f"ordering ({fs['order']}) + symbolic analysis {fs['analyse_s']:.2f} s, CHOLMOD's numeric "
                      f"factorisation {fs['numeric_s']:.2f} s ({fs['factor_flops'] / 1e9:.1f} Gflop), selected inversion "
                      f"{g['flops'] / 1e9:.1f} Gflop: forward solve W = L⁻¹PE {g['solve_s']:.2f} s (+ {g['prefault_wait_s']:.2f} s "
                      f"waiting for the page-fault helper), WᵀW by one `dsyrk` per supernode {g['syrk_s']:.2f} s, mirror + "
                      f"permutation + area scaling {g['permute_s']:.2f} s, reactions {g['reactions_s']:.2f} s; "
                      f"Python and the rest {t['factor'] + t['greens'] - inside:.2f} s. "
                      f"The dense floor's potrf + potri does n³ = {n ** 3 / 1e9:.0f} Gflop for the same Ξ."]
    c = res["cvxopt_default"]
    t = c["timings"]
    L += ["", f"The same default kidney on the pip-only route (what runs when SuiteSparse cannot be installed: "
              f"cvxopt's CHOLMOD with a single-threaded BLAS in an AMD order, the selected inversion in numpy and "
              f"SciPy's BLAS): factor {t['factor']:.2f} s, greens {t['greens']:.2f} s, total {sum(t.values()):.2f} s. "
              f"Rows above: CHOLMOD backend `{res['precompute'][0].get('backend')}`."]
    if res.get("p2"):
        p1 = {r["free"]: r for r in res["precompute"]}
        L += ["", "**P2** (quadratic tetrahedra, the P2–P0 volumetric rule; one run each, same selected inversion "
                  "with one dgemm per supernode), beside the P1 row of the same mesh:", "",
              "| free vertices | element dofs | factor | greens | GF stage | total | P1 total | P2 / P1 total | "
              "dense floor | GF / dense floor | fill floor | peak RSS GiB |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in res["p2"]:
            t = r["timings"]
            gf = t["factor"] + t["greens"]
            q = p1.get(r["free"])
            p1_total = sum(q["timings"].values()) if q else float("nan")
            L.append(f"| {r['free']} | {r['dofs']} | {t['factor']:.2f} | {t['greens']:.2f} | {gf:.2f} | "
                     f"{sum(t.values()):.2f} | {p1_total:.2f} | {sum(t.values()) / p1_total:.1f}x | "
                     f"{r['dense_floor_s']:.2f} | {gf / r['dense_floor_s']:.2f} | {r['fill_floor_s']:.2f} | "
                     f"{r['peak_rss_gib']:.2f} |")
    if res.get("remesh_300k"):
        r = res["remesh_300k"]
        x = r["runs"][0]
        L += ["", f"**Remesh of a {x['triangles_in']:,}-triangle surface** (a 20 mm sphere to 2 mm edges, in a fresh "
                  f"process as `--surface` runs it; the real-inputs issue's target ≤ 60 s): "
                  + ", ".join(f"{t:.1f}" for t in r["remesh_s"]) + " s; reading the STL alone (noise reference) "
                  + ", ".join(f"{t:.2f}" for t in r["read_s"]) + f" s; {x['volume_vertices']:,} volume vertices, "
                  f"Hausdorff {x['hausdorff_mm']:.3f} mm, volume {100 * x['volume_change']:+.2f} %."]
    if res.get("repair_routes"):
        import repair_compare

        L += ["", repair_compare.markdown(res["repair_routes"])]
    s = res["scaling"]
    L += ["", f"Scaling: total time ∝ n_free^{s['time_vs_free_exponent']:.2f}, "
              f"∝ condensed dofs^{s['time_vs_condensed_dofs_exponent']:.2f}.", ""]
    f = res["float32"]
    L += [f"float32 storage of Ξ (default kidney): {f['bytes_float32'] / 2**20:.0f} MiB vs "
          f"{f['bytes_float64'] / 2**20:.0f} MiB, load {f['load_s_float32']:.3f} s vs {f['load_s_float64']:.3f} s "
          f"(warm), masked K_i relative error max {f['K_rel_error_max']:.1e} (median {f['K_rel_error_median']:.1e}), "
          f"single-vertex K_i max {f['K_single_rel_error_max']:.1e}.", ""]
    L += ["**Runtime, loading** (a fresh process: read the artifact and form every K_i; deformation = "
          "`Stiffness.deformation` for one load; batch = `at_batch` of 1 M random queries from numpy, validated)", "",
          "| surface | vertices | load + all K_i (cold / warm) | deformation (eq. 16) | numpy batch M queries/s |",
          "|---|---|---|---|---|"]
    for name, r in res["runtime"].items():
        ld = r.get("load", {})
        lw = ld.get("warm")
        lc = ld.get("cold")
        load = "—"
        if lw:
            load = (f"{lc['load_s'] + lc['vertex_stiffness_s']:.3f} / " if lc else "n/a / ") + \
                   f"{lw['load_s'] + lw['vertex_stiffness_s']:.3f} s"
        deform = f"{lw['deformation_s'] * 1e3:.2f} ms" if lw else "—"
        L.append(f"| kidney (cone mask, r = 2 mean edges) | {r['surface_vertices']} | {load} | {deform} | "
                 f"{r['batch']['queries_per_s'] / 1e6:.1f} |")
    c = res["check_cost"]
    L += ["", f"Artifact checks at load (default kidney, warm): {c['load_verified_s']:.3f} s with the SHA-256 of "
              f"every dataset read (the surface, Ξ, the volume mesh) and of the attributes, "
              f"{c['load_unverified_s']:.3f} s without."]
    import runtime_bench

    if res["haptics"].get("date", res["date"]) != res["date"]:  # (ONLY=haptics: a run of its own)
        L += ["", f"The haptic step below was measured again on its own, {res['haptics']['date']} on "
                  f"{where(res, res['haptics'])} (`make bench ONLY=haptics`)."]
    L += ["", runtime_bench.markdown(res["haptics"])]
    import viewer_bench

    if res.get("display"):
        import display_bench

        L += ["", f"The display surface was measured {res['display']['date']} on {where(res, res['display'])}.", "",
              display_bench.markdown(res["display"])]
    if res["viewer"].get("date"):
        L += ["", f"The viewer below was measured again on its own, {res['viewer']['date']} on "
                  f"{where(res, res['viewer'])} (`make bench ONLY=viewer`)."]
    L += ["", viewer_bench.markdown({k: v for k, v in res["viewer"].items() if k not in ("date", "machine")})]
    return "\n".join(L) + "\n"

if __name__ == "__main__":
    main()
