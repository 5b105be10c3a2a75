/* pmask servo core, step 4: the force sent (pmask.runtime.contact.output).
 *
 * The law's force plus ½ δ² ∇k_n, the zero-order hold's first-order error ½ J Δp added back, viscous damping,
 * and the passivity observer/controller (Hannaford & Ryu): a smoothly switched damper takes out the energy the
 * hand did not put in beyond a slack of 10 % of the stored energy.  The velocity terms fade with the contact. */
#include "pm_internal.h"

/* the active contacts S->active[0..na) after the law: their forces, displacements, depths and statuses; 0 or -1 */
int pm__render(pm_servo *S, int32_t na)
{
    const int frictionless = S->frictionless;
    /* each contact's displacement of the surface: the law's own plus what the others move it */
    for (int32_t x = 0; x < na; x++) {
        int32_t l = S->active[x];
        lres *R = &S->res[l];
        const double *u = S->ubar + 3 * l;
        for (int a = 0; a < 3; a++) R->total[a] = R->u2[a] + (u[a] - R->ueff[a]);
    }
    double stored = 0.0, work = 0.0, motion2 = 0.0;
    for (int32_t x = 0; x < na; x++) {
        int32_t l = S->active[x];
        const cstate *st = &S->st[l];
        const lres *R = &S->res[l];
        double dpx = st->move[0], dpy = st->move[1], dpz = st->move[2];
        double vx = st->vel[0], vy = st->vel[1], vz = st->vel[2];
        motion2 += vx * vx + vy * vy + vz * vz;
        const double *hb = st->body_force;
        work += hb[0] * dpx + hb[1] * dpy + hb[2] * dpz;
        stored += 0.5 * (R->f[0] * R->total[0] + R->f[1] * R->total[1] + R->f[2] * R->total[2]);
    }
    double slack = PASSIVITY_SLACK * stored;
    double energy = S->o.passivity ? PYMIN(S->energy + work, stored + slack) : stored;
    double deficit = stored - slack - energy;
    double rate = S->o.rate;
    if (S->o.passivity) {
        double need = motion2 <= 0.0 ? PC_DAMPING_MAX : PYMIN(PC_DAMPING_MAX, deficit * rate / motion2);
        double wantd = deficit > 0.0 ? need : 0.0;
        S->pc_damping += (wantd - S->pc_damping) / PC_RAMP_TICKS;
    }
    double bpc = S->pc_damping * rate;
    for (int32_t x = 0; x < na; x++) {
        int32_t l = S->active[x];
        cstate *st = &S->st[l];
        const lres *R = &S->res[l];
        const geom *g = &S->geo[l];
        const double Nx = g->N[0], Ny = g->N[1], Nz = g->N[2], lam = g->lam;
        const double *Ki = g->Ki;
        const double gx = g->g[0], gy = g->g[1], gz = g->g[2];
        const double *f = R->f, *u2 = R->u2;
        const double delta = R->delta;
        const int sliding = R->sliding;
        double dpx = st->vel[0], dpy = st->vel[1], dpz = st->vel[2];
        double bx = f[0], by = f[1], bz = f[2];
        double hd = 0.5 * delta * delta;
        bx = bx + hd * gx;
        by = by + hd * gy;
        bz = bz + hd * gz;
        double nkn = pm__nkn(g->N, Ki);
        double dn = Nx * dpx + Ny * dpy + Nz * dpz;
        if (nkn == 0.0) return -1;
        double hz = 0.5 * lam / nkn * dn;
        double vx = hz * Nx, vy = hz * Ny, vz = hz * Nz;
        if (!sliding) {
            double den = Ki[0] + Ki[4] + Ki[8] - nkn;
            if (den == 0.0) return -1;
            double ht = lam / den;
            vx = vx + ht * (dpx - dn * Nx);
            vy = vy + ht * (dpy - dn * Ny);
            vz = vz + ht * (dpz - dn * Nz);
        }
        double bv = lam * S->o.damping * rate + bpc;
        vx = vx + bv * dpx;
        vy = vy + bv * dpy;
        vz = vz + bv * dpz;
        double vm = sqrt(vx * vx + vy * vy + vz * vz);
        double fm = 0.5 * sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2]);
        if (vm > fm) {
            double c = fm / vm;
            vx = c * vx;
            vy = c * vy;
            vz = c * vz;
        }
        bx = bx + vx;
        by = by + vy;
        bz = bz + vz;
        if (!(isfinite(bx) && isfinite(by) && isfinite(bz))) return -1;
        st->body_force[0] = bx;
        st->body_force[1] = by;
        st->body_force[2] = bz;
        st->force[0] = st->good_force[0] = -bx;
        st->force[1] = st->good_force[1] = -by;
        st->force[2] = st->good_force[2] = -bz;
        st->u_bar[0] = R->total[0];
        st->u_bar[1] = R->total[1];
        st->u_bar[2] = R->total[2];
        st->depth = delta;
        st->taper = lam;
        st->sliding = sliding;
        st->status = lam >= 1.0 - 1e-9 ? PM_CONTACT : PM_REGION_EDGE;
        if (sliding && !frictionless) {
            double mx = R->ueff[0] - u2[0], my = R->ueff[1] - u2[1], mz = R->ueff[2] - u2[2];
            double mn = mx * Nx + my * Ny + mz * Nz;
            mx = mx - mn * Nx;
            my = my - mn * Ny;
            mz = mz - mn * Nz;
            st->anchor[0] = st->anchor[0] + mx;
            st->anchor[1] = st->anchor[1] + my;
            st->anchor[2] = st->anchor[2] + mz;
            st->slip += sqrt(mx * mx + my * my + mz * mz);
        } else if (!sliding) {
            st->slip = 0.0;
        }
    }
    S->energy = energy;
    return 0;
}
