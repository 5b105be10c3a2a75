/* pmask servo core, step 3: several contacts solved together through the body (pmask.runtime.contact.coupling).
 *
 * Block Gauss-Seidel on the compliance whose diagonal blocks are the local laws' own and whose off-diagonal
 * blocks C_lk = Σ_i Σ_m φ_i(x_l) φ_m(x_k) ζ_m(i) come from the Green's functions; frictionless contacts start
 * from the exact solution of the coupled normal problem (the Delassus system), with a Jacobi first sweep (none for
 * a pair pressing on the law's first branch: the start is the laws' solution, coupling.pair_solved). */
#include "pm_internal.h"

void pm__compliance(const pm_table *tb, int64_t ta, const double *ba_in, int64_t tbi, const double *bb_in, double *C)
{
    const int64_t n3 = 3 * tb->nc;
    for (int k = 0; k < 9; k++) C[k] = 0.0;
    double ba[3], bb[3];   /* on the mesh's triangles, where ζ lives */
    ta = pm__mesh_point(tb, ta, ba_in, ba);
    tbi = pm__mesh_point(tb, tbi, bb_in, bb);
    const int64_t *ia = tb->mT + 3 * ta, *ib = tb->mT + 3 * tbi;
    for (int x = 0; x < 3; x++) {
        double pi = ba[x];
        int64_t ri = tb->row[ia[x]];
        if (pi == 0.0 || ri < 0) continue;
        for (int y = 0; y < 3; y++) {
            double pm = bb[y];
            int64_t rm = tb->row[ib[y]];
            if (pm == 0.0 || rm < 0) continue;
            double w = pi * pm;
            if (!tb->zeta) {  /* a compressed Ξ's sections: ζ_m(i) from its blocks */
                double Z[9];
                pm__greens_zeta(&tb->xi, rm, ri, Z);
                for (int k = 0; k < 9; k++) C[k] += w * Z[k];
                continue;
            }
            const double *blk = tb->zeta + 3 * rm * n3 + 3 * ri;   /* blk[c][r] = blk[c * n3 + r] */
            for (int r = 0; r < 3; r++)
                for (int c = 0; c < 3; c++) C[3 * r + c] += w * blk[c * n3 + r];
        }
    }
}

/* P_xy = ½ (ζ_y(x) + ζ_x(y)ᵀ) for mesh vertex i (x, of the first triangle) and m (y, of the second), 3x3 row-major
 * (ContactSurface.pair_blocks): from the ζ table, or from a compressed Ξ's sections (eq. 13, the mask's blocks);
 * zero where either vertex has no row */
static void pair_block(const pm_table *tb, int64_t i, int64_t m, double *o)
{
    const int64_t ri = tb->row[i], rm = tb->row[m];
    if (ri < 0 || rm < 0) {
        for (int k = 0; k < 9; k++) o[k] = 0.0;
        return;
    }
    if (tb->zeta) {
        const int64_t n3 = 3 * tb->nc;
        const double *z1 = tb->zeta + 3 * rm * n3 + 3 * ri;   /* ζ_y(x): (r, c) at z1[c * n3 + r] */
        const double *z2 = tb->zeta + 3 * ri * n3 + 3 * rm;   /* ζ_x(y) */
        for (int r = 0; r < 3; r++)
            for (int c = 0; c < 3; c++) o[3 * r + c] = 0.5 * (z1[c * n3 + r] + z2[r * n3 + c]);
        return;
    }
    double z1[9], z2[9];  /* ζ_y(x) and ζ_x(y), row-major */
    pm__greens_zeta(&tb->xi, rm, ri, z1);
    pm__greens_zeta(&tb->xi, ri, rm, z2);
    for (int r = 0; r < 3; r++)
        for (int c = 0; c < 3; c++) o[3 * r + c] = 0.5 * (z1[3 * r + c] + z2[3 * c + r]);
}

