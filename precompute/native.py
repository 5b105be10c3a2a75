"""ctypes binding of ``_surface_factor.c``: the P1 Green's-function stage without copies.

The shared library is compiled by ``tools/install_cholmod.sh`` (``make venv``) when Debian's
SuiteSparse headers are present; :func:`available` says whether it was.  Without it
:mod:`precompute.condense` runs the same algebra through scikit-sparse or cvxopt and SciPy's
LAPACK, with the same numbers (tested).
"""
from __future__ import annotations

import ctypes
import sys
from functools import lru_cache
from pathlib import Path

import numpy as np

#: where ``make venv`` puts the compiled library (inside the venv, never in the source tree)
LIBRARY = Path(sys.prefix) / "lib" / "pmask" / "libpmask_surface_factor.so"
SOURCE = Path(__file__).with_name("_surface_factor.c")

#: must equal pmask_abi_version() in _surface_factor.c
ABI_VERSION = 2

_F64 = np.ctypeslib.ndpointer(np.float64, flags="C_CONTIGUOUS")
_I64 = np.ctypeslib.ndpointer(np.int64, flags="C_CONTIGUOUS")
_c_long, _c_int, _p = ctypes.c_long, ctypes.c_int, ctypes.c_void_p


@lru_cache(maxsize=1)
def _lib():
    if not LIBRARY.exists():
        return None
    try:
        lib = ctypes.CDLL(str(LIBRARY))
        abi = lib.pmask_abi_version()
    except (OSError, AttributeError):
        abi = None
    if abi != ABI_VERSION:
        import warnings

        warnings.warn(f"{LIBRARY} is from another version of this code (stale build); run make venv to rebuild "
                      "it. Using the slower pip-only route meanwhile.", RuntimeWarning, stacklevel=2)
        return None
    lib.pmask_factor.argtypes = [_c_long, _I64, _I64, _F64, _c_long, _c_int, ctypes.POINTER(_p),
                                 ctypes.POINTER(ctypes.POINTER(ctypes.c_double)), ctypes.POINTER(_c_long), _F64]
    lib.pmask_factor.restype = _c_int
    lib.pmask_greens.argtypes = [_p, _c_long, _c_long, _c_long, _F64, _F64]
    lib.pmask_greens.restype = _c_int
    lib.pmask_free.argtypes = [_p]
    lib.pmask_free.restype = None
    return lib


def available() -> bool:
    """True when the compiled library is installed and loads."""
    return _lib() is not None


class _Owner:
    """Keeps CHOLMOD's factor alive while a numpy view of its trailing block exists."""

    def __init__(self, lib, handle):
        self._lib, self._handle = lib, handle

    def __del__(self):
        handle, self._handle = self._handle, None
        if handle:
            try:
                self._lib.pmask_free(handle)
            except Exception:  # interpreter shutdown: the process's memory goes with it
                pass


def factor(A, nt: int, *, reorder: bool = True):
    """Supernodal Cholesky of the lower-triangular CSC ``A`` in its order, the interior part (all
    but the last ``nt``) reordered by METIS when ``reorder`` (AMD if METIS fails);
    returns the trailing (nt, nt) block of L as a column-major view into CHOLMOD's storage (into a
    gathered copy when those columns span several supernodes: a body in pieces), and timings.

    Raises ``ArithmeticError(column)`` when A is not positive definite, ``MemoryError`` when
    CHOLMOD fails otherwise.
    """
    lib = _lib()
    n = A.shape[0]
    indptr = np.ascontiguousarray(A.indptr, dtype=np.int64)
    indices = np.ascontiguousarray(A.indices, dtype=np.int64)
    data = np.ascontiguousarray(A.data, dtype=np.float64)
    handle, block, ld, times = _p(), ctypes.POINTER(ctypes.c_double)(), _c_long(), np.zeros(7)
    status = lib.pmask_factor(n, indptr, indices, data, nt, int(reorder), ctypes.byref(handle),
                              ctypes.byref(block), ctypes.byref(ld), times)
    if status > 0:
        raise ArithmeticError(status - 1)
    if status < 0:
        raise MemoryError("CHOLMOD could not factorise the stiffness matrix (out of memory?)")
    owner = _Owner(lib, handle)
    ld = ld.value
    buf = (ctypes.c_double * ((nt - 1) * ld + nt)).from_address(ctypes.addressof(block.contents))
    buf._owner = owner  # freed with the last view
    L_TT = np.ndarray((nt, nt), np.float64, buffer=buf, strides=(8, 8 * ld))
    return L_TT, {"order_s": times[0], "analyse_s": times[1], "numeric_s": times[2],
                  "locate_s": times[3], "stored_L": int(times[4]), "in_place": bool(times[5]),
                  "interior_order": ("given", "AMD", "METIS")[int(times[6])]}


def greens(L_TT: np.ndarray, nf: int, areas: np.ndarray):
    """Ξ = (L_FF L_FFᵀ)⁻¹ diag(a) and reactions (L_UF L_FF⁻¹) diag(a) from the trailing block, in
    place: ``L_TT`` ((nt, nt), column-major with any leading dimension) is overwritten and the
    results are views of it (Ξ = its transposed top-left block).
    Returns Xi, reactions, timings, info (LAPACK's: k > 0 means singular at k)."""
    if L_TT.ndim != 2 or L_TT.shape[0] != L_TT.shape[1]:
        raise ValueError("L_TT must be a square, writeable, column-major float64 array")
    nt = L_TT.shape[0]
    ld = L_TT.strides[1] // 8
    if not (L_TT.dtype == np.float64 and L_TT.flags.writeable and L_TT.strides[0] == 8 and ld >= nt):
        raise ValueError("L_TT must be a square, writeable, column-major float64 array")
    a = np.ascontiguousarray(areas, dtype=np.float64)
    if len(a) != nf:
        raise ValueError(f"{len(a)} areas for {nf} free dofs")
    times = np.zeros(4)
    info = _lib().pmask_greens(L_TT.ctypes.data, ld, nt, nf, a, times)
    return L_TT[:nf, :nf].T, L_TT[nf:, :nf], {"trtri_s": times[0], "reactions_s": times[1], "lauum_s": times[2],
                                              "mirror_s": times[3]}, info


def cholmod_version() -> str | None:
    """CHOLMOD's version of the native library (for provenance), None when it is not built."""
    lib = _lib()
    if lib is None:
        return None
    v = (ctypes.c_int * 3)()
    try:
        lib.cholmod_l_version(v)
    except AttributeError:  # CHOLMOD before 3.0.14 has no version call
        return "unknown"
    return ".".join(str(x) for x in v)
