/* The P1 Green's-function stage by selected inversion over CHOLMOD's supernodal factor.
 *
 * Built by tools/build_native.sh (make venv) against Debian's SuiteSparse and the system LAPACK
 * (threaded OpenBLAS after tools/install_cholmod.sh), loaded with ctypes by precompute/native.py.
 * The maths is in precompute/condense.py.  In short, with A = K_FF (every unconstrained dof),
 * P A P^T = L L^T (METIS nested dissection, postordered supernodes) and E the unit columns of the
 * wanted dofs (the free surface),
 *
 *     (A^-1)_EE = E^T P^T L^-T L^-1 P E = W^T W,      W = L^-1 P E.
 *
 * Column w of W is non-zero only on the elimination-tree path from w's pivot to the root, so the
 * rows of supernode s carry only the wanted columns of s's subtree; with the tree postordered and
 * the wanted dofs sorted by pivot those are one contiguous range [lo_s, hi_s).  Then
 *
 *     W^T W = sum_s  W_s^T W_s     (a rank-|s| update of the [lo_s, hi_s)^2 block: one dsyrk),
 *
 * and W_s comes from a blocked forward solve restricted to that range (dtrsm on the diagonal
 * block, dgemm + scatter onto the ancestors' rows).  On the kidney this is ~6x fewer flops than
 * forming the dense Schur complement and inverting it (potrf + trtri + lauum, n^3; 13.9 against
 * 82 Gflop at the default size): only the top separators (a few hundred dofs) meet every surface
 * dof.  precompute/selinv.py is the same algorithm in numpy (the pip-only route; tested against
 * this file on the same factor).
 *
 *   pmask_factor   A (lower CSC) -> CHOLMOD's supernodal L (METIS, AMD if METIS fails), whose
 *                  arrays the caller reads (and may checkpoint) through pmask_factor_arrays.
 *   pmask_selinv   from those arrays (CHOLMOD not needed): X[i, j] = (A^-1)[want_i, want_j] scale_j
 *                  into the caller's zeroed nw x nw buffer, row-major, in place.
 *   pmask_free     frees what pmask_factor returned.
 */
#include <pthread.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <time.h>
#include <unistd.h>
#include <cholmod.h>

void dtrsm_(const char *side, const char *uplo, const char *transa, const char *diag, const int *m,
            const int *n, const double *alpha, const double *a, const int *lda, double *b, const int *ldb,
            size_t, size_t, size_t, size_t);
void dsyrk_(const char *uplo, const char *trans, const int *n, const int *k, const double *alpha,
            const double *a, const int *lda, const double *beta, double *c, const int *ldc, size_t, size_t);
void dgemm_(const char *transa, const char *transb, const int *m, const int *n, const int *k,
            const double *alpha, const double *a, const int *lda, const double *b, const int *ldb,
            const double *beta, double *c, const int *ldc, size_t, size_t);

/* bumped whenever a signature below changes; precompute/native.py refuses a library built from
 * another version (a stale build in the venv) instead of calling it with the wrong arguments */
int pmask_abi_version(void) { return 3; }

typedef struct {
    cholmod_common c;
    cholmod_factor *L;
} pm_factor;

/* Faults a zeroed buffer in from its end, writing nothing new: an atomic add of zero per page. */
typedef struct { double *x; size_t n; } prefault_job;

static void *prefault(void *arg)
{
    prefault_job *job = arg;
    size_t step = (size_t)sysconf(_SC_PAGESIZE) / sizeof(double), k;
    for (k = job->n; k >= step; k -= step)
        __atomic_fetch_add((long *)(job->x + k - step), 0L, __ATOMIC_RELAXED);
    return NULL;
}

/* Transparent huge pages for a large buffer (when the kernel offers them on request): measured on
 * this VM, the first touch of 1.2 GB in a fresh process drops from ~2.5 s to ~0.9 s. */
static void want_huge_pages(void *p, size_t bytes)
{
#ifdef MADV_HUGEPAGE
    size_t page = (size_t)sysconf(_SC_PAGESIZE);
    size_t a = ((size_t)p + page - 1) / page * page, b = ((size_t)p + bytes) / page * page;
    if (b > a)
        madvise((void *)a, b - a, MADV_HUGEPAGE);
#else
    (void)p;
    (void)bytes;
#endif
}

static double now(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return t.tv_sec + 1e-9 * t.tv_nsec;
}

void pmask_free(pm_factor *f)
{
    if (f == NULL)
        return;
    if (f->L != NULL)
        cholmod_l_free_factor(&f->L, &f->c);
    cholmod_l_finish(&f->c);
    free(f);
}

