r"""Haptic contact at 1 kHz: proxies on the surface, one contact law, several contacts coupled through
the body, a passivity controller, and the deformation a display shows.

One algorithm, written here in plain Python floats and, operation for operation, in C
(``runtime/servo/pmask_servo.c``); :class:`HapticContact` and :class:`Contacts` run the C when it is
built and this code otherwise (``engine="python"`` forces it), and a test requires both to give the
same statuses and forces equal to 1e-12 on recorded probe traces.

Per contact and tick, with the probe p (the tool centre):

1. **Tracking.**  The point of the surface under p along the interpolated vertex normal (a Phong
   projection, p = x + s N(x), continuous over edges where a closest point jumps by depth x dihedral
   angle), found by walking from the proxy's triangle; a spatial grid restarts tracking in O(1).  The
   normals are the area-weighted ones, blended near creases sharper than 30° into normals averaged over
   ``normal_radius`` (deep under a sharp crease the projection is otherwise ill-conditioned).  Contact
   begins when the tool sphere (radius r_tool) crosses the surface from outside.
2. **The proxy** x follows that projection along the surface (a god-object step: across edges, never
   through the body) by at most ``proxy_speed`` (1.25) times the probe's motion per tick.
3. **The contact law** at the proxy, with N = N(x), K = K(x) (eq. 15, rendered: symmetric, the support
   blended, the region tapered by λ), the displacement the tool imposes ū = p − r_tool N − x_a (x_a: the
   proxy, or with friction the material point the tool holds) and the penetration δ = −N·ū:

   - the normal force is λ k_n δ with k_n = 1/(Nᵀ K⁻¹ N), the normal stiffness when the surface may slide
     under the tool (the Schur complement of K's tangential block).  f = K ū pushed the hand sideways by
     0.5–0.8 x the normal force through K's normal–tangential coupling and did net work round closed loops;
   - friction is a spring on the held point's tangential offset w with the tangential stiffness
     k_t = 2λ / (tr K⁻¹ − Nᵀ K⁻¹ N), kept while |k_t w| ≤ μ λ k_n δ and otherwise held on the cone's edge
     while the point slides; μ weakens from μ_s to μ_d over ``slip_length`` of slip, so breaking away is
     continuous.  Bounding the cone by the penetration's own normal force keeps K's coupling from locking
     it (a tangential offset raised the normal force, which widened the cone: a wedge);
   - the tangential term ½ δ² ∇k_n (∇k_n averaged per vertex, interpolated) makes the force the gradient
     of the stored energy ½ λ k_n δ² + ½ k_t |w|²: without it a loop over tissue of varying stiffness gave
     back 3.9 % of its stored energy, with it 0.4 %.
4. **Several contacts** are solved together through the compliance C (3s x 3s): the diagonal blocks the
   local laws' own (so that s = 1 is exactly the single contact), the off-diagonal ones the displacement
   at x_l per unit force at x_k from the Green's functions, C_lk = Σ_i Σ_m φ_i(x_l) φ_m(x_k) ζ_m(i)
   (symmetrised).  Block Gauss–Seidel: each contact applies the law to the displacement left to it,
   ū_l − Σ_{k≠l} C_lk f_k; a contact whose penetration that leaves is ≤ 0 would pull and is released
   (the LCP's complementarity), friction in the same local law (as SOFA's LCP does).
5. **The zero-order hold's first-order error** ½ J Δp (Colgate's kT/2 damping, J the law's stiffness) is
   added, viscous damping b_v (Δp / T), and a **passivity observer/controller** (Hannaford & Ryu): the energy
   the hand has put in, E += f_held · Δp (the force the device held during the last tick), is compared with
   the energy stored, V; beyond a slack of 10 % of V a damper b_pc v (≤ 1 N·s/m, smoothly switched) takes out
   the difference.  Velocities are low-pass filtered over 10 ms and the velocity terms fade with the
   contact (at most half the elastic force), so a kink in the path or the release is not felt as a step.

``step`` never raises: a NaN/inf or malformed sample, or an implausible jump, returns the last good
force decaying and leaves the state alone; a probe far outside the model (wrong units?) gets
``FAR_OUTSIDE``; anything unexpected gets ``INTERNAL_ERROR`` with the decaying force, and is logged.
"""
from __future__ import annotations

import logging
import math
from enum import IntEnum

import numpy as np

from pmask.errors import InputError
from pmask.runtime.device import Device
from pmask.runtime.geometry import contact_normals, triangle_frames, triangle_neighbours
from pmask.runtime.spatial import TriangleGrid
from pmask.runtime.stiffness import zeta_compliance, zeta_deformation

log = logging.getLogger(__name__)


class Status(IntEnum):
    NO_CONTACT = 0      #: probe outside the body (or not tracked): zero force
    CONTACT = 1         #: in contact: force from the contact law
    BAD_SAMPLE = 2      #: NaN/inf or malformed probe sample: last good force, decaying
    JUMP = 3            #: probe moved implausibly far in one step: last good force, decaying
    OUTSIDE_REGION = 4  #: over a triangle without precomputed stiffness (λ = 0): zero force
    FAR_OUTSIDE = 5     #: probe more than 10 model sizes away: are probe and model in the same units?
    REGION_EDGE = 6     #: in contact where the force tapers out at the edge of the contact region (0 < λ < 1)
    INTERNAL_ERROR = 7  #: a bug: last good force, decaying (logged)


#: Gauss-Seidel sweeps of the several-contact solve (s = 1 needs one); both engines run exactly this many
#: unless the forces stop changing (relative 1e-13), which both test the same way
GS_SWEEPS = 60
#: the far-outside test: distance from the model's bounding box, in bounding-box diagonals
FAR_FACTOR = 10.0
#: the passivity observer's slack, relative to the stored energy.  Within a triangle the shaded normal N
#: differs from the exact gradient of the projection depth by up to half a dihedral angle, so the work
#: done and the stored energy drift apart and meet again (±3-6 % over a tour circle, ±8-10 % over 300
#: ticks of the 35 mm/s stroke, measured); the controller acts only beyond this slack (2 % turned that
#: drift into 10-40 % dissipation per loop and a rough force), so it catches sustained generation (a
#: device bouncing on a stiff support) and bounds what a closed loop can give back to twice the slack.
#: The loops themselves give back < 1 % (measured on the tour) because the force is the stored energy's
#: gradient (normal and ½ δ² ∇k_n) with the zero-order hold's first-order error removed.
PASSIVITY_SLACK = 0.10
#: the velocity estimate of the velocity terms (zero-order-hold compensation, damping, the controller):
#: Δp low-pass filtered over ~1/VELOCITY_FILTER ticks (10 ms), so that a kink in the probe's path
#: changes them over several ticks instead of one
VELOCITY_FILTER = 0.1
#: the controller is a virtual damper b_pc v whose coefficient follows what the deficit needs with a
#: time constant of PC_RAMP_TICKS ticks, so that it is never felt switching on (a one-tick correction
#: changed the force by up to half of it); 1 N·s/m is a fifth of what CHAI3D's device descriptions allow
#: as virtual damping, and 6x the kT/2 that a 350 N/m support needs at 1 kHz
PC_DAMPING_MAX = 1.0
PC_RAMP_TICKS = 50
#: thread mode: the servo thread sleeps to this many seconds before each tick and spins the rest.  On this
#: 2-core VM with a busy Python thread beside it, a real-time thread woken from sleep began 0.3 % of its
#: ticks more than a period late (up to 10 ms); sleeping to 200 µs before and spinning left 0-1 ticks in
#: 15,000 more than 1 ms late.  It costs a fifth of a core at 1 kHz.
SPIN = 2e-4


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


