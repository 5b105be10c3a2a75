r"""Step 4, the force sent: the zero-order hold's error, damping and the passivity observer/controller.

The law's force plus the tangential term ½ δ² (I − δ_f S)⁻¹ ∇k (which makes the frictionless force the gradient
of the stored energy ½ k δ², :mod:`pmask.runtime.contact.law`) and, frictionless, the **proxy-offset term**
φ (I − δ_f S)⁻¹ S e: e = P (x − p) is how far the proxy x is off the probe's normal line, which it is where its
speed is limited or it moves by dead reckoning (:func:`pmask.runtime.contact.tracking.follow`); the penetration at
the proxy then changes by (S e) · dx as the proxy moves, by dx = (I − δ_f S)⁻¹ P dp, so the energy's gradient has
this term too (faded out towards the focal depth: :func:`pmask.runtime.contact.linalg3.lag_weight`).  Then three
velocity terms on the probe's motion Δp (low-pass filtered over 10 ms):

- the zero-order hold's first-order error ½ J Δp (Colgate's kT/2 damping) is added back, J the stiffness the
  force has: sliding, the stored energy's Hessian k N Nᵀ − ψ'(δ) (N tᵀ + t Nᵀ) − φ S (I − δ_f S)⁻¹ with
  t = (I − δ_f S)⁻¹ ∇k, ψ'(δ) = δ (δ* when frozen) and φ the normal force (past δ*, λ k* in place of k); K̃ while
  friction holds the contact.  Its normal part alone over-damped a slide whose depth and stiffness change along
  it: out and back over the kidney's hilum lip 2 mm deep the hand lost 5.2 % of the press's work, 0.02 % with
  the whole J (tests/test_haptics.py);
- viscous damping b_v (Δp / T);
- a **passivity observer/controller** (Hannaford & Ryu): the energy the hand has put in,
  E += f_held · Δp (the force the device held during the last tick), is compared with the energy stored, V;
  beyond a slack of 10 % of V a damper b_pc v (≤ 1 N·s/m, smoothly switched) takes out the difference.

The velocity terms fade with the contact (at most half the elastic force), so a kink in the path or the
release is not felt as a step.

**The deep hold.** Past δ_lin (status DEEP, inside the full contact region) the law's own ‖F‖ can fall while the
press goes deeper (:mod:`pmask.runtime.contact.law`'s "Deep presses"; the haptics guide's "Pressing deep" traces the
cases), which the hands issue forbids. There the force sent is the law's scaled by hs ≥ 1: while δ grows and the
hand does work against it (f · Δp > 0), hs = max(1, m / ‖f‖) with m the magnitude sent at the last tick, so ‖f‖
never falls; otherwise hs − 1 shrinks by DEEP_RELEASE a tick (a 10-tick time constant). Along a force that resists
the motion the extra only takes energy out (tests/test_deep.py: in and out along 30° lines the hold's own work is
never positive, to 1e-6 of the press's: its ten-tick release can give back a little of what it held). Short of δ_lin
it holds the same way while δ grows by at least half the probe's motion a tick (a press, not a slide along the
surface): at the contact surface's rounded lip, 7 mm from the support, a 45° push lost 0.09 % of its force at 4 mm
(the benchmarks' deep pushes, by hand), and a slide into softer tissue must ease. Here a contact's status turns DEEP
when its penetration reaches δ_lin. The native core's ``core/output.c`` is the same code operation for operation.
"""
from __future__ import annotations

import math

from pmask.runtime.contact.law import GEO_LAM, GEO_k, increment_depth, increment_stiffness, taper_gradient
from pmask.runtime.contact.linalg3 import lag_weight, mul3, speed_up
from pmask.runtime.contact.state import DEEP_RELEASE, PASSIVITY_SLACK, PC_DAMPING_MAX, PC_RAMP_TICKS, Status