/* A: n x n lower CSC, sorted rows.  Returns 0 and a handle on success; k > 0 if A is not positive
 * definite at (permuted) column k-1; -1 on a CHOLMOD failure (out of memory, say).
 * times: analyse (ordering included), numeric, nnz(L) as stored, the order used (1 AMD, 2 METIS),
 * CHOLMOD's flop count. */
int pmask_factor(long n, long *Ap, long *Ai, double *Ax, pm_factor **out, double *times)
{
    cholmod_sparse A;
    pm_factor *f = calloc(1, sizeof *f);
    int status = 0, k;
    double t0;

    *out = NULL;
    if (f == NULL)
        return -1;
    cholmod_l_start(&f->c);
    f->c.print = 0;
    f->c.supernodal = CHOLMOD_SUPERNODAL;
    f->c.postorder = 1;          /* subtrees must be contiguous column ranges (pmask_selinv) */

    memset(&A, 0, sizeof A);
    A.nrow = A.ncol = (size_t)n;
    A.nzmax = (size_t)Ap[n];
    A.p = Ap;
    A.i = Ai;
    A.x = Ax;
    A.stype = -1;                /* the lower triangle holds the symmetric matrix */
    A.itype = CHOLMOD_LONG;
    A.xtype = CHOLMOD_REAL;
    A.dtype = CHOLMOD_DOUBLE;
    A.sorted = 1;
    A.packed = 1;

    /* nested dissection: the selected inversion's work is sum over columns of (wanted dofs in the
     * column's subtree)^2, which METIS's small top separators keep ~2x below AMD's (kidney) */
    t0 = now();
    for (k = 0; k < 2 && f->L == NULL; k++) {
        f->c.nmethods = 1;
        f->c.method[0].ordering = k == 0 ? CHOLMOD_METIS : CHOLMOD_AMD;
        f->c.status = CHOLMOD_OK;
        f->L = cholmod_l_analyze(&A, &f->c);
        times[3] = k == 0 ? 2 : 1;
    }
    times[0] = now() - t0;
    if (f->L == NULL) {
        pmask_free(f);
        return -1;
    }
    t0 = now();
    cholmod_l_factorize(&A, f->L, &f->c);
    times[1] = now() - t0;
    if (f->c.status == CHOLMOD_NOT_POSDEF)
        status = (int)f->L->minor + 1;
    else if (f->c.status != CHOLMOD_OK || !f->L->is_super)
        status = -1;
    if (status != 0) {
        pmask_free(f);
        return status;
    }
    times[2] = (double)f->L->xsize;
    times[4] = f->c.fl;
    *out = f;
    return 0;
}

/* The supernodal arrays of the factor (CHOLMOD's storage, valid until pmask_free):
 * sizes = nsuper, len(s), len(x); arrays = super, pi, px (nsuper + 1 each), s, x, Perm (n). */
void pmask_factor_arrays(pm_factor *f, long *sizes, void **arrays)
{
    cholmod_factor *L = f->L;
    sizes[0] = (long)L->nsuper;
    sizes[1] = (long)L->ssize;
    sizes[2] = (long)L->xsize;
    arrays[0] = L->super;
    arrays[1] = L->pi;
    arrays[2] = L->px;
    arrays[3] = L->s;
    arrays[4] = L->x;
    arrays[5] = L->Perm;
}

/* Selected inverse of A = P^T L L^T P on the wanted dofs (see the top of this file).
 * n, nsuper, super, pi, px, Ls, Lx, Perm: CHOLMOD's supernodal factor (postordered).
 * want: nw distinct dofs of A; scale: nw factors; D: nw x nw, all zero on entry.
 * On return D[j + i nw] = (A^-1)[want_i, want_j] scale_j: read row-major, the scaled inverse X
 * (computed column-major as its transpose diag(scale) A^-1, both triangles).
 * times: setup, forward solve (trsm + gemm + scatter), syrk, mirror + permutation; the flops of
 * the dense kernels; the doubles of W; the wait for the prefault helper after the solve.
 * Returns 0; -2 for a bad want list; -3 if the factor is not postordered; -1 out of memory. */
