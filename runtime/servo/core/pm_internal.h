/* pmask servo core: what its files share (not part of the public API; see pmask_servo.h).
 *
 * One file per step of the contact algorithm, as pmask.runtime.contact has one module per step:
 *   table.c     loading and checking a runtime table        bvh.c       the nearest triangle (restarts tracking)
 *   tracking.c  step 1: the probe's projection and the proxy law.c       step 2: the contact law at the proxy
 *   coupling.c  step 3: several contacts solved together   output.c    step 4: zero-order hold, damping, passivity
 *   servo.c     a servo's state, the tick, publishing       thread.c    thread mode, exchange, the clock
 *   display.c   the deformation of eq. 16 for a display     zeta.c      the ζ table's rows (pm_zeta_rows)
 *   greens.c    a compressed Ξ's sections (table 1.4) and the coupling blocks formed from them
 *
 * Written operation for operation like the Python (the same expressions in the same order, Python's min/max
 * as PYMIN/PYMAX, and the divisions that raise ZeroDivisionError in Python turned into the same
 * INTERNAL_ERROR hold).  Compile without contraction of multiply-adds (-ffp-contract=off), or the last bits
 * of the forces differ from the Python step's.
 *
 * Sharing between threads (thread mode): every field another thread reads while the servo thread runs is
 * either an atomic (running, stop_flag, the far warning, the ring indices) or inside a sequence lock whose
 * payload is copied word by word with relaxed atomic loads and stores (publishing), or a triple buffer whose
 * hand-over is an atomic exchange (the probes from pm_servo_set_probes).  ThreadSanitizer finds no race in the
 * CI job that drives all of them beside a running thread.
 */
#ifndef PM_INTERNAL_H
#define PM_INTERNAL_H

#if !defined(_POSIX_C_SOURCE) || _POSIX_C_SOURCE < 200809L
#undef _POSIX_C_SOURCE
#define _POSIX_C_SOURCE 200809L
#endif

#include "../pmask_servo.h"

#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#if !defined(_WIN32)
#include <pthread.h>
#define PM_THREADS 1
#else
#define PM_THREADS 0
#endif

#if defined(__GNUC__) && !defined(_WIN32)
#define PM_HIDDEN __attribute__((visibility("hidden")))
#else
#define PM_HIDDEN
#endif

/* kernels chosen by the CPU at run time (x86-64 with GCC or Clang: __builtin_cpu_supports and target attributes),
 * each bit for bit the baseline's; PMASK_DISABLE_CPU_FEATURES=AVX2 keeps the baseline (coupling.c) */
#if defined(__x86_64__) && defined(__GNUC__)
#define PM_X86_DISPATCH 1
#else
#define PM_X86_DISPATCH 0
#endif
/* two doubles in one register (GCC's and Clang's vector extension): each lane is the scalar's multiply and add,
 * so sums in lanes are the Python's to the bit (no fused multiply-add: -ffp-contract=off) */
typedef double pm_v2 __attribute__((vector_size(16)));

static inline pm_v2 load2(const double *p)
{
    pm_v2 v;
    memcpy(&v, p, sizeof v);
    return v;
}

/* a coupled pair's block C_ab = Σ_x Σ_y φ_a,x φ_b,y P_xy (P: 81 doubles, Sab: 9) */
typedef void (*pm_block_sum_fn)(const double *P, const double *ba, const double *bb, double *Sab);

/* ------------------------------------------------------------------ constants (pmask.runtime.contact.state) */
#define GS_SWEEPS 60
#define PIVOTS 4
#define FAR_FACTOR 10.0
#define PROXY_SPEED 1.75
#define PASSIVITY_SLACK 0.10
#define VELOCITY_FILTER 0.1
#define PC_DAMPING_MAX 1.0
#define PC_RAMP_TICKS 50.0
#define DEEP_RELEASE 0.9  /* state.DEEP_RELEASE: the deep hold's excess kept a tick once a press stops pushing on */
/* samples the exchange ring holds (pm_servo_exchange): a Python loop may run this many ticks ahead */
#define PM_RING 64

