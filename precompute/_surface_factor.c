/* The P1 Green's-function stage in place: CHOLMOD's supernodal factor with the surface last,
 * then LAPACK on its dense trailing block, without copying the factor.
 *
 * Built by tools/build_native.sh (make venv) against Debian's SuiteSparse and the system LAPACK
 * (threaded OpenBLAS after tools/install_cholmod.sh), loaded with ctypes by precompute/native.py.
 * The maths is the one in precompute/condense.py; this file removes copies:
 *
 *   pmask_factor   A (lower CSC, already permuted: interior, free surface, fixed surface)
 *                  -> supernodal L = chol(A) in that order (the interior reordered by METIS)
 *                  and a pointer to the trailing nt x nt block of L, column-major with a
 *                  leading dimension ld >= nt.  When the trailing columns lie in CHOLMOD's
 *                  last supernode (a connected body: its Schur complement is dense; relaxed
 *                  amalgamation may add interior columns in front, hence ld > nt) the pointer
 *                  is into CHOLMOD's own storage; otherwise the block is gathered into a copy.
 *   pmask_greens   on such a block (from pmask_factor or a checkpoint), in place: W = L_FF^-1
 *                  (trtri), reactions L_UF W (trmm), G = W^T W (lauum), then the mirror and the
 *                  area scaling in one tiled pass, so that the block holds Xi^T and the
 *                  reactions: no new 3n x 3n array (its first touch costs 0.1-0.4 s here).
 *   pmask_free     frees what pmask_factor returned.
 */
#include <pthread.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>
#include <cholmod.h>

void dtrtri_(const char *uplo, const char *diag, const int *n, double *a, const int *lda, int *info,
             size_t, size_t);
void dlauum_(const char *uplo, const int *n, double *a, const int *lda, int *info, size_t);
void dtrmm_(const char *side, const char *uplo, const char *transa, const char *diag, const int *m,
            const int *n, const double *alpha, const double *a, const int *lda, double *b, const int *ldb,
            size_t, size_t, size_t, size_t);

/* bumped whenever a signature below changes; precompute/native.py refuses a library built from
 * another version (a stale build in the venv) instead of calling it with the wrong arguments */
int pmask_abi_version(void) { return 2; }

typedef struct {
    cholmod_common c;
    cholmod_factor *L;
    double *block;     /* the trailing block (inside L->x, or malloc'ed when copied) */
    long ld;           /* its leading dimension */
    int owns_block;
} pm_factor;

/* Page-faulting the factor's storage costs ~0.1 s per 200 MB on this VM.  CHOLMOD touches the
 * storage of the dense last supernode (most of it) only at the end, after the interior's small
 * supernodes, during which the second core is mostly idle: a helper thread faults it in from the
 * end meanwhile.  It writes nothing: an atomic add of zero per page. */
typedef struct { double *x; size_t n; } prefault_job;

static void *prefault(void *arg)
{
    prefault_job *job = arg;
    size_t step = (size_t)sysconf(_SC_PAGESIZE) / sizeof(double), k;
    for (k = job->n; k >= step; k -= step)
        __atomic_fetch_add((long *)(job->x + k - step), 0L, __ATOMIC_RELAXED);
    return NULL;
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
    if (f->owns_block)
        free(f->block);
    if (f->L != NULL)
        cholmod_l_free_factor(&f->L, &f->c);
    cholmod_l_finish(&f->c);
    free(f);
}

/* Returns 0 and *out (a handle) and *block on success; k > 0 if A is not positive definite at
 * column k-1; -1 on a CHOLMOD failure (out of memory, say).  times: order, analyse, numeric,
 * locate/copy, nnz(L) as stored, 1 if the block is CHOLMOD's own storage (0: gathered), the interior
 * order used (0 as given, 1 AMD, 2 METIS). */
