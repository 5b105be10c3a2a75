"""ctypes binding of ``_selected_inverse.c``: the P1 Green's-function stage by selected inversion.

The shared library is the extension module ``pmask.precompute._selinv``, compiled by the build backend
(``setup.py``) when SuiteSparse's headers are present (``make system-deps``); :func:`available` says
whether it was.  Without it
:mod:`pmask.precompute.greens` runs the same algorithm through cvxopt's CHOLMOD and :mod:`pmask.precompute.selinv`
(numpy and SciPy's BLAS): the same numbers (tested), slower.
"""
from __future__ import annotations

import contextlib
import ctypes
import importlib.util
import threading
import time
from functools import lru_cache
from pathlib import Path

import numpy as np

from pmask.errors import ResourceError

from pmask.precompute.selinv import FACTOR_ARRAYS  # the supernodal layout, in pmask_factor_arrays' order

SOURCE = Path(__file__).with_name("_selected_inverse.c")


def _library_path() -> Path | None:
    """The compiled extension's file (where the build put it), None when it was not built."""
    try:
        spec = importlib.util.find_spec("pmask.precompute._selinv")
    except (ImportError, ValueError):
        return None
    return Path(spec.origin) if spec is not None and spec.origin else None


#: the compiled library, or None when this installation has none (pip-only route)
LIBRARY = _library_path()

#: must equal pmask_abi_version() in _selected_inverse.c
ABI_VERSION = 6

_F64 = np.ctypeslib.ndpointer(np.float64, flags="C_CONTIGUOUS")
_I64 = np.ctypeslib.ndpointer(np.int64, flags="C_CONTIGUOUS")
_c_long, _c_int, _p = ctypes.c_int64, ctypes.c_int, ctypes.c_void_p


@lru_cache(maxsize=1)
def _lib():
    if LIBRARY is None or not Path(LIBRARY).exists():
        return None
    try:
        lib = ctypes.CDLL(str(LIBRARY))
        abi = lib.pmask_abi_version()
    except (OSError, AttributeError):
        abi = None
    if abi != ABI_VERSION:
        import warnings

        warnings.warn(f"{LIBRARY} is from another version of this code (stale build); run `make venv` (or "
                      "`pip install -e .`) to rebuild it. Using the slower pip-only route meanwhile.",
                      RuntimeWarning, stacklevel=2)
        return None
    lib.pmask_factor.argtypes = [_c_long, _I64, _I64, _F64, ctypes.POINTER(_p), _F64]
    lib.pmask_factor.restype = _c_int
    lib.pmask_factor_arrays.argtypes = [_p, _I64, ctypes.POINTER(_p)]
    lib.pmask_factor_arrays.restype = None
    _flag = ctypes.POINTER(ctypes.c_int32)
    lib.pmask_selinv.argtypes = [_c_long, _c_long, _I64, _I64, _I64, _I64, _c_long, _F64, _c_long, _I64, _c_long, _I64,
                                 _F64, _p, _F64, _flag]
    lib.pmask_selinv.restype = _c_int
    lib.pmask_selcols.argtypes = [_c_long, _c_long, _I64, _I64, _I64, _I64, _c_long, _F64, _c_long, _I64, _c_long, _I64,
                                  _c_long, _I64, _I64, _F64, _p, _F64, _flag]
    lib.pmask_selcols.restype = _c_int
    lib.pmask_cancel_set.argtypes = [_flag, ctypes.c_int32]
    lib.pmask_cancel_set.restype = None
    lib.pmask_free.argtypes = [_p]
    lib.pmask_free.restype = None
    return lib


def available() -> bool:
    """True when the compiled library is installed and loads."""
    return _lib() is not None


class _Owner:
    """Keeps CHOLMOD's factor alive while numpy views of its arrays exist."""

    def __init__(self, lib, handle):
        self._lib, self._handle = lib, handle

    def __del__(self):
        handle, self._handle = self._handle, None
        if handle:
            try:
                self._lib.pmask_free(handle)
            except Exception:  # interpreter shutdown: the process's memory goes with it
                pass


def _view(address: int, dtype, count: int, owner) -> np.ndarray:
    ctype = ctypes.c_double if dtype == np.float64 else ctypes.c_int64
    buf = (ctype * max(count, 1)).from_address(address)
    buf._owner = owner  # freed with the last view
    return np.frombuffer(buf, dtype=dtype, count=count)