void pm__triangle_pairs(const pm_table *tb, int64_t ta, int64_t tbi, int64_t oa, int64_t ob, double *P)
{
    const int64_t *ia = tb->mT + 3 * ta, *ib = tb->mT + 3 * tbi;
    int xo[3] = {-1, -1, -1}, yo[3] = {-1, -1, -1};  /* each corner's place in the old pair (-1: new) */
    double Q[81];
    if (oa >= 0 && ob >= 0) {
        const int64_t *qa = tb->mT + 3 * oa, *qb = tb->mT + 3 * ob;
        memcpy(Q, P, sizeof Q);
        for (int x = 0; x < 3; x++)
            for (int k = 0; k < 3; k++) {
                if (qa[k] == ia[x]) xo[x] = k;
                if (qb[k] == ib[x]) yo[x] = k;
            }
    }
    for (int x = 0; x < 3; x++)
        for (int y = 0; y < 3; y++) {
            double *o = P + 27 * x + 9 * y;
            if (xo[x] >= 0 && yo[y] >= 0)
                memcpy(o, Q + 27 * xo[x] + 9 * yo[y], 9 * sizeof *o);
            else
                pair_block(tb, ia[x], ib[y], o);
        }
}

/* the pair function's blocks (pm_servo_create_paired), checked: 0, or -1 when it fails or gives a non-finite
 * number (the sums below take P as finite).  The last PM_PAIR_CACHE pairs it gave are kept, so that contacts
 * going back and forth over an edge ask once (a grasp slid 10 mm on the organ-scale kidney asked 102 times for 25
 * pairs, by hand); an entry is replaced round robin.  The core's own compressed sections (pm__greens_pairs) form
 * only the vertex pairs a move makes new (oa, ob: the mesh triangles whose blocks P holds, or -1). */
static int pair_blocks_given(pm_servo *S, int64_t ta, int64_t tbi, int64_t oa, int64_t ob, double *P)
{
    for (int k = 0; k < PM_PAIR_CACHE; k++)
        if (S->given_tri[2 * k] == ta && S->given_tri[2 * k + 1] == tbi) {
            memcpy(P, S->given_P + 81 * k, 81 * sizeof *P);
            return 0;
        }
    if (S->pairs == pm__greens_pairs)  /* the core's own compressed sections: only the vertex pairs that are new */
        pm__triangle_pairs(S->tab, ta, tbi, oa, ob, P);
    else if (S->pairs(S->pairs_user, ta, tbi, P))
        return -1;
    for (int k = 0; k < 81; k++)
        if (!isfinite(P[k])) return -1;
    const int k = S->given_next;
    S->given_next = (k + 1) % PM_PAIR_CACHE;
    memcpy(S->given_P + 81 * k, P, 81 * sizeof *P);
    S->given_tri[2 * k] = ta;
    S->given_tri[2 * k + 1] = tbi;
    return 0;
}

/* C_ab = Σ_x Σ_y φ_x φ_y P_xy, the pair's coupling block (3x3 row-major, the sum in the Python's order: three
 * independent row sums t_x = Σ_y w_xy P_xy, w_xy = φ_x φ_y, then (t_0 + t_1) + t_2, a shorter chain of dependent
 * adds than nine in a row, for the pair's tick waits on it; a zero weight adds w·P = ±0, which leaves a sum as it
 * was, P being finite: the table's loader checks).  Each entry of C is a lane of a vector: every lane is the
 * scalar's multiplies and adds in the same order (no fused multiply-add: -ffp-contract=off, and the AVX2 kernel
 * is not built with FMA), so both kernels give the Python's sums to the bit (tested against each other and the
 * Python engine with PMASK_DISABLE_CPU_FEATURES=AVX2). */
static void block_sum_sse2(const double *P, const double *ba, const double *bb, double *Sab)
{
    pm_v2 r01[3], r23[3], r45[3], r67[3];  /* two entries a register */
    double r8[3];
    for (int i = 0; i < 3; i++) {
        const double *o = P + 27 * i;
        const double w0 = ba[i] * bb[0], w1 = ba[i] * bb[1], w2 = ba[i] * bb[2];
        const pm_v2 v0 = {w0, w0}, v1 = {w1, w1}, v2 = {w2, w2};
        r01[i] = v0 * load2(o) + v1 * load2(o + 9) + v2 * load2(o + 18);
        r23[i] = v0 * load2(o + 2) + v1 * load2(o + 11) + v2 * load2(o + 20);
        r45[i] = v0 * load2(o + 4) + v1 * load2(o + 13) + v2 * load2(o + 22);
        r67[i] = v0 * load2(o + 6) + v1 * load2(o + 15) + v2 * load2(o + 24);
        r8[i] = w0 * o[8] + w1 * o[17] + w2 * o[26];
    }
    const pm_v2 s01 = r01[0] + r01[1] + r01[2], s23 = r23[0] + r23[1] + r23[2];
    const pm_v2 s45 = r45[0] + r45[1] + r45[2], s67 = r67[0] + r67[1] + r67[2];
    memcpy(Sab, &s01, sizeof s01);
    memcpy(Sab + 2, &s23, sizeof s23);
    memcpy(Sab + 4, &s45, sizeof s45);
    memcpy(Sab + 6, &s67, sizeof s67);
    Sab[8] = r8[0] + r8[1] + r8[2];
}

