/* The servo core's threads under the sanitizers (make sanitize; CI fails on any report).
 *
 *   servo_threads TABLE [COMPRESSED]
 *
 * 1. Thread mode: the servo's thread runs at 1 kHz for two contacts while three threads of the application
 *    call pm_servo_set_probes (a scripted press and circle), pm_servo_read / pm_servo_state, and
 *    pm_servo_deformation (when the table has a zeta section) beside it.  Each published state must be one
 *    the tick wrote: its point lies on its triangle at its barycentrics (a torn copy would mix two ticks).
 * 2. Exchange mode: two application threads take turns exchanging a scripted trace; every answer equals a
 *    second servo stepped on the same samples in the same order (bit for bit).
 * 3. A table over the file's own sections (pm_table_from_sections: borrowed, no copy) steps the trace as the
 *    loaded table does, bit for bit.
 * 4. The same sections without "zeta" and "contact_row", coupled through a pair function
 *    (pm_servo_create_paired) that reads the file's ζ section itself: the same steps as the loaded table, bit for
 *    bit, stepped by the caller and in exchange mode (the pair function then runs on the servo's thread).
 * 5. (servo_threads TABLE COMPRESSED: a table exported from a compressed artifact of the same model, table 1.4)
 *    Contacts coupled from Ξ's compressed sections by the core itself: stepped, then in exchange mode (the blocks
 *    then formed on the servo's thread) bit for bit the same, every force within 1e-3 of the largest of the ζ
 *    table's and the displayed deformation within 1e-3 of its (the compression's bound), and the blocks of a
 *    pair of triangles read both ways transposes of each other, bit for bit.
 * Prints one line per part; exits 1 on a failed check.
 */
#define _POSIX_C_SOURCE 200809L
#include <math.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "pmask_servo.h"

#define N 2
#define EXCHANGES 600

typedef struct {
    pm_servo *servo;
    const pm_table *table;
    double top[3];
    int32_t stop;      /* atomic */
    int64_t torn;      /* atomic: published states inconsistent with themselves */
    int64_t reads;     /* atomic */
} shared;

static void probe_at(const shared *sh, int64_t k, int which, double *p)
{
    double t = (double)k / 1000.0, depth = t < 0.3 ? 0.01 * t : 0.003;   /* press 3 mm, then circle */
    double a = 6.283185307179586 * t, r = 0.002;
    p[0] = sh->top[0] + (which ? -0.008 : 0.008) + r * cos(a);
    p[1] = sh->top[1] + r * sin(a);
    p[2] = sh->top[2] - depth;
}

static void *writer(void *arg)
{
    shared *sh = arg;
    struct timespec ts = {0, 300000};
    for (int64_t k = 0; !__atomic_load_n(&sh->stop, __ATOMIC_ACQUIRE); k++) {
        double p[3 * N];
        for (int w = 0; w < N; w++) probe_at(sh, k, w, p + 3 * w);
        pm_servo_set_probes(sh->servo, p);
        nanosleep(&ts, NULL);
    }
    return NULL;
}

static void *reader(void *arg)
{
    shared *sh = arg;
    while (!__atomic_load_n(&sh->stop, __ATOMIC_ACQUIRE)) {
        double f[3 * N];
        int32_t st[N];
        pm_tick_stats stats;
        pm_servo_read(sh->servo, f, st, &stats);
        for (int32_t k = 0; k < N; k++) {
            pm_contact_state cs;
            pm_servo_state(sh->servo, k, &cs);
            if (cs.triangle < 0) continue;
            /* the point is the barycentric combination of the triangle's corners: recompute it from a
             * one-contact servo-free source (the table's stiffness is not needed: compare with bary sums) */
            double sb = cs.bary[0] + cs.bary[1] + cs.bary[2];
            if (!(fabs(sb - 1.0) < 1e-9) || !isfinite(cs.point[0])) __atomic_fetch_add(&sh->torn, 1, __ATOMIC_RELAXED);
        }
        __atomic_fetch_add(&sh->reads, 1, __ATOMIC_RELAXED);
    }
    return NULL;
}

