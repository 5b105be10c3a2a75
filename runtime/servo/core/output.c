/* pmask servo core, step 4: the force sent (pmask.runtime.contact.output).
 *
 * The law's force plus ½ δ² (I − δ S)⁻¹ ∇k, the zero-order hold's first-order error ½ J Δp added back, viscous damping,
 * and the passivity observer/controller (Hannaford & Ryu): a smoothly switched damper takes out the energy the
 * hand did not put in beyond a slack of 10 % of the stored energy.  The velocity terms fade with the contact.  Past
 * δ_lin the deep hold keeps |f| from falling while the press goes deeper (output.py's "The deep hold"). */
#include "pm_internal.h"

/* ∇λ on triangle t, on the tangent plane of N (law.taper_gradient): (λ_1 − λ_0) a + (λ_2 − λ_0) b, a and b the
 * duals of the triangle's edges; only a frozen contact reads it */
static void taper_gradient(const pm_table *tb, int64_t t, const double *N, double *gl)
{
    const int64_t *v = tb->T + 3 * t;
    const double *F = tb->frames + 12 * t;
    const double d1 = tb->taper[v[1]] - tb->taper[v[0]], d2 = tb->taper[v[2]] - tb->taper[v[0]];
    const double lx = d1 * F[3] + d2 * F[6], ly = d1 * F[4] + d2 * F[7], lz = d1 * F[5] + d2 * F[8];
    const double ln = lx * N[0] + ly * N[1] + lz * N[2];
    gl[0] = lx - ln * N[0];
    gl[1] = ly - ln * N[1];
    gl[2] = lz - ln * N[2];
}

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
        double e = 0.5 * (R->f[0] * R->total[0] + R->f[1] * R->total[1] + R->f[2] * R->total[2]);
        const double d0 = st->frozen_depth;
        if (st->frozen && R->delta > d0)  /* the law's energy past δ* (law.py) less ½ φ δ */
            e += 0.5 * d0 * (R->delta - d0) * (S->geo[l].k - S->geo[l].lam * st->frozen_stiffness);
        stored += e;
        if (hb[0] == 0.0 && hb[1] == 0.0 && hb[2] == 0.0) work += e;  /* its first tick: the hand's press */
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
        const double Nx = g->N[0], Ny = g->N[1], Nz = g->N[2], lam = g->lam, k = g->k;
        const double *f = R->f, *u2 = R->u2;
        const double delta = R->delta;
        const int sliding = R->sliding;
        double dpx = st->vel[0], dpy = st->vel[1], dpz = st->vel[2];
        /* past δ_t (inside the full region) increments keep the stiffness where they began (law.py) */
        const int full = lam >= 1.0 - 1e-9;
        if (!st->frozen) {
            if (full && delta > 0.0) {
                const double gm = sqrt(g->g[0] * g->g[0] + g->g[1] * g->g[1] + g->g[2] * g->g[2]);
                double dt = g->dlin;  /* law.increment_depth */
                if (FROZEN_CHANGE * k < dt * gm) dt = FROZEN_CHANGE * k / gm;
                if (delta >= dt) {
                    st->frozen = 1;
                    st->frozen_depth = st->depth < dt ? dt : delta;  /* a press crossing δ_t, or already past it */
                    st->frozen_stiffness = k;
                }
            }
        } else if (delta < st->frozen_depth) {
            st->frozen = 0;
        }
        /* the stored energy's gradient along the surface, ψ(δ) (I − δ_f S)⁻¹ ∇k, frozen also the increments'
           ½ k* (δ − δ*)² (I − δ_f S)⁻¹ ∇λ */
        const double d0 = st->frozen_depth;
        const double hd = st->frozen ? d0 * delta - 0.5 * d0 * d0 : 0.5 * delta * delta;
        double A[9], t3[3], a3[3];
        double d_f;
        const double lag = pm__lag_weight(g->S, delta, &d_f);  /* δ_f and the proxy-offset term's share */
        pm__speed_up(g->S, d_f, A);
        pm__mul3(A, g->g[0], g->g[1], g->g[2], t3);
        double bx = f[0] + hd * t3[0], by = f[1] + hd * t3[1], bz = f[2] + hd * t3[2];
        if (st->frozen) {
            const double hl = 0.5 * st->frozen_stiffness * (delta - d0) * (delta - d0);
            double gl[3];
            taper_gradient(S->tab, st->tri, g->N, gl);
            pm__mul3(A, gl[0], gl[1], gl[2], a3);
            bx = bx + hl * a3[0];
            by = by + hl * a3[1];
            bz = bz + hl * a3[2];
        }
        /* frictionless, the proxy's offset e = P (x − p) from the probe's normal line: the energy's gradient has
           φ (I − δ_f S)⁻¹ S e too, faded out towards the focal depth (output.py) */
        const double phi = -(f[0] * Nx + f[1] * Ny + f[2] * Nz);
        if (frictionless) {
            const double *ub = S->ubar + 3 * l;
            const double un = Nx * ub[0] + Ny * ub[1] + Nz * ub[2];
            double s3[3], e3[3];
            pm__mul3(g->S, un * Nx - ub[0], un * Ny - ub[1], un * Nz - ub[2], s3);
            pm__mul3(A, s3[0], s3[1], s3[2], e3);
            const double we = lag * phi;
            bx = bx + we * e3[0];
            by = by + we * e3[1];
            bz = bz + we * e3[2];
        }
        /* the zero-order hold's first-order error, ½ J Δp: J sliding the Hessian of the stored energy,
           k N Nᵀ − ψ'(δ) (N tᵀ + t Nᵀ) − φ S (I − δ_f S)⁻¹ with t = (I − δ_f S)⁻¹ ∇k and φ the normal force
           (output.py), K̃ stuck (past δ*: λ k* for k) */
        const double kt = st->frozen ? lam * st->frozen_stiffness : k;
        double vx, vy, vz;
        if (sliding) {
            const double vn = Nx * dpx + Ny * dpy + Nz * dpz;
            const double vt = t3[0] * dpx + t3[1] * dpy + t3[2] * dpz;
            const double hz = 0.5 * kt * vn;
            const double hc = -0.5 * (st->frozen ? d0 : delta);
            const double hp = -0.5 * phi;
            double m3[3], w3[3];
            pm__mul3(A, dpx, dpy, dpz, m3);
            pm__mul3(g->S, m3[0], m3[1], m3[2], w3);
            vx = hz * Nx + hc * (Nx * vt + t3[0] * vn) + hp * w3[0];
            vy = hz * Ny + hc * (Ny * vt + t3[1] * vn) + hp * w3[1];
            vz = hz * Nz + hc * (Nz * vt + t3[2] * vn) + hp * w3[2];
        } else {
            double q = kt / k, v3[3];
            pm__mul3(g->Kt, 0.5 * q * dpx, 0.5 * q * dpy, 0.5 * q * dpz, v3);
            vx = v3[0];
            vy = v3[1];
            vz = v3[2];
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
        /* (inside the full region) a press that goes deeper never feels softer: while δ grows (past δ_lin at all,
           short of it by at least half the probe's motion: a press, not a slide) and the hand does work against
           the force its magnitude is held at least at the last tick's; otherwise the factor returns to 1
           (output.py) */
        const double bm = sqrt(bx * bx + by * by + bz * bz);
        const double gain = delta - st->depth, *mv = st->move;
        double hs;
        if (full && gain > 0.0
            && (delta >= g->dlin || 4.0 * gain * gain >= mv[0] * mv[0] + mv[1] * mv[1] + mv[2] * mv[2])
            && bx * mv[0] + by * mv[1] + bz * mv[2] > 0.0)
            hs = st->hold_peak > bm ? st->hold_peak / bm : 1.0;
        else
            hs = 1.0 + (st->hold_scale - 1.0) * DEEP_RELEASE;
        bx = hs * bx;
        by = hs * by;
        bz = hs * bz;
        if (!(isfinite(bx) && isfinite(by) && isfinite(bz))) return -1;
        st->hold_scale = hs;
        st->hold_peak = hs * bm;
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
        st->status = delta >= g->dlin && delta > 0.0 ? PM_DEEP : full ? PM_CONTACT : PM_REGION_EDGE;
        if (sliding && !frictionless) {
            double mx = R->ueff[0] - u2[0], my = R->ueff[1] - u2[1], mz = R->ueff[2] - u2[2];
            double mn = mx * Nx + my * Ny + mz * Nz;
            mx = mx - mn * Nx;
            my = my - mn * Ny;
            mz = mz - mn * Nz;
            double ms = sqrt(mx * mx + my * my + mz * mz);
            double lim = sqrt(st->move[0] * st->move[0] + st->move[1] * st->move[1] + st->move[2] * st->move[2]);
            if (ms > lim) {
                double s = lim / ms;
                mx = s * mx;
                my = s * my;
                mz = s * mz;
            }
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