class Surface:
    """What the contact algorithm reads of a stiffness: the mesh, triangle frames and neighbours, contact
    normals, per-vertex rendered K, taper λ and ∇k_n, a spatial grid, and (for several contacts and the
    display) the ζ table.  The arrays are what a runtime table stores (:mod:`pmask.runtime.table`), and
    :meth:`from_table` rebuilds a Surface from one; plain-Python copies serve the per-tick code.

    stiffness : a :class:`pmask.runtime.stiffness.Stiffness` (or any ``SurfaceStiffness``).
    normal_radius : see :class:`Contacts` (default 3 mask radii, or 6 mean edges without masks).
    """

    def __init__(self, stiffness, normal_radius: float | None = None):
        P = np.asarray(stiffness.points, float)
        T = np.asarray(stiffness.triangles, np.int64)
        frames = triangle_frames(P, T)
        e = np.linalg.norm(P[T[:, 1]] - P[T[:, 0]], axis=1)
        mean_edge = float(e.mean()) if len(e) else 1.0
        if normal_radius is None:  # 3 mask radii (a single-vertex mask or a bare surface: 6 mean edges)
            masks = getattr(stiffness, "masks", None)
            r = getattr(masks, "radius", 0.0) if masks is not None else 0.0
            normal_radius = 3.0 * (r if r > 0 else 2.0 * mean_edge)
        normals = contact_normals(P, T, float(normal_radius))
        K = np.asarray(stiffness.K_vertex, float).reshape(len(P), 9)
        taper = np.asarray(getattr(stiffness, "taper", np.ones(len(P))), float)
        gradient = normal_stiffness_gradient(P, T, normals, K, taper, frames[:, 3:6], frames[:, 6:9])
        grid = TriangleGrid(P, T, frames=frames)
        lo, hi = P.min(axis=0), P.max(axis=0)
        self._setup(P, T, frames, triangle_neighbours(T), normals, K, taper, gradient, grid, lo, hi,
                    mean_edge, float(np.linalg.norm(hi - lo)), float(normal_radius))
        self.stiffness = stiffness
        self.meta = {}

    @classmethod
    def from_table(cls, table) -> "Surface":
        """A Surface from a runtime table (:func:`pmask.runtime.table.read_table`'s result or a path)."""
        from pmask.runtime.table import read_table

        t = table if isinstance(table, dict) else read_table(table)
        P, T = t["points"], t["triangles"]
        grid = TriangleGrid(P, T, frames=t["frames"])
        mean_edge, diag = (float(x) for x in t["lengths"][0])
        srf = cls.__new__(cls)
        srf._setup(P, T, t["frames"], t["neighbours"], t["normals"], t["stiffness"], t["taper"][:, 0], t["gradient"],
                   grid, t["bounds"][0], t["bounds"][1], mean_edge, diag, float(t["meta"].get("normal_radius", 0.0)))
        srf.stiffness = None
        srf.meta = t["meta"]
        if not isinstance(table, (dict, bytes, bytearray, memoryview)):  # the native core loads the same file
            srf.table_source, srf.table_sections = str(table), frozenset(t)
        if "zeta" in t:
            srf._coupling = (t["zeta"], t["contact_row"][:, 0])
        return srf

    def _setup(self, P, T, frames, neighbours, normals, K, taper, gradient, grid, lo, hi, mean_edge, diag,
               normal_radius):
        c = np.ascontiguousarray
        self.P, self.T = c(P, dtype=float), c(T, dtype=np.int64)
        self.tri_geom = c(frames, dtype=float)
        self.neighbours = c(neighbours, dtype=np.int64)
        self.vertex_normals = c(normals, dtype=float)
        self.K = c(np.reshape(K, (len(P), 9)), dtype=float)
        self.taper = c(taper, dtype=float)
        self.gradient = c(gradient, dtype=float)
        self.grid = grid
        self.lo, self.hi = np.asarray(lo, float), np.asarray(hi, float)
        self.mean_edge, self.diag, self.normal_radius = float(mean_edge), float(diag), float(normal_radius)
        # plain-Python views for the per-tick code
        self._tri = [tuple(r) for r in self.tri_geom.tolist()]
        self._nb = [tuple(r) for r in self.neighbours.tolist()]
        self._idx = [tuple(r) for r in self.T.tolist()]
        self._P = [tuple(r) for r in self.P.tolist()]
        self._N = [tuple(r) for r in self.vertex_normals.tolist()]
        self._K = [tuple(r) for r in self.K.tolist()]
        self._lam = self.taper.tolist()
        self._G = [tuple(r) for r in self.gradient.tolist()]
        self._coupling = None
        self._row = None

    def coupling(self):
        """(ζ table, surface vertex -> its row in the table) for the coupled solve and the display;
        None for a surface stiffness without Green's functions."""
        if self._coupling is None and self.stiffness is not None and hasattr(self.stiffness, "zeta_table"):
            self._coupling = (self.stiffness.zeta_table(), self.stiffness._contact_row)
        return self._coupling

    def compliance(self, t_l, b_l, t_k, b_k) -> list:
        """C_lk (9 floats): :func:`pmask.runtime.stiffness.zeta_compliance` on this surface's ζ table."""
        Zt, row = self.coupling()
        if self._row is None:
            self._row = np.asarray(row).tolist()
        return zeta_compliance(Zt, self._row, self._idx, t_l, b_l, t_k, b_k)

    def deformation_of(self, loads) -> np.ndarray:
        """The surface's displacement (n_s, 3) for point loads (eq. 16; :func:`zeta_deformation`)."""
        if getattr(self.stiffness, "compressed", False):  # no ζ table: Ξ's blocks of the loaded columns
            return self.stiffness.deformation_of(loads)
        Zt, row = self.coupling()
        return zeta_deformation(Zt, row, self.T, loads)