static void *display(void *arg)
{
    shared *sh = arg;
    int64_t nv = pm_table_vertices(sh->table);
    double *u = malloc((size_t)nv * 3 * sizeof(double));
    if (!u) return NULL;
    struct timespec ts = {0, 5000000};
    while (!__atomic_load_n(&sh->stop, __ATOMIC_ACQUIRE)) {
        if (pm_servo_deformation(sh->servo, u) == -1) break;  /* no zeta table */
        nanosleep(&ts, NULL);
    }
    free(u);
    return NULL;
}

typedef struct {
    pm_servo *servo;
    const shared *sh;
    int which;               /* this thread takes every other sample */
    pthread_mutex_t *turn;   /* the two threads alternate: the samples stay in trace order */
    int64_t *next;           /* next sample index, under turn */
    double (*forces)[3 * N];
    int32_t (*status)[N];
    int failed;
} exch;

static void *exchanger(void *arg)
{
    exch *e = arg;
    for (;;) {
        pthread_mutex_lock(e->turn);
        int64_t k = *e->next;
        if (k >= EXCHANGES) {
            pthread_mutex_unlock(e->turn);
            return NULL;
        }
        double p[3 * N];
        for (int w = 0; w < N; w++) probe_at(e->sh, k, w, p + 3 * w);
        int rc = pm_servo_exchange(e->servo, p, e->forces[k], e->status[k], 1.0);
        *e->next = k + 1;
        pthread_mutex_unlock(e->turn);
        if (rc != 0) e->failed = rc;
    }
}

static uint64_t le64(const unsigned char *p)
{
    uint64_t x = 0;
    for (int i = 7; i >= 0; i--) x = (x << 8) | p[i];
    return x;
}

/* parts 3 and 4: servos x and y stepped on the trace side by side; the ticks whose forces or statuses differ
 * (x's forces and statuses kept in forces/status when given) */
static int64_t step_both(pm_servo *x, pm_servo *y, const shared *sh, double (*forces)[3 * N], int32_t (*status)[N])
{
    int64_t differ = 0;
    for (int64_t k = 0; k < EXCHANGES; k++) {
        double p[3 * N], fx[3 * N], fy[3 * N];
        int32_t sx[N], sy[N];
        for (int w = 0; w < N; w++) probe_at(sh, k, w, p + 3 * w);
        pm_servo_step(x, p, fx, sx);
        pm_servo_step(y, p, fy, sy);
        if (forces) memcpy(forces[k], fx, sizeof fx);
        if (status) memcpy(status[k], sx, sizeof sx);
        if (memcmp(fx, fy, sizeof fx) != 0 || memcmp(sx, sy, sizeof sx) != 0) differ++;
    }
    return differ;
}

/* parts 4 and 5: servo y from reset in exchange mode on the trace; the samples whose answers differ from the
 * stepped forces and statuses, or -1 when the thread does not start */
static int64_t exchange_differs(pm_servo *y, const shared *sh, double (*forces)[3 * N], int32_t (*status)[N])
{
    int64_t differ = 0;
    pm_servo_reset(y);
    if (pm_servo_start_exchange(y, 1000.0, PM_SPIN_DEFAULT)) return -1;
    for (int64_t k = 0; k < EXCHANGES; k++) {
        double p[3 * N], f[3 * N];
        int32_t s[N];
        for (int w = 0; w < N; w++) probe_at(sh, k, w, p + 3 * w);
        if (pm_servo_exchange(y, p, f, s, 1.0) != 0 || memcmp(f, forces[k], sizeof f) != 0 ||
            memcmp(s, status[k], sizeof s) != 0)
            differ++;
    }
    pm_servo_stop(y);
    return differ;
}

