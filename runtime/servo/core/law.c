/* pmask servo core, step 2: the contact law at the proxy (pmask.runtime.contact.law).
 *
 * K̃ = c K with c = k Nᵀ K⁻¹ N (normal stiffness k with the tangential directions free); frictionless
 * f = −k δ N; stuck f = K̃ ū while inside the friction cone; sliding f = (1 − τ) f_stuck + τ f_free on the
 * cone's edge; the surface's own displacement K̃⁻¹ f.  See law.py for the derivation and the DEEP regime. */
#include "pm_internal.h"

/* the law's inputs at the proxy (law.geometry): N, K̃, K̃⁻¹, k, λ, ∇k and S on the tangent plane, δ_lin, and ū;
 * 0 or -1 (where the Python raises) */
int pm__geometry(const pm_servo *S, cstate *st, const double *p, geom *g, double *u)
{
    const pm_table *tb = S->tab;
    int64_t t = st->tri;
    const double *b = st->b;
    if (pm__normal_at(tb, t, b, g->N)) return -1;
    const double Nx = g->N[0], Ny = g->N[1], Nz = g->N[2];
    double gr[3], Sm[9];
    pm__at(tb, t, b, g->K, &g->lam, &g->k, gr, Sm, &g->dlin);
    const double gx = gr[0], gy = gr[1], gz = gr[2];
    pm__inverse3(g->K, g->Ki);
    if (g->k > 0.0) {  /* law.scaled */
        double c = g->k * pm__nkn(g->N, g->Ki);
        if (c == 0.0) return -1;
        for (int i = 0; i < 9; i++) g->Kt[i] = c * g->K[i];
        for (int i = 0; i < 9; i++) g->Kti[i] = g->Ki[i] / c;
    } else {
        for (int i = 0; i < 9; i++) g->Kt[i] = g->Kti[i] = 0.0;
    }
    double gn = gx * Nx + gy * Ny + gz * Nz;
    double c[3];
    pm__point_at(tb, t, b, c);
    if (st->has_anchor) {
        double ax = st->anchor[0], ay = st->anchor[1], az = st->anchor[2];
        double an = Nx * (ax - c[0]) + Ny * (ay - c[1]) + Nz * (az - c[2]);
        c[0] = ax - an * Nx;
        c[1] = ay - an * Ny;
        c[2] = az - an * Nz;
        st->anchor[0] = c[0];
        st->anchor[1] = c[1];
        st->anchor[2] = c[2];
    }
    double r = S->o.tool_radius;
    g->g[0] = gx - gn * Nx;
    g->g[1] = gy - gn * Ny;
    g->g[2] = gz - gn * Nz;
    pm__tangent_part(g->N, Sm, g->S);
    u[0] = p[0] - r * Nx - c[0];
    u[1] = p[1] - r * Ny - c[1];
    u[2] = p[2] - r * Nz - c[2];
    return 0;
}

static void result(lres *R, double fx, double fy, double fz, const double *u2, int sliding, double delta)
{
    R->f[0] = fx;
    R->f[1] = fy;
    R->f[2] = fz;
    R->u2[0] = u2[0];
    R->u2[1] = u2[1];
    R->u2[2] = u2[2];
    R->sliding = sliding;
    R->delta = delta;
}

/* the frictionless normal force and its ratio to k δ (law.secant): k δ, or past δ* k δ* + λ k* (δ − δ*) */
static double secant(const cstate *st, double k, double lam, double delta, double *q)
{
    const double d0 = st->frozen_depth;
    if (st->frozen && delta > d0) {
        double fc = k * d0 + lam * st->frozen_stiffness * (delta - d0);
        *q = fc / (k * delta);
        return fc;
    }
    *q = 1.0;
    return k * delta;
}