/* Python's max(a, b) and min(a, b): the first argument unless the second is larger (smaller) */
#define PYMAX(a, b) ((b) > (a) ? (b) : (a))
#define PYMIN(a, b) ((b) < (a) ? (b) : (a))

/* ------------------------------------------------------------------ the table (table.c, bvh.c, greens.c) */
/* Ξ compressed as the artifact stores it (pmask.runtime.compressed; the table's xi_* and mask_* sections,
 * pmask.runtime.table.greens_sections): positions in cluster order, blocks over pairs of leaf clusters, dense ones
 * pair by pair (exact, or 16 bits with a scale per column), low-rank ones as U Vᵀ, and the core masks by contact
 * vertex, from which the coupling blocks are formed when contacts land on new triangles (pm__greens_pairs) */
typedef struct {
    int64_t n, nleaves, nd, nl, nowner, item;  /* contact vertices, leaves, dense and low-rank blocks, lookup
                                                  entries, bytes of a factor's value (4 or 8; 2: int16 words
                                                  times a float32 scale per column, table 1.5) */
    int64_t maxrank;                           /* the largest rank of a low-rank block */
    int symmetric;                             /* only the blocks on and above the diagonal are stored */
    const int64_t *leaves, *dense_index, *near_index, *lowrank_index, *owner, *mask_ptr, *mask_cols;
    const double *scale, *exact, *qscale, *mask_w;
    const unsigned char *mask, *q, *U, *V;     /* bits, int16 and float32/64 (or int16) values, little-endian */
    const unsigned char *Us, *Vs;              /* item 2: the factors' column scales (float32), block after block */
    const unsigned char *exact48;              /* table 1.5: the exact pairs in 48-bit fixed point, 28 uint16 words
                                                  a pair (pmask.runtime.compressed.pack_exact); NULL: float64 */
    int64_t *position, *leaf_of;               /* made at load: contact index -> position -> leaf */
    int64_t *so;                               /* item 2, made at load: each low-rank block's first scale */
} pm_greens;

struct pm_table {
    int64_t nv, nt, nc;           /* surface vertices, triangles, contact vertices (ζ table rows / 3) */
    const double *P, *frames, *N, *K, *taper, *grad;
    const double *kn, *shape, *dlin;  /* normal stiffness k_j, shape operator S_j (9), linear depth δ_lin,j */
    const int64_t *T, *nb;
    /* the bounding-volume hierarchy of the triangles, built at load (pm_table_nearest) */
    double *box;                  /* per node: lower corner, upper corner */
    int64_t *node;                /* per node: left child, or -1 - (first index into order) for a leaf */
    int64_t *leaf_count;          /* per node: triangles in a leaf, 0 for an inner node */
    int64_t *order;               /* triangles, leaves' runs */
    int64_t nnodes;
    double lo[3], hi[3], mean_edge, diag;
    /* the finite-element mesh's surface under the contact surface (its Loop subdivision surface,
     * pmask.runtime.contact.subdivision): nm vertices, nmt triangles; each contact triangle's mesh triangle
     * (parent) and its corners' barycentrics there (corners, 9 a triangle); parent NULL: the mesh itself */
    int64_t nm, nmt;
    const int64_t *mT, *parent;
    const double *corners;
    const int64_t *row;           /* mesh vertex -> contact row, -1 (NULL without ζ) */
    const double *zeta;           /* (3 nc, 3 nc): rows 3m..3m+2 = ζ_mᵀ (NULL without) */
    pm_greens xi;                 /* a compressed Ξ's own sections (table 1.4; n = 0 without) */
    int64_t nd, ndt;              /* display surface: vertices, triangles (0 without) */
    const double *dP, *dbary, *dlift;  /* its points, embedding weights, lifts (nd x 3 each) */
    const int64_t *dT, *dV;       /* its triangles (ndt x 3), its vertices' simulation vertices (nd x 3) */
    char *meta;
    unsigned char *blob;
    size_t size;
};

