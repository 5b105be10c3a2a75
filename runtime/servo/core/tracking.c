/* pmask servo core, step 1: tracking and the proxy (pmask.runtime.contact.tracking).
 *
 * The contact point is the surface point under the probe along the interpolated vertex normal (a Phong
 * projection), found by walking from the proxy's triangle; the bounding-volume hierarchy restarts tracking.
 * The proxy follows that projection along the surface by at most proxy_speed times the probe's motion. */
#include "pm_internal.h"

#define PROJECT_STEPS 8
#define PROJECT_TOL 1e-13

/* the Phong projection of p onto triangle t's plane, p = x + s N(x): Newton's method on the fixed point b = g(b),
   from the flat projection, to PROJECT_TOL; a fixed-point step where the Jacobian nearly vanishes (tracking.project) */
static void project(const pm_table *tb, int64_t t, const double *p, double *b0o, double *b1o, double *b2o, double *so)
{
    const double *F = tb->frames + 12 * t;
    const double ox = F[0], oy = F[1], oz = F[2], ax = F[3], ay = F[4], az = F[5], bx = F[6], by = F[7], bz = F[8];
    const double nx = F[9], ny = F[10], nz = F[11];
    const int64_t *v = tb->T + 3 * t;
    const double *n0 = tb->N + 3 * v[0], *n1 = tb->N + 3 * v[1], *n2 = tb->N + 3 * v[2];
    const double m1x = n1[0] - n0[0], m1y = n1[1] - n0[1], m1z = n1[2] - n0[2];  /* ∂N/∂b1 */
    const double m2x = n2[0] - n0[0], m2y = n2[1] - n0[1], m2z = n2[2] - n0[2];  /* ∂N/∂b2 */
    const double e1 = nx * m1x + ny * m1y + nz * m1z;
    const double e2 = nx * m2x + ny * m2y + nz * m2z;
    double dx = p[0] - ox, dy = p[1] - oy, dz = p[2] - oz;
    double h = nx * dx + ny * dy + nz * dz;
    double b1 = ax * dx + ay * dy + az * dz;
    double b2 = bx * dx + by * dy + bz * dz;
    double s = h;
    for (int it = 0; it < PROJECT_STEPS; it++) {
        double b0 = 1.0 - b1 - b2;
        double Nx = b0 * n0[0] + b1 * n1[0] + b2 * n2[0];
        double Ny = b0 * n0[1] + b1 * n1[1] + b2 * n2[1];
        double Nz = b0 * n0[2] + b1 * n1[2] + b2 * n2[2];
        double hn = Nx * nx + Ny * ny + Nz * nz;
        if (hn < 0.1) break;
        s = h / hn;
        double qx = dx - s * Nx, qy = dy - s * Ny, qz = dz - s * Nz;
        double r1 = ax * qx + ay * qy + az * qz - b1;  /* g(b) − b */
        double r2 = bx * qx + by * qy + bz * qz - b2;
        if (fabs(r1) + fabs(r2) <= PROJECT_TOL) break;  /* converged: b, and s with it */
        double c1 = s * e1 / hn, c2 = s * e2 / hn;  /* ∂q/∂b_k = c_k N − s m_k */
        double u1x = c1 * Nx - s * m1x, u1y = c1 * Ny - s * m1y, u1z = c1 * Nz - s * m1z;
        double u2x = c2 * Nx - s * m2x, u2y = c2 * Ny - s * m2y, u2z = c2 * Nz - s * m2z;
        double j11 = 1.0 - (ax * u1x + ay * u1y + az * u1z);  /* I − ∂g/∂b */
        double j12 = -(ax * u2x + ay * u2y + az * u2z);
        double j21 = -(bx * u1x + by * u1y + bz * u1z);
        double j22 = 1.0 - (bx * u2x + by * u2y + bz * u2z);
        double det = j11 * j22 - j12 * j21, d1, d2;
        if (det > 0.05) {
            d1 = (j22 * r1 - j12 * r2) / det;
            d2 = (j11 * r2 - j21 * r1) / det;
        } else {  /* a fold: the fixed-point step */
            d1 = r1;
            d2 = r2;
        }
        b1 += d1;
        b2 += d2;
    }
    *b0o = 1.0 - b1 - b2;
    *b1o = b1;
    *b2o = b2;
    *so = s;
}

