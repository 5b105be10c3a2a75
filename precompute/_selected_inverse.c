/* The P1 Green's-function stage by selected inversion over CHOLMOD's supernodal factor.
 *
 * Built by the build backend (setup.py, as the extension pmask.precompute._selinv) against Debian's
 * SuiteSparse and the system LAPACK (threaded OpenBLAS after `make system-deps`), loaded with ctypes by
 * precompute/native.py.  The maths is in precompute/greens.py.  In short, with A = K_FF (every
 * unconstrained dof),
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
 *                  into the caller's zeroed nw x nw buffer, row-major, in place (P1: the load is a
 *                  scaled unit column, so the block is symmetric and one dsyrk per supernode).
 *   pmask_selcols  X = E^T A^-1 B = W_E^T W_B for a sparse load B (P2: a P1 traction's consistent
 *                  load reaches corner and edge nodes), one dgemm per supernode; see below.
 *   pmask_free     frees what pmask_factor returned.
 *
 * Indices are int64_t (CHOLMOD's SuiteSparse_long on LP64 and LLP64 alike); BLAS takes int, and every
 * size passed to it is checked to fit (-5 otherwise).  The factor's arrays may come from a checkpoint on
 * disk: they are checked (-6) before any of them is used as an index.  Each call takes its own cancel flag
 * (pmask_cancel_set from another thread): the loops stop at the next supernode and return -4.
 */
#define _DEFAULT_SOURCE  /* madvise and MADV_HUGEPAGE (glibc hides them under a bare _POSIX_C_SOURCE) */
#define _POSIX_C_SOURCE 200809L  /* clock_gettime, CLOCK_MONOTONIC, sysconf under -std=c99 */
#include <limits.h>
#include <pthread.h>
#include <stdint.h>
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
int pmask_abi_version(void) { return 6; }

/* A call's cancel flag (NULL: none), set by the caller's other thread (Ctrl-C, a time budget) through
 * pmask_cancel_set: the supernode loops stop at the next supernode and return -4.  CHOLMOD's
 * factorisation cannot be stopped inside. */
void pmask_cancel_set(int32_t *flag, int32_t value) { __atomic_store_n(flag, value, __ATOMIC_RELAXED); }

static int cancelled(const int32_t *flag) { return flag != NULL && __atomic_load_n(flag, __ATOMIC_RELAXED) != 0; }

/* -6 unless the supernodal arrays (from CHOLMOD, or read back from a checkpoint) describe a factor of an
 * n x n matrix whose every index lies in range: super strictly increasing from 0 to n, pi and px
 * non-decreasing within Ls's ns and Lx's nx entries, each supernode's row list starting with its own
 * columns and then rows below them, Perm a permutation of 0..n-1 (iperm: workspace of n). */
static int check_factor(int64_t n, int64_t nsuper, const int64_t *super, const int64_t *pi, const int64_t *px,
                        const int64_t *Ls, int64_t ns, int64_t nx, const int64_t *Perm, int64_t *iperm)
{
    int64_t s, k;
    if (n < 0 || nsuper < 0 || ns < 0 || nx < 0 || super[0] != 0 || super[nsuper] != n || pi[0] != 0 || px[0] != 0)
        return -6;
    for (s = 0; s < nsuper; s++) {
        int64_t nc = super[s + 1] - super[s], nrow = pi[s + 1] - pi[s];
        if (nc <= 0 || nrow < nc || pi[s + 1] > ns || px[s + 1] < px[s] || nrow > INT64_MAX / nc ||
            px[s + 1] - px[s] < nrow * nc || px[s + 1] > nx)
            return -6;
        for (k = 0; k < nrow; k++) {
            int64_t r = Ls[pi[s] + k];
            if (k < nc ? r != super[s] + k : (r < super[s + 1] || r >= n || (k > nc && r <= Ls[pi[s] + k - 1])))
                return -6;
        }
    }
    for (k = 0; k < n; k++)
        iperm[k] = -1;
    for (k = 0; k < n; k++) {
        if (Perm[k] < 0 || Perm[k] >= n || iperm[Perm[k]] >= 0)
            return -6;
        iperm[Perm[k]] = k;
    }
    return 0;
}