def normal_stiffness_gradient(P, T, VN, K, taper, dual_a, dual_b) -> np.ndarray:
    """(n_s, 3): the surface gradient of the normal stiffness k_n = λ / (nᵀ K⁻¹ n), per vertex.

    On each triangle, the gradient of the linear interpolant of the vertex values (∇φ_1 = a, ∇φ_2 = b,
    ∇φ_0 = −a − b with a, b the duals of the edges); at a vertex, the area-weighted mean over its
    triangles.  Interpolated (eq. 15's way) and projected on the tangent plane, it gives the tangential
    force ½ δ² ∇k_n that makes the frictionless force the gradient of the stored energy ½ k_n δ²
    (continuous across edges, unlike the per-triangle gradient, which jumps by a few % of the force)."""
    Kv = K.reshape(-1, 3, 3)
    Ki = np.linalg.inv(Kv + 1e-300 * np.eye(3))
    k = taper / np.maximum(np.einsum("vi,vij,vj->v", VN, Ki, VN), 1e-300)
    g_t = (k[T[:, 1]] - k[T[:, 0]])[:, None] * dual_a + (k[T[:, 2]] - k[T[:, 0]])[:, None] * dual_b
    area = 0.5 * np.linalg.norm(np.cross(P[T[:, 1]] - P[T[:, 0]], P[T[:, 2]] - P[T[:, 0]]), axis=1)
    g = np.zeros_like(P)
    w = np.zeros(len(P))
    for c in range(3):
        np.add.at(g, T[:, c], area[:, None] * g_t)
        np.add.at(w, T[:, c], area)
    return g / np.maximum(w, 1e-300)[:, None]


class _State:
    """One contact's state between ticks (the same fields as the C struct)."""

    def __init__(self):
        self.reset()

    def reset(self):
        self.tri = -1                     # proxy triangle (the probe's projection, rate-limited), -1 when not
        self.b = (1.0, 0.0, 0.0)          # tracking; proxy barycentrics
        self.anchor = None                # with friction: the material point the tool holds (x, y, z)
        self.in_contact = False
        self.above = False                # the probe was seen outside the body since tracking began
        self.sliding = False
        self.slip = 0.0                   # how far the anchor has slid since it broke away
        self.last = None                  # last good probe sample
        self.move = (0.0, 0.0, 0.0)       # the probe's motion since the sample before
        self.vel = (0.0, 0.0, 0.0)        # that motion, low-pass filtered (the damping terms' velocity x T)
        self.target = None                # this tick's projection (triangle, b0, b1, b2) while in contact
        self.bad = 0                      # consecutive implausible samples
        self.law_force = (0.0, 0.0, 0.0)  # the contact law's force at the last tick (the coupled solve's start)
        self.force = (0.0, 0.0, 0.0)      # force rendered to the user (−f)
        self.good_force = (0.0, 0.0, 0.0)
        self.body_force = (0.0, 0.0, 0.0)  # force on the body held during the next tick (PC's work)
        self.u_bar = (0.0, 0.0, 0.0)      # the surface's displacement at the contact (the law's ū' plus what
                                          # the other contacts move it): what the display meets
        self.depth = 0.0
        self.taper = 0.0
        self.status = Status.NO_CONTACT


