"""The house: the runtime installs alone, the code hash follows what runs, the version is reported."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from conftest import ROOT


@pytest.mark.slow
def test_the_runtime_installs_alone_and_runs_a_haptic_step(tmp_path, kidney_small):
    """`pip install <checkout>` into a fresh venv brings numpy and h5py only, and a haptic loop runs."""
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    py = venv / "bin" / "python"
    env = dict(os.environ, PIP_DISABLE_PIP_VERSION_CHECK="1")
    env.pop("PMASK_REQUIRE_NATIVE", None)
    r = subprocess.run([str(py), "-m", "pip", "install", "--quiet", str(ROOT)], capture_output=True, text=True,
                       env=env, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    listed = subprocess.run([str(py), "-m", "pip", "list", "--format=freeze"], capture_output=True, text=True,
                            check=True).stdout.lower()
    for heavy in ("scipy", "gmsh", "scikit-fem", "meshio", "trimesh", "cvxopt", "matplotlib", "tqdm"):
        assert f"{heavy}==" not in listed, f"{heavy} was installed with the runtime alone"
    code = ("import numpy as np, sys; from pmask.runtime import Model, HapticContact, Status\n"
            "m = Model.load(sys.argv[1]); s = m.stiffness('linear', 2 * m.mean_edge_length)\n"
            "i = m.contact[m.core][np.argmax(m.points[m.contact[m.core], 2])]; p0 = m.points[i]\n"
            "h = HapticContact(s); out = [h.step(p0 + [0, 0, dz]) for dz in np.linspace(2e-3, -1e-3, 40)]\n"
            "f, st = out[-1]; assert st == Status.CONTACT and f[2] > 0, (f, st); print('ok', f)\n"
            "assert 'scipy' not in sys.modules\n")
    r = subprocess.run([str(py), "-c", code, str(kidney_small)], capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 0 and r.stdout.startswith("ok"), r.stdout + r.stderr
    r = subprocess.run([str(venv / "bin" / "pmask"), "precompute", "kidney", "-o", str(tmp_path / "k.h5")],
                       capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 2 and "pmask[precompute]" in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_the_code_hash_ignores_prose_and_follows_code():
    from pmask.pipeline.stages import _without_docstrings

    a = 'def f(x):\n    """Old words."""\n    return x + 1  # a comment\n'
    b = 'def f(x):\n    """New words, and more of them."""\n    return x + 1\n'
    c = 'def f(x):\n    """Old words."""\n    return x + 2\n'
    assert _without_docstrings(a) == _without_docstrings(b)
    assert _without_docstrings(a) != _without_docstrings(c)


def test_version():
    from pmask.pipeline.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