/* -5 unless every supernode's row count fits BLAS's int (m and k are bounded by the caller's sizes) */
static int check_blas_sizes(int64_t nsuper, const int64_t *pi, int64_t most)
{
    if (most > INT_MAX)
        return -5;
    for (int64_t s = 0; s < nsuper; s++)
        if (pi[s + 1] - pi[s] > INT_MAX)
            return -5;
    return 0;
}

typedef struct {
    cholmod_common c;
    cholmod_factor *L;
} pm_factor;

/* Faults a zeroed buffer in from its end, writing nothing new: an atomic add of zero per page. */
typedef struct { double *x; size_t n; const int32_t *cancel; } prefault_job;

static void *prefault(void *arg)
{
    prefault_job *job = arg;
    size_t step = (size_t)sysconf(_SC_PAGESIZE) / sizeof(double), k;
    for (k = job->n; k >= step && !cancelled(job->cancel); k -= step)
        __atomic_fetch_add((int64_t *)(job->x + k - step), (int64_t)0, __ATOMIC_RELAXED);
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
int pmask_factor(int64_t n, int64_t *Ap, int64_t *Ai, double *Ax, pm_factor **out, double *times)
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
        status = f->L->minor < (size_t)INT_MAX ? (int)f->L->minor + 1 : INT_MAX;
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
void pmask_factor_arrays(pm_factor *f, int64_t *sizes, void **arrays)
{
    cholmod_factor *L = f->L;
    sizes[0] = (int64_t)L->nsuper;
    sizes[1] = (int64_t)L->ssize;
    sizes[2] = (int64_t)L->xsize;
    arrays[0] = L->super;
    arrays[1] = L->pi;
    arrays[2] = L->px;
    arrays[3] = L->s;
    arrays[4] = L->x;
    arrays[5] = L->Perm;
}

/* The supernodal elimination tree of a postordered factor: each supernode's parent, the first
 * column of its subtree, and each column's supernode. */
typedef struct {
    int64_t *snode, *parent, *fc, *iperm;
} pm_tree;

static void tree_free(pm_tree *t)
{
    free(t->snode);
    free(t->parent);
    free(t->fc);
    free(t->iperm);
    t->snode = t->parent = t->fc = t->iperm = NULL;
}

/* 0; -1 out of memory; -3 if a subtree is not a contiguous range of columns (not postordered) */
static int tree_init(pm_tree *t, int64_t n, int64_t nsuper, const int64_t *super, const int64_t *pi,
                     const int64_t *Ls, const int64_t *Perm)
{
    int64_t s, k, *ncols_sub = calloc(nsuper > 0 ? nsuper : 1, sizeof(int64_t));
    t->snode = malloc(sizeof(int64_t) * (n > 0 ? n : 1));
    t->parent = malloc(sizeof(int64_t) * (nsuper > 0 ? nsuper : 1));
    t->fc = malloc(sizeof(int64_t) * (nsuper > 0 ? nsuper : 1));
    t->iperm = malloc(sizeof(int64_t) * (n > 0 ? n : 1));
    if (!ncols_sub || !t->snode || !t->parent || !t->fc || !t->iperm) {
        free(ncols_sub);
        tree_free(t);
        return -1;
    }
    for (k = 0; k < n; k++)
        t->iperm[Perm[k]] = k;
    for (s = 0; s < nsuper; s++) {
        for (k = super[s]; k < super[s + 1]; k++)
            t->snode[k] = s;
        t->fc[s] = super[s];
        t->parent[s] = -1;
    }
    for (s = 0; s < nsuper; s++) {
        int64_t nc = super[s + 1] - super[s], nrow = pi[s + 1] - pi[s];
        int64_t par = nrow > nc ? t->snode[Ls[pi[s] + nc]] : -1;
        t->parent[s] = par;
        ncols_sub[s] += nc;
        if (par >= 0) {
            if (par <= s)
                goto unordered;
            if (t->fc[s] < t->fc[par])
                t->fc[par] = t->fc[s];
            ncols_sub[par] += ncols_sub[s];
        }
        if (ncols_sub[s] != super[s + 1] - t->fc[s])   /* the subtree is not a contiguous range */
            goto unordered;
    }
    free(ncols_sub);
    return 0;
unordered:
    free(ncols_sub);
    tree_free(t);
    return -3;
}

/* Selected inverse of A = P^T L L^T P on the wanted dofs (see the top of this file).
 * n, nsuper, super, pi, px, Ls, Lx, Perm: CHOLMOD's supernodal factor (postordered).
 * want: nw distinct dofs of A; scale: nw factors; D: nw x nw, all zero on entry.
 * On return D[j + i nw] = (A^-1)[want_i, want_j] scale_j: read row-major, the scaled inverse X
 * (computed column-major as its transpose diag(scale) A^-1, both triangles).
 * times: setup, forward solve (trsm + gemm + scatter), syrk, mirror + permutation; the flops of
 * the dense kernels; the doubles of W; the wait for the prefault helper after the solve.
 * ns, nx: the lengths of Ls and Lx.  cancel: this call's flag (NULL: none).
 * Returns 0; -2 for a bad want list; -3 if the factor is not postordered; -1 out of memory; -4 if
 * cancelled; -5 if a block is too large for BLAS's int; -6 if the factor's arrays are not a valid factor. */
int pmask_selinv(int64_t n, int64_t nsuper, const int64_t *super, const int64_t *pi, const int64_t *px, const int64_t *Ls,
                 int64_t ns, const double *Lx, int64_t nx, const int64_t *Perm, int64_t nw, const int64_t *want,
                 const double *scale, double *D, double *times, const int32_t *cancel)
{
    pm_tree tree = {0};
    int64_t *iperm = NULL, *rank = NULL, *cnt = NULL, *snode = NULL, *fc = NULL, *lo = NULL, *woff = NULL,
            *sp = NULL;
    double *W = NULL, *U = NULL, *tmp = NULL;
    int64_t s, k, i, j, r, total = 0, umax = 0;
    int status = 0, started = 0;
    pthread_t helper;
    const double one = 1.0, zero = 0.0;
    double t0 = now(), t_solve = 0, t_syrk = 0, flops = 0;

    iperm = malloc(sizeof(int64_t) * n);
    rank = malloc(sizeof(int64_t) * n);
    cnt = malloc(sizeof(int64_t) * (n + 1));
    lo = malloc(sizeof(int64_t) * nsuper);
    woff = malloc(sizeof(int64_t) * (nsuper + 1));
    sp = malloc(sizeof(int64_t) * (nw > 0 ? nw : 1));
    if (!iperm || !rank || !cnt || !lo || !woff || !sp) {
        status = -1;
        goto done;
    }
    if ((status = check_factor(n, nsuper, super, pi, px, Ls, ns, nx, Perm, iperm)) != 0 ||
        (status = check_blas_sizes(nsuper, pi, nw)) != 0)
        goto done;
    for (k = 0; k < n; k++)
        rank[k] = -1;
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
    if ((status = tree_init(&tree, n, nsuper, super, pi, Ls, Perm)) != 0)
        goto done;
    snode = tree.snode;
    fc = tree.fc;
    /* W_s: m_s x nc_s column-major (the transpose of W's rows of s, restricted to [lo_s, hi_s)) */
    woff[0] = 0;
    for (s = 0; s < nsuper; s++) {
        int64_t nc = super[s + 1] - super[s], nr = pi[s + 1] - pi[s] - nc, m;
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
            int64_t m = cnt[super[s + 1]] - lo[s];
            W[woff[s] + (cnt[k] - lo[s]) + (k - super[s]) * m] = 1.0;
        }
    times[0] = now() - t0;

    /* the helper faults D in (first touch costs ~0.5 s per GB on this VM) while the forward
     * solve runs; the products then write into mapped memory */
    {
        prefault_job job = {D, (size_t)nw * (size_t)nw, cancel};
        want_huge_pages(D, sizeof(double) * job.n);
        started = pthread_create(&helper, NULL, prefault, &job) == 0;

        /* forward solve W = L^-1 P E, supernode by supernode (children before parents) */
        t0 = now();
        for (s = 0; s < nsuper && !cancelled(cancel); s++) {
            int64_t nc = super[s + 1] - super[s], nrow = pi[s + 1] - pi[s], nr = nrow - nc;
            int64_t m = cnt[super[s + 1]] - lo[s];
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
                int64_t row = Ls[pi[s] + nc + i], t = snode[row];
                int64_t mt = cnt[super[t + 1]] - lo[t];
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
    if (cancelled(cancel)) {
        status = -4;
        goto done;
    }
    times[6] = now() - t0 - t_solve;   /* waiting for the helper */

    /* (A^-1)_EE[lo:hi, lo:hi] += W_s^T W_s  (lower triangle), one rank-nc_s update per supernode */
    t0 = now();
    for (s = 0; s < nsuper; s++) {
        int64_t nc = super[s + 1] - super[s], m = cnt[super[s + 1]] - lo[s];
        int im = (int)m, inc = (int)nc, inw = (int)nw;
        if (cancelled(cancel)) {
            status = -4;
            goto done;
        }
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
        int64_t i0, j0;
        for (j0 = 0; j0 < nw; j0 += T) {
            int64_t j1 = j0 + T < nw ? j0 + T : nw;
            if (cancelled(cancel)) {
                status = -4;
                goto done;
            }
            for (i0 = j0; i0 < nw; i0 += T) {
                int64_t i1 = i0 + T < nw ? i0 + T : nw;
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
            int64_t cur = j;
            if (cancelled(cancel)) {
                free(moved);
                free(first);
                status = -4;
                goto done;
            }
            if (moved[j])
                continue;
            memcpy(first, D + j * nw, sizeof(double) * nw);
            for (;;) {
                int64_t nxt = sp[cur];
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
    tree_free(&tree);
    free(iperm);
    free(rank);
    free(cnt);
    free(lo);
    free(woff);
    free(sp);
    free(W);
    free(U);
    free(tmp);
    return status;
}

/* Position of value q in the sorted array a[0..m): the caller knows it is there. */
static int64_t find_sorted(const int64_t *a, int64_t m, int64_t q)
{
    int64_t lo = 0, hi = m;
    while (hi - lo > 1) {
        int64_t mid = lo + (hi - lo) / 2;
        if (a[mid] <= q)
            lo = mid;
        else
            hi = mid;
    }
    return lo;
}

/* X = E^T A^-1 B = W_E^T W_B with W = L^-1 P (.), for wanted rows E (unit columns) and a sparse B.
 *
 * W_E's columns meet each supernode s in a contiguous range of the rows sorted by pivot, as in
 * pmask_selinv.  A column of W_B is non-zero on the union of the tree paths up from the pivots of its
 * non-zeros; for a consistent P2 load those are the neighbours of one vertex, on its path or below it
 * in a few branches, so every supernode keeps the sorted set of W_B columns that reach it (columns
 * numbered by their lowest pivot, which keeps the sets of the large top supernodes contiguous).
 * Then X += W_E,s^T W_B,s is one dgemm per supernode: straight into X where the set is contiguous,
 * through a tile buffer and a scatter where it is not.
 *
 * n, nsuper, super, pi, px, Ls, Lx, Perm: the postordered supernodal factor (pmask_factor_arrays).
 * rows: nE distinct dofs; B: n x k in CSC (Bp, Bi, Bx; any row order, duplicates summed).
 * X: nE x k, zero on entry; on return X[i * k + c] = (A^-1 B)[rows_i, c] (row-major).
 * times: setup, forward solves, products, output permutation; flops; doubles of W_E and W_B.
 * ns, nx: the lengths of Ls and Lx.  cancel: this call's flag (NULL: none).
 * Returns 0; -2 for a bad row list or an index of B out of range; -3 if the factor is not
 * postordered; -1 out of memory; -4 if cancelled; -5 if a block is too large for BLAS's int; -6 if the
 * factor's arrays are not a valid factor. */
int pmask_selcols(int64_t n, int64_t nsuper, const int64_t *super, const int64_t *pi, const int64_t *px,
                  const int64_t *Ls, int64_t ns, const double *Lx, int64_t nx, const int64_t *Perm, int64_t nE,
                  const int64_t *rows, int64_t k, const int64_t *Bp, const int64_t *Bi, const double *Bx, double *X,
                  double *times, const int32_t *cancel)
{
    enum { TILE = 256 };
    pm_tree tree = {0};
    int64_t *rankE = NULL, *cntE = NULL, *spE = NULL, *loE = NULL, *woffE = NULL;
    int64_t *start = NULL, *orderB = NULL, *posB = NULL, *stamp = NULL, *setlen = NULL, *setoff = NULL,
            *sets = NULL, *woffB = NULL, *where = NULL;
    double *WE = NULL, *WB = NULL, *U = NULL, *tile = NULL, *rowtmp = NULL;
    int64_t s, c, q, i, j, r, totalE = 0, totalB = 0, umax = 0, settotal = 0, tmax = 0;
    int status = 0;
    const double one = 1.0, zero = 0.0;
    double t0 = now(), t_solve = 0, t_gemm = 0, flops = 0;
    const int64_t n1 = n > 0 ? n : 1, ns1 = nsuper > 0 ? nsuper : 1, k1 = k > 0 ? k : 1,
                  e1 = nE > 0 ? nE : 1;

    {
        int64_t *iperm = malloc(sizeof(int64_t) * n1);
        if (!iperm)
            return -1;
        status = check_factor(n, nsuper, super, pi, px, Ls, ns, nx, Perm, iperm);
        free(iperm);
        if (status == 0)
            status = check_blas_sizes(nsuper, pi, nE > k ? nE : k);
        if (status != 0)
            return status;
    }
    if ((status = tree_init(&tree, n, nsuper, super, pi, Ls, Perm)) != 0)
        return status;
    rankE = malloc(sizeof(int64_t) * n1);
    cntE = malloc(sizeof(int64_t) * (n + 1));
    spE = malloc(sizeof(int64_t) * e1);
    loE = malloc(sizeof(int64_t) * ns1);
    woffE = malloc(sizeof(int64_t) * (nsuper + 1));
    start = malloc(sizeof(int64_t) * k1);
    orderB = malloc(sizeof(int64_t) * k1);
    posB = malloc(sizeof(int64_t) * k1);
    stamp = malloc(sizeof(int64_t) * ns1);
    setlen = calloc(ns1, sizeof(int64_t));
    setoff = malloc(sizeof(int64_t) * (nsuper + 1));
    woffB = malloc(sizeof(int64_t) * (nsuper + 1));
    where = malloc(sizeof(int64_t) * k1);
    rowtmp = malloc(sizeof(double) * k1);
    if (!rankE || !cntE || !spE || !loE || !woffE || !start || !orderB || !posB || !stamp || !setlen ||
        !setoff || !woffB || !where || !rowtmp) {
        status = -1;
        goto done;
    }
    /* E: sorted (pivot-order) positions and each supernode's range [loE, cntE[super[s+1]]) */
    for (j = 0; j < n; j++)
        rankE[j] = -1;
    for (i = 0; i < nE; i++) {
        if (rows[i] < 0 || rows[i] >= n || rankE[tree.iperm[rows[i]]] >= 0) {
            status = -2;
            goto done;
        }
        rankE[tree.iperm[rows[i]]] = i;
    }
    cntE[0] = 0;
    for (j = 0; j < n; j++) {
        cntE[j + 1] = cntE[j];
        if (rankE[j] >= 0)
            spE[rankE[j]] = cntE[j + 1]++;
    }
    /* B: each column's lowest pivot; columns numbered in that order (a counting sort) */
    for (c = 0; c < k; c++) {
        start[c] = n;
        for (q = Bp[c]; q < Bp[c + 1]; q++) {
            if (Bi[q] < 0 || Bi[q] >= n) {
                status = -2;
                goto done;
            }
            if (tree.iperm[Bi[q]] < start[c])
                start[c] = tree.iperm[Bi[q]];
        }
    }
    {
        int64_t *count = calloc(n + 2, sizeof(int64_t));
        if (count == NULL) {
            status = -1;
            goto done;
        }
        for (c = 0; c < k; c++)
            count[start[c] + 1]++;
        for (j = 0; j <= n; j++)
            count[j + 1] += count[j];
        for (c = 0; c < k; c++)
            orderB[count[start[c]]++] = c;
        free(count);
    }
    for (q = 0; q < k; q++)
        posB[orderB[q]] = q;
    /* the set of each supernode: walk up from every non-zero's supernode until a supernode already
     * holds this column; twice, to count and then to fill (in increasing q: each set comes sorted) */
    for (int pass = 0; pass < 2; pass++) {
        for (s = 0; s < nsuper; s++)
            stamp[s] = -1;
        if (pass == 1) {
            setoff[0] = 0;
            for (s = 0; s < nsuper; s++) {
                setoff[s + 1] = setoff[s] + setlen[s];
                setlen[s] = 0;
            }
            settotal = setoff[nsuper];
            sets = malloc(sizeof(int64_t) * (settotal > 0 ? settotal : 1));
            if (sets == NULL) {
                status = -1;
                goto done;
            }
        }
        for (q = 0; q < k; q++) {
            c = orderB[q];
            for (r = Bp[c]; r < Bp[c + 1]; r++)
                for (s = tree.snode[tree.iperm[Bi[r]]]; s >= 0 && stamp[s] != q; s = tree.parent[s]) {
                    stamp[s] = q;
                    if (pass == 1)
                        sets[setoff[s] + setlen[s]] = q;
                    setlen[s]++;
                }
        }
    }
    /* storage: W_E,s (mE x nc) and W_B,s (mB x nc), column-major */
    woffE[0] = woffB[0] = 0;
    for (s = 0; s < nsuper; s++) {
        int64_t nc = super[s + 1] - super[s], nr = pi[s + 1] - pi[s] - nc;
        int64_t mE = cntE[super[s + 1]] - cntE[tree.fc[s]], mB = setlen[s];
        loE[s] = cntE[tree.fc[s]];
        woffE[s + 1] = woffE[s] + mE * nc;
        woffB[s + 1] = woffB[s] + mB * nc;
        if (mE * nr > umax)
            umax = mE * nr;
        if (mB * nr > umax)
            umax = mB * nr;
        if (mB > tmax)
            tmax = mB;
    }
    totalE = woffE[nsuper];
    totalB = woffB[nsuper];
    WE = calloc(totalE > 0 ? totalE : 1, sizeof(double));
    WB = calloc(totalB > 0 ? totalB : 1, sizeof(double));
    U = malloc(sizeof(double) * (umax > 0 ? umax : 1));
    tile = malloc(sizeof(double) * (tmax > 0 ? tmax : 1) * TILE);
    if (!WE || !WB || !U || !tile) {
        status = -1;
        goto done;
    }
    want_huge_pages(WE, sizeof(double) * totalE);
    want_huge_pages(WB, sizeof(double) * totalB);
    for (i = 0; i < nE; i++) {   /* W_E starts as P E, W_B as P B */
        int64_t piv = tree.iperm[rows[i]];
        s = tree.snode[piv];
        int64_t m = cntE[super[s + 1]] - loE[s];
        WE[woffE[s] + (spE[i] - loE[s]) + (piv - super[s]) * m] = 1.0;
    }
    for (c = 0; c < k; c++)
        for (r = Bp[c]; r < Bp[c + 1]; r++) {
            int64_t piv = tree.iperm[Bi[r]], t = tree.snode[piv];
            int64_t at = find_sorted(sets + setoff[t], setlen[t], posB[c]);
            WB[woffB[t] + at + (piv - super[t]) * setlen[t]] += Bx[r];
        }
    times[0] = now() - t0;

    for (s = 0; s < nsuper; s++) {
        int64_t nc = super[s + 1] - super[s], nrow = pi[s + 1] - pi[s], nr = nrow - nc;
        int64_t mE = cntE[super[s + 1]] - loE[s], mB = setlen[s];
        if (cancelled(cancel)) {
            status = -4;
            goto done;
        }
        const int64_t *set = sets + setoff[s];
        const double *Lss = Lx + px[s];
        int inc = (int)nc, inr = (int)nr, ild = (int)nrow;
        double *XE = WE + woffE[s], *XB = WB + woffB[s];

        t0 = now();
        for (int side = 0; side < 2; side++) {   /* the forward solve of s, for W_E then W_B */
            int64_t m = side == 0 ? mE : mB;
            int im = (int)m;
            double *Xs = side == 0 ? XE : XB;
            if (m == 0)
                continue;
            dtrsm_("R", "L", "T", "N", &im, &inc, &one, Lss, &ild, Xs, &im, 1, 1, 1, 1);
            flops += (double)m * nc * nc;
            if (nr == 0)
                continue;
            dgemm_("N", "T", &im, &inr, &inc, &one, Xs, &im, Lss + nc, &ild, &zero, U, &im, 1, 1);
            flops += 2.0 * m * nr * nc;
            /* scatter U onto the ancestors' rows; the rows of s are sorted, so one owner at a time */
            for (i = 0; i < nr;) {
                int64_t t = tree.snode[Ls[pi[s] + nc + i]], i1 = i;
                while (i1 < nr && tree.snode[Ls[pi[s] + nc + i1]] == t)
                    i1++;
                if (side == 0) {
                    int64_t mt = cntE[super[t + 1]] - loE[t];
                    for (; i < i1; i++) {
                        double *dst = WE + woffE[t] + (loE[s] - loE[t]) + (Ls[pi[s] + nc + i] - super[t]) * mt;
                        const double *src = U + i * m;
                        for (r = 0; r < m; r++)
                            dst[r] -= src[r];
                    }
                } else {
                    const int64_t *tset = sets + setoff[t];
                    int64_t mt = setlen[t];
                    for (r = 0; r < m; r++)   /* s's set is a subset of t's */
                        where[r] = find_sorted(tset, mt, set[r]);
                    for (; i < i1; i++) {
                        double *dst = WB + woffB[t] + (Ls[pi[s] + nc + i] - super[t]) * mt;
                        const double *src = U + i * m;
                        for (r = 0; r < m; r++)
                            dst[where[r]] -= src[r];
                    }
                }
            }
        }
        t_solve += now() - t0;

        /* X[loE:hiE, set] += W_E,s^T W_B,s, i.e. (row-major X as column-major X^T) X^T += XB XE^T */
        t0 = now();
        if (mE > 0 && mB > 0) {
            int imB = (int)mB, imE = (int)mE;
            if (set[mB - 1] - set[0] == mB - 1) {   /* contiguous: straight into X */
                int ik = (int)k;
                dgemm_("N", "T", &imB, &imE, &inc, &one, XB, &imB, XE, &imE, &one, X + set[0] + loE[s] * k,
                       &ik, 1, 1);
            } else {                                /* a tile of rows at a time, then scattered */
                for (int64_t e0 = 0; e0 < mE; e0 += TILE) {
                    int ie = (int)(mE - e0 < TILE ? mE - e0 : TILE);
                    dgemm_("N", "T", &imB, &ie, &inc, &one, XB, &imB, XE + e0, &imE, &zero, tile, &imB, 1, 1);
                    for (int64_t e = 0; e < ie; e++) {
                        double *dst = X + (loE[s] + e0 + e) * k;
                        const double *src = tile + e * mB;
                        for (r = 0; r < mB; r++)
                            dst[set[r]] += src[r];
                    }
                }
            }
            flops += 2.0 * mE * mB * nc;
        }
        t_gemm += now() - t0;
    }
    times[1] = t_solve;
    times[2] = t_gemm;

    /* X is in sorted orders; put the rows in the caller's order (following the permutation's cycles,
     * one row of scratch), then gather each row's columns */
    t0 = now();
    {
        char *moved = calloc(e1, 1);
        if (moved == NULL) {
            status = -1;
            goto done;
        }
        for (i = 0; i < nE; i++) {
            int64_t cur = i;
            if (cancelled(cancel)) {
                free(moved);
                status = -4;
                goto done;
            }
            if (moved[i])
                continue;
            memcpy(rowtmp, X + i * k, sizeof(double) * k);
            for (;;) {
                int64_t src = spE[cur];
                moved[cur] = 1;
                if (src == i) {
                    memcpy(X + cur * k, rowtmp, sizeof(double) * k);
                    break;
                }
                memcpy(X + cur * k, X + src * k, sizeof(double) * k);
                cur = src;
            }
        }
        free(moved);
        for (i = 0; i < nE; i++) {
            double *row = X + i * k;
            for (c = 0; c < k; c++)
                rowtmp[c] = row[posB[c]];
            memcpy(row, rowtmp, sizeof(double) * k);
        }
    }
    times[3] = now() - t0;
    times[4] = flops;
    times[5] = (double)(totalE + totalB);

done:
    tree_free(&tree);
    free(rankE);
    free(cntE);
    free(spE);
    free(loE);
    free(woffE);
    free(start);
    free(orderB);
    free(posB);
    free(stamp);
    free(setlen);
    free(setoff);
    free(sets);
    free(woffB);
    free(where);
    free(WE);
    free(WB);
    free(U);
    free(tile);
    free(rowtmp);
    return status;
}