#: (deadline on time.monotonic(), seconds, the flag that sets it) of the running stage, or None
_deadline: tuple | None = None
#: native calls still running after Ctrl-C or a budget, with their arguments (the C code may still write
#: into them, so they must outlive the call): (done event, args, keep).  The next call waits for them:
#: two of our BLAS-heavy calls at once gave wrong numbers with the threaded OpenBLAS.
_pending: list = []
#: how often the waiting thread looks at Ctrl-C and the clock [s]
POLL_S = 0.05


@contextlib.contextmanager
def budget(seconds: float | None, flag: str = "--solve-timeout"):
    """Native calls inside stop with :class:`ResourceError` once ``seconds`` have passed (None: no limit)."""
    global _deadline
    previous = _deadline
    _deadline = (time.monotonic() + seconds, seconds, flag) if seconds else None
    try:
        yield
    finally:
        _deadline = previous


def _run(fn, *args, keep=(), cancellable=False):
    """``fn(*args)`` (a ctypes function: it releases the GIL) in a helper thread, so that Ctrl-C and the
    :func:`budget` stop it within about a supernode: with ``cancellable`` the call gets a cancel flag of its
    own as its last argument, which the selected inversion's loops read between supernodes (then they return
    -4).  CHOLMOD's factorisation cannot be stopped inside; it is left to finish in the background with its
    arguments (and ``keep``: buffers passed as addresses) kept alive."""
    lib = _lib()
    flag = ctypes.c_int32(0)
    while _pending:  # a cancelled call ends within a supernode; an abandoned factorisation when it is done
        _pending[0][0].wait()
        _pending.pop(0)
    result, done = {}, threading.Event()
    call_args = (*args, ctypes.byref(flag)) if cancellable else args

    def target():
        try:
            result["status"] = fn(*call_args)
        finally:
            done.set()

    threading.Thread(target=target, name="pmask-native", daemon=True).start()
    try:  # (an Event, not Thread.join: a join that Ctrl-C interrupted returned at once when asked again)
        while not done.wait(POLL_S):
            if _deadline is not None and time.monotonic() > _deadline[0]:
                raise ResourceError(f"the factorisation and Green's functions did not finish within {_deadline[1]:g} s "
                                    f"({_deadline[2]}); coarsen the mesh, restrict --contact, or allow longer")
    except BaseException:  # Ctrl-C or the budget: stop the C loops, then go
        if cancellable:
            lib.pmask_cancel_set(ctypes.byref(flag), 1)
        _pending.append((done, args, (keep, flag)))
        if done.wait(1.0):
            _pending.pop()
        raise
    return result["status"]


def factor(A):
    """CHOLMOD's supernodal Cholesky P A Pᵀ = L Lᵀ of the lower-triangular CSC ``A`` (METIS nested
    dissection, AMD if METIS fails; supernodes postordered).

    Returns the factor as a dict of numpy arrays (:data:`FACTOR_ARRAYS`: views into CHOLMOD's storage,
    kept alive by the views) and stats.  Raises ``ArithmeticError(column)`` when A is not positive
    definite, ``MemoryError`` when CHOLMOD fails otherwise.
    """
    lib = _lib()
    n = A.shape[0]
    indptr = np.ascontiguousarray(A.indptr, dtype=np.int64)
    indices = np.ascontiguousarray(A.indices, dtype=np.int64)
    data = np.ascontiguousarray(A.data, dtype=np.float64)
    handle, times = _p(), np.zeros(5)
    status = _run(lib.pmask_factor, n, indptr, indices, data, ctypes.byref(handle), times, keep=(handle,))
    if status > 0:
        raise ArithmeticError(status - 1)
    if status < 0:
        raise MemoryError("CHOLMOD could not factorise the stiffness matrix (out of memory?)")
    owner = _Owner(lib, handle)
    sizes, ptrs = np.zeros(3, np.int64), (_p * 6)()
    lib.pmask_factor_arrays(handle, sizes, ptrs)
    nsuper, ns, nx = (int(v) for v in sizes)
    counts = (nsuper + 1, nsuper + 1, nsuper + 1, ns, nx, n)
    arrays = {name: _view(ptrs[k], np.float64 if name == "x" else np.int64, counts[k], owner)
              for k, name in enumerate(FACTOR_ARRAYS)}
    return arrays, {"analyse_s": times[0], "numeric_s": times[1], "stored_L": int(times[2]),
                    "order": ("given", "AMD", "METIS")[int(times[3])], "factor_flops": float(times[4]),
                    "supernodes": nsuper}


