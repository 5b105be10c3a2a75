/* pmask servo core: the surface displacement a display shows (eq. 16), with display forces that make the
 * interpolated response meet every contact's displacement (Contacts.deformation). */
#include "pm_internal.h"

/* the contact point (t, b) less the mesh point under it (ContactSurface.mesh_offset): 0 on the mesh itself */
static void mesh_offset(const pm_table *tb, int64_t t, const double *b, double *off)
{
    off[0] = off[1] = off[2] = 0.0;
    if (!tb->parent) return;
    double x[3], beta[3];
    pm__point_at(tb, t, b, x);
    const int64_t *i = tb->mT + 3 * pm__mesh_point(tb, t, b, beta);
    for (int r = 0; r < 3; r++)
        off[r] = x[r] - (beta[0] * tb->P[3 * i[0] + r] + beta[1] * tb->P[3 * i[1] + r] + beta[2] * tb->P[3 * i[2] + r]);
}

static int deformation(pm_servo *s, double *out)
{
    const pm_table *tb = s->tab;
    if (!tb->zeta && !tb->xi.n) return -1;
    const int32_t n = s->n;
    /* one consistent snapshot of the published contacts */
    pm_contact_state *snap = s->dsnap;
    pm__read_states(s, snap);
    int32_t na = 0;
    int64_t tri[64];
    double b[64][3], u[64][3], f[64][3];
    for (int32_t l = 0; l < n; l++) {
        const pm_contact_state *one = &snap[l];
        if (one->status == PM_CONTACT || one->status == PM_REGION_EDGE || one->status == PM_DEEP) {
            tri[na] = one->triangle;
            memcpy(b[na], one->bary, sizeof b[na]);
            memcpy(u[na], one->u_bar, sizeof u[na]);
            f[na][0] = -one->force[0];
            f[na][1] = -one->force[1];
            f[na][2] = -one->force[2];
            na++;
        }
    }
    const int64_t nv = tb->nm;   /* the mesh's vertices: ζ's */
    for (int64_t i = 0; i < 3 * nv; i++) out[i] = 0.0;
    if (na == 0) return 0;
    /* C_disp f = ū' (Gaussian elimination with partial pivoting), or the rendered forces if singular */
    const int64_t m = 3 * (int64_t)na;
    double *A = s->dC, *x = s->du;
    for (int32_t i = 0; i < na; i++)
        for (int32_t j = 0; j < na; j++) {
            double C[9];
            pm__compliance(tb, tri[i], b[i], tri[j], b[j], C);
            for (int r = 0; r < 3; r++)
                for (int c = 0; c < 3; c++) A[(3 * i + r) * m + 3 * j + c] = C[3 * r + c];
        }
    /* on a subdivided contact surface the mesh point under a contact is moved by ū' plus the contact point's
     * offset from it (ContactSurface.mesh_offset, operation for operation) */
    for (int32_t i = 0; i < na; i++) {
        double off[3];
        mesh_offset(tb, tri[i], b[i], off);
        for (int r = 0; r < 3; r++) x[3 * i + r] = u[i][r] + off[r];
    }
    int singular = 0;
    for (int64_t k = 0; k < m && !singular; k++) {
        int64_t piv = k;
        for (int64_t i = k + 1; i < m; i++)
            if (fabs(A[i * m + k]) > fabs(A[piv * m + k])) piv = i;
        if (A[piv * m + k] == 0.0) {
            singular = 1;
            break;
        }
        if (piv != k) {
            for (int64_t j = 0; j < m; j++) {
                double tmp = A[k * m + j];
                A[k * m + j] = A[piv * m + j];
                A[piv * m + j] = tmp;
            }
            double tmp = x[k];
            x[k] = x[piv];
            x[piv] = tmp;
        }
        for (int64_t i = k + 1; i < m; i++) {
            double q = A[i * m + k] / A[k * m + k];
            for (int64_t j = k; j < m; j++) A[i * m + j] -= q * A[k * m + j];
            x[i] -= q * x[k];
        }
    }
    if (!singular)
        for (int64_t i = m - 1; i >= 0; i--) {
            double acc = x[i];
            for (int64_t j = i + 1; j < m; j++) acc -= A[i * m + j] * x[j];
            x[i] = acc / A[i * m + i];
        }
    for (int64_t i = 0; i < m; i++)
        if (!isfinite(x[i])) singular = 1;
    if (singular)
        for (int32_t i = 0; i < na; i++)
            for (int r = 0; r < 3; r++) x[3 * i + r] = f[i][r];
    /* eq. 16: v(contact vertex) += Σ_loads Σ_k φ_k (f @ Zt[3 row_k : 3 row_k + 3]) */
    const int64_t n3 = 3 * tb->nc;
    int64_t mt[64];
    double mb[64][3];
    for (int32_t i = 0; i < na; i++) mt[i] = pm__mesh_point(tb, tri[i], b[i], mb[i]);
    if (!tb->zeta) {  /* a compressed Ξ: the loads spread over their masks, then one product Ξ x (MaskedXi) */
        const pm_greens *g = &tb->xi;
        for (int64_t i = 0; i < n3; i++) s->dx[i] = 0.0;
        for (int32_t i = 0; i < na; i++) {
            const int64_t *tv = tb->mT + 3 * mt[i];
            for (int k = 0; k < 3; k++) {
                const int64_t rm = tb->row[tv[k]];
                const double phi = mb[i][k];
                if (phi == 0.0 || rm < 0) continue;
                for (int64_t e = g->mask_ptr[rm]; e < g->mask_ptr[rm + 1]; e++) {
                    const double w = phi * g->mask_w[e];
                    double *dx = s->dx + 3 * g->mask_cols[e];
                    for (int a = 0; a < 3; a++) dx[a] += w * x[3 * i + a];
                }
            }
        }
        pm__greens_matvec(tb, s->dx, s->dy, &s->gw);
        for (int64_t v = 0; v < nv; v++) {
            const int64_t rv = tb->row[v];
            for (int a = 0; a < 3; a++) out[3 * v + a] = rv < 0 ? 0.0 : s->dy[3 * rv + a];
        }
        return 0;
    }
    for (int64_t v = 0; v < nv; v++) {
        int64_t rv = tb->row[v];
        if (rv < 0) continue;
        double acc[3] = {0.0, 0.0, 0.0};
        for (int32_t i = 0; i < na; i++) {
            const int64_t *tv = tb->mT + 3 * mt[i];
            for (int k = 0; k < 3; k++) {
                int64_t rm = tb->row[tv[k]];
                double phi = mb[i][k];
                if (phi == 0.0 || rm < 0) continue;
                const double *Z = tb->zeta + 3 * rm * n3 + 3 * rv;
                double fx = phi * x[3 * i], fy = phi * x[3 * i + 1], fz = phi * x[3 * i + 2];
                for (int c = 0; c < 3; c++) acc[c] += fx * Z[c] + fy * Z[n3 + c] + fz * Z[2 * n3 + c];
            }
        }
        out[3 * v] = acc[0];
        out[3 * v + 1] = acc[1];
        out[3 * v + 2] = acc[2];
    }
    return 0;
}