def render(c, states, active, geo, ubar, result) -> None:
    """Set every active contact's force (on the user and on the body), displacement, depth and status from the
    law's result, and move a sliding anchor; updates the observer's energy and the controller's damping."""
    frictionless = c._frictionless
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
        e = 0.5 * (f[0] * u2[0] + f[1] * u2[1] + f[2] * u2[2])
        delta, d0 = result[l][0][3], st.frozen_depth
        if st.frozen and delta > d0:  # the law's energy past δ* (law.py) less ½ φ δ
            e += 0.5 * d0 * (delta - d0) * (geo[l][GEO_k] - increment_stiffness(st, geo[l][GEO_LAM]))
        stored += e
        if hb[0] == 0.0 and hb[1] == 0.0 and hb[2] == 0.0:  # its first tick: the device held no force yet, the
            work += e                                       # energy of that tick's press is the hand's
    slack = PASSIVITY_SLACK * stored
    energy = min(c._energy + work, stored + slack) if c.passivity else stored
    deficit = stored - slack - energy
    rate = c.device.rate
    if c.passivity:  # the damping that would dissipate the deficit in one tick at this speed, capped
        need = PC_DAMPING_MAX if motion2 <= 0.0 else min(PC_DAMPING_MAX, deficit * rate / motion2)
        want = need if deficit > 0.0 else 0.0
        c._pc_damping += (want - c._pc_damping) / PC_RAMP_TICKS
    bpc = c._pc_damping * rate
    for l in active:
        st = states[l]
        (f, u2, sliding, delta), ueff = result[l]
        g = geo[l]
        Nx, Ny, Nz, Kt, _, k, lam, (gx, gy, gz), S, dlin = g
        dpx, dpy, dpz = st.vel  # the velocity terms use the filtered motion
        # past δ_t (inside the full region) increments keep the stiffness where they began (law.py)
        full = lam >= 1.0 - 1e-9
        if not st.frozen:
            if full and delta > 0.0:
                dt = increment_depth(dlin, k, gx, gy, gz)
                if delta >= dt:
                    # δ_t where a press crosses it (st.depth: the last tick's), else where it is (law.py)
                    st.frozen, st.frozen_depth, st.frozen_stiffness = True, dt if st.depth < dt else delta, k
        elif delta < st.frozen_depth:
            st.frozen = False
        # the stored energy's gradient along the surface, ψ(δ) (I − δ_f S)⁻¹ ∇k: ψ = ½ δ², frozen
        # δ* δ − ½ δ*² and the increments' ½ k* (δ − δ*)² (I − δ_f S)⁻¹ ∇λ; δ_f = min(δ, R/2) the depth whose
        # speed-up the proxy moves with (tracking.follow)
        d0 = st.frozen_depth
        hd = d0 * delta - 0.5 * d0 * d0 if st.frozen else 0.5 * delta * delta
        d_f, lag = lag_weight(S, delta)  # δ_f and the proxy-offset term's share
        A = speed_up(S, d_f)
        tx, ty, tz = mul3(A, gx, gy, gz)
        bx, by, bz = f[0] + hd * tx, f[1] + hd * ty, f[2] + hd * tz
        if st.frozen:
            hl = 0.5 * st.frozen_stiffness * (delta - d0) * (delta - d0)
            ax, ay, az = mul3(A, *taper_gradient(c.surface, st.tri, Nx, Ny, Nz))
            bx, by, bz = bx + hl * ax, by + hl * ay, bz + hl * az
        # the proxy-offset term φ (I − δ_f S)⁻¹ S e, e = P (x − p), faded out towards the focal depth (module doc)
        phi = -(f[0] * Nx + f[1] * Ny + f[2] * Nz)
        if frictionless:
            ux, uy, uz = ubar[l]
            un = Nx * ux + Ny * uy + Nz * uz
            ex, ey, ez = mul3(A, *mul3(S, un * Nx - ux, un * Ny - uy, un * Nz - uz))
            we = lag * phi
            bx, by, bz = bx + we * ex, by + we * ey, bz + we * ez
        # the zero-order hold's first-order error, ½ J Δp (Colgate's kT/2): sliding (frictionless) J the stored energy's
        # Hessian (module doc), K̃ stuck
        kt = increment_stiffness(st, lam) if st.frozen else k  # the normal stiffness of an increment
        if sliding:
            vn = Nx * dpx + Ny * dpy + Nz * dpz
            vt = tx * dpx + ty * dpy + tz * dpz
            hz = 0.5 * kt * vn
            hc = -0.5 * (d0 if st.frozen else delta)  # ½ ψ'(δ)
            hp = -0.5 * phi
            wx, wy, wz = mul3(S, *mul3(A, dpx, dpy, dpz))
            vx = hz * Nx + hc * (Nx * vt + tx * vn) + hp * wx
            vy = hz * Ny + hc * (Ny * vt + ty * vn) + hp * wy
            vz = hz * Nz + hc * (Nz * vt + tz * vn) + hp * wz
        else:
            q = kt / k
            vx, vy, vz = mul3(Kt, 0.5 * q * dpx, 0.5 * q * dpy, 0.5 * q * dpz)
        bv = lam * c.damping * rate + bpc  # viscous damping and the controller's, on Δp / T
        vx, vy, vz = vx + bv * dpx, vy + bv * dpy, vz + bv * dpz
        # the velocity terms fade with the contact: at most half the elastic force (as a Hunt-Crossley
        # damping scales with the penetration), so that they reach zero with it at release
        vm = math.sqrt(vx * vx + vy * vy + vz * vz)
        fm = 0.5 * math.sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2])
        if vm > fm:
            s = fm / vm
            vx, vy, vz = s * vx, s * vy, s * vz
        bx, by, bz = bx + vx, by + vy, bz + vz
        # (inside the full region) a press that goes deeper never feels softer: while δ grows (past δ_lin at all,
        # short of it by at least half the probe's motion: a press, not a slide) and the hand does work against the
        # force (f·Δp > 0) its magnitude is held at least at the last tick's, the factor hs ≥ 1 on it only resisting
        # the motion (so it can only take energy out); otherwise hs returns to 1 over DEEP_RELEASE's 10 ticks (in a
        # region's edge band too, where the force fades with λ)
        bm = math.sqrt(bx * bx + by * by + bz * bz)
        mx, my, mz = st.move
        gain = delta - st.depth
        if (full and gain > 0.0 and (delta >= dlin or 4.0 * gain * gain >= mx * mx + my * my + mz * mz)
                and bx * mx + by * my + bz * mz > 0.0):
            hs = st.hold_peak / bm if st.hold_peak > bm else 1.0
        else:
            hs = 1.0 + (st.hold_scale - 1.0) * DEEP_RELEASE
        bx, by, bz = hs * bx, hs * by, hs * bz
        if not (math.isfinite(bx) and math.isfinite(by) and math.isfinite(bz)):
            raise FloatingPointError("non-finite contact force")  # never sent to a device
        st.hold_scale, st.hold_peak = hs, hs * bm
        if c._trace is not None:
            c._trace.append((l, f, (bx, by, bz), delta, lam))
        st.body_force = (bx, by, bz)
        st.force = st.good_force = (-bx, -by, -bz)
        st.u_bar, st.depth, st.taper, st.sliding = total[l], delta, lam, sliding
        st.status = (Status.DEEP if delta >= dlin and delta > 0.0 else Status.CONTACT if full else
                     Status.REGION_EDGE)
        # the anchor slides by the tangential part of (ū left to it) − ū', at most as far as the tool moved (a
        # tool drags the point it holds no faster than itself: a breakaway at depth, where the static-to-dynamic
        # drop μ_s → μ_d is tens of mN, is spread over ticks while the law keeps the force on the cone)
        if sliding and not frictionless:
            mx, my, mz = ueff[0] - u2[0], ueff[1] - u2[1], ueff[2] - u2[2]
            mn = mx * Nx + my * Ny + mz * Nz
            mx, my, mz = mx - mn * Nx, my - mn * Ny, mz - mn * Nz
            ms = math.sqrt(mx * mx + my * my + mz * mz)
            lim = math.sqrt(st.move[0] * st.move[0] + st.move[1] * st.move[1] + st.move[2] * st.move[2])
            if ms > lim:
                s = lim / ms
                mx, my, mz = s * mx, s * my, s * mz
            ax, ay, az = st.anchor
            st.anchor = (ax + mx, ay + my, az + mz)
            st.slip += math.sqrt(mx * mx + my * my + mz * mz)
        elif not sliding:
            st.slip = 0.0
    c._energy = energy