#if PM_X86_DISPATCH
/* the same sums four entries a register (AVX2, chosen at run time: pm__block_sum_kernel): a coupled pair's tick
 * about 100 instructions shorter on the default kidney (the bench's callgrind counts, the baseline's beside) */
typedef double pm_v4 __attribute__((vector_size(32)));

__attribute__((target("avx2"))) static void block_sum_avx2(const double *P, const double *ba, const double *bb,
                                                          double *Sab)
{
    pm_v4 lo[3], hi[3];  /* entries 0-3 and 4-7 of each row sum */
    double r8[3];
#define PM_ROW(i)                                                                     \
    do {                                                                              \
        const double *o = P + 27 * (i);                                               \
        const double w0 = ba[i] * bb[0], w1 = ba[i] * bb[1], w2 = ba[i] * bb[2];      \
        const pm_v4 v0 = {w0, w0, w0, w0}, v1 = {w1, w1, w1, w1}, v2 = {w2, w2, w2, w2}; \
        pm_v4 a, b, c, d, e, f;                                                       \
        memcpy(&a, o, sizeof a);                                                      \
        memcpy(&b, o + 9, sizeof b);                                                  \
        memcpy(&c, o + 18, sizeof c);                                                 \
        memcpy(&d, o + 4, sizeof d);                                                  \
        memcpy(&e, o + 13, sizeof e);                                                 \
        memcpy(&f, o + 22, sizeof f);                                                 \
        lo[i] = v0 * a + v1 * b + v2 * c;                                             \
        hi[i] = v0 * d + v1 * e + v2 * f;                                             \
        r8[i] = w0 * o[8] + w1 * o[17] + w2 * o[26];                                  \
    } while (0)
    PM_ROW(0);  /* unrolled by hand: the loop kept its row sums on the stack (80 instructions against 122) */
    PM_ROW(1);
    PM_ROW(2);
#undef PM_ROW
    const pm_v4 s03 = lo[0] + lo[1] + lo[2], s47 = hi[0] + hi[1] + hi[2];
    memcpy(Sab, &s03, sizeof s03);
    memcpy(Sab + 4, &s47, sizeof s47);
    Sab[8] = r8[0] + r8[1] + r8[2];
}
#endif

pm_block_sum_fn pm__block_sum_kernel(void)
{
#if PM_X86_DISPATCH
    const char *off = getenv("PMASK_DISABLE_CPU_FEATURES");  /* as numpy's NPY_DISABLE_CPU_FEATURES */
    __builtin_cpu_init();
    if (__builtin_cpu_supports("avx2") && !(off && strstr(off, "AVX2"))) return block_sum_avx2;
#endif
    return block_sum_sse2;
}

int pm__block_sum_is_avx2(pm_block_sum_fn f)
{
#if PM_X86_DISPATCH
    return f == block_sum_avx2;
#else
    (void)f;
    return 0;
#endif
}

/* C_ab for one pair of active contacts a < b: Σ_x Σ_y φ_x φ_y P_xy over the pair's blocks (those kept while both
 * contacts stay on the same mesh triangles, and a move's shared vertex pairs: pm__triangle_pairs; on the 1,543-
 * vertex kidney's subdivided surface two coupled contacts circling read 1,883 vertex-pair blocks where keying on
 * the surface's triangles and reading all nine read 10,098, by callgrind) (coupling.coupling_blocks); only C_ab
 * is stored (C_ba = C_abᵀ is read transposed: less_coupling).  0, or -1 when the pair function fails. */