/* the point (t, b) of the contact surface on the mesh: its mesh triangle, beta its barycentrics there
 * (ContactSurface.mesh_point, operation for operation) */
static inline int64_t pm__mesh_point(const pm_table *tb, int64_t t, const double *b, double *beta)
{
    if (!tb->parent) {
        beta[0] = b[0];
        beta[1] = b[1];
        beta[2] = b[2];
        return t;
    }
    const double *c = tb->corners + 9 * t;
    beta[0] = b[0] * c[0] + b[1] * c[3] + b[2] * c[6];
    beta[1] = b[0] * c[1] + b[1] * c[4] + b[2] * c[7];
    beta[2] = b[0] * c[2] + b[1] * c[5] + b[2] * c[8];
    return tb->parent[t];
}

PM_HIDDEN int pm__build_bvh(pm_table *t);
PM_HIDDEN void pm__free_bvh(pm_table *t);
/* a section of a table being loaded (table.c) */
typedef struct {
    const unsigned char *data;
    uint64_t rows, cols;
    uint32_t dtype;
    int found;
} section;
/* a required (or, with optional, possibly absent) section of the given type and shape; rows < 0: any */
PM_HIDDEN int pm__want(const pm_section *secs, int32_t nsec, const char *name, uint32_t dtype, int64_t rows,
                       int64_t cols, int optional, section *s, char *err, size_t errlen);
/* the xi_* sections, checked (0: absent or read; -1: a message in err), and what they own */
PM_HIDDEN int pm__greens_assign(pm_table *t, const pm_section *secs, int32_t nsec, char *err, size_t errlen);
PM_HIDDEN void pm__greens_free(pm_table *t);
/* the nine vertex-pair blocks of mesh triangles ta, tbi (81 doubles, x of ta outer: P_xy = ½ (ζ_y(x) + ζ_x(y)ᵀ),
 * zero where either vertex has no row; ContactSurface.pair_blocks) from the ζ table or a compressed Ξ's sections
 * (coupling.c).  P holding those of mesh triangles oa, ob (≥ 0; -1: none), the vertex pairs the two pairs share
 * are moved, not read again: a contact moving to a neighbouring triangle keeps six of the nine. */
PM_HIDDEN void pm__triangle_pairs(const pm_table *tb, int64_t ta, int64_t tbi, int64_t oa, int64_t ob, double *P);
/* a pm_pair_fn over the table's compressed Ξ (user: the table) */
PM_HIDDEN int pm__greens_pairs(void *user, int64_t ta, int64_t tb, double *P);
/* ζ_m(i) (3x3, row-major) for contact vertices m, i */
PM_HIDDEN void pm__greens_zeta(const pm_greens *x, int64_t m, int64_t i, double *Z);
/* the deformation's workspace on a compressed Ξ (allocated with the servo): x and y in cluster order (3 n_c
 * each), each vertex's scale a, loaded vertices before each position (n_c + 1), a low-rank product (max rank) */
typedef struct {
    double *xs, *ys, *as, *tk;
    int64_t *nz;
} pm_greens_work;
/* y = Ξ x (3 n_c, contact order; x loaded on a few vertices): the blocks whose columns (or, below a symmetric
 * form's diagonal, rows) hold load (CompressedXi.matvec) */
PM_HIDDEN void pm__greens_matvec(const pm_table *t, const double *x, double *y, pm_greens_work *wk);

