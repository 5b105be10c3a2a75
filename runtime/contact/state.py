"""What a contact is between ticks: its :class:`Status`, its :class:`ContactState`, and the constants both
engines share (``runtime/servo/core/pm_internal.h`` defines the same numbers)."""
from __future__ import annotations

from enum import IntEnum


class Status(IntEnum):
    NO_CONTACT = 0      #: probe outside the body (or not tracked): zero force
    CONTACT = 1         #: in contact: force from the contact law
    BAD_SAMPLE = 2      #: NaN/inf or malformed probe sample: last good force, decaying
    JUMP = 3            #: probe moved implausibly far in one step: last good force, decaying
    OUTSIDE_REGION = 4  #: over a triangle without precomputed stiffness (λ = 0): zero force
    FAR_OUTSIDE = 5     #: probe more than 10 model sizes away: are probe and model in the same units?
    REGION_EDGE = 6     #: in contact where the force tapers out at the edge of the contact region (0 < λ < 1)
    INTERNAL_ERROR = 7  #: a bug: last good force, decaying (logged)
    DEEP = 8            #: deeper than the linear contact is meaningful (δ ≥ δ_lin): the force keeps growing
                        #: along the normal (:mod:`pmask.runtime.contact.law`)


#: the statuses of a contact that presses (a force from the law, shown on the display)
TOUCHING = (Status.CONTACT, Status.REGION_EDGE, Status.DEEP)


#: Gauss-Seidel sweeps of the several-contact solve (s = 1 needs one); both engines run exactly this many
#: unless the forces stop changing (relative 1e-13), which both test the same way
GS_SWEEPS = 60
#: the default ``proxy_speed``: the proxy moves at most this many times the probe's motion a tick.  On a convex part
#: the projection of a probe δ deep runs 1 / (1 − δ/R) as fast as the probe; 1.75 keeps up with it to 0.43 R, near
#: where the proxy moves by dead reckoning (R/2, speed 2: linalg3.FOCAL_FRACTION).  1.25 before lagged past R/5, and
#: the lag dragged a frictionless slide (out and back across the hilum's lip 2 mm deep: 2.2x the press's work lost,
#: 0.41x with 1.75 and the law of then); 2 let a 45° push at the hilum's saddle lose 0.03 % of its force for a few
#: ticks while the proxy ran to softer tissue (tests/test_deep.py), which the issue forbids
PROXY_SPEED = 1.75
#: the far-outside test: distance from the model's bounding box, in bounding-box diagonals
FAR_FACTOR = 10.0
#: the passivity observer's slack, relative to the stored energy.  Within a triangle the shaded normal N
#: differs from the exact gradient of the projection depth by up to half a dihedral angle, so the work
#: done and the stored energy drift apart and meet again (±3-6 % over a tour circle, ±8-10 % over 300
#: ticks of the 35 mm/s stroke, measured); the controller acts only beyond this slack (2 % turned that
#: drift into 10-40 % dissipation per loop and a rough force), so it catches sustained generation (a
#: device bouncing on a stiff support) and bounds what a closed loop can give back to twice the slack.
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
#: past δ_lin, once a press stops pushing on, the factor that held its force up keeps this share of its excess
#: over 1 a tick (output.py): a 10-tick time constant, so that letting go of the hold is not felt as a step
DEEP_RELEASE = 0.9
#: thread mode: the servo thread sleeps to this many seconds before each tick and spins the rest.  On a
#: 2-core VM with a busy Python thread beside it, a real-time thread woken from sleep began 0.3 % of its
#: ticks more than a period late (up to 10 ms); sleeping to 200 µs before and spinning left 0-1 ticks in
#: 15,000 more than 1 ms late.  It costs a fifth of a core at 1 kHz.
SPIN = 2e-4


class ContactState:
    """One contact's state between ticks (the same fields as the C ``cstate``)."""

    def __init__(self):
        self.reset()

    def reset(self):
        self.tri = -1                     # proxy triangle (the probe's projection, rate-limited), -1 when not
        self.b = (1.0, 0.0, 0.0)          # tracking; proxy barycentrics
        self.anchor = None                # with friction: the material point the tool holds (x, y, z)
        self.frozen = False               # past δ_t: increments of depth at the stiffness k* where it began
        self.frozen_depth = 0.0           # δ*: δ_t, or δ when it froze past δ_t (law.py)
        self.frozen_stiffness = 0.0       # k* = k there
        self.hold_scale = 1.0             # the deep hold (past δ_lin, or short of it on a press): the factor on
        self.hold_peak = 0.0              # the force that keeps a deeper press from feeling softer, and the
        #                                   magnitude it held (output.py)
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


def hold(c, st: ContactState, status: Status) -> None:
    """The last good force, decaying by ``c.decay`` per tick (bad samples, jumps, internal errors)."""
    d = c.decay
    g = st.good_force
    st.good_force = (g[0] * d, g[1] * d, g[2] * d)
    st.force = st.good_force
    st.body_force = (-st.force[0], -st.force[1], -st.force[2])
    st.status = status


def release(st: ContactState, status: Status = Status.NO_CONTACT) -> None:
    """No force: the contact's per-contact quantities back to zero (tracking kept)."""
    st.force = st.good_force = st.body_force = st.law_force = (0.0, 0.0, 0.0)
    st.u_bar = (0.0, 0.0, 0.0)
    st.depth = 0.0
    st.taper = 0.0
    st.sliding = False
    st.anchor = None
    st.frozen = False
    st.hold_scale, st.hold_peak = 1.0, 0.0
    st.slip = 0.0
    st.status = status