int pmask_selinv(long n, long nsuper, const long *super, const long *pi, const long *px, const long *Ls,
                 const double *Lx, const long *Perm, long nw, const long *want, const double *scale,
                 double *D, double *times)
{
    long *iperm = NULL, *rank = NULL, *cnt = NULL, *snode = NULL, *parent = NULL, *fc = NULL,
         *ncols_sub = NULL, *lo = NULL, *woff = NULL, *sp = NULL;
    double *W = NULL, *U = NULL, *tmp = NULL;
    long s, k, i, j, r, total = 0, umax = 0;
    int status = 0, started = 0;
    pthread_t helper;
    const double one = 1.0, zero = 0.0;
    double t0 = now(), t_solve = 0, t_syrk = 0, flops = 0;

    iperm = malloc(sizeof(long) * n);
    rank = malloc(sizeof(long) * n);
    cnt = malloc(sizeof(long) * (n + 1));
    snode = malloc(sizeof(long) * n);
    parent = malloc(sizeof(long) * nsuper);
    fc = malloc(sizeof(long) * nsuper);
    ncols_sub = calloc(nsuper, sizeof(long));
    lo = malloc(sizeof(long) * nsuper);
    woff = malloc(sizeof(long) * (nsuper + 1));
    sp = malloc(sizeof(long) * (nw > 0 ? nw : 1));
    if (!iperm || !rank || !cnt || !snode || !parent || !fc || !ncols_sub || !lo || !woff || !sp) {
        status = -1;
        goto done;
    }
    for (k = 0; k < n; k++) {
        iperm[Perm[k]] = k;
        rank[k] = -1;
    }
    for (i = 0; i < nw; i++) {
        if (want[i] < 0 || want[i] >= n || rank[iperm[want[i]]] >= 0) {
            status = -2;
            goto done;
        }
        rank[iperm[want[i]]] = i;   /* the caller's index, for now */
    }
    /* cnt[k]: wanted pivots before column k; sp[i]: sorted (pivot-order) position of want_i */
    cnt[0] = 0;
    for (k = 0; k < n; k++) {
        cnt[k + 1] = cnt[k];
        if (rank[k] >= 0) {
            sp[rank[k]] = cnt[k];
            cnt[k + 1]++;
        }
    }
    /* supernodal elimination tree; fc[s]: first column of s's subtree */
    for (s = 0; s < nsuper; s++) {
        for (k = super[s]; k < super[s + 1]; k++)
            snode[k] = s;
        fc[s] = super[s];
        parent[s] = -1;
    }
    for (s = 0; s < nsuper; s++) {
        long nc = super[s + 1] - super[s], nrow = pi[s + 1] - pi[s];
        if (nrow > nc)
            parent[s] = snode[Ls[pi[s] + nc]];
        ncols_sub[s] += nc;
        if (parent[s] >= 0) {
            if (parent[s] <= s) {
                status = -3;
                goto done;
            }
            if (fc[s] < fc[parent[s]])
                fc[parent[s]] = fc[s];
            ncols_sub[parent[s]] += ncols_sub[s];
        }
        if (ncols_sub[s] != super[s + 1] - fc[s]) {   /* the subtree is not a contiguous range */
            status = -3;
            goto done;
        }
    }
    /* W_s: m_s x nc_s column-major (the transpose of W's rows of s, restricted to [lo_s, hi_s)) */
    woff[0] = 0;
    for (s = 0; s < nsuper; s++) {
        long nc = super[s + 1] - super[s], nr = pi[s + 1] - pi[s] - nc, m;
        lo[s] = cnt[fc[s]];
        m = cnt[super[s + 1]] - lo[s];
        woff[s + 1] = woff[s] + m * nc;
        if (m * nr > umax)
            umax = m * nr;
    }
    total = woff[nsuper];
    W = calloc(total > 0 ? total : 1, sizeof(double));
    U = malloc(sizeof(double) * (umax > 0 ? umax : 1));
    tmp = malloc(sizeof(double) * (nw > 0 ? nw : 1));
    if (!W || !U || !tmp) {
        status = -1;
        goto done;
    }
    want_huge_pages(W, sizeof(double) * total);
    want_huge_pages(U, sizeof(double) * umax);
    for (k = 0; k < n; k++)       /* W = L^-1 P E starts as P E */
        if (rank[k] >= 0) {
            s = snode[k];
            long m = cnt[super[s + 1]] - lo[s];
            W[woff[s] + (cnt[k] - lo[s]) + (k - super[s]) * m] = 1.0;
        }
    times[0] = now() - t0;

    /* the helper faults D in (first touch costs ~0.5 s per GB on this VM) while the forward
     * solve runs; the products then write into mapped memory */
    {
        prefault_job job = {D, (size_t)nw * (size_t)nw};
        want_huge_pages(D, sizeof(double) * job.n);
        started = pthread_create(&helper, NULL, prefault, &job) == 0;

        /* forward solve W = L^-1 P E, supernode by supernode (children before parents) */
        t0 = now();
        for (s = 0; s < nsuper; s++) {
            long nc = super[s + 1] - super[s], nrow = pi[s + 1] - pi[s], nr = nrow - nc;
            long m = cnt[super[s + 1]] - lo[s];
            int im = (int)m, inc = (int)nc, inr = (int)nr, ild = (int)nrow;
            double *X = W + woff[s];
            const double *Lss = Lx + px[s];
            if (m == 0)
                continue;
            /* rows of s:  W_s <- L_ss^-1 W_s, i.e. X <- X L_ss^-T */
            dtrsm_("R", "L", "T", "N", &im, &inc, &one, Lss, &ild, X, &im, 1, 1, 1, 1);
            flops += (double)m * nc * nc;
            if (nr == 0)
                continue;
            /* ancestors' rows: W_R -= L_Rs W_s, i.e. U = X L_Rs^T, then scattered */
            dgemm_("N", "T", &im, &inr, &inc, &one, X, &im, Lss + nc, &ild, &zero, U, &im, 1, 1);
            flops += 2.0 * m * nr * nc;
            for (i = 0; i < nr; i++) {
                long row = Ls[pi[s] + nc + i], t = snode[row];
                long mt = cnt[super[t + 1]] - lo[t];
                double *dst = W + woff[t] + (lo[s] - lo[t]) + (row - super[t]) * mt;
                const double *src = U + i * m;
                for (r = 0; r < m; r++)
                    dst[r] -= src[r];
            }
        }
        t_solve = now() - t0;
        if (started)
            pthread_join(helper, NULL);
        started = 0;
    }
    times[6] = now() - t0 - t_solve;   /* waiting for the helper */

    /* (A^-1)_EE[lo:hi, lo:hi] += W_s^T W_s  (lower triangle), one rank-nc_s update per supernode */
    t0 = now();
    for (s = 0; s < nsuper; s++) {
        long nc = super[s + 1] - super[s], m = cnt[super[s + 1]] - lo[s];
        int im = (int)m, inc = (int)nc, inw = (int)nw;
        if (m == 0)
            continue;
        dsyrk_("L", "N", &im, &inc, &one, W + woff[s], &im, &one, D + lo[s] + lo[s] * nw, &inw, 1, 1);
        flops += (double)m * m * nc;
    }
    t_syrk = now() - t0;
    times[1] = t_solve;
    times[2] = t_syrk;

    t0 = now();
    /* mirror the lower triangle (tiles of the strict upper part from their transposes) */
    {
        enum { T = 64 };
        long i0, j0;
        for (j0 = 0; j0 < nw; j0 += T) {
            long j1 = j0 + T < nw ? j0 + T : nw;
            for (i0 = j0; i0 < nw; i0 += T) {
                long i1 = i0 + T < nw ? i0 + T : nw;
                for (j = j0; j < j1; j++)
                    for (i = (i0 > j + 1 ? i0 : j + 1); i < i1; i++)
                        D[j + i * nw] = D[i + j * nw];
            }
        }
    }
    /* D[:, j] <- s * D[sp, sp[j]] in place, one pass: follow the cycles of sp, each column gathered
     * from the one it replaces (still intact), the cycle's first column from a copy */
    {
        char *moved = calloc(nw > 0 ? nw : 1, 1);
        double *first = malloc(sizeof(double) * (nw > 0 ? nw : 1));
        if (moved == NULL || first == NULL) {
            free(moved);
            free(first);
            status = -1;
            goto done;
        }
        for (j = 0; j < nw; j++) {
            long cur = j;
            if (moved[j])
                continue;
            memcpy(first, D + j * nw, sizeof(double) * nw);
            for (;;) {
                long nxt = sp[cur];
                const double *src = nxt == j ? first : D + nxt * nw;
                double *col = D + cur * nw;
                moved[cur] = 1;
                for (i = 0; i < nw; i++)
                    tmp[i] = src[sp[i]] * scale[i];
                memcpy(col, tmp, sizeof(double) * nw);
                if (nxt == j)
                    break;
                cur = nxt;
            }
        }
        free(moved);
        free(first);
    }
    times[3] = now() - t0;
    times[4] = flops;
    times[5] = (double)total;

done:
    free(iperm);
    free(rank);
    free(cnt);
    free(snode);
    free(parent);
    free(fc);
    free(ncols_sub);
    free(lo);
    free(woff);
    free(sp);
    free(W);
    free(U);
    free(tmp);
    return status;
}