static inline int coupling_pair(pm_servo *S, int32_t a, int32_t b)
{
    const pm_table *tb = S->tab;
    const size_t ab = (size_t)a * S->n + b;
    double *P = S->pair_P + 81 * ab;
    const int64_t ta = S->st[a].tri, tbi = S->st[b].tri;
    /* φ on the mesh triangles, where ζ lives (a subdivided contact surface; on the mesh itself, as they are) */
    const double *ba = S->st[a].b, *bb = S->st[b].b;
    double mba[3], mbb[3];
    int64_t ma = ta, mb = tbi;
    if (tb->parent) {
        ma = pm__mesh_point(tb, ta, ba, mba);
        mb = pm__mesh_point(tb, tbi, bb, mbb);
        ba = mba;
        bb = mbb;
    }
    const int64_t oa = S->pair_tri[2 * ab], ob = S->pair_tri[2 * ab + 1];
    if (oa != ma || ob != mb) {  /* new mesh triangles: the vertex pairs they share with the old kept */
        if (tb->zeta) {
            pm__triangle_pairs(tb, ma, mb, oa, ob, P);
        } else if (pair_blocks_given(S, ma, mb, oa, ob, P)) {
            S->pair_tri[2 * ab] = -1;  /* asked again next tick */
            return -1;
        }
        S->pair_tri[2 * ab] = ma;
        S->pair_tri[2 * ab + 1] = mb;
    }
    S->block_sum(P, ba, bb, S->cpl + 9 * ab);
    return 0;
}

/* C_lk for every pair of active contacts (act ascending, so a < b is x < y); a pair, the usual coupled case,
 * without the loops.  0, or -1 when the pair function fails. */
static int coupling_blocks(pm_servo *S, const int32_t *act, int32_t na)
{
    if (na == 2) return coupling_pair(S, act[0], act[1]);
    for (int32_t x = 0; x < na; x++)
        for (int32_t y = x + 1; y < na; y++)
            if (coupling_pair(S, act[x], act[y])) return -1;
    return 0;
}

/* x with A x = r, Gaussian elimination without pivoting (A s x s row-major, SPD), in place: 0, or -1 when a
 * pivot is not positive (coupling.solve_spd) */
static int solve_spd(double *A, double *r, double *x, int32_t s)
{
    for (int32_t k = 0; k < s; k++) {
        double p = A[k * s + k];
        if (!(p > 0.0)) return -1;
        for (int32_t i = k + 1; i < s; i++) {
            double q = A[i * s + k] / p;
            for (int32_t j = k + 1; j < s; j++) A[i * s + j] = A[i * s + j] - q * A[k * s + j];
            r[i] = r[i] - q * r[k];
        }
    }
    for (int32_t i = s - 1; i >= 0; i--) {
        double acc = r[i];
        for (int32_t j = i + 1; j < s; j++) acc = acc - A[i * s + j] * x[j];
        x[i] = acc / A[i * s + i];
    }
    return 0;
}

/* contact l's row of the coupled normal problem: its normal stiffness s_l (k, or past δ* λ k*) and δ̄_l (with δ*
 * (1 − k/k*) taken off past δ*) (coupling.normal_start); 0 or -1 (a zero stiffness: the Python's
 * ZeroDivisionError) */
static inline int normal_row(const pm_servo *S, int32_t l, double *s_l, double *r_l)
{
    const geom *g = &S->geo[l];
    const double *u = S->ubar + 3 * l;
    double r = -(g->N[0] * u[0] + g->N[1] * u[1] + g->N[2] * u[2]);
    const cstate *st = &S->st[l];
    double s = g->k;
    if (st->frozen) {  /* φ = k δ* + λ k* (δ − δ*) */
        s = g->lam * st->frozen_stiffness;
        if (s == 0.0) return -1;
        r = r - st->frozen_depth * (1.0 - g->k / s);
    } else if (s == 0.0) {
        return -1;
    }
    *s_l = s;
    *r_l = r;
    return 0;
}

/* its diagonal A_ll = 1/s_l */
static inline int normal_diagonal(const pm_servo *S, int32_t l, double *A_ll, double *r_l)
{
    double s;
    if (normal_row(S, l, &s, r_l)) return -1;
    *A_ll = 1.0 / s;
    return 0;
}

