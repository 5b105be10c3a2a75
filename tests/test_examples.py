"""The examples run as tests (on a small kidney) and their outputs hold real numbers."""
from __future__ import annotations

import csv
import runpy

import numpy as np

from conftest import ROOT
from pmask.pipeline.strokes import stroke_path

#: the example as its user runs it (a script of its own, importing the installed package)
stroke = runpy.run_path(str(ROOT / "examples" / "stroke.py"), run_name="example")


def test_stroke_example_writes_traces_and_plot(kidney_small, tmp_path, capsys):
    assert stroke["main"]([str(kidney_small), "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "single" in printed and "linear" in printed and "roughness" in printed
    assert (tmp_path / "stroke.png").stat().st_size > 10_000
    n = len(stroke_path())
    for name in ("single", "linear"):
        with open(tmp_path / f"stroke_{name}.csv") as fh:
            rows = list(csv.DictReader(fh))
        assert len(rows) == n
        f = np.array([[float(r["fx_N"]), float(r["fy_N"]), float(r["fz_N"])] for r in rows])
        status = np.array([int(r["status"]) for r in rows])
        assert np.all(status[200:] == 1)  # in contact for the whole slide
        mag = np.linalg.norm(f[200:], axis=1)
        assert mag.min() > 0.2 * mag.max()
        # 1 kHz steps of a continuous force: no step larger than 3 % of the force
        assert np.linalg.norm(np.diff(f[200:], axis=0), axis=1).max() < 0.03 * mag.max()