/* 0, or -1 where the Python raises (ZeroDivisionError) */
int pm__locate(const pm_servo *S, int64_t t, const double *p, int retry, located *out)
{
    const pm_table *tb = S->tab;
    int64_t prev = -1;
    double b0 = 0, b1 = 0, b2 = 0, s = 0;
    int spent = 1;
    for (int32_t it = 0; it < S->o.max_walk; it++) {
        project(tb, t, p, &b0, &b1, &b2, &s);
        if (b0 >= 0.0 && b1 >= 0.0 && b2 >= 0.0) {
            out->t = t;
            out->b0 = b0;
            out->b1 = b1;
            out->b2 = b2;
            out->s = s;
            return 0;
        }
        int k = (b0 <= b1 && b0 <= b2) ? 0 : (b1 <= b2 ? 1 : 2);
        int64_t nb = tb->nb[3 * t + k];
        if (nb < 0 || nb == prev) {
            if (retry) {
                int64_t near = pm_table_nearest(tb, p);
                if (near != t && near != prev) return pm__locate(S, near, p, 0, out);
            }
            spent = 0;
            break;
        }
        prev = t;
        t = nb;
    }
    if (spent) project(tb, t, p, &b0, &b1, &b2, &s);
    b0 = PYMAX(b0, 0.0);
    b1 = PYMAX(b1, 0.0);
    b2 = PYMAX(b2, 0.0);
    double tot = b0 + b1 + b2;
    if (tot == 0.0) return -1;
    out->t = t;
    out->b0 = b0 / tot;
    out->b1 = b1 / tot;
    out->b2 = b2 / tot;
    out->s = s;
    return 0;
}


int pm__normal_at(const pm_table *tb, int64_t t, const double *b, double *N)
{
    const int64_t *v = tb->T + 3 * t;
    const double *a = tb->N + 3 * v[0], *bb = tb->N + 3 * v[1], *c = tb->N + 3 * v[2];
    double x = b[0] * a[0] + b[1] * bb[0] + b[2] * c[0];
    double y = b[0] * a[1] + b[1] * bb[1] + b[2] * c[1];
    double z = b[0] * a[2] + b[1] * bb[2] + b[2] * c[2];
    double r = sqrt(x * x + y * y + z * z);
    if (r == 0.0) return -1;
    N[0] = x / r;
    N[1] = y / r;
    N[2] = z / r;
    return 0;
}


int pm__move_proxy(const pm_servo *S, cstate *st, const double *target, double limit)
{
    const pm_table *tb = S->tab;
    int64_t t = st->tri;
    double b0 = st->b[0], b1 = st->b[1], b2 = st->b[2];
    double remaining = limit;
    for (int32_t it = 0; it < S->o.max_walk; it++) {
        const double *F = tb->frames + 12 * t;
        double dx = target[0] - F[0], dy = target[1] - F[1], dz = target[2] - F[2];
        double q1 = F[3] * dx + F[4] * dy + F[5] * dz;
        double q2 = F[6] * dx + F[7] * dy + F[8] * dz;
        double d0 = (1.0 - q1 - q2) - b0, d1 = q1 - b1, d2 = q2 - b2;
        const int64_t *v = tb->T + 3 * t;
        const double *v0 = tb->P + 3 * v[0], *v1 = tb->P + 3 * v[1], *v2 = tb->P + 3 * v[2];
        double ex = d0 * v0[0] + d1 * v1[0] + d2 * v2[0];
        double ey = d0 * v0[1] + d1 * v1[1] + d2 * v2[1];
        double ez = d0 * v0[2] + d1 * v1[2] + d2 * v2[2];
        double dist = sqrt(ex * ex + ey * ey + ez * ez);
        if (dist <= 0.0 || remaining <= 0.0) break;
        double a = PYMIN(1.0, remaining / dist);
        int exit_k = -1;
        double exit_a = a;
        const double bk[3] = {b0, b1, b2}, dk[3] = {d0, d1, d2};
        for (int k = 0; k < 3; k++)
            if (dk[k] < 0.0 && bk[k] + exit_a * dk[k] < 0.0) {
                exit_a = -bk[k] / dk[k];
                exit_k = k;
            }
        b0 = b0 + exit_a * d0;
        b1 = b1 + exit_a * d1;
        b2 = b2 + exit_a * d2;
        remaining -= exit_a * dist;
        if (exit_k < 0) break;
        int64_t nb = tb->nb[3 * t + exit_k];
        if (nb < 0) break;
        double bs[3] = {b0, b1, b2};
        bs[exit_k] = 0.0;
        const int64_t *w = tb->T + 3 * nb;
        double nbv[3];
        for (int j = 0; j < 3; j++) {
            double val = 0.0;
            for (int k = 0; k < 3; k++)
                if (v[k] == w[j]) val = bs[k];
            nbv[j] = val;
        }
        t = nb;
        b0 = nbv[0];
        b1 = nbv[1];
        b2 = nbv[2];
    }
    b0 = PYMAX(b0, 0.0);
    b1 = PYMAX(b1, 0.0);
    b2 = PYMAX(b2, 0.0);
    double tot = b0 + b1 + b2;
    if (tot == 0.0) return -1;
    st->tri = t;
    st->b[0] = b0 / tot;
    st->b[1] = b1 / tot;
    st->b[2] = b2 / tot;
    return 0;
}