/* part 4's pair function: the nine vertex-pair blocks of mesh triangles ta, tb from the file's own ζ section and
 * contact rows, P_xy = ½ (ζ_y(x) + ζ_x(y)ᵀ) (written here from the table format, not from the core's code) */
typedef struct {
    const double *zeta;
    const int64_t *row, *tri;
    int64_t n3;
    int64_t calls;  /* atomic */
} zeta_pairs;

static int pairs_from_zeta(void *user, int64_t ta, int64_t tb, double *P)
{
    zeta_pairs *z = user;
    __atomic_fetch_add(&z->calls, 1, __ATOMIC_RELAXED);
    for (int x = 0; x < 3; x++)
        for (int y = 0; y < 3; y++) {
            const int64_t ri = z->row[z->tri[3 * ta + x]], rm = z->row[z->tri[3 * tb + y]];
            for (int r = 0; r < 3; r++)
                for (int c = 0; c < 3; c++) {
                    double v = 0.0;
                    if (ri >= 0 && rm >= 0)  /* ζ_y(x)[r][c] is row 3 rm + c, column 3 ri + r of the section */
                        v = 0.5 * (z->zeta[(3 * rm + c) * z->n3 + 3 * ri + r] + z->zeta[(3 * ri + r) * z->n3 + 3 * rm + c]);
                    P[27 * x + 9 * y + 3 * r + c] = v;
                }
        }
    return 0;
}

/* part 4: the loaded table's steps, stepped and exchanged, against a servo on the sections less the ζ table
 * coupled through pairs_from_zeta */
static int paired_steps_the_same(const pm_section *secs, uint32_t n, const pm_table *loaded, const shared *sh)
{
    pm_section *less = calloc(n, sizeof *less);
    pm_table *t = NULL;
    pm_servo *x = NULL, *y = NULL;
    zeta_pairs z = {NULL, NULL, NULL, 0, 0};
    uint32_t m = 0;
    int rc = 1;
    char err[512];
    if (!less) return 1;
    for (uint32_t i = 0; i < n; i++) {
        if (!strcmp(secs[i].name, "zeta")) {
            z.zeta = secs[i].data;
            z.n3 = secs[i].cols;
        } else if (!strcmp(secs[i].name, "contact_row")) {
            z.row = secs[i].data;
        } else {
            if (!strcmp(secs[i].name, "mesh_triangles") || (!strcmp(secs[i].name, "triangles") && !z.tri))
                z.tri = secs[i].data;  /* the mesh's triangles: mesh_triangles where the surface is subdivided */
            less[m++] = secs[i];
        }
    }
    static double forces[EXCHANGES][3 * N];
    static int32_t status[EXCHANGES][N];
    if (!z.zeta || !z.row || !z.tri) {
        fprintf(stderr, "error: part 4 needs a table with its zeta section\n");
        goto out;
    }
    pm_options o;
    pm_options_default(loaded, &o);
    o.friction = 0.3;
    o.coupled = 1;
    if (pm_table_from_sections(less, (int32_t)m, &t, err, sizeof err) || pm_table_has_zeta(t) ||
        !pm_servo_create(t, N, &o, &y, err, sizeof err) ||  /* refused: coupled, no ζ, no pair function */
        pm_servo_create(loaded, N, &o, &x, err, sizeof err) ||
        pm_servo_create_paired(t, N, &o, pairs_from_zeta, &z, &y, err, sizeof err)) {
        fprintf(stderr, "error: part 4: %s\n", err);
        goto out;
    }
    const int64_t differ = step_both(x, y, sh, forces, status);
    const int64_t stepped = __atomic_load_n(&z.calls, __ATOMIC_RELAXED);
    const int64_t differ_thread = exchange_differs(y, sh, forces, status);
    if (differ_thread < 0) goto out;
    printf("a pair function in place of the zeta table: %d steps, %lld differ stepped, %lld in exchange mode; "
           "%lld pairs asked for stepped\n", EXCHANGES, (long long)differ, (long long)differ_thread, (long long)stepped);
    rc = differ != 0 || differ_thread != 0 || stepped < 1 || stepped > EXCHANGES / 4;
out:
    pm_servo_free(x);
    pm_servo_free(y);
    pm_table_free(t);
    free(less);
    return rc;
}

