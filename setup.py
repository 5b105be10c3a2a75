"""Compiled parts, built by the build backend (setuptools) into the package.

- ``pmask.precompute._selinv``: the P1/P2 Green's-function stage by selected inversion, C over the
  system's CHOLMOD and LAPACK (needs SuiteSparse's headers: ``make system-deps``).  Loaded with ctypes
  by ``pmask.precompute.native``; without it the pip-only route (cvxopt + numpy) runs the same algorithm.
- ``pmask.runtime.servo._core``: the haptic servo core (``runtime/servo/pmask_servo.c``, C99 over libc,
  libm and pthreads) with its CPython binding.  Without it the Python engine runs the same step.
  ``-ffp-contract=off``: no fused multiply-adds, so that the C's forces equal the Python engine's to
  the last bit (a test holds them to 1e-12).

Every extension is optional: a machine without a compiler or without the headers still installs,
and runs the pure-Python fallbacks.  ``PMASK_REQUIRE_NATIVE=1`` (CI sets it) turns a missing header
or a compile error into a failed build, so that a broken C source cannot hide behind a fallback.
"""
import os
import sys
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

REQUIRED = os.environ.get("PMASK_REQUIRE_NATIVE", "") not in ("", "0")
SUITESPARSE = os.environ.get("PMASK_SUITESPARSE_INCLUDE", "/usr/include/suitesparse")
WARN = ["-Wall", "-Wextra", "-Wno-unused-parameter"] + (["-Werror"] if REQUIRED else [])


def extensions():
    exts = [Extension(
        "pmask.runtime.servo._core", ["runtime/servo/_coremodule.c", "runtime/servo/pmask_servo.c"],
        include_dirs=["runtime/servo"], depends=["runtime/servo/pmask_servo.h"],
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


setup(ext_modules=extensions(), cmdclass={"build_ext": BuildExt})
