"""The display surface at the scan's resolution (the scans issue's item 6): how long embedding it takes in the
precompute, and how long deforming it takes per frame in C (``pm_display_deform``) and in numpy, beside a copy
of the same number of bytes (the memory floor: the deformation reads the embedding and writes every point).

Cases: the corpus's 327,680-triangle sphere (the issue's "300k-triangle display surface"), and the Stanford
bunny scan that pymeshfix ships (99,785 triangles, a real scan with holes, precomputed with --repair).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np


def _timed(fn, runs: int) -> dict:
    ts = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    ts = np.array(ts) * 1e3
    return {"median_ms": float(np.median(ts)), "p99_ms": float(np.percentile(ts, 99)), "runs": runs}


def one(name: str, artifact: Path, summary: dict, work: Path) -> dict:
    from pmask.runtime import Model, servo
    from pmask.runtime.table import export_table

    m = Model.load(artifact)
    ds = m.display()
    rng = np.random.default_rng(0)
    u = rng.normal(size=(len(m.points), 3)) * 1e-3
    contacts = [m.points[int(np.argmax(m.points[:, 2]))]]
    r = m.default_radius
    out = {"case": name, "display_triangles": int(len(ds.triangles)), "display_vertices": int(len(ds.points)),
           "simulation_vertices": int(len(m.points)), "folded": int(m.attrs["display"]["folded"]),
           "embed_s": float(summary["timings"]["display"]),
           "numpy": _timed(lambda: ds.deform(u, contacts, r), 20)}
    dst = np.empty_like(ds.points)
    out["copy_floor"] = _timed(lambda: np.copyto(dst, ds.points), 200)
    if servo.available():
        table = servo.load_table(export_table(m, work / f"{name}.tbl", zeta=False))
        res = np.empty_like(ds.points)
        c = np.ascontiguousarray(contacts, float)
        out["c"] = _timed(lambda: table.display_deform(u, c, r, res), 200)
    return out


def run(work: Path) -> dict:
    import meshio

    from pmask.pipeline.corpus import corpus
    from pmask.pipeline.stages import Spec, run as precompute

    res = []
    v, f = corpus()["over 300,000 triangles"]
    stl = work / "sphere327k.stl"
    meshio.write_points_cells(stl, v, [("triangle", f)])
    print("  display: 327,680-triangle sphere ...", flush=True)
    s = precompute(Spec(model="sphere", surface=str(stl), units="mm", edge_length=4.0, fixed="z<-17"), work / "sph.h5")
    res.append(one("sphere 327k", work / "sph.h5", s, work))
    try:
        import pymeshfix

        bunny = Path(pymeshfix.__file__).parent / "examples" / "StanfordBunny.ply"
    except ImportError:
        bunny = None
    if bunny is not None and bunny.exists():
        print("  display: the Stanford bunny scan ...", flush=True)
        s = precompute(Spec(model="bunny", surface=str(bunny), units="mm", edge_length=4.0, fixed="z<3",
                            repair="meshfix"), work / "bunny.h5")
        res.append(one("Stanford bunny (scan)", work / "bunny.h5", s, work))
    return {"cases": res}


def markdown(res: dict) -> str:
    L = ["**Display surface at the scan's resolution** (`pm_display_deform` in C and `DisplaySurface.deform` in "
         "numpy, per frame, one contact laid on; the copy floor copies the same points once; embedding = the "
         "precompute's display stage)", "",
         "| case | display triangles | simulation vertices | folded | embed s | C median / p99 ms | numpy median ms "
         "| copy floor median ms |", "|---|---|---|---|---|---|---|---|"]
    for r in res["cases"]:
        c = r.get("c")
        L.append(f"| {r['case']} | {r['display_triangles']:,} | {r['simulation_vertices']:,} | {r['folded']} | "
                 f"{r['embed_s']:.2f} | " + (f"{c['median_ms']:.2f} / {c['p99_ms']:.2f}" if c else "—")
                 + f" | {r['numpy']['median_ms']:.1f} | {r['copy_floor']['median_ms']:.2f} |")
    return "\n".join(L)


if __name__ == "__main__":
    import tempfile

    print(json.dumps(run(Path(tempfile.mkdtemp())), indent=1))