static int borrowed_table_steps_the_same(const char *path, const pm_table *loaded, const shared *sh)
{
    FILE *f = fopen(path, "rb");
    if (!f) return 1;
    fseek(f, 0, SEEK_END);
    long size = ftell(f);
    fseek(f, 0, SEEK_SET);
    unsigned char *blob = malloc((size_t)size);
    int rc = 1;
    pm_section *secs = NULL, *secs_all = NULL;
    char (*names)[33] = NULL;
    pm_table *borrowed = NULL;
    pm_servo *x = NULL, *y = NULL;
    char err[512];
    if (!blob || fread(blob, 1, (size_t)size, f) != (size_t)size) goto out;
    uint32_t n = (uint32_t)le64(blob + 32) & 0xFFFFFFFFu;
    secs = calloc(n, sizeof *secs);
    secs_all = calloc(n, sizeof *secs_all);
    names = calloc(n, sizeof *names);
    if (!secs || !secs_all || !names) goto out;
    for (uint32_t i = 0; i < n; i++) {
        const unsigned char *e = blob + 64 + 64 * (size_t)i;
        memcpy(names[i], e, 32);
        secs[i] = (pm_section){names[i], (int32_t)(le64(e + 32) & 0xFFFFFFFFu), (int64_t)le64(e + 48),
                               (int64_t)le64(e + 56), blob + le64(e + 40)};
    }
    if (pm_table_from_sections(secs, (int32_t)n, &borrowed, err, sizeof err)) {
        fprintf(stderr, "error: %s\n", err);
        goto out;
    }
    memcpy(secs_all, secs, n * sizeof *secs);  /* for part 4 */
    free(secs);  /* the list may go; the arrays stay */
    secs = NULL;
    pm_options o;
    pm_options_default(loaded, &o);
    o.friction = 0.3;
    if (pm_servo_create(loaded, N, &o, &x, err, sizeof err) || pm_servo_create(borrowed, N, &o, &y, err, sizeof err))
        goto out;
    const int64_t differ = step_both(x, y, sh, NULL, NULL);
    printf("a table over the file's sections: %d steps, %lld differ from the loaded table's\n", EXCHANGES,
           (long long)differ);
    rc = differ != 0;
    if (paired_steps_the_same(secs_all, n, loaded, sh)) rc = 1;
out:
    pm_servo_free(x);
    pm_servo_free(y);
    pm_table_free(borrowed);
    free(secs);
    free(secs_all);
    free(names);
    free(blob);
    fclose(f);
    return rc;
}

