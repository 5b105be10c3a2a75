"""The README as a new user meets it: short, its code runs as written, its links lead somewhere."""
from __future__ import annotations

import os
import re
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT

README = (ROOT / "README.md").read_text()


def quickstart() -> str:
    block = README.split("<!-- quickstart: tests/test_readme.py runs this block as written -->", 1)[1]
    block = block.split("<!-- /quickstart -->", 1)[0]
    return block.split("```python", 1)[1].split("```", 1)[0]


def test_the_readme_fits_on_a_few_screens():
    """The first-hour issue's bound: at most ~250 lines (it was 930)."""
    assert len(README.splitlines()) <= 250


def test_the_haptics_quick_start_runs_as_written(kidney_default, tmp_path):
    """The README's twenty lines, run as a user would: in a folder holding artifacts/kidney.h5 (the session's
    default kidney, what `make precompute MODEL=kidney` writes), in a fresh interpreter.  The probe pressed 2 mm
    into the top of the kidney is in contact, and the force pushes the hand back out (+z) with the normal
    stiffness it should have: the normal stiffness k_n = 1/(nᵀK⁻¹n) lies between K's smallest and largest
    eigenvalue, so f_z / 2 mm does too, within 10 % (the proxy's interpolated K and normal, and the ½ δ² ∇k_n
    term, move it by a few per cent)."""
    code = quickstart()
    assert len(code.strip().splitlines()) <= 22
    (tmp_path / "artifacts").mkdir()
    os.symlink(kidney_default, tmp_path / "artifacts" / "kidney.h5")
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    first, second = r.stdout.strip().splitlines()[-2:]
    assert first.startswith("CONTACT ")
    force = [float(x) for x in re.findall(r"[-+]?\d+\.\d*(?:e[-+]?\d+)?", first)]
    k_norm, u_max = (float(x) for x in second.split())
    assert force[2] > 0 and abs(force[2]) > 3 * max(abs(force[0]), abs(force[1]))
    from pmask.runtime import Model

    model = Model.load(kidney_default)
    stiff = model.stiffness()
    top = model.points[np.argmax(model.points[:, 2])]
    lam = np.linalg.eigvalsh(stiff.at(*stiff.locate(top)))
    assert k_norm == pytest.approx(lam[-1], rel=1e-9)
    assert 0.9 * lam[0] <= force[2] / 2e-3 <= 1.1 * lam[-1]
    assert 0 < u_max < 0.02  # the surface moves, by less than the body's size


def test_the_readme_links_lead_somewhere():
    for target in re.findall(r"\]\(([^)#]+)\)", README):
        if target.startswith("http"):
            continue
        assert (ROOT / target).exists(), target


def test_the_contacts_a_tick_holds_are_the_benchmarks():
    """The README's counts of contacts each engine keeps in the 1 ms tick are the stored benchmark's
    (bench/results.json, `make bench ONLY=haptics`), not typed from memory."""
    import json

    tick = json.loads((ROOT / "bench" / "results.json").read_text())["haptics"]["several_tick"]
    m = re.search(r"in the 1 ms tick: up to (\d+) in the C core, (\d+) driven from Python, (\d+) in the pure-Python "
                  r"engine", " ".join(README.split()))  # wherever the lines break
    assert m, "the README no longer says how many contacts each engine keeps in the tick"
    assert [int(x) for x in m.groups()] == [tick[k]["contacts"] for k in ("c", "binding", "python")]


def test_the_side_of_twice_the_readme_gives_two_coupled_contacts_is_the_benchmarks():
    """The README says on which side of the hands issue's bound (at most twice one) two coupled contacts in C
    are; the stored benchmark's side-by-side ratio (one process, bench/results.json) says which side of 2 it
    is, so the sentence changes with it."""
    import json

    ratio = json.loads((ROOT / "bench" / "results.json").read_text())["haptics"]["several"]["2"]["c_ratio"]
    text = " ".join(README.split())
    above = "two coupled contacts cost a little more than twice one in C" in text
    within = "two coupled contacts cost at most twice one in C" in text
    assert above != within, "the README says neither (or both) of the two sentences"
    assert within == (ratio["coupled_over_one"]["median"] <= 2.0), ratio