class Contacts:
    """s instruments in contact with one body, coupled through its Green's functions.

    stiffness : a :class:`pmask.runtime.stiffness.Stiffness` (or any ``SurfaceStiffness``; without Green's
        functions the contacts are solved independently).
    n : how many instruments.
    friction : static Coulomb coefficient μ_s (0: frictionless); dynamic_friction : μ_d (default μ_s).
    damping : viscous damping b_v [N·s/m] on the probe's velocity while in contact.
    tool_radius : the radius of the spherical tool tip r_tool [model units]: it rests on the surface.
    slip_length : friction weakens from μ_s to μ_d over this much slip after breakaway [model units]
        (default a quarter of the mean edge length), so that breaking away is continuous.
    device : a :class:`pmask.runtime.Device` (servo rate for velocities; default 1 kHz).
    passivity : the passivity observer/controller (default on).
    max_jump : largest plausible probe move per tick [model units]; default 5 mean edge lengths.
    decay : factor per tick on the last good force while samples are bad; reset_after : after this many
        implausible samples in a row, tracking restarts.
    proxy_speed : the proxy moves at most this many times the probe's own motion per tick.
    normal_radius : near a crease sharper than 30°, the contact normal blends into the normal averaged over
        a ball of this radius (default: 3 mask radii; :func:`pmask.runtime.geometry.contact_normals`).  The
        Phong projection is well conditioned only above the crease's focal depth (~ radius / angle); at the
        kidney's hilum lip, probed 5 mm deep, 1 mask radius left the force turning 7x faster than pressing
        on free tissue does, 3 radii brought it in line.
    coupled : solve several contacts together (default: when the stiffness has Green's functions).
    engine : "native" (the C core; refused if it is not built), "python", or None (native if built).
    """

    def __init__(self, stiffness, n: int = 1, *, friction=0.0, dynamic_friction=None, damping=0.0,
                 tool_radius=0.0, slip_length=None, device: Device | None = None, passivity: bool = True, max_jump=None,
                 decay=0.9, reset_after: int = 50, max_walk: int = 24, proxy_speed=1.25, coupled=None,
                 normal_radius=None, engine: str | None = None):
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
        if normal_radius is not None:
            normal_radius = _num("normal_radius", normal_radius)
        self.surface = stiffness if isinstance(stiffness, Surface) else Surface(stiffness, normal_radius)
        s = self.surface
        self.tool_radius = _num("tool_radius", tool_radius, hi=0.5 * s.diag)
        self.max_jump = 5.0 * s.mean_edge if max_jump is None else _num("max_jump", max_jump, lo=0.0, lo_open=True)
        self.slip_length = (0.25 * s.mean_edge if slip_length is None
                            else _num("slip_length", slip_length, lo=0.0, lo_open=True))
        self.coupled = (s.coupling() is not None and self.n > 1) if coupled is None else bool(coupled)
        if self.coupled and s.coupling() is None:
            raise InputError("coupled contacts need Green's functions (a Stiffness from Model.stiffness)")
        self._margin = 2.0 * self.max_jump + self.tool_radius
        self._energy = 0.0
        self._pc_damping = 0.0
        self._far_warned = False
        self._trace = None  # a list to record (contact, law's force, output body force, δ, λ) per tick
        self._states = [_State() for _ in range(self.n)]
        self.engine = "python"
        self._native = None
        self._thread = None
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
                self._hold(st, Status.INTERNAL_ERROR)
        return [st.force for st in self._states], [st.status for st in self._states]

    @property
    def states(self) -> list:
        """Each contact after the last step (``tri``, ``b``, ``u_bar``, ``force``, ``body_force``, ``status``,
        ``in_contact``, ``depth``, ``taper``, ``sliding``), from whichever engine runs."""
        if self._native is not None:
            return [self._native.state(k) for k in range(self.n)]
        return self._states

    # ------------------------------------------------------------------ thread mode
    def start(self, rate: float | None = None, spin: float = SPIN) -> None:
        """Run the step on a thread of its own at ``rate`` Hz (default the device's), on the probes last given
        to :meth:`set_probes`; :meth:`read` returns the latest forces.  With the native core the thread is a
        native one (a real-time priority where the process may have one): its ticks never take the GIL, so
        Python threads beside it (graphics, I/O) cannot delay them.  Without it, a Python thread runs the
        Python step (the same API; its ticks share the GIL).  ``spin``: the thread sleeps to this many seconds
        before each tick and spins the rest (:data:`SPIN`; 0 sleeps only)."""
        rate = float(self.device.rate if rate is None else _num("rate", rate, lo=0.0, lo_open=True, hi=1e5))
        spin = _num("spin", spin, hi=0.01)
        if self.running:
            raise InputError("the servo thread is already running")
        if self._native is not None:
            self._native.start(rate, spin)
        else:
            self._thread = _PythonServoThread(self, rate, spin)
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
        """The probe samples the servo thread uses from its next tick (never blocks the thread)."""
        if self._native is not None:
            self._native.set_probes(probes)
        elif self._thread is not None:
            self._thread.probes = probes
        else:
            raise InputError("set_probes() needs a running servo thread: start() it first")

    def read(self):
        """(forces, statuses) of the servo thread's latest tick."""
        if self._native is not None:
            return self._native.read()[:2]
        return [st.force for st in self._states], [st.status for st in self._states]

    def tick_stats(self) -> dict:
        """The servo thread's timing: ticks, late (a force not ready within its own period, or a tick
        skipped), max_lateness and step_max [s]."""
        if self._native is not None:
            return self._native.read()[2]
        t = self._thread
        if t is not None:
            return dict(t.stats)
        return getattr(self, "_last_stats", {"ticks": 0, "late": 0, "max_lateness": 0.0, "step_max": 0.0})

    # ------------------------------------------------------------------ geometry (same as the C)
    def _project(self, t, px, py, pz):
        """Phong projection onto triangle t's plane: p = x + s N(x); returns (b0, b1, b2, s).  Two
        fixed-point steps from the flat projection (each contracts by about depth x normal variation /
        edge length, ~0.05 at haptic depths)."""
        ox, oy, oz, ax, ay, az, bx, by, bz, nx, ny, nz = self.surface._tri[t]
        i0, i1, i2 = self.surface._idx[t]
        VN = self.surface._N
        n0x, n0y, n0z = VN[i0]
        n1x, n1y, n1z = VN[i1]
        n2x, n2y, n2z = VN[i2]
        dx, dy, dz = px - ox, py - oy, pz - oz
        h = nx * dx + ny * dy + nz * dz
        b1 = ax * dx + ay * dy + az * dz
        b2 = bx * dx + by * dy + bz * dz
        s = h
        for _ in range(2):
            b0 = 1.0 - b1 - b2
            Nx = b0 * n0x + b1 * n1x + b2 * n2x
            Ny = b0 * n0y + b1 * n1y + b2 * n2y
            Nz = b0 * n0z + b1 * n1z + b2 * n2z
            hn = Nx * nx + Ny * ny + Nz * nz
            if hn < 0.1:  # normals turned away from the face: keep the flat projection
                break
            s = h / hn
            qx, qy, qz = dx - s * Nx, dy - s * Ny, dz - s * Nz
            b1 = ax * qx + ay * qy + az * qz
            b2 = bx * qx + by * qy + bz * qz
        return 1.0 - b1 - b2, b1, b2, s

    def _locate(self, t, px, py, pz, retry=True):
        """Walk from triangle t to the one holding the projection of p; return (t, b0, b1, b2, s).

        Two triangles that send the walk to each other hold p's projection on their shared edge (the gap
        of a convex edge) unless the projection map folds there (normals blended near a crease): then the
        spatial grid's nearest triangle restarts the walk, once."""
        prev = -1
        nbs = self.surface._nb
        for _ in range(self.max_walk):
            b0, b1, b2, s = self._project(t, px, py, pz)
            if b0 >= 0.0 and b1 >= 0.0 and b2 >= 0.0:
                return t, b0, b1, b2, s
            k = 0 if (b0 <= b1 and b0 <= b2) else (1 if b1 <= b2 else 2)
            nb = nbs[t][k]
            if nb < 0 or nb == prev:
                if retry:
                    near = self.surface.grid.nearest((px, py, pz))
                    if near != t and near != prev:
                        return self._locate(near, px, py, pz, retry=False)
                break  # a ridge or an open edge: clamp onto t (already projected)
            prev, t = t, nb
        else:
            b0, b1, b2, s = self._project(t, px, py, pz)  # walk budget spent: clamp where it ended
        b0, b1, b2 = max(b0, 0.0), max(b1, 0.0), max(b2, 0.0)
        tot = b0 + b1 + b2
        return t, b0 / tot, b1 / tot, b2 / tot, s

    def _point(self, t, b0, b1, b2):
        i0, i1, i2 = self.surface._idx[t]
        P = self.surface._P
        a, b, c = P[i0], P[i1], P[i2]
        return (b0 * a[0] + b1 * b[0] + b2 * c[0], b0 * a[1] + b1 * b[1] + b2 * c[1],
                b0 * a[2] + b1 * b[2] + b2 * c[2])

    def _normal(self, t, b0, b1, b2):
        """Unit interpolated (shaded) normal at barycentric b of triangle t."""
        i0, i1, i2 = self.surface._idx[t]
        VN = self.surface._N
        a, b, c = VN[i0], VN[i1], VN[i2]
        x = b0 * a[0] + b1 * b[0] + b2 * c[0]
        y = b0 * a[1] + b1 * b[1] + b2 * c[1]
        z = b0 * a[2] + b1 * b[2] + b2 * c[2]
        r = math.sqrt(x * x + y * y + z * z)
        return x / r, y / r, z / r

    def _stiffness(self, t, b0, b1, b2):
        """K(x) (eq. 15, 9 floats row-major), λ(x) and the interpolated ∇k_n at barycentric b of triangle t."""
        i0, i1, i2 = self.surface._idx[t]
        KK, G = self.surface._K, self.surface._G
        k0, k1, k2 = KK[i0], KK[i1], KK[i2]
        lam = self.surface._lam
        K = [b0 * k0[i] + b1 * k1[i] + b2 * k2[i] for i in range(9)]
        g0, g1, g2 = G[i0], G[i1], G[i2]
        g = (b0 * g0[0] + b1 * g1[0] + b2 * g2[0], b0 * g0[1] + b1 * g1[1] + b2 * g2[1],
             b0 * g0[2] + b1 * g1[2] + b2 * g2[2])
        return K, b0 * lam[i0] + b1 * lam[i1] + b2 * lam[i2], g

    # ------------------------------------------------------------------ the tick
    def _hold(self, st, status):
        d = self.decay
        g = st.good_force
        st.good_force = (g[0] * d, g[1] * d, g[2] * d)
        st.force = st.good_force
        st.body_force = (-st.force[0], -st.force[1], -st.force[2])
        st.status = status

    def _none(self, st, status=Status.NO_CONTACT):
        st.force = st.good_force = st.body_force = st.law_force = (0.0, 0.0, 0.0)
        st.u_bar = (0.0, 0.0, 0.0)
        st.depth = 0.0
        st.taper = 0.0
        st.sliding = False
        st.anchor = None
        st.slip = 0.0
        st.status = status

    def _move_proxy(self, st, tx, ty, tz, limit):
        """Slide the proxy along the surface towards the point (tx, ty, tz), by a path of length at most
        ``limit`` (a god-object step): in each triangle towards the target's flat projection on its plane,
        across an edge into the neighbour when the straight path leaves the triangle."""
        surf = self.surface
        t, (b0, b1, b2) = st.tri, st.b
        remaining = limit
        for _ in range(self.max_walk):
            ox, oy, oz, ax, ay, az, bx, by, bz, _, _, _ = surf._tri[t]
            dx, dy, dz = tx - ox, ty - oy, tz - oz
            q1 = ax * dx + ay * dy + az * dz  # the target's flat projection on t's plane, barycentric
            q2 = bx * dx + by * dy + bz * dz
            d0, d1, d2 = (1.0 - q1 - q2) - b0, q1 - b1, q2 - b2
            i0, i1, i2 = surf._idx[t]
            P = surf._P
            v0, v1, v2 = P[i0], P[i1], P[i2]
            ex = d0 * v0[0] + d1 * v1[0] + d2 * v2[0]
            ey = d0 * v0[1] + d1 * v1[1] + d2 * v2[1]
            ez = d0 * v0[2] + d1 * v1[2] + d2 * v2[2]
            dist = math.sqrt(ex * ex + ey * ey + ez * ez)
            if dist <= 0.0 or remaining <= 0.0:
                break
            a = min(1.0, remaining / dist)  # how far along towards the target this step may go
            exit_k, exit_a = -1, a
            for k, (bk, dk) in enumerate(((b0, d0), (b1, d1), (b2, d2))):
                if dk < 0.0 and bk + exit_a * dk < 0.0:
                    exit_a, exit_k = -bk / dk, k
            b0, b1, b2 = b0 + exit_a * d0, b1 + exit_a * d1, b2 + exit_a * d2
            remaining -= exit_a * dist
            if exit_k < 0:
                break
            nb = surf._nb[t][exit_k]
            if nb < 0:
                break  # an open edge: stay on it
            bs = [b0, b1, b2]
            bs[exit_k] = 0.0
            w = {surf._idx[t][k]: bs[k] for k in range(3)}
            t = nb
            b0, b1, b2 = (w.get(v, 0.0) for v in surf._idx[t])
        b0, b1, b2 = max(b0, 0.0), max(b1, 0.0), max(b2, 0.0)
        tot = b0 + b1 + b2
        st.tri, st.b = t, (b0 / tot, b1 / tot, b2 / tot)

    def _prepare(self, st, sample):
        """Steps 1 (tracking) of one contact.  Returns the probe as a tuple and whether the contact is active."""
        try:
            px, py, pz = (float(c) for c in sample)
        except Exception:  # not three numbers (None, a string, an object whose __float__ raises, 10**400)
            self._hold(st, Status.BAD_SAMPLE)
            return None, False
        if not (math.isfinite(px) and math.isfinite(py) and math.isfinite(pz)):
            self._hold(st, Status.BAD_SAMPLE)
            return None, False
        last = st.last
        if last is not None:
            dx, dy, dz = abs(px - last[0]), abs(py - last[1]), abs(pz - last[2])
            mj = self.max_jump  # the per-axis test first: no overflow for absurd samples
            if dx > mj or dy > mj or dz > mj or dx * dx + dy * dy + dz * dz > mj * mj:
                st.bad += 1
                if st.bad <= self.reset_after:
                    self._hold(st, Status.JUMP)
                    return None, False
                st.reset()  # tracking restarts here: the jump is not a motion
                last = None
        st.bad = 0
        s = self.surface
        lo, hi = s.lo, s.hi
        gx = max(lo[0] - px, px - hi[0], 0.0)
        gy = max(lo[1] - py, py - hi[1], 0.0)
        gz = max(lo[2] - pz, pz - hi[2], 0.0)
        st.move = (px - last[0], py - last[1], pz - last[2]) if last is not None else (0.0, 0.0, 0.0)
        a, v = VELOCITY_FILTER, st.vel
        st.vel = (v[0] + a * (st.move[0] - v[0]), v[1] + a * (st.move[1] - v[1]), v[2] + a * (st.move[2] - v[2]))
        st.last = (px, py, pz)
        st.target = None
        far = FAR_FACTOR * s.diag  # per axis first: no overflow for absurd samples
        if gx > far or gy > far or gz > far or gx * gx + gy * gy + gz * gz > far * far:
            if not self._far_warned:
                log.warning("probe at (%.4g, %.4g, %.4g) is more than %g model sizes from the model (size %.3g): "
                            "are the probe and the model in the same length unit?", px, py, pz, FAR_FACTOR, s.diag)
                self._far_warned = True
            st.tri, st.in_contact, st.above = -1, False, False
            self._none(st, Status.FAR_OUTSIDE)
            return None, False
        m = self._margin
        if gx > m or gy > m or gz > m:
            st.tri, st.in_contact, st.above = -1, False, False
            self._none(st)
            return None, False
        r = self.tool_radius
        if st.tri < 0:  # (re)start tracking
            t = s.grid.nearest((px, py, pz))
            t, b0, b1, b2, h = self._locate(t, px, py, pz)
            st.tri, st.b = t, (b0, b1, b2)
            st.above = h >= r  # starting inside the body is not a contact
            self._none(st)
            return None, False
        t, b0, b1, b2, h = self._locate(st.tri, px, py, pz)
        if not st.in_contact:
            st.tri, st.b = t, (b0, b1, b2)
            if h >= r or not st.above:
                st.above = st.above or h >= r
                self._none(st)
                return None, False
            st.in_contact, st.sliding = True, False  # crossed the surface: the proxy is born at the projection
            st.anchor, st.slip = None, 0.0
            st.body_force = (0.0, 0.0, 0.0)
            return (px, py, pz), True
        st.target = (t, b0, b1, b2)  # the contact ends where the penetration at the proxy reaches zero
        return (px, py, pz), True

    def _local(self, st, geo, ux, uy, uz):
        """The contact law (step 2) for the displacement (ux, uy, uz) left to this contact.
        Returns (f on the body, ū' after the law, sliding, penetration δ)."""
        Nx, Ny, Nz, K, Ki, lam, _ = geo
        delta = -(Nx * ux + Ny * uy + Nz * uz)
        if delta <= 0.0 or lam <= 0.0:
            return (0.0, 0.0, 0.0), (ux, uy, uz), False, 0.0
        nkn = (Nx * (Ki[0] * Nx + Ki[1] * Ny + Ki[2] * Nz) + Ny * (Ki[3] * Nx + Ki[4] * Ny + Ki[5] * Nz)
               + Nz * (Ki[6] * Nx + Ki[7] * Ny + Ki[8] * Nz))
        fc = lam * delta / nkn  # the normal force: λ k_n δ, k_n = 1/(Nᵀ K⁻¹ N)
        fx, fy, fz = -fc * Nx, -fc * Ny, -fc * Nz
        if self._frictionless:
            return (fx, fy, fz), (-delta * Nx, -delta * Ny, -delta * Nz), True, delta
        # friction: a tangential spring on the anchor's offset w, stiffness k_t = 2λ / (tr K⁻¹ − Nᵀ K⁻¹ N)
        # (the tangential stiffness with the normal force free), bounded by μ f_c; the tool drags the point
        # it holds, so the force on the body is along w, as the normal part is along ū's normal part
        wx, wy, wz = ux + delta * Nx, uy + delta * Ny, uz + delta * Nz
        kt = 2.0 * lam / (Ki[0] + Ki[4] + Ki[8] - nkn)
        tx, ty, tz = kt * wx, kt * wy, kt * wz
        ft = math.sqrt(tx * tx + ty * ty + tz * tz)
        # friction weakens with slip from μ_s to μ_d: a continuous breakaway
        mu = (self.dynamic_friction + (self.friction - self.dynamic_friction) * math.exp(-st.slip / self.slip_length)
              if st.sliding else self.friction)
        if ft <= mu * fc:  # stick: inside the cone
            return (fx + tx, fy + ty, fz + tz), (ux, uy, uz), False, delta
        c = mu * fc / ft  # slide: on the cone's edge, the anchor moves so that the spring holds it there
        tx, ty, tz = c * tx, c * ty, c * tz
        return ((fx + tx, fy + ty, fz + tz), (-delta * Nx + tx / kt, -delta * Ny + ty / kt, -delta * Nz + tz / kt),
                True, delta)

    def _geometry(self, st, p):
        """N, K, K⁻¹, λ, ∇k_n at the proxy, and ū = p − r_tool N − x_a with x_a the proxy (frictionless) or
        the anchor the tool holds (step 2's inputs)."""
        t, (b0, b1, b2) = st.tri, st.b
        Nx, Ny, Nz = self._normal(t, b0, b1, b2)
        K, lam, (gx, gy, gz) = self._stiffness(t, b0, b1, b2)
        Ki = _inverse3(K)
        gn = gx * Nx + gy * Ny + gz * Nz  # on the tangent plane
        cx, cy, cz = self._point(t, b0, b1, b2)
        if st.anchor is not None:  # the anchor, kept on the tangent plane at the proxy (it would drift off a
            ax, ay, az = st.anchor  # curved surface as it slides along successive tangent planes)
            an = Nx * (ax - cx) + Ny * (ay - cy) + Nz * (az - cz)
            cx, cy, cz = ax - an * Nx, ay - an * Ny, az - an * Nz
            st.anchor = (cx, cy, cz)
        r = self.tool_radius
        return ((Nx, Ny, Nz, K, Ki, lam, (gx - gn * Nx, gy - gn * Ny, gz - gn * Nz)),
                (p[0] - r * Nx - cx, p[1] - r * Ny - cy, p[2] - r * Nz - cz))

    def _step(self, samples):
        states = self._states
        probes = [self._prepare(st, smp) for st, smp in zip(states, samples)]
        frictionless = self._frictionless
        geo, ubar, active = {}, {}, []
        for l, (p, ok) in enumerate(probes):
            if not ok:
                continue
            st = states[l]
            if st.target is not None:  # the proxy follows the projection, at most proxy_speed |Δp| a tick
                self._move_proxy(st, *self._point(*st.target), self.proxy_speed * _norm(st.move))
            if not frictionless and st.anchor is None:  # contact begins: the tool holds the point under it
                st.anchor = self._point(st.tri, *st.b)
            g, u = self._geometry(st, p)
            if g[5] <= 0.0:  # λ = 0 here: outside the precomputed region, no force; the proxy follows the probe
                if not frictionless and st.target is not None:
                    self._move_proxy(st, *self._point(*st.target), self.proxy_speed * _norm(st.move))
                self._none(st, Status.OUTSIDE_REGION)
                continue
            geo[l], ubar[l] = g, u
            active.append(l)
        if not active:
            self._energy, self._pc_damping = 0.0, 0.0
            return
        result = self._solve(active, geo, ubar)
        for l in list(active):
            (f, u2, sliding, delta), ueff = result[l]
            if delta <= 0.0:  # the tool is out at the proxy: the contact ends, with zero force already
                st = states[l]
                if st.target is not None:
                    st.tri, st.b = st.target[0], st.target[1:]
                st.in_contact, st.above = False, True
                self._none(st)
                active.remove(l)
        if not active:
            self._energy, self._pc_damping = 0.0, 0.0
            return
        # each contact's displacement of the surface: the law's own ū' plus what the others' forces move it,
        # (ū − ū left to it); the display meets it, and ½ Σ f·u is the coupled body's stored energy
        total = {}
        for l in active:
            (f, u2, _, _), ueff = result[l]
            u = ubar[l]
            total[l] = (u2[0] + (u[0] - ueff[0]), u2[1] + (u[1] - ueff[1]), u2[2] + (u[2] - ueff[2]))
        # the passivity observer: the hand's work through the held forces against the energy stored
        stored, work, motion2 = 0.0, 0.0, 0.0
        for l in active:
            st = states[l]
            (f, _, _, _), _ = result[l]
            u2 = total[l]
            dpx, dpy, dpz = st.move
            vx, vy, vz = st.vel
            motion2 += vx * vx + vy * vy + vz * vz
            hb = st.body_force
            work += hb[0] * dpx + hb[1] * dpy + hb[2] * dpz
            stored += 0.5 * (f[0] * u2[0] + f[1] * u2[1] + f[2] * u2[2])
        slack = PASSIVITY_SLACK * stored
        energy = min(self._energy + work, stored + slack) if self.passivity else stored
        deficit = stored - slack - energy
        rate = self.device.rate
        if self.passivity:  # the damping that would dissipate the deficit in one tick at this speed, capped
            need = PC_DAMPING_MAX if motion2 <= 0.0 else min(PC_DAMPING_MAX, deficit * rate / motion2)
            want = need if deficit > 0.0 else 0.0
            self._pc_damping += (want - self._pc_damping) / PC_RAMP_TICKS
        bpc = self._pc_damping * rate
        for l in active:
            st = states[l]
            (f, u2, sliding, delta), ueff = result[l]
            Nx, Ny, Nz, K, Ki, lam, (gx, gy, gz) = geo[l]
            dpx, dpy, dpz = st.vel  # the velocity terms use the filtered motion
            bx, by, bz = f
            hd = 0.5 * delta * delta  # the stored energy's gradient along the surface: ½ δ² ∇k_n
            bx, by, bz = bx + hd * gx, by + hd * gy, bz + hd * gz
            # the zero-order hold's first-order error, ½ J Δp (Colgate's kT/2): J = λ k_n N Nᵀ, plus k_t on the
            # tangent plane while friction holds
            nkn = (Nx * (Ki[0] * Nx + Ki[1] * Ny + Ki[2] * Nz) + Ny * (Ki[3] * Nx + Ki[4] * Ny + Ki[5] * Nz)
                   + Nz * (Ki[6] * Nx + Ki[7] * Ny + Ki[8] * Nz))
            dn = Nx * dpx + Ny * dpy + Nz * dpz
            hz = 0.5 * lam / nkn * dn
            vx, vy, vz = hz * Nx, hz * Ny, hz * Nz
            if not sliding:
                ht = lam / (Ki[0] + Ki[4] + Ki[8] - nkn)  # ½ k_t
                vx, vy, vz = vx + ht * (dpx - dn * Nx), vy + ht * (dpy - dn * Ny), vz + ht * (dpz - dn * Nz)
            bv = lam * self.damping * rate + bpc  # viscous damping and the controller's, on Δp / T
            vx, vy, vz = vx + bv * dpx, vy + bv * dpy, vz + bv * dpz
            # the velocity terms fade with the contact: at most half the elastic force (as a Hunt-Crossley
            # damping scales with the penetration), so that they reach zero with it at release
            vm = math.sqrt(vx * vx + vy * vy + vz * vz)
            fm = 0.5 * math.sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2])
            if vm > fm:
                c = fm / vm
                vx, vy, vz = c * vx, c * vy, c * vz
            bx, by, bz = bx + vx, by + vy, bz + vz
            if not (math.isfinite(bx) and math.isfinite(by) and math.isfinite(bz)):
                raise FloatingPointError("non-finite contact force")  # never sent to a device
            if self._trace is not None:
                self._trace.append((l, f, (bx, by, bz), delta, lam))
            st.body_force = (bx, by, bz)
            st.force = st.good_force = (-bx, -by, -bz)
            st.u_bar, st.depth, st.taper, st.sliding = total[l], delta, lam, sliding
            st.status = Status.CONTACT if lam >= 1.0 - 1e-9 else Status.REGION_EDGE
            if sliding and not frictionless:  # the anchor slides by the tangential part of (ū left to it) − ū'
                mx, my, mz = ueff[0] - u2[0], ueff[1] - u2[1], ueff[2] - u2[2]
                mn = mx * Nx + my * Ny + mz * Nz
                mx, my, mz = mx - mn * Nx, my - mn * Ny, mz - mn * Nz
                ax, ay, az = st.anchor
                st.anchor = (ax + mx, ay + my, az + mz)
                st.slip += math.sqrt(mx * mx + my * my + mz * mz)
            elif not sliding:
                st.slip = 0.0
        self._energy = energy

    def _solve(self, active, geo, ubar):
        """Step 3: the contact law for every active contact, the several coupled by block Gauss-Seidel on
        the compliance (one sweep when uncoupled).  Returns {l: ((f, ū', sliding, δ), ū left to l)}."""
        states = self._states
        coupling = self._coupling_blocks(active) if self.coupled and len(active) > 1 else None
        if coupling and self._frictionless:
            force = self._normal_start(active, geo, ubar, coupling)
        else:
            force = {l: states[l].law_force for l in active}  # warm start: last tick's forces
        result = {}
        for _ in range(GS_SWEEPS if coupling else 1):
            change, size = 0.0, 0.0
            for l in active:
                ux, uy, uz = ubar[l]
                if coupling:
                    for k in active:
                        if k != l:
                            C, (gx, gy, gz) = coupling[(l, k)], force[k]
                            ux -= C[0] * gx + C[1] * gy + C[2] * gz
                            uy -= C[3] * gx + C[4] * gy + C[5] * gz
                            uz -= C[6] * gx + C[7] * gy + C[8] * gz
                res = self._local(states[l], geo[l], ux, uy, uz)
                old = force[l]
                force[l] = res[0]
                result[l] = (res, (ux, uy, uz))
                change = max(change, abs(res[0][0] - old[0]), abs(res[0][1] - old[1]), abs(res[0][2] - old[2]))
                size = max(size, abs(res[0][0]), abs(res[0][1]), abs(res[0][2]))
            if change <= 1e-13 * size:
                break
        for l in active:
            states[l].law_force = force[l]
        return result

    def _normal_start(self, active, geo, ubar, coupling):
        """Frictionless contacts' start for the sweeps: the normal forces φ (f_l = −φ_l N_l) that solve the
        coupled normal problem with every active contact pressing, A φ = δ̄ with A_ll = Nᵀ K⁻¹ N / λ (the law's
        own compliance), A_lk = N_lᵀ C_lk N_k and δ̄_l = −N_l · ū_l (the Delassus system, symmetric positive
        definite: Gaussian elimination without pivoting), clipped at zero.  When no contact would pull
        (the usual case) this is the solution and the sweeps stop after one; otherwise they release the
        pulling ones from there.  (From last tick's forces the sweeps took 12-15 to converge to 1e-13.)"""
        s = len(active)
        A = [[0.0] * s for _ in range(s)]
        r = [0.0] * s
        for x, l in enumerate(active):
            Nx, Ny, Nz, K, Ki, lam, _ = geo[l]
            nkn = (Nx * (Ki[0] * Nx + Ki[1] * Ny + Ki[2] * Nz) + Ny * (Ki[3] * Nx + Ki[4] * Ny + Ki[5] * Nz)
                   + Nz * (Ki[6] * Nx + Ki[7] * Ny + Ki[8] * Nz))
            A[x][x] = nkn / lam
            ux, uy, uz = ubar[l]
            r[x] = -(Nx * ux + Ny * uy + Nz * uz)
            for y, k in enumerate(active):
                if k != l:
                    C = coupling[(l, k)]
                    Mx, My, Mz = geo[k][0], geo[k][1], geo[k][2]
                    cx = C[0] * Mx + C[1] * My + C[2] * Mz
                    cy = C[3] * Mx + C[4] * My + C[5] * Mz
                    cz = C[6] * Mx + C[7] * My + C[8] * Mz
                    A[x][y] = Nx * cx + Ny * cy + Nz * cz
        phi = _solve_spd(A, r)
        out = {}
        for x, l in enumerate(active):
            p = 0.0 if phi is None else max(phi[x], 0.0)
            Nx, Ny, Nz = geo[l][0], geo[l][1], geo[l][2]
            out[l] = (-p * Nx, -p * Ny, -p * Nz)
        return out

    def _coupling_blocks(self, active):
        """C_lk (symmetrised, 9 floats row-major) for every ordered pair of active contacts."""
        st, srf = self._states, self.surface
        out = {}
        for a in active:
            for b in active:
                if a < b:
                    C = srf.compliance(st[a].tri, st[a].b, st[b].tri, st[b].b)
                    Ct = srf.compliance(st[b].tri, st[b].b, st[a].tri, st[a].b)
                    S = [0.5 * (C[3 * i + j] + Ct[3 * j + i]) for i in range(3) for j in range(3)]
                    out[(a, b)] = S
                    out[(b, a)] = [S[3 * j + i] for i in range(3) for j in range(3)]
        return out

    # ------------------------------------------------------------------ display
    def deformation(self) -> np.ndarray:
        """The surface displacement (n_s, 3) for the contacts as they are after the last step (eq. 16),
        with display forces that make the interpolated response meet every contact's displacement ū'
        exactly: C_disp f_disp = ū', C_disp the exact interpolation of the ζ table (its diagonal blocks
        are Σ_i Σ_m φ_i φ_m ζ_m(i) rather than the inverse of eq. 15's K, which differ by 5-10 % between
        vertices).  Zero where nothing is in contact."""
        if self.surface.coupling() is None:
            raise InputError("deformation needs Green's functions (a Stiffness from Model.stiffness, or a "
                             "runtime table exported with its zeta table)")
        if self._native is not None and self._native.has_zeta:
            return self._native.deformation()
        loads = self.display_loads()
        return self.surface.deformation_of(loads) if loads else np.zeros((len(self.surface.P), 3))

    def display_loads(self):
        """[(triangle, barycentrics, display force), ...] for the active contacts (see :meth:`deformation`)."""
        act = [st for st in self.states if st.status in (Status.CONTACT, Status.REGION_EDGE)]
        if not act:
            return []
        s = len(act)
        C = np.zeros((3 * s, 3 * s))
        for i, a in enumerate(act):
            for j, b in enumerate(act):
                C[3 * i:3 * i + 3, 3 * j:3 * j + 3] = np.reshape(self.surface.compliance(a.tri, a.b, b.tri, b.b), (3, 3))
        u = np.concatenate([np.asarray(st.u_bar) for st in act])
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

    def __init__(self, contacts, rate, spin):
        import threading

        self.contacts, self.period, self.spin = contacts, 1.0 / rate, min(spin, 0.5 / rate)
        self.probes = [None] * contacts.n
        self.stats = {"ticks": 0, "late": 0, "max_lateness": 0.0, "step_max": 0.0}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="pmask-servo", daemon=True)

    def start(self):
        self._thread.start()

    def stop(self):
        self._stop.set()
        self._thread.join()

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