/* A_lk = N_lᵀ C_lk N_k (coupling.normal_start) */
static inline double normal_coupling(const pm_servo *S, int32_t l, int32_t k)
{
    const double *C = S->cpl + 9 * ((size_t)l * S->n + k), *N = S->geo[l].N;
    const double Mx = S->geo[k].N[0], My = S->geo[k].N[1], Mz = S->geo[k].N[2];
    double cx = C[0] * Mx + C[1] * My + C[2] * Mz;
    double cy = C[3] * Mx + C[4] * My + C[5] * Mz;
    double cz = C[6] * Mx + C[7] * My + C[8] * Mz;
    return N[0] * cx + N[1] * cy + N[2] * cz;
}

/* the coupled normal problem's A (na x na, row-major) and δ̄ (coupling.normal_start); 0 or -1 (a zero stiffness) */
static int normal_system(const pm_servo *S, const int32_t *act, int32_t na, double *A, double *r)
{
    for (int32_t a = 0; a < na; a++) {
        if (normal_diagonal(S, act[a], &A[a * na + a], &r[a])) return -1;
        for (int32_t b = a + 1; b < na; b++)  /* A is symmetric (C_kl = C_lkᵀ): each pair once */
            A[a * na + b] = A[b * na + a] = normal_coupling(S, act[a], act[b]);
    }
    return 0;
}

/* the frictionless start: the coupled normal problem, a linear complementarity problem solved exactly by Murty's
 * least-index principal pivoting (coupling.normal_start) */