/* ------------------------------------------------------------------ a contact's state (servo.c) */
typedef struct {
    int64_t tri;
    double b[3];
    int has_anchor;
    double anchor[3];
    int in_contact, above, sliding;
    int frozen;                   /* past δ_t: increments of depth at the stiffness where they began */
    double frozen_depth, frozen_stiffness;  /* δ* and k* */
    double hold_scale, hold_peak; /* the deep hold (past δ_lin, or short of it on a press): the factor that keeps a
                                     deeper press from feeling softer, the magnitude it held (output.c) */
    double slip;
    int has_last;
    double last[3], move[3], vel[3];
    int has_target;
    int64_t target_t;
    double target_b[3];
    int32_t bad;
    double law_force[3];
    double force[3], good_force[3], body_force[3], u_bar[3], depth, taper;
    int32_t status;
} cstate;

typedef struct {   /* the law's inputs at the proxy (law.c's geometry; law.GEO_K ...) */
    double N[3], K[9], Ki[9];   /* K(x) and its inverse (workspace) */
    double Kt[9], Kti[9];       /* the law's K̃ = c K and K̃⁻¹ */
    double k, lam, g[3];        /* normal stiffness, taper, ∇k on the tangent plane */
    double S[9], dlin;          /* the shape operator on the tangent plane, δ_lin */
} geom;

typedef struct {   /* the law's result and the displacement left to the contact */
    double f[3], u2[3];
    int sliding;
    double delta;
    double ueff[3];
    double total[3];  /* the surface's displacement at the contact: u2 + (ū − ueff) */
} lres;

typedef struct {
    int64_t t;
    double b0, b1, b2, s;
} located;

/* the published results, as 64-bit words (copied with relaxed atomics under the sequence lock) */
typedef struct {
    uint64_t seq;       /* odd while the tick writes */
    uint64_t *words;    /* stats (5), forces (3n), statuses (n, two per word), states (n x PUB_STATE_WORDS) */
    size_t nwords;
    uint64_t *stage;    /* the writer's staging copy */
} published;
#define PUB_STATE_WORDS (sizeof(pm_contact_state) / 8)

struct pm_servo {
    const pm_table *tab;
    int32_t n;
    pm_options o;
    int frictionless;
    double margin, energy, pc_damping;
    int far_warned;
    int32_t far_pending;    /* atomic: 1 once a far probe was seen, until taken */
    double far_probe[3];    /* written once, before far_pending's release store */
    cstate *st;
    /* per-tick workspace, allocated at creation */
    double *probe;
    int *ok;
    geom *geo;
    double *ubar;     /* 3n */
    int32_t *active;  /* n */
    lres *res;        /* n */
    double *gsf;      /* 3n: Gauss-Seidel forces */
    double *cpl;      /* n*n*9 coupling blocks */
    int64_t *pair_tri; /* n*n*2: the mesh triangles each pair's kept vertex-pair blocks are for (-1: none) */
    double *pair_P;   /* n*n*81: those blocks (coupling.c) */
    pm_block_sum_fn block_sum;  /* their sum for the pair's weights: the kernel this CPU runs (coupling.c) */
    pm_pair_fn pairs;   /* those blocks without the table's ζ section (pm_servo_create_paired), and its user */
    void *pairs_user;
    int64_t *given_tri; /* PM_PAIR_CACHE x 2: the triangle pairs the pair function gave last (-1: none) */
    double *given_P;    /* PM_PAIR_CACHE x 81: their blocks (coupling.c: a contact that goes back and forth over
                           an edge asks once; the function may take the GIL) */
    int32_t given_next; /* the entry replaced next (round robin) */
    double *nA, *nr, *nx;  /* the frictionless start's normal system (n*n, n, n) */
    double *nW, *nwr, *nsol; /* its pressing contacts' system, eliminated in place, and solution (n*n, n, n) */
    int32_t *npress, *nidx; /* which contacts press; their indices (n, n) */
    /* display solve */
    double *dC, *du;
    double *dx, *dy;              /* a compressed Ξ's deformation: the masked loads and Ξ x (3 n_c each) */
    pm_greens_work gw;
    int32_t *dact;
    pm_contact_state *dsnap;
    /* the published results */
    published pub;
    pm_tick_stats stats;    /* the servo thread's own copy (published with the state) */
    /* pm_servo_set_probes -> the servo thread: a triple buffer (3 x 3n doubles); writers serialised by a mutex */
    double *tb;
    uint32_t tb_middle;     /* atomic: index of the middle buffer, | 4 when it holds a sample not yet taken */
    uint32_t tb_back, tb_front;
    int tb_seen;            /* the servo thread has taken a sample */
    /* pm_servo_exchange: a ring of samples in and of results out (single producer, single consumer each) */
    double *ring_in;        /* PM_RING x 3n */
    double *ring_out;       /* PM_RING x 3n forces */
    int32_t *ring_status;   /* PM_RING x n */
    uint64_t ring_head, ring_tail, ring_done;  /* atomics: samples submitted, taken, answered */
    int exchange;           /* the thread runs on the exchange ring */
    /* thread mode */
    double *tick_probes, *tick_forces;
    int32_t *tick_status;
    pm_io io;
    int has_io;
    double period, spin;
    int32_t running;        /* atomic */
    int32_t stop_flag;      /* atomic */
#if PM_THREADS
    pthread_t thread;
    pthread_mutex_t in_lock;  /* serialises pm_servo_set_probes and pm_servo_exchange callers */
    pthread_mutex_t display_lock;  /* pm_servo_deformation's workspace, one caller at a time */
    int lock_ok;
#endif
};

