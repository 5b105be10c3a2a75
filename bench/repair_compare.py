"""The repair routes side by side over the corpus (pmask.pipeline.corpus): which cases each turns into
an artifact, and how much of the intended solid it keeps.  Part of `make bench`; run alone with
`python bench/repair_compare.py`.  A measurement, not a test: nothing here asserts."""
from __future__ import annotations

import contextlib
import io
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: the cases made from the 20 mm sphere at the origin (the intended solid: that sphere)
SPHERE_CASES = ("holes", "flipped patch", "self-intersection", "debris", "touching at a point", "touching shells",
                "several shells", "over 300,000 triangles")
EDGE_MM = 5.0
ROUTES = (None, "meshfix", "voxel")


def run_case(v, f, route, work: Path) -> dict:
    import meshio

    from pmask.pipeline.cli import main
    from pmask.runtime import Model

    stl = work / "case.stl"
    meshio.write_points_cells(stl, v, [("triangle", f)])
    out = work / "case.h5"
    out.unlink(missing_ok=True)
    err = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        logging.disable(logging.WARNING)
        try:
            code = main(["precompute", "--surface", str(stl), "--units", "mm", "--edge-length", str(EDGE_MM),
                         "--fixed", "z<-8", "-o", str(out)] + (["--repair", route] if route else []))
        finally:
            logging.disable(logging.NOTSET)
    r = {"ok": code == 0, "seconds": time.perf_counter() - t0}
    if code == 0:
        m = Model.load(out)
        P = m.points * 1e3
        r["radius_error_mm"] = float(np.abs(np.linalg.norm(P, axis=1) - 20.0).max())
        p = P[m.triangles]
        r["volume_mm3"] = float(np.einsum("ij,ij->i", np.cross(p[:, 0], p[:, 1]), p[:, 2]).sum() / 6)
    else:
        r["message"] = next((line for line in err.getvalue().splitlines() if line.startswith("pmask: error")), "")[:160]
    return r


def run() -> dict:
    from pmask.pipeline.corpus import corpus

    cases = corpus()
    res = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, (v, f) in cases.items():
            for route in ROUTES:
                print(f"repair routes: {name} / {route or 'no repair'} ...", file=sys.stderr, flush=True)
                res[f"{name}|{route or 'none'}"] = run_case(v, f, route, Path(tmp))
    from pmask.pipeline.corpus import union_volume

    return {"edge_mm": EDGE_MM, "sphere_volume_mm3": 4 / 3 * np.pi * 20.0**3, "union_volume_mm3": union_volume(),
            "cases": res}


def markdown(res: dict) -> str:
    names = sorted({k.split("|")[0] for k in res["cases"]})
    L = [f"**Repair routes over the corpus** (`bench/repair_compare.py`; remeshed at {res['edge_mm']:g} mm; "
         "each cell: artifact (volume against the intended solid: the 20 mm sphere, or the union of the overlapping shells; largest radial error from the sphere) or refused; seconds)",
         "", "| case | no repair | --repair meshfix | --repair voxel |", "|---|---|---|---|"]
    for n in names:
        cells = []
        for route in ("none", "meshfix", "voxel"):
            r = res["cases"][f"{n}|{route}"]
            if not r["ok"]:
                cells.append(f"refused ({r['seconds']:.1f} s)")
            elif n in SPHERE_CASES:
                cells.append(f"artifact: volume {100 * (r['volume_mm3'] / res['sphere_volume_mm3'] - 1):+.1f} %, "
                             f"radius ±{r['radius_error_mm']:.2f} mm ({r['seconds']:.1f} s)")
            elif n == "overlapping shells":
                cells.append(f"artifact: volume {100 * (r['volume_mm3'] / res['union_volume_mm3'] - 1):+.1f} % "
                             f"of the union ({r['seconds']:.1f} s)")
            else:
                cells.append(f"artifact ({r['seconds']:.1f} s)")
        L.append(f"| {n} | " + " | ".join(cells) + " |")
    ok = {route: sum(res["cases"][f"{n}|{route}"]["ok"] for n in names) for route in ("none", "meshfix", "voxel")}
    L += ["", f"Artifacts: no repair {ok['none']}, meshfix {ok['meshfix']}, voxel {ok['voxel']} of {len(names)} cases."]
    return "\n".join(L)


if __name__ == "__main__":
    out = run()
    print(json.dumps(out, indent=1))
    print(markdown(out))