/* part 5: coupled contacts on a compressed artifact's table against the loaded one's ζ table */
static int compressed_couples(const char *path, const pm_table *loaded, const shared *sh)
{
    pm_table *c = NULL;
    pm_servo *x = NULL, *y = NULL;
    char err[512];
    int rc = 1;
    static double forces[EXCHANGES][3 * N];
    static int32_t status[EXCHANGES][N];
    if (pm_table_load(path, &c, err, sizeof err) || !pm_table_has_greens(c) || pm_table_has_zeta(c)) {
        fprintf(stderr, "error: part 5 needs a table with a compressed Xi: %s\n", err);
        goto out;
    }
    pm_options o;
    pm_options_default(loaded, &o);
    o.friction = 0.3;
    o.coupled = 1;
    if (pm_servo_create(loaded, N, &o, &x, err, sizeof err) || pm_servo_create(c, N, &o, &y, err, sizeof err)) {
        fprintf(stderr, "error: part 5: %s\n", err);
        goto out;
    }
    double worst = 0.0, largest = 0.0;
    int64_t touching = 0;
    for (int64_t k = 0; k < EXCHANGES; k++) {
        double p[3 * N], fx[3 * N];
        for (int w = 0; w < N; w++) probe_at(sh, k, w, p + 3 * w);
        pm_servo_step(x, p, fx, NULL);
        pm_servo_step(y, p, forces[k], status[k]);
        touching += status[k][0] == PM_CONTACT && status[k][1] == PM_CONTACT;
        for (int i = 0; i < 3 * N; i++) {
            worst = fmax(worst, fabs(forces[k][i] - fx[i]));
            largest = fmax(largest, fabs(fx[i]));
        }
    }
    const int64_t differ_thread = exchange_differs(y, sh, forces, status);
    if (differ_thread < 0) goto out;
    /* the displayed deformation after the last tick, from Ξ's compressed sections and from the ζ table */
    const int64_t nv = pm_table_vertices(loaded);
    double *ux = malloc((size_t)nv * 3 * sizeof *ux), *uy = malloc((size_t)nv * 3 * sizeof *uy);
    double du = 0.0, un = 0.0;
    if (!ux || !uy || pm_table_vertices(c) != nv || pm_servo_deformation(x, ux) || pm_servo_deformation(y, uy)) {
        free(ux);
        free(uy);
        fprintf(stderr, "error: part 5: no deformation\n");
        goto out;
    }
    for (int64_t i = 0; i < 3 * nv; i++) {
        du += (uy[i] - ux[i]) * (uy[i] - ux[i]);
        un += ux[i] * ux[i];
    }
    free(ux);
    free(uy);
    int64_t asymmetric = 0;
    const int64_t nt = pm_table_triangles(c);
    for (int64_t k = 0; k < 200; k++) {
        const int64_t ta = (k * 7919) % nt, tb = (k * 104729 + 13) % nt;
        double P[81], Q[81];
        if (pm_table_pair_blocks(c, ta, tb, P) || pm_table_pair_blocks(c, tb, ta, Q)) {
            asymmetric++;
            continue;
        }
        for (int a = 0; a < 3; a++)
            for (int b = 0; b < 3; b++)
                for (int r = 0; r < 3; r++)
                    for (int q = 0; q < 3; q++)
                        asymmetric += P[27 * a + 9 * b + 3 * r + q] != Q[27 * b + 9 * a + 3 * q + r];
    }
    printf("a compressed Xi in place of the zeta table: %d steps (%lld both touching), forces within %.2e of the "
           "largest, the deformation within %.2e, %lld differ in exchange mode, %lld asymmetric block entries\n",
           EXCHANGES, (long long)touching, largest > 0 ? worst / largest : 0.0, un > 0 ? sqrt(du / un) : 0.0,
           (long long)differ_thread, (long long)asymmetric);
    rc = !(largest > 0) || worst > 1e-3 * largest || !(un > 0) || du > 1e-6 * un || touching < EXCHANGES / 2 ||
         differ_thread || asymmetric;
out:
    pm_servo_free(x);
    pm_servo_free(y);
    pm_table_free(c);
    return rc;
}