/* step 1 for one contact (tracking.prepare): returns 1 when active (probe in p), 0 when not, -1 on an internal error */
int pm__prepare(pm_servo *S, cstate *st, const double *sample, double *p)
{
    const pm_table *tb = S->tab;
    double px = sample[0], py = sample[1], pz = sample[2];
    if (!(isfinite(px) && isfinite(py) && isfinite(pz))) {
        pm__hold(S, st, PM_BAD_SAMPLE);
        return 0;
    }
    if (st->has_last) {
        double dx = fabs(px - st->last[0]), dy = fabs(py - st->last[1]), dz = fabs(pz - st->last[2]);
        double mj = S->o.max_jump;
        if (dx > mj || dy > mj || dz > mj || dx * dx + dy * dy + dz * dz > mj * mj) {
            st->bad += 1;
            if (st->bad <= S->o.reset_after) {
                pm__hold(S, st, PM_JUMP);
                return 0;
            }
            pm__state_reset(st);
        }
    }
    st->bad = 0;
    double gx = PYMAX(PYMAX(tb->lo[0] - px, px - tb->hi[0]), 0.0);
    double gy = PYMAX(PYMAX(tb->lo[1] - py, py - tb->hi[1]), 0.0);
    double gz = PYMAX(PYMAX(tb->lo[2] - pz, pz - tb->hi[2]), 0.0);
    if (st->has_last) {
        st->move[0] = px - st->last[0];
        st->move[1] = py - st->last[1];
        st->move[2] = pz - st->last[2];
    } else {
        st->move[0] = st->move[1] = st->move[2] = 0.0;
    }
    double a = VELOCITY_FILTER;
    for (int k = 0; k < 3; k++) st->vel[k] = st->vel[k] + a * (st->move[k] - st->vel[k]);
    st->has_last = 1;
    st->last[0] = px;
    st->last[1] = py;
    st->last[2] = pz;
    st->has_target = 0;
    double far = FAR_FACTOR * tb->diag;
    if (gx > far || gy > far || gz > far || gx * gx + gy * gy + gz * gz > far * far) {
        if (!S->far_warned) {  /* reported once; the probe is written before the flag's release store */
            S->far_warned = 1;
            S->far_probe[0] = px;
            S->far_probe[1] = py;
            S->far_probe[2] = pz;
            __atomic_store_n(&S->far_pending, 1, __ATOMIC_RELEASE);
        }
        st->tri = -1;
        st->in_contact = 0;
        st->above = 0;
        pm__release(st, PM_FAR_OUTSIDE);
        return 0;
    }
    double m = S->margin;
    if (gx > m || gy > m || gz > m) {
        st->tri = -1;
        st->in_contact = 0;
        st->above = 0;
        pm__release(st, PM_NO_CONTACT);
        return 0;
    }
    double r = S->o.tool_radius;
    double pp[3] = {px, py, pz};
    located L;
    if (st->tri < 0) {
        int64_t t = pm_table_nearest(tb, pp);
        if (pm__locate(S, t, pp, 1, &L)) return -1;
        st->tri = L.t;
        st->b[0] = L.b0;
        st->b[1] = L.b1;
        st->b[2] = L.b2;
        st->above = L.s >= r;
        pm__release(st, PM_NO_CONTACT);
        return 0;
    }
    /* a jump out of contact: the walk starts from the grid's nearest triangle (tracking.prepare) */
    const double jump2 = st->move[0] * st->move[0] + st->move[1] * st->move[1] + st->move[2] * st->move[2];
    if (!st->in_contact && jump2 > tb->mean_edge * tb->mean_edge) st->tri = pm_table_nearest(tb, pp);
    if (pm__locate(S, st->tri, pp, 1, &L)) return -1;
    if (!st->in_contact) {
        st->tri = L.t;
        st->b[0] = L.b0;
        st->b[1] = L.b1;
        st->b[2] = L.b2;
        if (L.s >= r || !st->above) {
            st->above = st->above || L.s >= r;
            pm__release(st, PM_NO_CONTACT);
            return 0;
        }
        st->in_contact = 1;
        st->sliding = 0;
        st->has_anchor = 0;
        st->slip = 0.0;
        st->body_force[0] = st->body_force[1] = st->body_force[2] = 0.0;
        p[0] = px;
        p[1] = py;
        p[2] = pz;
        return 1;
    }
    st->has_target = 1;
    st->target_t = L.t;
    st->target_b[0] = L.b0;
    st->target_b[1] = L.b1;
    st->target_b[2] = L.b2;
    p[0] = px;
    p[1] = py;
    p[2] = pz;
    return 1;
}

