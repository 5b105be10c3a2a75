r"""Haptic contact at 1 kHz: proxies on the surface, one contact law, several contacts coupled through
the body, a passivity controller, and the deformation a display shows.

:class:`Contacts` (s instruments) and :class:`HapticContact` (one) validate the options, hold the state and
run each tick as four steps, one module each in :mod:`pmask.runtime.contact`:

1. tracking and the proxy (:mod:`~pmask.runtime.contact.tracking`),
2. the contact law with friction (:mod:`~pmask.runtime.contact.law`),
3. several contacts solved together (:mod:`~pmask.runtime.contact.coupling`),
4. the zero-order hold, damping and the passivity controller (:mod:`~pmask.runtime.contact.output`).

The same algorithm runs, operation for operation, in C (``runtime/servo/core/``, one file per step); these
classes run the C when it is built and the Python steps otherwise (``engine="python"`` forces them), and a
test requires both to give the same statuses and forces equal to 1e-12 on recorded probe traces.

``step`` never raises: a NaN/inf or malformed sample, or an implausible jump, returns the last good force
decaying and leaves the state alone; a probe far outside the model (wrong units?) gets ``FAR_OUTSIDE``;
anything unexpected gets ``INTERNAL_ERROR`` with the decaying force, and is logged.
"""
from __future__ import annotations

import logging
import math

import numpy as np

from pmask.errors import InputError
from pmask.runtime.contact import coupling, law, output, tracking
from pmask.runtime.contact.state import PROXY_SPEED, SPIN, TOUCHING, ContactState, Status, hold, release
from pmask.runtime.contact.surface import ContactSurface
from pmask.runtime.device import Device

log = logging.getLogger(__name__)

__all__ = ["Contacts", "HapticContact", "Status", "ContactSurface"]


def _num(name, v, lo=0.0, lo_open=False, hi=math.inf):
    try:
        x = float(v)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{name} must be a number, got {v!r}") from None
    if not math.isfinite(x) or x < lo or (lo_open and x == lo) or x > hi:
        rng = f"{'>' if lo_open else '>='} {lo:g}" + (f" and <= {hi:g}" if hi < math.inf else "")
        raise InputError(f"{name} must be a finite number {rng}, got {v!r}")
    return x


def _int(name, v, lo=1):
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
        raise InputError(f"{name} must be a whole number >= {lo}, got {v!r}")
    return int(v)


def _levels(v):
    """The contact surface's subdivision levels: a whole number 0..MAX_LEVELS or "auto" (None)."""
    from pmask.runtime.contact.subdivision import MAX_LEVELS

    if isinstance(v, str) and v == "auto":
        return None
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 0 <= v <= MAX_LEVELS:
        raise InputError(f"levels must be a whole number from 0 to {MAX_LEVELS} or 'auto', got {v!r}")
    return int(v)


