"""The house: the runtime installs alone, the code hash follows what runs, the version is reported."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from conftest import ROOT


def tracked_copy(dest):
    """The checkout's tracked files (what a fresh clone holds), copied to ``dest``."""
    import shutil

    files = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    for name in files.decode().split("\0"):
        if name and (ROOT / name).is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, dest / name)
    return dest


@pytest.mark.slow
def test_the_runtime_installs_alone_and_runs_a_haptic_step(tmp_path, kidney_small):
    """`pip install <checkout>` into a fresh venv brings numpy and h5py only, and a haptic loop runs.  The
    checkout is left as it was (the build, the metadata and the viewer's page are made in temporary folders),
    Python started in the checkout's root imports the installed package (the top-level pmask/ folder used to
    shadow it), and the installed code hashes to the same digest as the checkout's (an artifact's input hash must
    not depend on how pmask was installed)."""
    src = tracked_copy(tmp_path / "src")
    before = sorted(str(p.relative_to(src)) for p in src.rglob("*"))
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    py = venv / "bin" / "python"
    env = dict(os.environ, PIP_DISABLE_PIP_VERSION_CHECK="1")
    env.pop("PMASK_REQUIRE_NATIVE", None)
    r = subprocess.run([str(py), "-m", "pip", "install", "--quiet", str(src)], capture_output=True, text=True,
                       env=env, timeout=900)
    assert r.returncode == 0, r.stdout + r.stderr
    assert sorted(str(p.relative_to(src)) for p in src.rglob("*")) == before, "the install wrote into the checkout"
    r = subprocess.run([str(py), "-c", "import pmask.runtime, pmask.runtime.servo as s; print(pmask.runtime.__file__)"],
                       cwd=src, capture_output=True, text=True)
    assert r.returncode == 0 and str(venv) in r.stdout, r.stdout + r.stderr
    digest = "from pmask.pipeline.stages import code_digest; print(code_digest())"
    installed = subprocess.run([str(py), "-c", digest], cwd=tmp_path, capture_output=True, text=True)
    from pmask.pipeline.stages import code_digest

    assert installed.returncode == 0, installed.stderr
    assert installed.stdout.strip() == code_digest()
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