/* servo.c */
PM_HIDDEN void pm__state_reset(cstate *s);
PM_HIDDEN void pm__hold(const pm_servo *S, cstate *st, int32_t status);
PM_HIDDEN void pm__release(cstate *st, int32_t status);
PM_HIDDEN int pm__step_inner(pm_servo *S, const double *probes);
PM_HIDDEN void pm__publish(pm_servo *s, const pm_tick_stats *stats);
PM_HIDDEN void pm__read_states(pm_servo *s, pm_contact_state *out);
PM_HIDDEN void pm__read_published(pm_servo *s, int32_t k, pm_contact_state *one, double *forces, int32_t *status,
                                  pm_tick_stats *stats);
/* tracking.c (step 1) */
PM_HIDDEN int pm__locate(const pm_servo *S, int64_t t, const double *p, int retry, located *out);
PM_HIDDEN int pm__move_proxy(const pm_servo *S, cstate *st, const double *target, double limit);
PM_HIDDEN int pm__prepare(pm_servo *S, cstate *st, const double *sample, double *p);
PM_HIDDEN int pm__follow(pm_servo *S, cstate *st);
PM_HIDDEN int pm__normal_at(const pm_table *tb, int64_t t, const double *b, double *N);
/* law.c (step 2) */
PM_HIDDEN int pm__geometry(const pm_servo *S, cstate *st, const double *p, geom *g, double *u);
PM_HIDDEN int pm__local_law(const pm_servo *S, const cstate *st, const geom *g, double ux, double uy, double uz,
                            lres *R);
/* the law for two contacts at once, u (3 each) the displacements left to them: each a lane of a register where both
 * are frictionless and pressing on the law's first branch, else pm__local_law for each; the results are those of
 * pm__local_law to the bit */
PM_HIDDEN int pm__local_law2(const pm_servo *S, const cstate *sa, const geom *ga, const double *ua, lres *Ra,
                             const cstate *sb, const geom *gb, const double *ub, lres *Rb);
/* coupling.c (step 3) */
#define PM_PAIR_CACHE 64
PM_HIDDEN void pm__compliance(const pm_table *tb, int64_t ta, const double *ba, int64_t tbi, const double *bb,
                              double *C);
PM_HIDDEN int pm__solve(pm_servo *S, const int32_t *act, int32_t na);
/* the block-sum kernel for this CPU (and the environment's PMASK_DISABLE_CPU_FEATURES), and whether it is AVX2's */
PM_HIDDEN pm_block_sum_fn pm__block_sum_kernel(void);
PM_HIDDEN int pm__block_sum_is_avx2(pm_block_sum_fn f);
/* output.c (step 4) */
PM_HIDDEN int pm__render(pm_servo *S, int32_t na);