class Contacts:
    """s instruments in contact with one body, coupled through its Green's functions.

    Parameters
    ----------
    stiffness
        a :class:`pmask.runtime.stiffness.Stiffness` (or any ``SurfaceStiffness``; without Green's
        functions the contacts are solved independently).
    n
        how many instruments.
    friction
        static Coulomb coefficient μ_s (0: frictionless); dynamic_friction : μ_d (default μ_s).
    damping
        viscous damping b_v [N·s/m] on the probe's velocity while in contact.
    tool_radius
        the radius of the spherical tool tip r_tool [model units]: it rests on the surface.
    slip_length
        friction weakens from μ_s to μ_d over this much slip after breakaway [model units]
        (default a quarter of the mean edge length), so that breaking away is continuous.
    device
        a :class:`pmask.runtime.Device` (servo rate for velocities; default 1 kHz).
    passivity
        the passivity observer/controller (default on).
    max_jump
        largest plausible probe move per tick [model units]; default 5 mean edge lengths.
    decay
        factor per tick on the last good force while samples are bad; reset_after : after this many
        implausible samples in a row, tracking restarts.
    proxy_speed
        the proxy moves at most this many times the probe's own motion per tick (default 1.75: the speed of the
        probe's projection 0.43 radii of curvature deep; deeper than half a radius the proxy moves by dead
        reckoning instead, :func:`pmask.runtime.contact.tracking.follow`).
    normal_radius
        near a crease sharper than 30°, the contact normal blends into the normal averaged over
        a ball of this radius (default: 3 mask radii; :func:`pmask.runtime.geometry.contact_normals`).  The
        Phong projection is well conditioned only above the crease's focal depth (~ radius / angle); at the
        kidney's hilum lip, probed 5 mm deep, 1 mask radius left the force turning 7x faster than pressing
        on free tissue does, 3 radii brought it in line.
    levels
        the contact surface: "auto" (default) the mesh's Loop subdivision surface after the fewest levels that bring
        the angle between its facets and the interpolated contact normals within 3.5° (two on the default kidney;
        none on a mesh fine enough already; at most 400,000 triangles); n the surface after n levels (0: the
        finite-element mesh's own triangles).  It passes through the mesh's vertices
        (:mod:`pmask.runtime.contact.subdivision`), and K_i and λ ride on it linearly from the mesh (eq. 15), so
        the law is the gradient of its energy to within that small angle.  Measured on the default kidney's grid
        of closed loops (tests/test_passivity_grid.py), controller off: at most 0.22 % of a loop's energy given
        back on the default surface, 1.78 % on the mesh.
    coupled
        solve several contacts together (default: when the stiffness has Green's functions).
    engine
        "native" (the C core; refused if it is not built), "python", or None (native if built).
    """

    def __init__(self, stiffness, n: int = 1, *, friction=0.0, dynamic_friction=None, damping=0.0,
                 tool_radius=0.0, slip_length=None, device: Device | None = None, passivity: bool = True, max_jump=None,
                 decay=0.9, reset_after: int = 50, max_walk: int = 24, proxy_speed=PROXY_SPEED, coupled=None,
                 normal_radius=None, levels="auto", engine: str | None = None):
        self.n = _int("n", n)
        self.friction = _num("friction", friction)
        self.dynamic_friction = self.friction if dynamic_friction is None else _num("dynamic_friction", dynamic_friction)
        self.damping = _num("damping", damping)
        self.decay = _num("decay", decay, hi=1.0)
        if self.decay >= 1.0:
            raise InputError(f"decay must lie in [0, 1), got {decay!r}")
        self.reset_after = _int("reset_after", reset_after)
        self.max_walk = _int("max_walk", max_walk)
        self.proxy_speed = _num("proxy_speed", proxy_speed, lo=1.0)
        self.device = Device() if device is None else device
        if not isinstance(self.device, Device):
            raise InputError(f"device must be a pmask.runtime.Device, got {device!r}")
        self.passivity = bool(passivity)
        self._frictionless = self.friction == 0.0 and self.dynamic_friction == 0.0
        self._pair_blocks = {}  # (a, b) -> (mesh triangle a, mesh triangle b, their vertex-pair blocks): coupling.py
        if normal_radius is not None:
            normal_radius = _num("normal_radius", normal_radius)
        levels = _levels(levels)
        self.surface = (stiffness if isinstance(stiffness, ContactSurface)
                        else ContactSurface.of(stiffness, normal_radius, levels))
        s = self.surface
        self.tool_radius = _num("tool_radius", tool_radius, hi=0.5 * s.diag)
        self.max_jump = 5.0 * s.mean_edge if max_jump is None else _num("max_jump", max_jump, lo=0.0, lo_open=True)
        self.slip_length = (0.25 * s.mean_edge if slip_length is None
                            else _num("slip_length", slip_length, lo=0.0, lo_open=True))
        self.coupled = (s.greens and self.n > 1) if coupled is None else bool(coupled)
        if self.coupled and not s.greens:
            raise InputError("coupled contacts need Green's functions (a Stiffness from Model.stiffness)")
        self._margin = 2.0 * self.max_jump + self.tool_radius
        self._energy = 0.0
        self._pc_damping = 0.0
        self._far_warned = False
        self._trace = None  # a list to record (contact, law's force, output body force, δ, λ) per tick
        self._states = [ContactState() for _ in range(self.n)]
        self.engine = "python"
        self._native = None
        self._thread = None
        self._exchange = False
        if engine not in (None, "native", "python"):
            raise InputError(f"engine must be 'native', 'python' or None, got {engine!r}")
        if engine != "python":
            servo = _servo_module()
            if servo is not None and servo.available():
                self._native = servo.NativeContacts(self)
                self.engine = "native"
                self.step = self._native.step  # the C step straight from the caller: no Python frame between
            elif engine == "native":
                raise InputError("engine='native' but the native servo core is not built (no compiler at "
                                 "install time?); pip install the package again with a C compiler present")
        if self._native is None:
            s.python_views()  # the Python steps' plain-Python copies now, not on the first tick

    # ------------------------------------------------------------------ public
    def reset(self) -> None:
        """Forget all contact state (not while the servo thread runs)."""
        if self.running:
            raise InputError("reset() while the servo thread runs: stop() it first")
        for st in self._states:
            st.reset()
        self._energy = 0.0
        self._pc_damping = 0.0
        if self._native is not None:
            self._native.reset()

    def step(self, probes):
        """One tick: a probe sample per instrument; returns (forces on the users, statuses).  Never raises."""
        try:
            samples = list(probes)
            if len(samples) != self.n:
                raise ValueError("wrong count")
        except Exception:
            samples = [None] * self.n
        try:
            self._step(samples)
        except Exception:  # a bug: never let it reach the servo loop
            log.exception("internal error in the haptic step (please report it); holding the last force")
            for st in self._states:
                hold(self, st, Status.INTERNAL_ERROR)
        return [st.force for st in self._states], [st.status for st in self._states]

    @property
    def states(self) -> list:
        """Each contact after the last step (``tri``, ``b``, ``u_bar``, ``force``, ``body_force``, ``status``,
        ``in_contact``, ``depth``, ``taper``, ``sliding``), from whichever engine runs."""
        if self._native is not None:
            return [self._native.state(k) for k in range(self.n)]
        return self._states

    # ------------------------------------------------------------------ thread mode
    def start(self, rate: float | None = None, spin: float = SPIN, *, exchange: bool = False) -> None:
        """Run the step on a thread of its own at ``rate`` Hz (default the device's).

        By default the thread steps on the probes last given to :meth:`set_probes` and :meth:`read` returns the
        latest forces: for a display or a loop that only needs the newest force.  With ``exchange=True`` each
        sample given to :meth:`exchange` is used by exactly one tick, in order, and :meth:`exchange` returns that
        tick's forces: a device loop in Python gets the thread's timing and the forces :meth:`step` would give on
        the same samples (a tick with no sample waiting runs no step: ``tick_stats()["idle"]``).

        With the native core the thread is a native one (a real-time priority where the process may have one):
        its ticks never take the GIL, so Python threads beside it (graphics, I/O) cannot delay them (on a
        compressed artifact the core holds Ξ's compressed sections; only where they would take more than half the
        memory available does a tick whose coupled contacts land on a new pair of triangles take the GIL to ask
        for their blocks: the large-organs guide).  Without it, a Python thread runs the Python step (the same
        API; its ticks share the GIL).  ``spin``: the thread
        sleeps to this many seconds before each tick and spins the rest (:data:`SPIN`; 0 sleeps only)."""
        rate = float(self.device.rate if rate is None else _num("rate", rate, lo=0.0, lo_open=True, hi=1e5))
        spin = _num("spin", spin, hi=0.01)
        if self.running:
            raise InputError("the servo thread is already running")
        self._exchange = bool(exchange)
        if self._native is not None:
            self._native.start(rate, spin, self._exchange)
        else:
            self._thread = _PythonServoThread(self, rate, spin, self._exchange)
            self._thread.start()

    def stop(self) -> None:
        """Stop the servo thread (waits for its current tick)."""
        if self._native is not None:
            self._native.stop()
        elif self._thread is not None:
            self._thread.stop()
            self._last_stats = dict(self._thread.stats)
            self._thread = None

    @property
    def running(self) -> bool:
        if self._native is not None:
            return self._native.running()
        return self._thread is not None

    def set_probes(self, probes) -> None:
        """The probe samples the servo thread uses from its next tick (never blocks the thread; from any
        thread)."""
        if not self.running:
            raise InputError("set_probes() needs a running servo thread: start() it first")
        if self._exchange:
            raise InputError("the servo thread runs in exchange mode: give samples with exchange()")
        if self._native is not None:
            self._native.set_probes(probes)
        else:
            self._thread.probes = probes

    def exchange(self, probes, timeout: float = 0.1):
        """Tick-synchronous: queue one sample per instrument, wait for the tick that uses it (at most one period
        plus what is queued before it; the GIL is released meanwhile) and return that tick's (forces, statuses).
        Needs ``start(exchange=True)``.  Raises :class:`~pmask.errors.InputError` if no tick answers within
        ``timeout`` seconds (the thread is stalled)."""
        if not self.running or not self._exchange:
            raise InputError("exchange() needs the servo thread started with start(exchange=True)")
        timeout = _num("timeout", timeout, lo=0.0, lo_open=True, hi=3600.0)
        out = (self._native.exchange(probes, timeout) if self._native is not None
               else self._thread.exchange(probes, timeout))
        if out is None:
            raise InputError(f"no servo tick answered within {timeout:g} s (is the machine overloaded?)")
        return out

    def read(self):
        """(forces, statuses) of the servo thread's latest tick."""
        if self._native is not None:
            return self._native.read()[:2]
        return [st.force for st in self._states], [st.status for st in self._states]

    def tick_stats(self) -> dict:
        """The servo thread's timing: ticks, late (a force not ready within its own period, or a tick
        skipped), max_lateness and step_max [s], idle (exchange mode: ticks with no sample waiting)."""
        if self._native is not None:
            return self._native.read()[2]
        t = self._thread
        if t is not None:
            return dict(t.stats)
        return getattr(self, "_last_stats", {"ticks": 0, "late": 0, "max_lateness": 0.0, "step_max": 0.0,
                                             "idle": 0})

    # ------------------------------------------------------------------ the tick
    def _step(self, samples):
        states = self._states
        probes = [tracking.prepare(self, st, smp) for st, smp in zip(states, samples)]  # step 1
        frictionless = self._frictionless
        geo, ubar, active = {}, {}, []
        for l, (p, ok) in enumerate(probes):
            if not ok:
                continue
            st = states[l]
            tracking.follow(self, st)  # the proxy follows the projection, at most proxy_speed |Δp| a tick
            if not frictionless and st.anchor is None:  # contact begins: the tool holds the point under it
                st.anchor = tracking.point(self.surface, st.tri, *st.b)
            g, u = law.geometry(self, st, p)
            if g[law.GEO_LAM] <= 0.0:  # λ = 0 here: outside the precomputed region, no force; the proxy follows the probe
                if not frictionless:
                    tracking.follow(self, st)
                release(st, Status.OUTSIDE_REGION)
                continue
            geo[l], ubar[l] = g, u
            active.append(l)
        if not active:
            self._energy, self._pc_damping = 0.0, 0.0
            return
        result = coupling.solve(self, states, active, geo, ubar)  # steps 2 and 3
        for l in list(active):
            g, (ux, uy, uz) = geo[l], ubar[l]
            if g[0] * ux + g[1] * uy + g[2] * uz >= 0.0:  # the tool is out at the proxy: the contact ends (a
                st = states[l]  # contact the others' pushes carried away from its tool stays, with no force)
                if st.target is not None:
                    st.tri, st.b = st.target[0], st.target[1:]
                st.in_contact, st.above = False, True
                release(st)
                active.remove(l)
        if not active:
            self._energy, self._pc_damping = 0.0, 0.0
            return
        output.render(self, states, active, geo, ubar, result)  # step 4

    # ------------------------------------------------------------------ display
    def deformation(self) -> np.ndarray:
        """The surface displacement (n_s, 3) for the contacts as they are after the last step (eq. 16),
        with display forces that make the interpolated response meet every contact's displacement ū'
        exactly: C_disp f_disp = ū', C_disp the exact interpolation of the ζ table (its diagonal blocks
        are Σ_i Σ_m φ_i φ_m ζ_m(i) rather than the inverse of eq. 15's K, which differ by 5-10 % between
        vertices).  On a subdivided contact surface the mesh point under a contact lies off the contact point
        by the subdivision's offset (:meth:`ContactSurface.mesh_offset`), and it is moved by ū' plus that
        offset, so that the shown mesh meets the instrument where the contact surface does: draw it on
        ``surface.mesh_points`` (the mesh's points, except near a crease, which the contact surface rounds).  Zero
        where nothing is in contact."""
        if not self.surface.greens:
            raise InputError("deformation needs Green's functions (a Stiffness from Model.stiffness, or a "
                             "runtime table exported with its zeta table)")
        if self._native is not None and self._native.has_greens:
            return self._native.deformation()
        loads = self.display_loads()
        return self.surface.deformation_of(loads) if loads else np.zeros((self.surface.n_mesh, 3))

    def display_loads(self):
        """[(triangle, barycentrics, display force), ...] for the active contacts (see :meth:`deformation`)."""
        act = [st for st in self.states if st.status in TOUCHING]
        if not act:
            return []
        s = len(act)
        C = np.zeros((3 * s, 3 * s))
        for i, a in enumerate(act):
            for j, b in enumerate(act):
                C[3 * i:3 * i + 3, 3 * j:3 * j + 3] = np.reshape(self.surface.compliance(a.tri, a.b, b.tri, b.b), (3, 3))
        u = np.concatenate([np.add(st.u_bar, self.surface.mesh_offset(st.tri, st.b)) for st in act])
        try:
            f = np.linalg.solve(C, u)
        except np.linalg.LinAlgError:
            f = np.concatenate([-np.asarray(st.force) for st in act])
        if not np.all(np.isfinite(f)):
            f = np.concatenate([-np.asarray(st.force) for st in act])
        return [(st.tri, np.asarray(st.b), f[3 * i:3 * i + 3]) for i, st in enumerate(act)]


