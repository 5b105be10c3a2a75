"""How many times the tiles' passes read W's store, counted from its index (a model: nothing is read), for the
route's order and for the orders of the design that the large-organs guide's "What is not there yet" describes:
`make bench ONLY=reads` on the organ-scale kidneys' real partitions and W's real index.

The route's order is what :meth:`pmask.precompute.compress.SweepStore.passed` reads (tests/test_compress.py holds
this count to the bytes a real pass reads, P1): for each supernode block X_s a tile of the pass reaches and asks
rows of, the block whole where it fits one read, else each tile's own columns' rows of it (row by row) and every
row chunk of :data:`~pmask.precompute.compress.READ_BYTES` that holds a row any tile asks.  The rows a tile asks:
those it forms and those it sketches (today), or only those of the blocks it forms (``formed_only``: the design's
sketches come from the tiles that own each side of a block, from their own rows).  ``order``: "W", the rows of
each block in W's (pivot) order, as stored, or "cluster", in the cluster tree's order within each block;
``rows``: every asked row read alone instead of in chunks.  P1 only (a P2 pass also reads W_B's blocks).

The Z store of the design (each large cluster's X_s,Cᵀ Ω over every supernode its rows reach,
:data:`~pmask.precompute.compress.SKETCH_SAMPLES` columns) is given as its size against W's: every cluster that is
a side of a sketched block, an upper bound (a far pair shares only the supernodes above both).
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from pmask.precompute import compress

HERE = Path(__file__).resolve().parent

#: the variants the bench counts: (name, formed_only, order, rows)
VARIANTS = (("now", False, "W", False), ("now_rows", False, "W", True), ("formed", True, "W", False),
            ("formed_cluster", True, "cluster", False), ("formed_rows", True, "W", True))


def _asked_rows(tree, column: int, blocks, formed_only: bool) -> tuple[np.ndarray, np.ndarray, set]:
    """A tile's asked rows (contact dofs) and its columns, as :func:`~pmask.precompute.compress._tile_plan` makes
    them, and its sketched blocks."""
    p = compress._tile_plan(tree, column, blocks, True)
    rows, sk = p["rows"], p["sketch"]
    if formed_only:  # the rows of the blocks it forms: no sketched rows, no samples
        c0, c1 = p["c0"], p["c1"]
        mask = np.zeros(len(rows), bool)
        for i, j, far in blocks:
            if not (far and compress.sketches(tree, i, j, c0, c1)):
                mask[3 * int(tree.start[i]):3 * int(tree.stop[i])] = True
    else:
        mask = sk.formed | np.any([g.rows for g in sk.groups], 0) if sk.groups else sk.formed
    sketched = {(i, j) for i, j, far in blocks if far and compress.sketches(tree, i, j, p["c0"], p["c1"])}
    return rows[mask], p["dcols"], sketched


def _reached(first: np.ndarray, parent: np.ndarray, n: int) -> np.ndarray:
    out = np.zeros(n, bool)
    for s in np.unique(first):
        while s >= 0 and not out[s]:
            out[s] = True
            s = parent[s]
    return out


def pass_reads(store: "compress.SweepStore", tree, columns: list[int], plans: list, formed_only: bool = False,
               order: str = "W", rows: bool = False, cache: dict | None = None) -> int:
    """Bytes one pass of tiles ``columns`` (blocks ``plans``) reads of W's store (module docstring).  ``cache``:
    each tile's asked rows kept there for the next call (a dict; the same store, tree and plans)."""
    ix = store.index
    lo, hi, ncol, pos, parent, first = (ix[k] for k in ("lo", "hi", "ncol", "pos", "parent", "first"))
    ns = len(lo)
    cache = {} if cache is None else cache
    tiles = []
    for c, blocks in zip(columns, plans):
        if (c, formed_only) not in cache:
            r, dcols, _ = _asked_rows(tree, c, blocks, formed_only)
            cache[c, formed_only] = (np.sort(pos[r]), pos[dcols], _reached(first[dcols], parent, ns))
        tiles.append(cache[c, formed_only])
    rank = None
    if order == "cluster":  # each contact dof's place in the cluster tree's order
        dofs = (3 * tree.perm[:, None] + np.arange(3)).ravel()
        cpos = np.empty(len(dofs), np.int64)
        cpos[dofs] = np.arange(len(dofs))
        at = np.empty(len(pos), np.int64)
        at[pos] = np.arange(len(pos))  # the dof at each of W's positions
        rank = cpos[at]
    total = 0
    for s in np.flatnonzero(np.any([t[2] for t in tiles], 0)):
        m, nc = int(hi[s] - lo[s]), int(ncol[s])
        step = max(1, compress.READ_BYTES // (8 * nc))
        mine = []
        for ps, pj, reached in tiles:
            if not reached[s]:
                continue
            a, b = np.searchsorted(ps, lo[s]), np.searchsorted(ps, hi[s])
            own = pj[(pj >= lo[s]) & (pj < hi[s])]
            if b > a and len(own):
                mine.append((ps[a:b], own))
        if not mine:
            continue
        if m <= step and not rows:  # read whole, once for the pass
            total += 8 * m * nc
            continue
        asked = np.unique(np.concatenate([q for q, _ in mine]))
        if m <= step:  # (rows: the asked rows and the tiles' own, each once)
            total += 8 * nc * len(np.union1d(asked, np.concatenate([o for _, o in mine])))
            continue
        total += 8 * nc * sum(len(o) for _, o in mine)  # each tile's own columns' rows, row by row, first
        if rows:
            total += 8 * nc * len(asked)
        elif order == "W":
            chunks = np.unique((asked - lo[s]) // step)
            total += 8 * nc * int(np.sum(np.minimum(step, m - chunks * step)))
        else:
            ranks = np.argsort(np.argsort(rank[lo[s]:hi[s]]))  # each row's place in cluster order in the block
            chunks = np.unique(ranks[asked - lo[s]] // step)
            total += 8 * nc * int(np.sum(np.minimum(step, m - chunks * step)))
    return total


def z_store_bytes(store: "compress.SweepStore", tree, columns: list[int], plans: list) -> int:
    """The design's Z store (module docstring): for every cluster that is a side of a sketched block, its
    :data:`~pmask.precompute.compress.SKETCH_SAMPLES` columns over every supernode its rows reach."""
    ix = store.index
    ncol, parent, first = ix["ncol"], ix["parent"], ix["first"]
    sides = set()
    for c, blocks in zip(columns, plans):
        sides |= {k for ij in _asked_rows(tree, c, blocks, True)[2] for k in ij}
    total = 0
    for k in sides:
        dofs = (3 * tree.perm[int(tree.start[k]):int(tree.stop[k]), None] + np.arange(3)).ravel()
        total += 8 * compress.SKETCH_SAMPLES * int(ncol[_reached(first[dofs], parent, len(ncol))].sum())
    return total


def reads(store, tree, groups: list[list[int]], plan: dict) -> dict:
    """W's reads (its store's size each) of the passes ``groups``, for every variant, and the Z store's size."""
    size, cache = float(store.path.stat().st_size), {}
    out = {name: sum(pass_reads(store, tree, g, [plan[c] for c in g], fo, order, rw, cache) for g in groups) / size
           for name, fo, order, rw in VARIANTS}
    out["passes"] = len(groups)
    return out


def model(params: dict, work: Path, threads_options=(1, 3)) -> dict:
    """The organ-scale kidney at ``params`` (bench/compress_bench.py's LARGE or ORGAN), P1, r_max 10 mm: its
    factor, W swept to ``work``, its partition cut into passes as the route cuts them on this machine's two local
    workers (:func:`~pmask.precompute.compress.passes`, at ``PASSES_PER_THREAD`` of each of ``threads_options``),
    and each cut's modelled reads."""
    import psutil

    import compress_bench
    from pmask.pipeline import stages

    spec = stages.Spec(model="kidney", params=params, r_max=compress_bench.R_MAX, element="P1")
    mesh = stages.support_stage(spec, stages.mesh_stage(spec))
    surf = stages.surface_stage(spec, mesh)
    factor, _ = stages.factor_stage(spec, mesh, surf)
    pts = mesh.points[surf.vertices[surf.regions.contact]]
    store = compress.sweep(factor, work / "W.bin", key="read model")
    del factor
    tree = compress.cluster_tree(pts)
    panel = compress.panel_size(len(pts))
    cols = compress.panels(tree, panel)
    plan = {c: [b for b in compress.partition(tree, c, compress_bench.R_MAX) if tree.start[b[0]] <= tree.start[b[1]]]
            for c in cols}
    limit = psutil.virtual_memory().total / 2  # a LocalCluster's two workers' memory limits
    held, widest = compress.source_bytes(store), int(store.index["ncol"].max(initial=0))
    budget = compress.pass_budget([limit, limit], [1, 1])
    est = compress.tile_estimates(tree, cols, plan, held, len(pts), panel, widest)
    out = {"contact": len(pts), "W_bytes": int(store.path.stat().st_size), "tiles": len(cols)}
    default = compress.PASSES_PER_THREAD
    for per in threads_options:
        compress.PASSES_PER_THREAD = per
        try:
            groups = compress.passes(tree, cols, plan, budget, held, len(pts), panel, widest, 2, est)
        finally:
            compress.PASSES_PER_THREAD = default
        out[f"{per} a thread"] = reads(store, tree, groups, plan)
        print(params, per, out[f"{per} a thread"], flush=True)
    out["Z_of_W"] = z_store_bytes(store, tree, cols, [plan[c] for c in cols]) / out["W_bytes"]
    return out


def main(out: Path) -> dict:
    """`make bench ONLY=reads`: the model at the organ-scale kidney and at issue #27's 50,000, stored in the
    compressed-Ξ section's results (``out``) under "read_model"."""
    import tempfile

    import compress_bench
    from run import machine

    res = json.loads(out.read_text()) if out.exists() else {}
    rm = {"date": time.strftime("%Y-%m-%d %H:%M"), "machine": machine(), "read_bytes": compress.READ_BYTES}
    for key, params in (("large", compress_bench.LARGE), ("organ", compress_bench.ORGAN)):
        with tempfile.TemporaryDirectory() as tmp:
            rm[key] = model(params, Path(tmp))
    res["read_model"] = rm
    out.write_text(json.dumps(res, indent=1, default=float))
    return res


if __name__ == "__main__":
    sys.path.insert(0, str(HERE))
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else HERE / "compress_results.json")