static int normal_start(pm_servo *S, const int32_t *act, int32_t na, int *left)
{
    double *A = S->nA, *r = S->nr, *x = S->nx, *W = S->nW, *wr = S->nwr;
    int32_t *press = S->npress, *idx = S->nidx;
    *left = 0;
    if (na == 2) {  /* a pair pressing (a grasp: the usual coupled case), each row times its stiffness so that one
                       division is on the way (the elimination's chain of three showed in the pair's tick), and
                       what each leaves the other, ū_l − C_lk f_k = ū_l + φ_k C_lk N_k, from the products A_lk
                       is made of; anything else goes the general way below */
        const int32_t l = act[0], k = act[1];
        double s0, s1, r0, r1;
        if (normal_row(S, l, &s0, &r0) || normal_row(S, k, &s1, &r1)) return -1;
        const double *C = S->cpl + 9 * ((size_t)l * S->n + k), *N = S->geo[l].N, *M = S->geo[k].N;
        const double cx = C[0] * M[0] + C[1] * M[1] + C[2] * M[2];  /* C_lk N_k */
        const double cy = C[3] * M[0] + C[4] * M[1] + C[5] * M[2];
        const double cz = C[6] * M[0] + C[7] * M[1] + C[8] * M[2];
        const double c = N[0] * cx + N[1] * cy + N[2] * cz;  /* A_lk = N_lᵀ C_lk N_k */
        const double e0 = s0 * r0, e1 = s1 * r1, g0 = c * s0, g1 = c * s1, d = 1.0 - g0 * g1;
        if (s0 > 0.0 && s1 > 0.0 && d > 0.0) {
            const double x1 = (e1 - g1 * e0) / d, x0 = e0 - g0 * x1;
            if (x0 >= 0.0 && x1 >= 0.0) {
                double *gl = S->gsf + 3 * l, *gk = S->gsf + 3 * k;
                gl[0] = -x0 * N[0];
                gl[1] = -x0 * N[1];
                gl[2] = -x0 * N[2];
                gk[0] = -x1 * M[0];
                gk[1] = -x1 * M[1];
                gk[2] = -x1 * M[2];
                const double wx = C[0] * N[0] + C[3] * N[1] + C[6] * N[2];  /* C_kl N_l = C_lkᵀ N_l */
                const double wy = C[1] * N[0] + C[4] * N[1] + C[7] * N[2];
                const double wz = C[2] * N[0] + C[5] * N[1] + C[8] * N[2];
                const double *ul = S->ubar + 3 * l, *uk = S->ubar + 3 * k;
                double *vl = S->res[l].ueff, *vk = S->res[k].ueff;
                vl[0] = ul[0] + x1 * cx;
                vl[1] = ul[1] + x1 * cy;
                vl[2] = ul[2] + x1 * cz;
                vk[0] = uk[0] + x0 * wx;
                vk[1] = uk[1] + x0 * wy;
                vk[2] = uk[2] + x0 * wz;
                *left = 1;
                /* both pressing on the law's first branch (no δ*): the start is the laws' solution, f_l = −φ_l N_l
                   with φ_l = k_l δ_l on δ_l = −N_l · ū'_l, so their results are taken from it (the surface's
                   displacement K̃⁻¹ f, δ from ū' as the law has it) and no sweep runs: the law's chain (δ, then k δ,
                   then f) is off the pair's tick.  Anywhere else the laws run on ū' (a Jacobi sweep). */
                const double dl = -(N[0] * vl[0] + N[1] * vl[1] + N[2] * vl[2]);
                const double dk = -(M[0] * vk[0] + M[1] * vk[1] + M[2] * vk[2]);
                if (x0 > 0.0 && x1 > 0.0 && dl > 0.0 && dk > 0.0 && !S->st[l].frozen && !S->st[k].frozen) {
                    lres *Rl = &S->res[l], *Rk = &S->res[k];
                    memcpy(Rl->f, gl, sizeof Rl->f);
                    memcpy(Rk->f, gk, sizeof Rk->f);
                    pm__mul3(S->geo[l].Kti, gl[0], gl[1], gl[2], Rl->u2);
                    pm__mul3(S->geo[k].Kti, gk[0], gk[1], gk[2], Rk->u2);
                    Rl->sliding = Rk->sliding = 1;
                    Rl->delta = dl;
                    Rk->delta = dk;
                    *left = 2;
                }
                return 0;
            }
        }
    }
    /* every contact pressing (the usual case): the pivoting's first solve, eliminated in place of the system
       itself; only when a contact pulls is the system built again (the same values) for the pivots */
    if (normal_system(S, act, na, W, wr)) return -1;
    int ok = solve_spd(W, wr, x, na) == 0, pulls = 0;
    for (int32_t a = 0; ok && a < na; a++) pulls |= x[a] < 0.0;
    if (pulls) {
        if (normal_system(S, act, na, A, r)) return -1;
        for (int32_t a = 0; a < na; a++) press[a] = 1;
        for (int32_t it = 0; it < PIVOTS * na; it++) {
            int32_t m = 0;
            for (int32_t a = 0; a < na; a++)
                if (press[a]) idx[m++] = a;
            for (int32_t i = 0; i < m; i++) {
                for (int32_t j = 0; j < m; j++) W[i * m + j] = A[idx[i] * na + idx[j]];
                wr[i] = r[idx[i]];
            }
            ok = solve_spd(W, wr, S->nsol, m) == 0;
            if (!ok) break;
            for (int32_t a = 0; a < na; a++) x[a] = 0.0;
            for (int32_t i = 0; i < m; i++) x[idx[i]] = S->nsol[i];
            int32_t flip = -1;
            for (int32_t a = 0; a < na && flip < 0; a++) {
                if (press[a]) {
                    if (x[a] < 0.0) flip = a;
                } else {
                    double w = r[a];
                    for (int32_t b = 0; b < na; b++)
                        if (press[b]) w = w - A[a * na + b] * x[b];
                    if (w > 0.0) flip = a;
                }
            }
            if (flip < 0) break;
            press[flip] = !press[flip];
        }
    }
    for (int32_t a = 0; a < na; a++) {
        int32_t l = act[a];
        double p = ok ? PYMAX(x[a], 0.0) : 0.0;
        const double *N = S->geo[l].N;
        S->gsf[3 * l] = -p * N[0];
        S->gsf[3 * l + 1] = -p * N[1];
        S->gsf[3 * l + 2] = -p * N[2];
    }
    return 0;
}

/* u less C_lk g_k, the others' push on contact l through the body; C_lk is stored for l < k only (C_kl = C_lkᵀ) */
static inline __attribute__((always_inline)) void less_coupling(const pm_servo *S, int32_t l, int32_t k, double *u)
{
    const double *g = S->gsf + 3 * k;
    const double gx = g[0], gy = g[1], gz = g[2];
    if (l < k) {
        const double *C = S->cpl + 9 * ((size_t)l * S->n + k);
        u[0] -= C[0] * gx + C[1] * gy + C[2] * gz;
        u[1] -= C[3] * gx + C[4] * gy + C[5] * gz;
        u[2] -= C[6] * gx + C[7] * gy + C[8] * gz;
    } else {
        const double *C = S->cpl + 9 * ((size_t)k * S->n + l);
        u[0] -= C[0] * gx + C[3] * gy + C[6] * gz;
        u[1] -= C[1] * gx + C[4] * gy + C[7] * gz;
        u[2] -= C[2] * gx + C[5] * gy + C[8] * gz;
    }
}