/* the proxy's move this tick (tracking.follow): towards this tick's projection, at most proxy_speed |Δp|;
 * deeper than half the radius of curvature by dead reckoning, (I − δ_f S)⁻¹ P Δp (blended in from 0.4 of it:
 * pm__reckoning), and so past δ_lin when the projection lies more than a mean edge away (another part of the
 * surface) */
int pm__follow(pm_servo *S, cstate *st)
{
    if (!st->has_target) return 0;
    const pm_table *tb = S->tab;
    double x[3] = {0.0, 0.0, 0.0}, xt[3] = {0.0, 0.0, 0.0};  /* the proxy's point, the projection's: once a tick */
    int known = 0;  /* both are (a DEEP tick's jump test) */
    if (st->depth > 0.0) {
        double N[3], Sm[9], St[9];
        if (pm__normal_at(tb, st->tri, st->b, N)) return -1;
        pm__shape_at(tb, st->tri, st->b, Sm);
        pm__tangent_part(N, Sm, St);
        double d;
        double w = pm__reckoning(St, st->depth, &d);
        if (st->status == PM_DEEP) {
            pm__point_at(tb, st->tri, st->b, x);
            pm__point_at(tb, st->target_t, st->target_b, xt);
            known = 1;
            const double ex = xt[0] - x[0], ey = xt[1] - x[1], ez = xt[2] - x[2];
            if (ex * ex + ey * ey + ez * ez > tb->mean_edge * tb->mean_edge) w = 1.0;  /* jumped */
        }
        if (w > 0.0) {
            double A[9], v[3];
            const double mx = st->move[0], my = st->move[1], mz = st->move[2];
            double mn = N[0] * mx + N[1] * my + N[2] * mz;
            pm__speed_up(St, d, A);
            pm__mul3(A, mx - mn * N[0], my - mn * N[1], mz - mn * N[2], v);
            if (!known) pm__point_at(tb, st->tri, st->b, x);
            if (w < 1.0) {  /* and the rest towards the projection, as far as following would go (the chord) */
                if (!known) pm__point_at(tb, st->target_t, st->target_b, xt);
                const double gx = xt[0] - x[0], gy = xt[1] - x[1], gz = xt[2] - x[2];
                const double g = sqrt(gx * gx + gy * gy + gz * gz), lim = S->o.proxy_speed * pm__norm3(st->move);
                const double f = (1.0 - w) * (g > lim ? lim / g : 1.0);
                v[0] = w * v[0] + f * gx;
                v[1] = w * v[1] + f * gy;
                v[2] = w * v[2] + f * gz;
            }
            double tg[3] = {x[0] + v[0], x[1] + v[1], x[2] + v[2]};
            return pm__move_proxy(S, st, tg, sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]));
        }
    }
    if (!known) pm__point_at(tb, st->target_t, st->target_b, xt);
    return pm__move_proxy(S, st, xt, S->o.proxy_speed * pm__norm3(st->move));
}
