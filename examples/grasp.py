"""
A two-jaw grasp: instruments coupled through the body
=====================================================

A two-jaw grasp of the kidney at 1 kHz: two instruments coupled through the body, against the same two
instruments rendered independently::

    python examples/grasp.py artifacts/kidney.h5 --out docs/

The jaws close on the kidney's upper and lower faces at its middle (2 mm outside to 2.5 mm in, in 0.8 s),
hold for 0.4 s and open again.  Coupled (:class:`pmask.runtime.Contacts` with Green's functions), each
jaw feels the body yield under the other jaw's push: the lower jaw is pressed by the body the upper jaw
moves down, so the squeeze takes more force than two independent contacts give.  Written: a CSV force
trace, a PNG plot, and the deformed surface at the end of the hold (meeting both jaws) as numbers.
"""
from __future__ import annotations

import argparse
import csv
import tempfile
from pathlib import Path

import numpy as np

#: the checkout's default kidney (`make precompute MODEL=kidney`), wherever the example runs from
DEFAULT_ARTIFACT = ((Path(__file__).resolve().parent if "__file__" in globals() else Path.cwd())  # (the docs' gallery
                    .parent / "artifacts" / "kidney.h5")                                           # runs it from here)

from pmask.runtime import Contacts, Model
from pmask.runtime.contact.state import TOUCHING


def jaw_points(model):
    """The touchable vertices at the top and the bottom of the kidney's middle, with their normals."""
    from pmask.runtime.geometry import vertex_normals

    free = model.contact[model.core]
    P = model.points
    middle = free[np.abs(P[free, 0]) < 0.3 * np.abs(P[free, 0]).max()]
    top, bottom = middle[np.argmax(P[middle, 2])], middle[np.argmin(P[middle, 2])]
    n = vertex_normals(model.points, model.triangles)
    return [(P[top], n[top]), (P[bottom], n[bottom])]


def jaw_path(jaws, rate=1000.0, close_s=0.8, hold_s=0.4, gap=2e-3, squeeze=2.5e-3):
    """Probe positions (ticks, 2, 3): each jaw moves along its vertex normal from ``gap`` outside to ``squeeze``
    inside, holds, and opens."""
    n_close, n_hold = int(close_s * rate), int(hold_s * rate)
    depth = np.concatenate([np.linspace(-gap, squeeze, n_close), np.full(n_hold, squeeze),
                            np.linspace(squeeze, -gap, n_close)])
    return np.stack([p - depth[:, None] * n for p, n in jaws], axis=1), n_close, n_hold


def run(contacts, path):
    forces = np.zeros(path.shape)
    status = np.zeros(path.shape[:2], int)
    for k, probes in enumerate(path):
        f, s = contacts.step(list(probes))
        forces[k], status[k] = f, s
    return forces, status


def shown(surface, v, st):
    """How far the displayed mesh moves the contact point: the displacement v at the mesh point under it (the
    contact surface may be the mesh's subdivision surface), less that point's offset from the contact point."""
    m, *beta = surface.mesh_point(st.tri, *st.b)
    return np.asarray(beta) @ v[surface.mesh_T[m]] - np.asarray(surface.mesh_offset(st.tri, st.b))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="A two-jaw grasp of the kidney at 1 kHz")
    ap.add_argument("artifact", nargs="?", default=str(DEFAULT_ARTIFACT),
                    help="the artifact (default: the checkout's artifacts/kidney.h5, from `make precompute`)")
    ap.add_argument("--out", default=None, help="folder for the CSV and PNG (default: a temporary folder)")
    ap.add_argument("--friction", type=float, default=0.3, help="jaw-tissue Coulomb coefficient")
    args = ap.parse_args(argv)
    model = Model.load(args.artifact)
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="pmask-example-"))
    out.mkdir(parents=True, exist_ok=True)
    stiff = model.stiffness("linear")
    jaws = jaw_points(model)
    path, n_close, n_hold = jaw_path(jaws)
    coupled = Contacts(stiff, 2, friction=args.friction)
    independent = Contacts(stiff, 2, friction=args.friction, coupled=False)
    runs = {}
    for name, c in (("coupled", coupled), ("independent", independent)):
        forces, status = run(c, path[:n_close + n_hold])
        if name == "coupled":  # the display at the end of the hold, before the jaws open
            v = c.deformation()
            meet = [np.linalg.norm(shown(c.surface, v, st) - np.asarray(st.u_bar)) / np.linalg.norm(st.u_bar)
                    for st in c.states]
        rest, rest_status = run(c, path[n_close + n_hold:])
        runs[name] = (np.concatenate([forces, rest]), np.concatenate([status, rest_status]))
    hold = slice(n_close, n_close + n_hold)
    squeeze = {name: np.linalg.norm(f[hold], axis=2).mean(axis=0) for name, (f, _) in runs.items()}
    in_contact = {name: float(np.mean(np.isin(s[hold], TOUCHING))) for name, (_, s) in runs.items()}
    for name in runs:
        print(f"{name:11s} jaw forces during the hold: upper {squeeze[name][0]:.4f} N, lower {squeeze[name][1]:.4f} N "
              f"(in contact {100 * in_contact[name]:.0f} % of the hold)")
    ratio = squeeze["coupled"] / squeeze["independent"]
    print(f"coupled / independent: upper {ratio[0]:.2f}, lower {ratio[1]:.2f}")
    print(f"largest displacement of the displayed surface {1e3 * np.linalg.norm(v, axis=1).max():.2f} mm; "
          f"it meets each jaw's displacement to {max(meet):.1e} of |u|")
    t = np.arange(len(path)) / 1000.0
    with open(out / "grasp.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t_s", "upper_coupled_N", "lower_coupled_N", "upper_independent_N", "lower_independent_N",
                    "status_upper", "status_lower"])
        fc, sc = runs["coupled"]
        fi, _ = runs["independent"]
        for k in range(len(path)):
            w.writerow([f"{t[k]:.3f}", *(f"{np.linalg.norm(x):.6e}" for x in (fc[k, 0], fc[k, 1], fi[k, 0], fi[k, 1])),
                        int(sc[k, 0]), int(sc[k, 1])])
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # pragma: no cover - matplotlib comes with the figures extra
        return 0
    fig, ax = plt.subplots(figsize=(8, 3.5))
    for name, style in (("coupled", "-"), ("independent", "--")):
        f, _ = runs[name]
        ax.plot(t, np.linalg.norm(f[:, 0], axis=1), style, color="C0", lw=1, label=f"upper jaw, {name}")
        ax.plot(t, np.linalg.norm(f[:, 1], axis=1), style, color="C1", lw=1, label=f"lower jaw, {name}")
    ax.set_xlabel("time [s] (1 kHz)")
    ax.set_ylabel("|force| [N]")
    ax.set_title("Two-jaw grasp: coupled through the body vs independent contacts")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "grasp.png", dpi=120)
    if argv is not None:  # called from code (the tests); run as a script the figure stays for the docs' gallery
        plt.close(fig)
    return 0


if __name__ == "__main__":
    main()