/* the contact law (law.local_law): 0 */
int pm__local_law(const pm_servo *S, const cstate *st, const geom *g, double ux, double uy, double uz, lres *R)
{
    const double Nx = g->N[0], Ny = g->N[1], Nz = g->N[2], lam = g->lam, k = g->k;
    double delta = -(Nx * ux + Ny * uy + Nz * uz);
    double u2[3] = {ux, uy, uz};
    if (delta <= 0.0 || lam <= 0.0 || k <= 0.0) {
        result(R, 0.0, 0.0, 0.0, u2, 0, 0.0);
        return 0;
    }
    double q;
    const double fc = secant(st, k, lam, delta, &q);
    if (S->frictionless) {
        double fx = -fc * Nx, fy = -fc * Ny, fz = -fc * Nz;
        pm__mul3(g->Kti, fx, fy, fz, u2);
        u2[0] = u2[0] / q;
        u2[1] = u2[1] / q;
        u2[2] = u2[2] / q;
        result(R, fx, fy, fz, u2, 1, delta);
        return 0;
    }
    double s3[3];
    pm__mul3(g->Kt, ux, uy, uz, s3);
    const double sx = q * s3[0], sy = q * s3[1], sz = q * s3[2];
    double phi = -(Nx * sx + Ny * sy + Nz * sz);
    double tx = sx + phi * Nx, ty = sy + phi * Ny, tz = sz + phi * Nz;
    double ft = sqrt(tx * tx + ty * ty + tz * tz);
    double mu = st->sliding ? S->o.dynamic_friction + (S->o.friction - S->o.dynamic_friction) *
                                                         exp(-st->slip / S->o.slip_length)
                            : S->o.friction;
    if (ft <= mu * phi) {
        result(R, sx, sy, sz, u2, 0, delta);
        return 0;
    }
    double a = ft - mu * phi;
    double tau = a / (a + mu * fc);
    double s = 1.0 - tau;
    double fx = s * sx - tau * fc * Nx, fy = s * sy - tau * fc * Ny, fz = s * sz - tau * fc * Nz;
    pm__mul3(g->Kti, fx, fy, fz, u2);
    u2[0] = u2[0] / q;
    u2[1] = u2[1] / q;
    u2[2] = u2[2] / q;
    result(R, fx, fy, fz, u2, 1, delta);
    return 0;
}

/* two frictionless contacts pressing (a grasp's jaws, or two instruments each on its own), the law's first branch
 * (δ > 0 on a region and past no δ*: f = −k δ N, the surface's displacement K̃⁻¹ f) in the two lanes of a register:
 * each lane the scalar's operations in its order, so bit for bit pm__local_law's (q = 1 there, and x / 1 is x), the
 * two contacts' chains side by side (the pair's tick waits on both); anything else the scalar law, each in turn */
int pm__local_law2(const pm_servo *S, const cstate *sa, const geom *ga, const double *ua, lres *Ra,
                   const cstate *sb, const geom *gb, const double *ub, lres *Rb)
{
    const pm_v2 Nx = {ga->N[0], gb->N[0]}, Ny = {ga->N[1], gb->N[1]}, Nz = {ga->N[2], gb->N[2]};
    const pm_v2 ux = {ua[0], ub[0]}, uy = {ua[1], ub[1]}, uz = {ua[2], ub[2]};
    const pm_v2 delta = -(Nx * ux + Ny * uy + Nz * uz);
    const double da = delta[0], db = delta[1];
    if (!(S->frictionless && da > 0.0 && db > 0.0 && ga->lam > 0.0 && gb->lam > 0.0 && ga->k > 0.0 && gb->k > 0.0 &&
          !(sa->frozen && da > sa->frozen_depth) && !(sb->frozen && db > sb->frozen_depth))) {
        if (pm__local_law(S, sa, ga, ua[0], ua[1], ua[2], Ra)) return -1;
        return pm__local_law(S, sb, gb, ub[0], ub[1], ub[2], Rb);
    }
    const pm_v2 k = {ga->k, gb->k};
    const pm_v2 fc = -(k * delta);  /* -fc: the scalar's f = −fc N is (−fc) N */
    const pm_v2 fx = fc * Nx, fy = fc * Ny, fz = fc * Nz;
    const double *A = ga->Kti, *B = gb->Kti;
    const pm_v2 m0 = {A[0], B[0]}, m1 = {A[1], B[1]}, m2 = {A[2], B[2]}, m3 = {A[3], B[3]}, m4 = {A[4], B[4]};
    const pm_v2 m5 = {A[5], B[5]}, m6 = {A[6], B[6]}, m7 = {A[7], B[7]}, m8 = {A[8], B[8]};
    const pm_v2 vx = m0 * fx + m1 * fy + m2 * fz, vy = m3 * fx + m4 * fy + m5 * fz, vz = m6 * fx + m7 * fy + m8 * fz;
    const double a2[3] = {vx[0], vy[0], vz[0]}, b2[3] = {vx[1], vy[1], vz[1]};
    result(Ra, fx[0], fy[0], fz[0], a2, 1, da);
    result(Rb, fx[1], fy[1], fz[1], b2, 1, db);
    return 0;
}
