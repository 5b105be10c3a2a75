"""The examples run as tests (on a small kidney) and their outputs hold real numbers."""
from __future__ import annotations

import csv
import runpy

import numpy as np

from conftest import ROOT
from pmask.pipeline.strokes import stroke_path
from pmask.runtime.contact.state import TOUCHING

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


grasp = runpy.run_path(str(ROOT / "examples" / "grasp.py"), run_name="example")


def test_grasp_example_squeezes_harder_coupled_and_the_display_meets_both_jaws(kidney_small, tmp_path, capsys):
    """Two jaws through the body: each needs more force than as an independent contact (the other jaw's push
    is felt), both hold contact, and the displayed surface meets each jaw to round-off (1e-8 of |u|)."""
    assert grasp["main"]([str(kidney_small), "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    ratios = [float(x) for x in printed.split("coupled / independent: upper ")[1].split("\n")[0].replace(
        "lower ", "").split(", ")]
    assert min(ratios) > 1.2
    meet = float(printed.split("it meets each jaw's displacement to ")[1].split(" ")[0])
    assert meet < 1e-8
    with open(tmp_path / "grasp.csv") as fh:
        rows = list(csv.DictReader(fh))
    hold = [r for r in rows if 0.85 <= float(r["t_s"]) < 1.15]
    touching = {str(int(x)) for x in TOUCHING}  # in contact (DEEP too: the coupled squeeze is past δ_lin)
    assert hold and all(r["status_upper"] in touching and r["status_lower"] in touching for r in hold)
    assert (tmp_path / "grasp.png").stat().st_size > 10_000


palpation = runpy.run_path(str(ROOT / "examples" / "palpation.py"), run_name="example")


def test_palpation_example_feels_the_mass_less_with_depth_and_more_with_contrast(tmp_path):
    """#26's palpation map: k_n over the mass against the same block without it, for a ball 1.5, 2 and 3 radii
    deep, 5x and 10x stiffer: every contrast above 1, the 10x mass felt more than the 5x at each depth, and
    both felt less the deeper they lie (the numbers are in the example's CSV and figure)."""
    assert palpation["main"](["--out", str(tmp_path)]) == 0
    with open(tmp_path / "palpation.csv") as fh:
        rows = list(csv.DictReader(fh))
    c5 = np.array([float(r["contrast_5x"]) for r in rows])
    c10 = np.array([float(r["contrast_10x"]) for r in rows])
    assert np.all(c5 > 1.0) and np.all(c10 > c5)
    assert np.all(np.diff(c5) < 0) and np.all(np.diff(c10) < 0)
    assert (tmp_path / "palpation.png").stat().st_size > 10_000
