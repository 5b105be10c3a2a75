"""Compiled parts, built by the build backend (setuptools) into the package.

- ``pmask.precompute._selinv``: the P1/P2 Green's-function stage by selected inversion, C over the
  system's CHOLMOD and LAPACK (needs SuiteSparse's headers: ``make system-deps``).  Loaded with ctypes
  by ``pmask.precompute.native``; without it the pip-only route (cvxopt + numpy) runs the same algorithm.
- ``pmask.runtime.servo._core``: the haptic servo core (``runtime/servo/core/*.c``, one C99 file per step of
  the contact algorithm, over libc, libm and pthreads) with its CPython binding.  Without it the Python engine runs the same step.
  ``-ffp-contract=off``: no fused multiply-adds, so that the C's forces equal the Python engine's to
  the last bit (a test holds them to 1e-12).

- ``pmask.viewer``'s page: ``viewer/src/viewer.js`` and three.js, bundled by esbuild into
  ``viewer/static/viewer.bundle.js`` with the versions locked in ``viewer/package-lock.json`` (``npm ci``
  from the npm registry at build time; nothing is fetched when the viewer runs).  Without npm the
  package installs and ``pmask view`` says how to build the page.

Every extension is optional: a machine without a compiler or without the headers still installs,
and runs the pure-Python fallbacks.  ``PMASK_REQUIRE_NATIVE=1`` (CI sets it) turns a missing header
or a compile error (or, for the viewer's page, a missing npm) into a failed build, so that a broken C source cannot hide behind a fallback.
"""
import glob
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build import build
from setuptools.command.build_ext import build_ext
from setuptools.command.build_py import build_py
from setuptools.command.egg_info import egg_info

REQUIRED = os.environ.get("PMASK_REQUIRE_NATIVE", "") not in ("", "0")
SUITESPARSE = os.environ.get("PMASK_SUITESPARSE_INCLUDE", "/usr/include/suitesparse")
WARN = ["-Wall", "-Wextra", "-Wno-unused-parameter"] + (["-Werror"] if REQUIRED else [])


def extensions():
    exts = [Extension(
        "pmask.runtime.servo._core", ["runtime/servo/_coremodule.c", *sorted(glob.glob("runtime/servo/core/*.c"))],
        include_dirs=["runtime/servo"], depends=["runtime/servo/pmask_servo.h", "runtime/servo/core/pm_internal.h"],
        extra_compile_args=["-O2", "-ffp-contract=off", "-fno-fast-math", "-pthread", *WARN],
        extra_link_args=["-pthread"], libraries=["m"], optional=not REQUIRED)]
    if Path(SUITESPARSE, "cholmod.h").is_file():
        exts.append(Extension(
            "pmask.precompute._selinv", ["precompute/_selinv_module.c", "precompute/_selected_inverse.c"],
            include_dirs=[SUITESPARSE], libraries=["cholmod", "lapack", "blas"],
            extra_compile_args=["-O2", "-pthread", *WARN], extra_link_args=["-pthread"], optional=not REQUIRED))
    elif REQUIRED:
        sys.exit(f"PMASK_REQUIRE_NATIVE is set but {SUITESPARSE}/cholmod.h is missing: run `make system-deps` "
                 "(Debian: libsuitesparse-dev) or set PMASK_SUITESPARSE_INCLUDE")
    else:
        print(f"note: no SuiteSparse headers in {SUITESPARSE}: the precompute will use the pip-only route "
              "(cvxopt's CHOLMOD, slower); `make system-deps` as root installs them", file=sys.stderr)
    return exts


class BuildExt(build_ext):
    """Say in one line what an optional extension's failure means instead of a bare compiler log."""

    def build_extension(self, ext):
        try:
            super().build_extension(ext)
        except Exception as exc:  # the compiler's own message is above this line
            if REQUIRED:
                raise
            print(f"note: {ext.name} did not compile ({exc}); its pure-Python fallback will be used",
                  file=sys.stderr)


VIEWER = Path(__file__).resolve().parent / "viewer"
#: what the page is built from (the lock file pins three.js and esbuild)
VIEWER_SOURCES = ("package.json", "package-lock.json", "src")


def build_viewer(where: Path) -> Path | None:
    """npm ci + esbuild in ``where`` (a copy of the viewer's sources, or the checkout's folder for an editable
    install): the page's bundle, unless it is newer than its sources and the lock file.  Returns the bundle,
    or None where it cannot be built (no npm: `pmask view` then says how to build it)."""
    bundle = where / "static" / "viewer.bundle.js"
    sources = [where / "package-lock.json", *sorted((where / "src").glob("*.js"))]
    if not sources[0].is_file():
        return None  # an sdist or checkout without the viewer's sources: nothing to build
    if bundle.is_file() and all(bundle.stat().st_mtime >= s.stat().st_mtime for s in sources):
        return bundle
    npm = shutil.which("npm")
    try:
        if npm is None:
            raise RuntimeError("npm is not installed")
        quiet = ["--silent"] if not REQUIRED else []
        if not (where / "node_modules" / "three").is_dir():
            subprocess.run([npm, "ci", "--ignore-scripts", "--no-audit", "--no-fund", *quiet], cwd=where, check=True)
        subprocess.run([npm, "run", "build", *quiet], cwd=where, check=True)
        return bundle
    except (RuntimeError, OSError, subprocess.CalledProcessError) as exc:
        if REQUIRED:
            raise SystemExit(f"PMASK_REQUIRE_NATIVE is set but the viewer's page did not build ({exc})")
        print(f"note: the viewer's page was not built ({exc}); `pmask view` will say how to build it",
              file=sys.stderr)
        return None


class BuildPy(build_py):
    """The viewer's page: an editable install builds it in the checkout (the package is the checkout); any other
    install builds it in a temporary copy of its sources and puts only the bundle into the build, so that
    installing from a checkout leaves the checkout as it was (no node_modules, no bundle)."""

    def run(self):
        if getattr(self, "editable_mode", False):
            build_viewer(VIEWER)
            super().run()
            return
        super().run()
        if not (VIEWER / "package-lock.json").is_file():
            return
        with tempfile.TemporaryDirectory(prefix="pmask-viewer-") as tmp:
            for name in VIEWER_SOURCES:
                src = VIEWER / name
                (shutil.copytree if src.is_dir() else shutil.copy2)(src, Path(tmp) / name)
            (Path(tmp) / "static").mkdir()
            bundle = build_viewer(Path(tmp))
            if bundle is not None:
                target = Path(self.build_lib) / "pmask" / "viewer" / "static"
                target.mkdir(parents=True, exist_ok=True)
                shutil.copy2(bundle, target / bundle.name)


class Build(build):
    """Build products in a temporary folder, not ``build/`` in the checkout (pip builds in place)."""

    def initialize_options(self):
        super().initialize_options()
        self.build_base = tempfile.mkdtemp(prefix="pmask-build-")


class EggInfo(egg_info):
    """The package metadata in a temporary folder, not ``pmask.egg-info`` in the checkout."""

    def initialize_options(self):
        super().initialize_options()
        self.egg_base = tempfile.mkdtemp(prefix="pmask-egg-")


setup(ext_modules=extensions(), cmdclass={"build": Build, "build_ext": BuildExt, "build_py": BuildPy,
                                          "egg_info": EggInfo})