/* ------------------------------------------------------------------ small shared helpers */
static inline double pm__norm3(const double *v) { return sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]); }

static inline void pm__point_at(const pm_table *tb, int64_t t, const double *b, double *x)
{
    const int64_t *v = tb->T + 3 * t;
    const double *a = tb->P + 3 * v[0], *bb = tb->P + 3 * v[1], *c = tb->P + 3 * v[2];
    x[0] = b[0] * a[0] + b[1] * bb[0] + b[2] * c[0];
    x[1] = b[0] * a[1] + b[1] * bb[1] + b[2] * c[1];
    x[2] = b[0] * a[2] + b[1] * bb[2] + b[2] * c[2];
}

/* ------------------------------------------------------------------ 3x3 algebra (pmask.runtime.contact.linalg3) */
/* Nᵀ K⁻¹ N (linalg3.normal_compliance) */
static inline double pm__nkn(const double *N, const double *Ki)
{
    const double Nx = N[0], Ny = N[1], Nz = N[2];
    return (Nx * (Ki[0] * Nx + Ki[1] * Ny + Ki[2] * Nz) + Ny * (Ki[3] * Nx + Ki[4] * Ny + Ki[5] * Nz) +
            Nz * (Ki[6] * Nx + Ki[7] * Ny + Ki[8] * Nz));
}

/* the inverse by cofactors, zeros for a singular matrix (linalg3.inverse3) */
static inline void pm__inverse3(const double *K, double *out)
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

/* M (x, y, z) (linalg3.mul3) */
static inline void pm__mul3(const double *M, double x, double y, double z, double *out)
{
    double a = M[0] * x + M[1] * y + M[2] * z, b = M[3] * x + M[4] * y + M[5] * z;
    double c = M[6] * x + M[7] * y + M[8] * z;
    out[0] = a;
    out[1] = b;
    out[2] = c;
}

/* P S P, P = I − N Nᵀ (linalg3.tangent_part) */
static inline void pm__tangent_part(const double *N, const double *Sm, double *out)
{
    double v[3];
    pm__mul3(Sm, N[0], N[1], N[2], v);
    double s = N[0] * v[0] + N[1] * v[1] + N[2] * v[2];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) out[3 * i + j] = Sm[3 * i + j] - N[i] * v[j] - v[i] * N[j] + s * N[i] * N[j];
}

/* (I − d S)⁻¹ (linalg3.speed_up) */
static inline void pm__speed_up(const double *Sm, double d, double *out)
{
    double M[9];
    for (int i = 0; i < 9; i++) M[i] = -d * Sm[i];
    M[0] = 1.0 - d * Sm[0];
    M[4] = 1.0 - d * Sm[4];
    M[8] = 1.0 - d * Sm[8];
    pm__inverse3(M, out);
}

/* κ_max of a shape operator on the tangent plane (linalg3.largest_curvature) */
static inline double pm__largest_curvature(const double *Sm)
{
    double tr = Sm[0] + Sm[4] + Sm[8];
    double m = Sm[0] * Sm[4] - Sm[1] * Sm[3] + Sm[0] * Sm[8] - Sm[2] * Sm[6] + Sm[4] * Sm[8] - Sm[5] * Sm[7];
    double disc = tr * tr - 4.0 * m;
    return 0.5 * (tr + sqrt(disc > 0.0 ? disc : 0.0));
}

#define FOCAL_FRACTION 0.5
#define FROZEN_CHANGE (0.125 / 1.4142135623730951)  /* 1/(8√2) (law.FROZEN_CHANGE: 0.125 / math.sqrt(2.0)) */

#define RECKON_FROM 0.4

/* the tracking depth min(δ, FOCAL_FRACTION / κ_max) from κ_max, which the two shares below need too
   (linalg3._depth) */