int pmask_factor(long n, long *Ap, long *Ai, double *Ax, long nt, int reorder, pm_factor **out,
                 double **block, long *ld, double *times)
{
    cholmod_sparse A;
    pm_factor *f = calloc(1, sizeof *f);
    long off = n - nt, k, s, j, r, *Perm = NULL;
    int status = 0, ordered = 0;
    double t0;

    *out = NULL;
    *block = NULL;
    if (f == NULL)
        return -1;
    cholmod_l_start(&f->c);
    f->c.print = 0;
    f->c.supernodal = CHOLMOD_SUPERNODAL;
    f->c.postorder = 0;          /* keep the surface last and in the given order */
    f->c.nmethods = 1;

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

    t0 = now();
    if (reorder && off > 0) {
        /* the interior by METIS nested dissection of its own graph (A_II); measured on the kidney
         * (CHOLMOD's flop count) 7 % fewer flops in all than AMD at 1,446 free vertices, 19 % at
         * 3,882; AMD of the same graph if METIS fails */
        cholmod_sparse *Aii = cholmod_l_allocate_sparse(off, off, Ap[off], 1, 1, -1, CHOLMOD_PATTERN, &f->c);
        Perm = malloc(sizeof(long) * n);
        if (Perm && Aii) {
            long *Bp = Aii->p, *Bi = Aii->i, q = 0;
            for (j = 0; j < off; j++) {      /* rows are sorted: the interior ones come first */
                Bp[j] = q;
                for (k = Ap[j]; k < Ap[j + 1] && Ai[k] < off; k++)
                    Bi[q++] = Ai[k];
            }
            Bp[off] = q;
            if (cholmod_l_metis(Aii, NULL, 0, 0, Perm, &f->c)) {
                ordered = 2;
            } else {
                f->c.status = CHOLMOD_OK;
                if (cholmod_l_amd(Aii, NULL, 0, Perm, &f->c))
                    ordered = 1;
            }
            for (k = off; k < n; k++)
                Perm[k] = k;   /* the surface keeps its order */
        }
        if (!ordered) {
            free(Perm);
            Perm = NULL;
        }
        cholmod_l_free_sparse(&Aii, &f->c);
    }
    f->c.method[0].ordering = Perm ? CHOLMOD_GIVEN : CHOLMOD_NATURAL;
    times[0] = now() - t0;
    times[6] = ordered;

    t0 = now();
    f->L = cholmod_l_analyze_p(&A, Perm, NULL, 0, &f->c);
    free(Perm);
    times[1] = now() - t0;
    if (f->L == NULL) {
        pmask_free(f);
        return -1;
    }
    t0 = now();
    {
        pthread_t helper;
        prefault_job job = {NULL, 0};
        int started = 0;
        /* allocate the numeric supernodal storage now, so that the helper can fault it in */
        if (cholmod_l_change_factor(CHOLMOD_REAL, 1, 1, 1, 1, f->L, &f->c) && f->L->x != NULL) {
            job.x = f->L->x;
            job.n = f->L->xsize;
            started = pthread_create(&helper, NULL, prefault, &job) == 0;
        }
        cholmod_l_factorize(&A, f->L, &f->c);
        if (started)
            pthread_join(helper, NULL);
    }
    times[2] = now() - t0;
    if (f->c.status == CHOLMOD_NOT_POSDEF) {
        status = (int)f->L->minor + 1;
    } else if (f->c.status != CHOLMOD_OK || !f->L->is_super) {
        status = -1;
    }
    if (status != 0) {
        pmask_free(f);
        return status;
    }

    t0 = now();
    {
        cholmod_factor *L = f->L;
        long *super = L->super, *pi = L->pi, *px = L->px, *Ls = L->s, *LP = L->Perm;
        double *Lx = L->x;
        long last = (long)L->nsuper - 1;
        for (k = off; k < n; k++)
            if (LP[k] != k)
                status = -1;  /* CHOLMOD moved the surface: should not happen */
        long j0 = off - super[last], nsrow = pi[last + 1] - pi[last];
        if (status == 0 && j0 >= 0 && nsrow - j0 == nt && Ls[pi[last] + j0] == off) {
            /* the surface columns lie in the last supernode (with, after relaxed amalgamation,
             * a few interior columns before them): use the block where it is */
            f->block = Lx + px[last] + j0 * nsrow + j0;
            f->ld = nsrow;
            times[5] = 1.0;
        } else if (status == 0) {
            f->block = malloc(sizeof(double) * nt * nt);
            f->owns_block = 1;
            f->ld = nt;
            if (f->block == NULL)
                status = -1;
            for (s = 0; s <= last && status == 0; s++) {
                long k1 = super[s], k2 = super[s + 1], nsrow = pi[s + 1] - pi[s];
                if (k2 <= off)
                    continue;
                for (j = (k1 > off ? 0 : off - k1); j < k2 - k1; j++) {
                    double *col = Lx + px[s] + j * nsrow, *dst = f->block + (k1 + j - off) * nt;
                    long *rows = Ls + pi[s];
                    memset(dst, 0, sizeof(double) * nt);
                    for (r = j; r < nsrow; r++)
                        dst[rows[r] - off] = col[r];
                }
            }
        }
        times[4] = (double)L->xsize;
    }
    times[3] = now() - t0;
    if (status != 0) {
        pmask_free(f);
        return status;
    }
    *out = f;
    *block = f->block;
    *ld = f->ld;
    return 0;
}

