/* pmask servo core, step 2: the contact law at the proxy (pmask.runtime.contact.law).
 *
 * The normal force λ k_n δ with k_n = 1/(Nᵀ K⁻¹ N), and friction as a spring on the held point's tangential
 * offset with k_t = 2λ / (tr K⁻¹ − Nᵀ K⁻¹ N), bounded by μ λ k_n δ, μ weakening from μ_s to μ_d with slip. */
#include "pm_internal.h"

static void inverse3(const double *K, double *out)
{
    double a = K[0], b = K[1], c = K[2], d = K[3], e = K[4], f = K[5], g = K[6], h = K[7], i = K[8];
    double A = e * i - f * h, B = -(d * i - f * g), C = d * h - e * g;
    double det = a * A + b * B + c * C;
    if (det == 0.0 || !isfinite(det)) {
        for (int k = 0; k < 9; k++) out[k] = 0.0;
        return;
    }
    double r = 1.0 / det;
    out[0] = A * r;
    out[1] = -(b * i - c * h) * r;
    out[2] = (b * f - c * e) * r;
    out[3] = B * r;
    out[4] = (a * i - c * g) * r;
    out[5] = -(a * f - c * d) * r;
    out[6] = C * r;
    out[7] = -(a * h - b * g) * r;
    out[8] = (a * e - b * d) * r;
}

/* the law's inputs at the proxy (law.geometry): N, K, K⁻¹, λ, ∇k_n and ū; 0 or -1 */
int pm__geometry(const pm_servo *S, cstate *st, const double *p, geom *g, double *u)
{
    const pm_table *tb = S->tab;
    int64_t t = st->tri;
    const double *b = st->b;
    if (pm__normal_at(tb, t, b, g->N)) return -1;
    const double Nx = g->N[0], Ny = g->N[1], Nz = g->N[2];
    const int64_t *v = tb->T + 3 * t;
    const double *k0 = tb->K + 9 * v[0], *k1 = tb->K + 9 * v[1], *k2 = tb->K + 9 * v[2];
    for (int i = 0; i < 9; i++) g->K[i] = b[0] * k0[i] + b[1] * k1[i] + b[2] * k2[i];
    const double *g0 = tb->grad + 3 * v[0], *g1 = tb->grad + 3 * v[1], *g2 = tb->grad + 3 * v[2];
    double gx = b[0] * g0[0] + b[1] * g1[0] + b[2] * g2[0];
    double gy = b[0] * g0[1] + b[1] * g1[1] + b[2] * g2[1];
    double gz = b[0] * g0[2] + b[1] * g1[2] + b[2] * g2[2];
    g->lam = b[0] * tb->taper[v[0]] + b[1] * tb->taper[v[1]] + b[2] * tb->taper[v[2]];
    inverse3(g->K, g->Ki);
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
    u[0] = p[0] - r * Nx - c[0];
    u[1] = p[1] - r * Ny - c[1];
    u[2] = p[2] - r * Nz - c[2];
    return 0;
}


/* the contact law (law.local_law): 0, or -1 where the Python raises */
int pm__local_law(const pm_servo *S, const cstate *st, const geom *g, double ux, double uy, double uz, lres *R)
{
    const double Nx = g->N[0], Ny = g->N[1], Nz = g->N[2], lam = g->lam;
    const double *Ki = g->Ki;
    double delta = -(Nx * ux + Ny * uy + Nz * uz);
    if (delta <= 0.0 || lam <= 0.0) {
        R->f[0] = R->f[1] = R->f[2] = 0.0;
        R->u2[0] = ux;
        R->u2[1] = uy;
        R->u2[2] = uz;
        R->sliding = 0;
        R->delta = 0.0;
        return 0;
    }
    double nkn = pm__nkn(g->N, Ki);
    if (nkn == 0.0) return -1;
    double fc = lam * delta / nkn;
    double fx = -fc * Nx, fy = -fc * Ny, fz = -fc * Nz;
    if (S->frictionless) {
        R->f[0] = fx;
        R->f[1] = fy;
        R->f[2] = fz;
        R->u2[0] = -delta * Nx;
        R->u2[1] = -delta * Ny;
        R->u2[2] = -delta * Nz;
        R->sliding = 1;
        R->delta = delta;
        return 0;
    }
    double wx = ux + delta * Nx, wy = uy + delta * Ny, wz = uz + delta * Nz;
    double den = Ki[0] + Ki[4] + Ki[8] - nkn;
    if (den == 0.0) return -1;
    double kt = 2.0 * lam / den;
    double tx = kt * wx, ty = kt * wy, tz = kt * wz;
    double ft = sqrt(tx * tx + ty * ty + tz * tz);
    double mu = st->sliding ? S->o.dynamic_friction + (S->o.friction - S->o.dynamic_friction) *
                                                         exp(-st->slip / S->o.slip_length)
                            : S->o.friction;
    if (ft <= mu * fc) {
        R->f[0] = fx + tx;
        R->f[1] = fy + ty;
        R->f[2] = fz + tz;
        R->u2[0] = ux;
        R->u2[1] = uy;
        R->u2[2] = uz;
        R->sliding = 0;
        R->delta = delta;
        return 0;
    }
    double c = mu * fc / ft;
    tx = c * tx;
    ty = c * ty;
    tz = c * tz;
    if (kt == 0.0) return -1;
    R->f[0] = fx + tx;
    R->f[1] = fy + ty;
    R->f[2] = fz + tz;
    R->u2[0] = -delta * Nx + tx / kt;
    R->u2[1] = -delta * Ny + ty / kt;
    R->u2[2] = -delta * Nz + tz / kt;
    R->sliding = 1;
    R->delta = delta;
    return 0;
}

