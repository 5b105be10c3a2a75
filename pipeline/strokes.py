"""Scripted probe paths over the kidney and what they measure (used by the reference tables, the
examples and the benchmarks).

The stroke: the probe comes down 3 mm above the upper face at x = -45 mm, y = 12 mm, presses
1.5 mm below the (analytic ellipsoid) surface in 0.2 s, then slides at 35 mm/s to x = +45 mm
keeping that depth: 2.77 s of samples at 1 kHz.  The path crosses the large flat-face triangles and
the smaller ones towards both poles.  Two smoothness figures per run:

- ``rms_step``: RMS over the sliding phase of |f(k+1) − f(k)| [N per 1 ms step];
- ``roughness``: RMS of |f| minus its 301 ms moving average (10.5 mm of path, about two triangles of
  the kidney's flat face), over the mean |f|: mesh artefacts are the part of the force that varies
  faster than the organ.
"""
from __future__ import annotations

import numpy as np

from pmask.meshes.kidney import SEMI_AXES

RATE = 1000.0  # Hz
DEPTH = 1.5e-3  # m
Y0 = 0.012  # m
X0, X1 = -0.045, 0.045  # m
SPEED = 0.035  # m/s


def stroke_path() -> np.ndarray:
    """Probe positions (n, 3) of the scripted stroke, one per 1 ms tick."""
    a, b, c = SEMI_AXES

    def top(x):
        return c * np.sqrt(max(1 - (x / a) ** 2 - (Y0 / b) ** 2, 0.0))

    approach = [(X0, Y0, top(X0) + 3e-3 - (3e-3 + DEPTH) * k / 200) for k in range(200)]
    n_slide = int(round((X1 - X0) / SPEED * RATE))
    slide = [(x, Y0, top(x) - DEPTH) for x in np.linspace(X0, X1, n_slide)]
    return np.array(approach + slide)


def run_stroke(stiffness, path: np.ndarray, **contact_options):
    """Drive a HapticContact along ``path``; return forces on the user (n, 3) and statuses (n,)."""
    from pmask.runtime import HapticContact

    h = HapticContact(stiffness, **contact_options)
    forces = np.zeros((len(path), 3))
    status = np.zeros(len(path), dtype=int)
    for k, p in enumerate(path):
        f, s = h.step(p)
        forces[k], status[k] = f, s
    return forces, status


def smoothness(forces: np.ndarray, status: np.ndarray, start: int = 200) -> dict:
    """Contact fraction, mean |f|, RMS step and roughness of the sliding phase (from tick ``start``)."""
    from pmask.runtime import Status

    f = forces[start:]
    ok = status[start:] == Status.CONTACT
    mag = np.linalg.norm(f, axis=1)
    step = np.linalg.norm(np.diff(f, axis=0), axis=1)
    w = 301
    smooth = np.convolve(mag, np.ones(w) / w, mode="same")
    inner = slice(w // 2, len(mag) - w // 2)
    return {"contact_fraction": float(ok.mean()), "mean_force": float(mag.mean()),
            "rms_step": float(np.sqrt(np.mean(step ** 2))),
            "roughness": float(np.sqrt(np.mean((mag - smooth)[inner] ** 2)) / mag.mean())}