/* B: nt x nt column-major (leading dimension ldb >= nt), lower-triangular L_TT on entry.
 * a: nf areas.  On return, in place (no new memory):
 *   B[0:nf, 0:nf] = diag(a) G with G = S^-1 = (L_FF L_FF^T)^-1, all of it (column-major), so that
 *                   its transpose, read row-major, is Xi = G diag(a): Xi[i, j] = B[j + i ldb];
 *   B[nf:nt, 0:nf] = the support reactions (L_UF L_FF^-1) diag(a).
 * Returns LAPACK's info of trtri (k > 0: S singular at k) or of lauum. */
int pmask_greens(double *B, long ldb, long nt, long nf, const double *a, double *times)
{
    int n = (int)nf, m = (int)(nt - nf), ld = (int)ldb, info = 0;
    const double one = 1.0;
    enum { T = 64 };
    double tile[T * T];
    long i0, j0, i, j;
    double t0 = now();

    dtrtri_("L", "N", &n, B, &ld, &info, 1, 1);
    times[0] = now() - t0;
    if (info != 0)
        return info;
    t0 = now();
    if (m > 0) {
        dtrmm_("R", "L", "N", "N", &m, &n, &one, B, &ld, B + nf, &ld, 1, 1, 1, 1);
        for (j = 0; j < nf; j++)
            for (i = nf; i < nt; i++)
                B[i + j * ldb] *= a[j];
    }
    times[1] = now() - t0;
    t0 = now();
    dlauum_("L", &n, B, &ld, &info, 1);
    times[2] = now() - t0;
    if (info != 0)
        return info;
    t0 = now();
    /* M = diag(a) G from the lower triangle of G, tile by tile: an off-diagonal tile (rows I, cols J,
     * I > J) gives M[I, J] = a_I G[I, J] in place and M[J, I] = a_J G[I, J]^T into the upper tile;
     * a diagonal tile goes through a copy. */
    for (j0 = 0; j0 < nf; j0 += T) {
        long j1 = j0 + T < nf ? j0 + T : nf;
        for (i0 = j0; i0 < nf; i0 += T) {
            long i1 = i0 + T < nf ? i0 + T : nf;
            if (i0 == j0) {
                for (j = j0; j < j1; j++)
                    for (i = j; i < i1; i++)
                        tile[(i - i0) + (j - j0) * T] = B[i + j * ldb];
                for (j = j0; j < j1; j++)
                    for (i = i0; i < i1; i++) {
                        double g = i >= j ? tile[(i - i0) + (j - j0) * T] : tile[(j - i0) + (i - j0) * T];
                        B[i + j * ldb] = a[i] * g;
                    }
            } else {
                for (j = j0; j < j1; j++)
                    for (i = i0; i < i1; i++) {
                        double g = B[i + j * ldb];
                        B[j + i * ldb] = a[j] * g;
                        B[i + j * ldb] = a[i] * g;
                    }
            }
        }
    }
    times[3] = now() - t0;
    return 0;
}
