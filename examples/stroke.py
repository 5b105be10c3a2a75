"""
A sliding stroke: single-vertex against masked stiffness
========================================================

A scripted sliding stroke across the kidney at 1 kHz::

    python examples/stroke.py artifacts/kidney.h5 --out docs/

The same stroke (:func:`pmask.pipeline.strokes.stroke_path`) runs with the single-vertex stiffness
(ρ = e_i / a_i) and with the paper's linear cone mask (r = 2 x mean edge length).  Written: a CSV
force trace per run, a PNG plot, and the two smoothness figures of
:func:`pmask.pipeline.strokes.smoothness` per run.
"""
from __future__ import annotations

import argparse
import csv
import tempfile
import sys
from pathlib import Path

import numpy as np

from pmask.pipeline.strokes import DEPTH, RATE, SPEED, run_stroke, smoothness, stroke_path
#: the checkout's default kidney (`make precompute MODEL=kidney`), wherever the example runs from
DEFAULT_ARTIFACT = ((Path(__file__).resolve().parent if "__file__" in globals() else Path.cwd())  # (the docs' gallery
                    .parent / "artifacts" / "kidney.h5")                                           # runs it from here)

from pmask.runtime import Model


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="A scripted sliding stroke across the kidney at 1 kHz")
    ap.add_argument("artifact", nargs="?", default=str(DEFAULT_ARTIFACT),
                    help="the artifact (default: the checkout's artifacts/kidney.h5, from `make precompute`)")
    ap.add_argument("--out", default=None, help="folder for the CSV and PNG (default: a temporary folder)")
    ap.add_argument("--radius-factor", type=float, default=2.0, help="mask radius in mean edge lengths")
    args = ap.parse_args(argv)
    model = Model.load(args.artifact)
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="pmask-example-"))
    out.mkdir(parents=True, exist_ok=True)
    path = stroke_path()
    t = np.arange(len(path)) / RATE
    runs = {"single": model.stiffness("single"),
            "linear": model.stiffness("linear", args.radius_factor * model.mean_edge_length)}
    results = {}
    for name, stiff in runs.items():
        forces, status = run_stroke(stiff, path)
        results[name] = (forces, status, smoothness(forces, status))
        with open(out / f"stroke_{name}.csv", "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["t_s", "probe_x_m", "probe_y_m", "probe_z_m", "status", "fx_N", "fy_N", "fz_N"])
            for k in range(len(path)):
                w.writerow([f"{t[k]:.3f}", *(f"{v:.6e}" for v in path[k]), int(status[k]),
                            *(f"{v:.6e}" for v in forces[k])])
        s = results[name][2]
        print(f"{name:7s} mean |f| {s['mean_force']:.4f} N, RMS step {s['rms_step'] * 1e3:.3f} mN/ms, "
              f"roughness {s['roughness']:.4f}, in contact {100 * s['contact_fraction']:.0f}%")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # pragma: no cover - matplotlib is a dependency of the offline half
        return 0
    fig, ax = plt.subplots(figsize=(8, 3.5))
    for name, (forces, _, s) in results.items():
        label = "single vertex" if name == "single" else f"linear cone mask, r = {args.radius_factor:g} x mean edge"
        ax.plot(t, np.linalg.norm(forces, axis=1), lw=1, label=f"{label} (roughness {s['roughness']:.3f})")
    ax.set_xlabel("time [s] (1 kHz samples)")
    ax.set_ylabel("|force| [N]")
    ax.set_title(f"Sliding stroke, {DEPTH * 1e3:g} mm deep, {SPEED * 1e3:g} mm/s: {Path(args.artifact).name}")
    ax.legend(loc="lower center", fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "stroke.png", dpi=120)
    if argv is not None:  # called from code (the tests); run as a script the figure stays for the docs' gallery
        plt.close(fig)
    return 0


if __name__ == "__main__":
    main()