static inline double pm__tracking_depth(double kmax, double delta)
{
    return kmax * delta > FOCAL_FRACTION ? FOCAL_FRACTION / kmax : delta;
}

/* the share w of the proxy's move made by dead reckoning, 0 up to κ_max δ = RECKON_FROM, 1 from FOCAL_FRACTION, a
   smoothstep between; *d the tracking depth (linalg3.reckoning) */
static inline double pm__reckoning(const double *Sm, double delta, double *d)
{
    double kmax = pm__largest_curvature(Sm);
    double x = kmax * delta;
    *d = pm__tracking_depth(kmax, delta);
    if (x <= RECKON_FROM) return 0.0;
    if (x >= FOCAL_FRACTION) return 1.0;
    double u = (x - RECKON_FROM) / (FOCAL_FRACTION - RECKON_FROM);
    return u * u * (3.0 - 2.0 * u);
}

#define LAG_TO 0.8

/* the share of the proxy-offset term the force keeps: 1 up to κ_max δ = FOCAL_FRACTION, 0 from LAG_TO, a
   smoothstep between; *d the tracking depth, from the same κ_max (linalg3.lag_weight) */
static inline double pm__lag_weight(const double *Sm, double delta, double *d)
{
    double kmax = pm__largest_curvature(Sm);
    double x = kmax * delta;
    *d = pm__tracking_depth(kmax, delta);
    if (x <= FOCAL_FRACTION) return 1.0;
    if (x >= LAG_TO) return 0.0;
    double u = (x - FOCAL_FRACTION) / (LAG_TO - FOCAL_FRACTION);
    return 1.0 - u * u * (3.0 - 2.0 * u);
}

/* S(x) alone, interpolated as pm__at does (surface.shape_at): what step 1 reads every tick */
static inline void pm__shape_at(const pm_table *tb, int64_t t, const double *b, double *Sm)
{
    const int64_t *v = tb->T + 3 * t;
    const double *s0 = tb->shape + 9 * v[0], *s1 = tb->shape + 9 * v[1], *s2 = tb->shape + 9 * v[2];
    for (int i = 0; i < 9; i++) Sm[i] = b[0] * s0[i] + b[1] * s1[i] + b[2] * s2[i];
}

/* K(x), λ(x), k(x), ∇k(x), S(x), δ_lin(x) interpolated at barycentric b of t (surface.at) */
static inline void pm__at(const pm_table *tb, int64_t t, const double *b, double *K, double *lam, double *k,
                          double *g, double *Sm, double *dlin)
{
    const int64_t *v = tb->T + 3 * t;
    const double *k0 = tb->K + 9 * v[0], *k1 = tb->K + 9 * v[1], *k2 = tb->K + 9 * v[2];
    for (int i = 0; i < 9; i++) K[i] = b[0] * k0[i] + b[1] * k1[i] + b[2] * k2[i];
    const double *s0 = tb->shape + 9 * v[0], *s1 = tb->shape + 9 * v[1], *s2 = tb->shape + 9 * v[2];
    for (int i = 0; i < 9; i++) Sm[i] = b[0] * s0[i] + b[1] * s1[i] + b[2] * s2[i];
    const double *g0 = tb->grad + 3 * v[0], *g1 = tb->grad + 3 * v[1], *g2 = tb->grad + 3 * v[2];
    for (int i = 0; i < 3; i++) g[i] = b[0] * g0[i] + b[1] * g1[i] + b[2] * g2[i];
    *lam = b[0] * tb->taper[v[0]] + b[1] * tb->taper[v[1]] + b[2] * tb->taper[v[2]];
    *k = b[0] * tb->kn[v[0]] + b[1] * tb->kn[v[1]] + b[2] * tb->kn[v[2]];
    *dlin = b[0] * tb->dlin[v[0]] + b[1] * tb->dlin[v[1]] + b[2] * tb->dlin[v[2]];
}

#endif