int pm__solve(pm_servo *S, const int32_t *act, int32_t na)
{
    const int coupled = S->o.coupled && na > 1;
    if (coupled && coupling_blocks(S, act, na)) return -1;
    int left = 0;  /* 1: the pair's start also left each contact its ū' (res[l].ueff); 2: and its law's result */
    if (coupled && S->frictionless) {
        if (normal_start(S, act, na, &left)) return -1;
    } else {
        for (int32_t x = 0; x < na; x++) {  /* warm start: last tick's forces */
            int32_t l = act[x];
            S->gsf[3 * l] = S->st[l].law_force[0];
            S->gsf[3 * l + 1] = S->st[l].law_force[1];
            S->gsf[3 * l + 2] = S->st[l].law_force[2];
        }
    }
    /* block Gauss-Seidel, each contact's law on ū less the others' latest forces through C_lk; from the exact
       frictionless start the first sweep is Jacobi instead (every ū' from the start, so the laws do not wait on
       one another; the start solves their normal problem, so the sweep only confirms it) */
    const int sweeps = left == 2 ? 0 : coupled ? GS_SWEEPS : 1, jacobi = coupled && S->frictionless;
    for (int sw = 0; sw < sweeps; sw++) {
        double change = 0.0, size = 0.0;
        if (sw == 0 && jacobi && !left)
            for (int32_t x = 0; x < na; x++) {
                const int32_t l = act[x];
                double *u = S->res[l].ueff;
                memcpy(u, S->ubar + 3 * l, 3 * sizeof *u);
                for (int32_t y = 0; y < na; y++)
                    if (y != x) less_coupling(S, l, act[y], u);
            }
        /* a pair whose laws do not wait on each other (the Jacobi sweep, or two contacts uncoupled): both at once */
        const int two = na == 2 && (!coupled || (sw == 0 && jacobi));
        if (two) {
            const int32_t a = act[0], b = act[1];
            const double *ua = coupled ? S->res[a].ueff : S->ubar + 3 * a;
            const double *ub = coupled ? S->res[b].ueff : S->ubar + 3 * b;
            if (pm__local_law2(S, &S->st[a], &S->geo[a], ua, &S->res[a], &S->st[b], &S->geo[b], ub, &S->res[b]))
                return -1;
        }
        for (int32_t x = 0; x < na; x++) {
            const int32_t l = act[x];
            lres *R = &S->res[l];
            if (two) {
                if (!coupled) memcpy(R->ueff, S->ubar + 3 * l, sizeof R->ueff);  /* coupled: ū' is there */
            } else {
                double ux = S->ubar[3 * l], uy = S->ubar[3 * l + 1], uz = S->ubar[3 * l + 2];
                if (coupled) {
                    double u[3] = {ux, uy, uz};
                    if (sw == 0 && jacobi)
                        memcpy(u, R->ueff, sizeof u);
                    else
                        for (int32_t y = 0; y < na; y++)
                            if (y != x) less_coupling(S, l, act[y], u);
                    ux = u[0];
                    uy = u[1];
                    uz = u[2];
                }
                if (pm__local_law(S, &S->st[l], &S->geo[l], ux, uy, uz, R)) return -1;
                R->ueff[0] = ux;
                R->ueff[1] = uy;
                R->ueff[2] = uz;
            }
            double *old = S->gsf + 3 * l;
            double c0 = fabs(R->f[0] - old[0]), c1 = fabs(R->f[1] - old[1]), c2 = fabs(R->f[2] - old[2]);
            old[0] = R->f[0];
            old[1] = R->f[1];
            old[2] = R->f[2];
            change = PYMAX(PYMAX(PYMAX(change, c0), c1), c2);
            size = PYMAX(PYMAX(PYMAX(size, fabs(R->f[0])), fabs(R->f[1])), fabs(R->f[2]));
        }
        if (change <= 1e-13 * size) break;
    }
    for (int32_t x = 0; x < na; x++) {
        int32_t l = act[x];
        memcpy(S->st[l].law_force, S->gsf + 3 * l, sizeof S->st[l].law_force);
    }
    return 0;
}
