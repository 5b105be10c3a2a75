"""The native servo core: the haptic contact step in C, for C/C++ haptic loops and behind the Python API.

- ``pmask_servo.h`` and ``core/*.c`` (C99, libc + libm + pthreads; one file per step of the contact algorithm,
  as :mod:`pmask.runtime.contact` has one module per step; shipped in this folder and in the wheel): load a
  runtime table (:mod:`pmask.runtime.table`), run the step of :mod:`pmask.runtime.haptics` for n instruments
  (operation for operation the Python engine's algorithm: a test holds them to identical statuses and forces
  equal to 1e-12), optionally on a thread of its own at a set rate.  :func:`include_dir` and :func:`sources`
  tell a C/C++ build where the files are.
- ``_core``: the CPython binding, built by the package's build backend; :class:`pmask.runtime.Contacts`
  and :class:`pmask.runtime.HapticContact` use it when it is built (``engine="native"`` insists,
  ``engine="python"`` forces the fallback).

Why the binding exists beside the Python engine: a Python step costs tens of µs, most of it the
interpreter, and a Python tick shares the GIL with every other Python thread; the C step costs well
under a µs, and in thread mode the tick never touches the GIL (``make bench`` measures both), but where coupled
contacts on a compressed artifact too large for the core's memory (:data:`GREENS_MEMORY_SHARE`) land on a new
pair of triangles: the core then asks the surface for their coupling blocks (``pm_servo_create_paired``), a
Python call.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from pmask.errors import InputError

try:
    from pmask.runtime.servo import _core
except ImportError:  # no compiler at install time: the Python engine runs instead
    _core = None

log = logging.getLogger("pmask.runtime.haptics")


def available() -> bool:
    """Whether the native core is built into this installation."""
    return _core is not None


def include_dir() -> Path:
    """The folder holding ``pmask_servo.h`` (and ``core/`` with the sources, :func:`sources`)."""
    return Path(__file__).resolve().parent


def sources() -> list[Path]:
    """The C files to compile into an application (with ``-ffp-contract=off`` for results identical to the
    Python engine's): ``cc -I$(include_dir) app.c $(sources) -lm -lpthread``."""
    return sorted((include_dir() / "core").glob("*.c"))


def load_table(source):
    """A runtime table in the C core: a path or bytes (the C loader's copy, checksums checked), or a dict of
    sections (:func:`pmask.runtime.table.table_arrays`, borrowed without a copy: the table keeps the arrays
    alive; the same checks but checksums); refusals raise :class:`pmask.runtime.table.TableError` with the
    C loader's message."""
    from pmask.runtime.table import TableError

    if _core is None:
        raise InputError("the native servo core is not built in this installation")
    try:
        return _core.Table(source)
    except (ValueError, BufferError) as exc:
        where = "" if isinstance(source, (bytes, bytearray, memoryview, dict)) else f"{source}: "
        raise TableError(f"{where}{exc}") from None


def display_deform(table, u, contacts=(), radius: float = 0.0) -> np.ndarray:
    """The native core's :meth:`pmask.runtime.display.DisplaySurface.deform` for a table exported with a
    display surface (``pm_display_deform``): (m, 3) displaced display points."""
    n = table.display_counts()[0]
    out = np.empty((n, 3))
    c = np.ascontiguousarray([x for x in contacts if x is not None] or np.zeros((0, 3)), float).reshape(-1, 3)
    table.display_deform(np.ascontiguousarray(u, float), c, float(radius), out)
    return out


def zeta_rows(xi_rows: np.ndarray, masks, out: np.ndarray) -> None:
    """The native core's loop of :meth:`pmask.runtime.stiffness.Stiffness.zeta_table` (``pm_zeta_rows``): row
    ``masks.centres[k]`` of ``out`` = Σ_p ρ_p ``xi_rows[j_p]`` over mask k; ``out`` (C-contiguous float64,
    the shape of ``xi_rows``) is written in place."""
    if _core is None:
        raise InputError("the native servo core is not built in this installation")
    if not (out.flags.c_contiguous and out.dtype == np.float64 and out.shape == xi_rows.shape):
        raise ValueError("zeta_rows: out must be a C-contiguous float64 array shaped like xi_rows")
    i64 = lambda a: np.ascontiguousarray(a, dtype=np.int64)  # noqa: E731
    _core.zeta_rows(xi_rows.shape[1], np.ascontiguousarray(xi_rows, dtype=float), i64(masks.centres),
                    i64(masks.indptr), i64(masks.indices), np.ascontiguousarray(masks.values, dtype=float), out)


#: the share of the memory still available (:func:`pmask.runtime.memory.available_memory`) a compressed artifact's
#: Green's functions may take in the native core when coupled contacts need them (:func:`_native_table`)
GREENS_MEMORY_SHARE = 0.5


def _native_table(surface, zeta: bool):
    """The surface's table in the C core, made once per surface (with or without the ζ table).  On a compressed
    artifact ``zeta`` hands over Ξ's compressed sections instead (:func:`pmask.runtime.table.greens_sections`,
    about the artifact's stored bytes, read whole), from which the core forms coupling blocks itself, so that
    its thread never takes the GIL, when they fit in :data:`GREENS_MEMORY_SHARE` of the memory available;
    otherwise none, and the core asks the surface for blocks (:class:`NativeContacts`)."""
    cache = surface.__dict__.setdefault("_native_tables", {})
    key = bool(zeta)
    if key not in cache:
        t = getattr(surface, "table", None)
        if t is not None:  # a surface from a table (ContactSurface.from_table): its own arrays, borrowed
            from pmask.runtime.table import table_arrays

            cache[key] = load_table(table_arrays({k: v for k, v in t.items() if k not in ("meta", "greens") and
                                                  (zeta or k != "zeta")}, t["meta"]))
        else:
            from pmask.runtime.table import surface_sections, table_arrays

            stiff = getattr(surface, "stiffness", None)
            if zeta and hasattr(stiff, "zeta_table") and not surface.compressed:
                stiff.zeta_table(rows=zeta_rows)  # kept by the stiffness: the C loop, 2-3x numpy's
            if zeta and surface.compressed and not _greens_fit(stiff):
                zeta = False
            try:
                sections = surface_sections(surface, zeta)
            except MemoryError:  # the check above is an estimate; the machine had less
                if not (zeta and surface.compressed):
                    raise
                log.warning("out of memory reading the compressed Green's functions for the native core: coupled "
                            "contacts ask Python for their blocks, a tick that asks waiting for the GIL (free memory "
                            "to have the core hold them)")
                sections = surface_sections(surface, False)
            cache[key] = load_table(table_arrays(sections, surface.meta))
    return cache[key]


def _greens_fit(stiff) -> bool:
    """Whether a compressed artifact's Green's functions fit in the native core (:data:`GREENS_MEMORY_SHARE`)."""
    from pmask.runtime.memory import available_memory

    need, avail = stiff.model.Xi.nbytes, available_memory()
    if avail is None or need <= GREENS_MEMORY_SHARE * avail:
        return True
    log.warning("the compressed Green's functions (%.2f GiB) exceed %g of the memory available (%.2f GiB): coupled "
                "contacts in the native core ask Python for their blocks, a tick that asks waiting for the GIL (free "
                "memory, or raise pmask.runtime.servo.GREENS_MEMORY_SHARE, to have the core hold them)",
                need / 2**30, GREENS_MEMORY_SHARE, avail / 2**30)
    return False


class NativeState:
    """One contact's state after a step, as the native core published it (the Python engine's fields)."""

    __slots__ = ("tri", "b", "u_bar", "force", "body_force", "status", "in_contact", "depth", "taper", "sliding",
                 "point")

    def __init__(self, values):
        (self.tri, self.b, self.u_bar, self.force, self.body_force, self.status, self.in_contact, self.depth,
         self.taper, self.sliding, self.point) = values


class NativeContacts:
    """The C step for a validated :class:`pmask.runtime.Contacts` (its options, its surface)."""

    def __init__(self, contacts):
        from pmask.runtime.haptics import Status

        _core.set_statuses(tuple(Status))
        srf = contacts.surface
        self.surface = srf
        self.table = _native_table(srf, zeta=contacts.coupled or srf._coupling is not None)
        c = contacts
        options = (c.friction, c.dynamic_friction, c.damping, c.tool_radius, c.slip_length, float(c.device.rate),
                   c.max_jump, c.decay, c.proxy_speed, c.reset_after, c.max_walk, int(c.passivity), int(c.coupled))
        # coupled without the table's ζ section or Ξ's compressed sections (a compressed Ξ too large for the
        # core's memory, _native_table): the core asks the surface for a pair of triangles' blocks when two
        # contacts first land on them (Ξ's near field and low-rank blocks, never a dense table;
        # pm_servo_create_paired); with either it forms them itself
        pairs = srf.pair_blocks if c.coupled and not self.table.has_greens() and srf.greens else None
        try:
            self.servo = _core.Servo(self.table, c.n, options, self._warn, pairs)
        except ValueError as exc:
            raise InputError(str(exc)) from None
        self.n = c.n
        self.step = self.servo.step
        self.step1 = self.servo.step1
        self.reset = self.servo.reset
        self.has_greens = self.table.has_greens()  # (the ζ table, or a table's compressed Ξ: the deformation)
        self._diag = srf.diag

    @staticmethod
    def _warn(kind, x, y, z):
        if kind == "far":
            log.warning("probe at (%.4g, %.4g, %.4g) is more than %g model sizes from the model: are the probe "
                        "and the model in the same length unit?", x, y, z, 10.0)
        else:
            log.error("internal error in the native haptic step (please report it); holding the last force")

    def state(self, k: int) -> NativeState:
        return NativeState(self.servo.state(k))

    def deformation(self) -> np.ndarray | None:
        """eq. 16 with the display forces, computed by the C core (None without its ζ table or a table's
        compressed Ξ)."""
        if not self.has_greens:
            return None
        out = np.empty((self.surface.n_mesh, 3))
        self.servo.deformation(out)
        return out

    # thread mode
    def start(self, rate: float, spin: float, exchange: bool = False) -> None:
        rc = (self.servo.start_exchange if exchange else self.servo.start)(float(rate), float(spin))
        if rc != 0:
            raise InputError({-1: "the servo thread is already running",
                              -2: f"rate must be in (0, 100 kHz] and spin in [0, 10 ms], got {rate}, {spin}",
                              -4: "could not start the servo thread", -5: "no threads on this platform"}.get(rc, f"error {rc}"))

    def stop(self) -> None:
        self.servo.stop()

    def running(self) -> bool:
        return self.servo.running()

    def set_probes(self, probes) -> None:
        self.servo.set_probes(probes)

    def read(self):
        forces, statuses, (ticks, late, lateness, step_max, idle) = self.servo.read()
        return forces, statuses, {"ticks": ticks, "late": late, "max_lateness": lateness, "step_max": step_max,
                                  "idle": idle}

    def exchange(self, probes, timeout: float):
        return self.servo.exchange(probes, float(timeout))


def table_meta(table) -> dict:
    """The metadata of a table loaded by :func:`load_table`."""
    return json.loads(table.meta())