int main(int argc, char **argv)
{
    if (argc != 2 && argc != 3) {
        fprintf(stderr, "usage: %s TABLE [COMPRESSED]\n", argv[0]);
        return 2;
    }
    char err[512];
    pm_table *table;
    if (pm_table_load(argv[1], &table, err, sizeof err)) {
        fprintf(stderr, "error: %s\n", err);
        return 1;
    }
    pm_options o;
    pm_options_default(table, &o);
    o.friction = 0.3;
    shared sh;
    memset(&sh, 0, sizeof sh);
    sh.table = table;
    {
        double lo[3], hi[3];
        pm_table_bounds(table, lo, hi);
        sh.top[0] = 0.5 * (lo[0] + hi[0]);
        sh.top[1] = 0.5 * (lo[1] + hi[1]);
        sh.top[2] = hi[2];
    }
    int rc = 0;
    pm_servo *a = NULL, *b = NULL;
    if (pm_servo_create(table, N, &o, &a, err, sizeof err) || pm_servo_create(table, N, &o, &b, err, sizeof err)) {
        fprintf(stderr, "error: %s\n", err);
        rc = 1;
        goto done;
    }
    /* 1. thread mode beside three application threads */
    sh.servo = a;
    if (pm_servo_start(a, 1000.0, PM_SPIN_DEFAULT, NULL)) {
        fprintf(stderr, "error: the servo thread did not start\n");
        rc = 1;
        goto done;
    }
    pthread_t t[3];
    pthread_create(&t[0], NULL, writer, &sh);
    pthread_create(&t[1], NULL, reader, &sh);
    pthread_create(&t[2], NULL, display, &sh);
    struct timespec run = {1, 0};
    nanosleep(&run, NULL);
    __atomic_store_n(&sh.stop, 1, __ATOMIC_RELEASE);
    for (int i = 0; i < 3; i++) pthread_join(t[i], NULL);
    pm_servo_stop(a);
    pm_tick_stats stats;
    pm_servo_read(a, NULL, NULL, &stats);
    printf("thread mode: %lld ticks, %lld reads beside them, %lld torn\n", (long long)stats.ticks,
           (long long)__atomic_load_n(&sh.reads, __ATOMIC_RELAXED), (long long)__atomic_load_n(&sh.torn, __ATOMIC_RELAXED));
    if (stats.ticks < 500 || sh.torn) rc = 1;

    /* 2. exchange mode: answers equal the step on the same samples */
    pm_servo_reset(a);
    if (pm_servo_start_exchange(a, 1000.0, PM_SPIN_DEFAULT)) {
        fprintf(stderr, "error: the exchange thread did not start\n");
        rc = 1;
        goto done;
    }
    static double forces[EXCHANGES][3 * N];
    static int32_t status[EXCHANGES][N];
    pthread_mutex_t turn = PTHREAD_MUTEX_INITIALIZER;
    int64_t next = 0;
    exch e[2];
    for (int i = 0; i < 2; i++) {
        e[i] = (exch){a, &sh, i, &turn, &next, forces, status, 0};
        pthread_create(&t[i], NULL, exchanger, &e[i]);
    }
    for (int i = 0; i < 2; i++) pthread_join(t[i], NULL);
    pm_servo_stop(a);
    int64_t differ = 0;
    for (int64_t k = 0; k < EXCHANGES; k++) {
        double p[3 * N], f[3 * N];
        int32_t s[N];
        for (int w = 0; w < N; w++) probe_at(&sh, k, w, p + 3 * w);
        pm_servo_step(b, p, f, s);
        if (memcmp(f, forces[k], sizeof f) != 0 || memcmp(s, status[k], sizeof s) != 0) differ++;
    }
    pm_servo_read(a, NULL, NULL, &stats);
    printf("exchange mode: %d samples, %lld differ from the step, %lld idle ticks, errors %d %d\n", EXCHANGES,
           (long long)differ, (long long)stats.idle, e[0].failed, e[1].failed);
    if (differ || e[0].failed || e[1].failed) rc = 1;

    /* 3. a table over arrays the application owns (pm_table_from_sections, no copy): the file's own sections
     *    from its directory; the same steps as the loaded table, bit for bit */
    if (borrowed_table_steps_the_same(argv[1], table, &sh)) rc = 1;
    /* 5. a compressed artifact's table: the core couples from Ξ's compressed sections */
    if (argc == 3 && compressed_couples(argv[2], table, &sh)) rc = 1;
done:
    pm_servo_free(a);
    pm_servo_free(b);
    pm_table_free(table);
    return rc;
}