int pm_servo_deformation(pm_servo *s, double *out)
{
#if PM_THREADS
    pthread_mutex_lock(&s->display_lock);  /* its workspace serves one caller at a time */
#endif
    int rc = deformation(s, out);
#if PM_THREADS
    pthread_mutex_unlock(&s->display_lock);
#endif
    return rc;
}

/* The display surface at the scan's resolution carried by the simulation surface (pmask.runtime.display):
 * out_d = x_d + Σ b_dk u_{v_dk} − w_d ℓ_d, w_d the largest smoothstep(1 − |x_d − p_c| / r) over the contacts. */
void pm_display_deform(const pm_table *t, const double *u, int32_t nc, const double *contacts, double radius,
                       double *out)
{
    const int64_t nd = t->nd;
    const int snap = nc > 0 && contacts && radius > 0.0;
    for (int64_t d = 0; d < nd; d++) {
        const int64_t *v = t->dV + 3 * d;
        const double *b = t->dbary + 3 * d, *x = t->dP + 3 * d;
        double w = 0.0;
        if (snap) {
            for (int32_t c = 0; c < nc; c++) {
                const double *p = contacts + 3 * c;
                const double dx = x[0] - p[0], dy = x[1] - p[1], dz = x[2] - p[2];
                const double dist = sqrt(dx * dx + dy * dy + dz * dz);
                double q = 1.0 - dist / radius;
                if (q <= 0.0) continue;
                if (q > 1.0) q = 1.0;
                q = q * q * (3.0 - 2.0 * q);
                if (q > w) w = q;
            }
        }
        for (int k = 0; k < 3; k++)
            out[3 * d + k] = x[k] + (b[0] * u[3 * v[0] + k] + b[1] * u[3 * v[1] + k] + b[2] * u[3 * v[2] + k])
                             - w * t->dlift[3 * d + k];
    }
}