class _PythonServoThread:
    """The Python engine's thread mode: the step at a set rate on an absolute schedule (the native core's
    rules for late ticks), sharing the GIL with the other Python threads."""

    def __init__(self, contacts, rate, spin, exchange=False):
        import collections
        import threading

        self.contacts, self.period, self.spin = contacts, 1.0 / rate, min(spin, 0.5 / rate)
        self.probes = [None] * contacts.n
        self.stats = {"ticks": 0, "late": 0, "max_lateness": 0.0, "step_max": 0.0, "idle": 0}
        self.exchange_mode = exchange
        self._queue = collections.deque()      # (sample, answer slot) waiting for a tick
        self._answered = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="pmask-servo", daemon=True)

    def start(self):
        self._thread.start()

    def stop(self):
        self._stop.set()
        self._thread.join()

    def exchange(self, probes, timeout):
        slot = [None]
        with self._answered:
            self._queue.append((probes, slot))
            self._answered.wait_for(lambda: slot[0] is not None, timeout)
        return slot[0]

    def _run(self):
        import time

        T, st = self.period, self.stats
        nxt = time.perf_counter() + T
        while not self._stop.is_set():
            delay = nxt - self.spin - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            while time.perf_counter() < nxt:
                pass
            begin = time.perf_counter()
            if self.exchange_mode:
                try:
                    probes, slot = self._queue.popleft()
                except IndexError:
                    probes = slot = None
                    st["idle"] += 1
                if slot is not None:
                    forces, statuses = Contacts.step(self.contacts, probes)
                    with self._answered:
                        slot[0] = (list(forces), list(statuses))
                        self._answered.notify_all()
            else:
                Contacts.step(self.contacts, self.probes)
            end = time.perf_counter()
            st["ticks"] += 1
            st["late"] += end > nxt + T
            st["max_lateness"] = max(st["max_lateness"], begin - nxt)
            st["step_max"] = max(st["step_max"], end - begin)
            nxt += T
            if end > nxt:
                behind = math.floor((end - nxt) / T) + 1
                st["late"] += behind
                nxt += behind * T