def _sub(a, b):
    return a[0] - b[0], a[1] - b[1], a[2] - b[2]


def _norm(v):
    return math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


def _solve_spd(A, r):
    """x with A x = r by Gaussian elimination without pivoting (A symmetric positive definite), in place;
    None if a pivot is not positive.  The native core runs the same operations in the same order."""
    s = len(r)
    for k in range(s):
        p = A[k][k]
        if not p > 0.0:
            return None
        for i in range(k + 1, s):
            q = A[i][k] / p
            for j in range(k + 1, s):
                A[i][j] = A[i][j] - q * A[k][j]
            r[i] = r[i] - q * r[k]
    x = [0.0] * s
    for i in range(s - 1, -1, -1):
        acc = r[i]
        for j in range(i + 1, s):
            acc = acc - A[i][j] * x[j]
        x[i] = acc / A[i][i]
    return x


def _inverse3(K):
    """Inverse of a 3x3 matrix (9 floats row-major) by cofactors; a singular one gives zeros."""
    a, b, c, d, e, f, g, h, i = K
    A, B, C = e * i - f * h, -(d * i - f * g), d * h - e * g
    det = a * A + b * B + c * C
    if det == 0.0 or not math.isfinite(det):
        return [0.0] * 9
    r = 1.0 / det
    return [A * r, -(b * i - c * h) * r, (b * f - c * e) * r,
            B * r, (a * i - c * g) * r, -(a * f - c * d) * r,
            C * r, -(a * h - b * g) * r, (a * e - b * d) * r]


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
        return self._point(st.tri, *st.b)

    def _state(self):
        return self._native.state(0) if self._native is not None else self._states[0]

    triangle = property(lambda self: self._state().tri)
    bary = property(lambda self: self._state().b)
    u_bar = property(lambda self: self._state().u_bar)
    force = property(lambda self: self._state().force)
    body_force = property(lambda self: self._state().body_force)
    status = property(lambda self: self._state().status)
    in_contact = property(lambda self: self._state().in_contact)
    depth = property(lambda self: self._state().depth)
    taper = property(lambda self: self._state().taper)
    sliding = property(lambda self: self._state().sliding)
