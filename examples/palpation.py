"""
Palpation: a stiffer mass felt through soft tissue
===================================================

How much stiffer the surface feels over a spherical mass, against the mass's depth and its contrast::

    python examples/palpation.py --out docs/

For each depth (the ball's centre 1.5, 2 and 3 radii under the upper face of the ``palpation`` block) and
contrast (5x and 10x stiffer than the tissue), the block is precomputed with the mass and once without it
(``--materials inclusion`` at the tissue's material), and the normal stiffness k_n = (nᵀ K_i⁻¹ n)⁻¹ at the
upper face's vertices over the mass (within half a radius of its axis) is compared: the palpation contrast,
k_n with the mass over k_n without.  Written: a CSV table and a PNG of the contrast against depth.  Each
precompute takes a couple of seconds (the default 4 mm mesh).
"""
from __future__ import annotations

import argparse
import csv
import tempfile
from pathlib import Path

import numpy as np

from pmask.pipeline.stages import Spec, run
from pmask.runtime import Model

RADIUS = 0.005
DEPTHS = (1.5, 2.0, 3.0)  # the ball's centre, in radii under the upper face
CONTRASTS = (5.0, 10.0)


def normal_stiffness_over_the_mass(path: Path) -> float:
    """Mean k_n = (nᵀ K_i⁻¹ n)⁻¹ (n = +z, the upper face) at the upper face's vertices within half a radius of
    the mass's axis, cone masks of 2 mean edge lengths."""
    m = Model.load(path)
    s = m.stiffness("linear", 2 * m.mean_edge_length)
    core = m.contact[m.core]
    top = np.flatnonzero((m.points[core, 2] > -1e-6) & (np.hypot(*m.points[core, :2].T) < 0.5 * RADIUS))
    n = np.array([0.0, 0.0, 1.0])
    return float(np.mean([1.0 / (n @ np.linalg.solve(K, n)) for K in s.K_vertex[core[top]]]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="The palpation contrast of a stiffer mass against its depth")
    ap.add_argument("--out", default=None, help="folder for the CSV and PNG (default: a temporary folder)")
    ap.add_argument("--size", type=float, default=0.004, help="largest mesh edge [m] (default 4 mm)")
    args = ap.parse_args(argv)
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="pmask-example-"))
    out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="pmask-palpation-"))
    rows = []
    for depth in DEPTHS:
        params = {"size": args.size, "depth": depth * RADIUS, "radius": RADIUS}
        plain = work / f"plain_{depth:g}.h5"
        run(Spec(model="palpation", params=params, materials="inclusion:1e4:0.45"), plain)
        k0 = normal_stiffness_over_the_mass(plain)
        row = {"depth_radii": depth, "depth_mm": depth * RADIUS * 1e3, "k_n_without_N_per_m": k0}
        for c in CONTRASTS:
            path = work / f"mass_{depth:g}_{c:g}.h5"
            run(Spec(model="palpation", params={**params, "contrast": c}), path)
            row[f"contrast_{c:g}x"] = normal_stiffness_over_the_mass(path) / k0
        rows.append(row)
        print(f"mass centre {depth:g} radii deep: k_n without {k0:.1f} N/m; with it "
              + ", ".join(f"{c:g}x stiffer: {row[f'contrast_{c:g}x']:.3f}" for c in CONTRASTS))
    with open(out / "palpation.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    try:
        import matplotlib

        if argv is not None:
            matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # pragma: no cover - matplotlib is a dependency of the offline half
        return 0
    fig, ax = plt.subplots(figsize=(6, 3.6))
    for c in CONTRASTS:
        ax.plot([r["depth_radii"] for r in rows], [r[f"contrast_{c:g}x"] for r in rows], "o-", label=f"mass {c:g}x stiffer")
    ax.axhline(1.0, color="0.6", lw=0.8)
    ax.set_xlabel("depth of the mass's centre [radii under the surface]")
    ax.set_ylabel("k_n over the mass / without it")
    ax.set_title(f"Palpation contrast: a {RADIUS * 2e3:g} mm ball in 10 kPa tissue")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "palpation.png", dpi=120)
    if argv is not None:
        plt.close(fig)
    return 0


if __name__ == "__main__":
    main()
