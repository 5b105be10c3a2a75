r"""Step 4, the force sent: the zero-order hold's error, damping and the passivity observer/controller.

The law's force plus the tangential term ½ δ² ∇k_n (which makes the frictionless force the gradient of the
stored energy ½ λ k_n δ²), then three velocity terms on the probe's motion Δp (low-pass filtered over 10 ms):

- the zero-order hold's first-order error ½ J Δp (Colgate's kT/2 damping, J the law's stiffness: λ k_n N Nᵀ,
  plus k_t on the tangent plane while friction holds) is added back;
- viscous damping b_v (Δp / T);
- a **passivity observer/controller** (Hannaford & Ryu): the energy the hand has put in,
  E += f_held · Δp (the force the device held during the last tick), is compared with the energy stored, V;
  beyond a slack of 10 % of V a damper b_pc v (≤ 1 N·s/m, smoothly switched) takes out the difference.

The velocity terms fade with the contact (at most half the elastic force), so a kink in the path or the
release is not felt as a step.  The native core's ``core/output.c`` is the same code operation for operation.
"""
from __future__ import annotations

import math

from pmask.runtime.contact.state import PASSIVITY_SLACK, PC_DAMPING_MAX, PC_RAMP_TICKS, Status


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
        stored += 0.5 * (f[0] * u2[0] + f[1] * u2[1] + f[2] * u2[2])
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
        if not (math.isfinite(bx) and math.isfinite(by) and math.isfinite(bz)):
            raise FloatingPointError("non-finite contact force")  # never sent to a device
        if c._trace is not None:
            c._trace.append((l, f, (bx, by, bz), delta, lam))
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
    c._energy = energy
