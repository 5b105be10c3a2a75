"""One precompute measured in its own process (so that its peak memory is its own).

    python bench/precompute_case.py SIZE OUT.h5 [--baseline] [--float32] [--p2]

Prints one JSON line: per-stage times, counts, peak RSS, the dense floor
(LAPACK potrf + potri of a dense SPD matrix of size 3 n_p: the least work of any
method that forms the dense Schur complement and inverts it), the fill floor
(writing (3 n_p)² doubles into a fresh array: what any method that outputs the
dense Ξ pays at least), and with --baseline the textbook route
on the same matrices: scipy ``splu`` with its defaults, then one solve per
right-hand side (3 n_p of them), checked against Ξ.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np


def dense_floor(n: int) -> float:
    import scipy.linalg.lapack as lapack

    rng = np.random.default_rng(0)
    X = rng.standard_normal((n, n))
    A = X @ X.T / n + np.eye(n)
    t0 = time.perf_counter()
    c, info = lapack.dpotrf(A, lower=1, overwrite_a=1)
    inv, info2 = lapack.dpotri(c, lower=1, overwrite_c=1)
    dt = time.perf_counter() - t0
    assert info == 0 and info2 == 0
    return dt


def fill_floor(n: int) -> float:
    t0 = time.perf_counter()
    X = np.empty((n, n))
    X.fill(1.0)
    return time.perf_counter() - t0


def baseline(out: Path) -> dict:
    """scipy splu (defaults) on K_FF, one solve per column of unit nodal forces at the contact dofs."""
    import scipy.sparse.linalg as spla

    from pmask.precompute.elasticity import dofs, stiffness_matrix
    from pmask.runtime.artifact import read_artifact

    d = read_artifact(out)
    P, T = d["volume/points"], d["volume/tets"]
    mat = d["attrs"]["material"]
    vi = d["surface/volume_index"]
    t0 = time.perf_counter()
    K = stiffness_matrix(P, T, mat["E"], mat["nu"]).tocsc()
    t_asm = time.perf_counter() - t0
    fixed = dofs(vi[d["surface/fixed"]])
    free = np.setdiff1d(np.arange(K.shape[0]), fixed)
    pos = np.searchsorted(free, dofs(vi[d["surface/contact"]]))
    t0 = time.perf_counter()
    lu = spla.splu(K[free][:, free].tocsc())
    t_factor = time.perf_counter() - t0
    t0 = time.perf_counter()
    n = len(pos)
    G = np.empty((n, n))
    e = np.zeros(len(free))
    for k, p in enumerate(pos):
        e[p] = 1.0
        G[:, k] = lu.solve(e)[pos]
        e[p] = 0.0
    t_solve = time.perf_counter() - t0
    a = np.repeat(d["surface/vertex_areas"][d["surface/contact"]], 3)
    err = float(np.abs(G * a[None, :] - d["greens/Xi"]).max() / np.abs(d["greens/Xi"]).max())
    return {"assemble_s": t_asm, "factor_s": t_factor, "solve_s": t_solve, "columns": n, "max_rel_diff_vs_Xi": err}


def main() -> None:
    from pmask.pipeline.stages import Spec, run

    size, out = float(sys.argv[1]), Path(sys.argv[2])
    dtype = "float32" if "--float32" in sys.argv else "float64"
    t0 = time.perf_counter()
    element = "P2" if "--p2" in sys.argv else "P1"
    s = run(Spec(model="kidney", params={"size": size}, dtype=dtype, element=element), out, force=True)
    wall = time.perf_counter() - t0
    with open("/proc/self/status") as f:  # the kernel's VmHWM: ru_maxrss would carry the parent's over fork and exec
        peak = next(int(line.split()[1]) for line in f if line.startswith("VmHWM:")) / 2**20  # GiB
    res = {"size": size, "element": element, "wall_s": wall, "peak_rss_gib": peak, **{k: s[k] for k in (
        "timings", "volume_vertices", "tets", "surface_vertices", "free", "fixed", "contact", "size_bytes", "dofs",
        "backend", "factor_stats")}}
    res["dense_floor_s"] = dense_floor(3 * s["contact"])
    res["fill_floor_s"] = fill_floor(3 * s["contact"])
    if "--baseline" in sys.argv:
        res["baseline"] = baseline(out)
    print(json.dumps(res))


if __name__ == "__main__":
    main()