def _servo_module():
    """The native servo core's binding, or None where it is not part of this installation yet."""
    try:
        from pmask.runtime import servo
    except ImportError:
        return None
    return servo


class HapticContact(Contacts):
    """One instrument: ``step(probe)`` returns (force on the user, Status).  See :class:`Contacts` for the
    options and the module docstring for the algorithm.  ``triangle``, ``bary``, ``u_bar``, ``force``,
    ``body_force``, ``status``, ``in_contact``, ``depth``, ``taper``, ``sliding`` describe the contact
    after the last step."""

    def __init__(self, stiffness, **options):
        super().__init__(stiffness, 1, **options)
        if self._native is not None:
            self.step = self._native.step1

    def step(self, probe):
        """One tick: the probe sample; returns (force on the user, Status).  Never raises."""
        forces, statuses = Contacts.step(self, [probe])
        return forces[0], statuses[0]

    @property
    def proxy(self):
        """The proxy's position on the surface (x, y, z), None when not tracking."""
        st = self._state()
        if st.tri < 0:
            return None
        return tracking.point(self.surface, st.tri, *st.b)

    def _state(self):
        return self._native.state(0) if self._native is not None else self._states[0]

    @property
    def triangle(self):
        """The mesh triangle the proxy lies in (an index into the model's surface triangles), -1 when not
        tracking; :attr:`bary` its barycentrics there (the contact surface's own triangle: ``_state().tri``)."""
        t = self._state().tri
        return self.surface.mesh_point(t, *self._state().b)[0] if t >= 0 else t

    @property
    def bary(self):
        st = self._state()
        return tuple(self.surface.mesh_point(st.tri, *st.b)[1:]) if st.tri >= 0 else st.b

    u_bar = property(lambda self: self._state().u_bar)
    force = property(lambda self: self._state().force)
    body_force = property(lambda self: self._state().body_force)
    status = property(lambda self: self._state().status)
    in_contact = property(lambda self: self._state().in_contact)
    depth = property(lambda self: self._state().depth)
    taper = property(lambda self: self._state().taper)
    sliding = property(lambda self: self._state().sliding)