def selected_inverse(L: dict, want: np.ndarray, scale: np.ndarray):
    """X[i, j] = (A⁻¹)[want_i, want_j] · scale_j from the supernodal factor ``L`` (:func:`factor`'s
    arrays, or the same loaded from a checkpoint): Wᵀ W with W = L⁻¹ P E, one dsyrk per supernode.

    Returns X ((nw, nw), C order) and timings/counts.
    """
    lib = _lib()
    arr = {k: np.ascontiguousarray(L[k], dtype=np.float64 if k == "x" else np.int64) for k in FACTOR_ARRAYS}
    n, nsuper = len(arr["perm"]), len(arr["super"]) - 1
    want = np.ascontiguousarray(want, dtype=np.int64)
    scale = np.ascontiguousarray(scale, dtype=np.float64)
    nw = len(want)
    if scale.shape != (nw,):
        raise ValueError(f"{len(scale)} scale factors for {nw} wanted dofs")
    D = np.zeros((nw, nw))
    times = np.zeros(7)
    status = _run(lib.pmask_selinv, n, nsuper, arr["super"], arr["pi"], arr["px"], arr["s"], len(arr["s"]), arr["x"],
                  len(arr["x"]), arr["perm"], nw, want, scale, D.ctypes.data, times, keep=(D, arr), cancellable=True)
    if status == -2:
        raise ValueError("wanted dofs must be distinct indices of the factorised matrix")
    _check_status(status)
    return D, {"setup_s": times[0], "solve_s": times[1], "syrk_s": times[2], "permute_s": times[3],
               "flops": float(times[4]), "W_doubles": int(times[5]), "prefault_wait_s": times[6]}


def selected_columns(L: dict, rows: np.ndarray, B):
    """X = Eᵀ A⁻¹ B: the rows ``rows`` of A⁻¹B from the supernodal factor ``L``, for a sparse B
    (W_Eᵀ W_B, one dgemm per supernode; see ``pmask_selcols`` and :func:`pmask.precompute.selinv.selected_columns`).

    Returns X ((len(rows), B.shape[1]), C order) and timings/counts.
    """
    import scipy.sparse as sp

    lib = _lib()
    arr = {k: np.ascontiguousarray(L[k], dtype=np.float64 if k == "x" else np.int64) for k in FACTOR_ARRAYS}
    n, nsuper = len(arr["perm"]), len(arr["super"]) - 1
    rows = np.ascontiguousarray(rows, dtype=np.int64)
    B = sp.csc_matrix(B)
    if B.shape[0] != n:
        raise ValueError(f"B has {B.shape[0]} rows for a factor of {n} dofs")
    B.sum_duplicates()
    k = B.shape[1]
    X = np.zeros((len(rows), k))
    times = np.zeros(6)
    Bp, Bi, Bx = (np.ascontiguousarray(B.indptr, np.int64), np.ascontiguousarray(B.indices, np.int64),
                  np.ascontiguousarray(B.data, np.float64))
    status = _run(lib.pmask_selcols, n, nsuper, arr["super"], arr["pi"], arr["px"], arr["s"], len(arr["s"]), arr["x"],
                  len(arr["x"]), arr["perm"], len(rows), rows, k, Bp, Bi, Bx, X.ctypes.data, times,
                  keep=(X, arr, Bp, Bi, Bx), cancellable=True)
    if status == -2:
        raise ValueError("wanted dofs must be distinct indices of the factorised matrix, and B's rows in range")
    _check_status(status)
    return X, {"setup_s": times[0], "solve_s": times[1], "gemm_s": times[2], "permute_s": times[3],
               "flops": float(times[4]), "W_doubles": int(times[5])}


class FactorArraysError(ValueError):
    """Supernodal arrays that are not a valid factor (a damaged checkpoint): nothing was computed."""


def _check_status(status: int) -> None:
    """The C's other refusals (-2 is the caller's message)."""
    if status == -3:
        raise ValueError("the factor's supernodes are not postordered")
    if status == -5:
        raise ResourceError("a block of the selected inversion is too large for BLAS's 32-bit sizes (over 2^31 "
                            "rows): coarsen the mesh or restrict --contact")
    if status == -6:
        raise FactorArraysError("the factor's arrays are not a valid supernodal factor (a damaged checkpoint?)")
    if status != 0:
        raise MemoryError("out of memory in the selected inversion")


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
