/* Benchmark of the native servo core, called from C as a C/C++ haptic application calls it.
 *
 *   servo_bench TABLE TRACE N [--friction MU] [--paced TICKS] [--batch QUERIES] [--reacquire COUNT]
 *               [--ratio ROUNDS]
 *
 * TRACE: little-endian int64 tick count, then ticks x N x 3 float64 probe positions.  Prints one JSON
 * object:
 *   tight      the step over the whole trace back to back (median, p99, p99.9, max in µs)
 *   paced      the step in a 1 kHz loop paced by pm_clock_sleep_until on an absolute schedule, as a device
 *              loop runs it (blocks of 500 ticks, alternating with the references below)
 *   blend_*    the noise/physics reference in the same loops: eq. 15 at the contact's own point, three 3x3
 *              blocks blended (the "physical limit"), timed the same way
 *   empty_*    the timer itself (two pm_clock_now calls around nothing)
 *   late       paced ticks whose step finished after the tick's period ended
 *   batch      K(x) for random points, single thread: queries per second; beside it the memory floor, the
 *              same bytes (32 read, 72 written per query) moved by memcpy and memset
 *   reacquire  the step on a tick where tracking restarts (the first tick after a reset, at a trace point
 *              near the surface): the spatial grid's query plus a short walk (median, p99, max µs)
 *   ratio      (N > 1) the N contacts coupled, the N contacts independent and the first contact alone, side by
 *              side in this one process: ROUNDS rounds, each the whole trace through each of the three servos
 *              in turn (the order rotating; the least of RATIO_PASSES passes), one clock reading around each
 *              pass (no timer in the ticks): the mean tick of each, and per round the ratios to the one contact
 *              (median, min, max)
 */
#define _POSIX_C_SOURCE 200809L
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "pmask_servo.h"

/* the library's own clock (pm_clock_now, pm_clock_sleep_until): what its servo thread schedules by */
#define now_s pm_clock_now
#define sleep_until pm_clock_sleep_until

static int cmp(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

static void stats(const char *name, double *t, size_t n, int comma)
{
    if (n == 0) {
        printf("\"%s\": null%s", name, comma ? ", " : "");
        return;
    }
    qsort(t, n, sizeof(double), cmp);
    printf("\"%s\": {\"median_us\": %.4f, \"p99_us\": %.4f, \"p999_us\": %.4f, \"max_us\": %.4f, \"n\": %zu}%s", name,
           1e6 * t[n / 2], 1e6 * t[(size_t)(0.99 * (double)(n - 1))], 1e6 * t[(size_t)(0.999 * (double)(n - 1))],
           1e6 * t[n - 1], n, comma ? ", " : "");
}

static uint64_t rng_state = 0x9E3779B97F4A7C15ull;
static double urand(void)
{
    rng_state ^= rng_state << 13;
    rng_state ^= rng_state >> 7;
    rng_state ^= rng_state << 17;
    return (double)(rng_state >> 11) * (1.0 / 9007199254740992.0);
}

/* The whole trace through a servo (reset first): seconds per tick, one clock reading around the pass. */
static double pass(pm_servo *servo, const double *trace, int64_t ticks, int32_t n, double *forces, int32_t *status)
{
    pm_servo_reset(servo);
    double a = now_s();
    for (int64_t k = 0; k < ticks; k++) pm_servo_step(servo, trace + 3 * (size_t)n * (size_t)k, forces, status);
    return (now_s() - a) / (double)ticks;
}

static void ratio_stats(const char *name, double *r, size_t m, int comma)
{
    qsort(r, m, sizeof(double), cmp);
    printf("\"%s\": {\"median\": %.4f, \"min\": %.4f, \"max\": %.4f}%s", name, r[m / 2], r[0], r[m - 1],
           comma ? ", " : "");
}

#define RATIO_PASSES 5

/* "ratio": the N contacts coupled, independent, and the first contact alone, side by side (see the top). */
static int ratio_rounds(const pm_table *table, const pm_options *opt, const double *trace, int64_t ticks, int32_t n,
                        long rounds)
{
    char err[512];
    pm_options o1 = *opt, oc = *opt, ou = *opt;
    oc.coupled = 1;
    ou.coupled = 0;
    pm_servo *s1 = NULL, *sc = NULL, *su = NULL;
    double *one = malloc((size_t)ticks * 3 * sizeof(double));
    double *forces = malloc(3 * (size_t)n * sizeof(double));
    int32_t *status = malloc((size_t)n * sizeof(int32_t));
    double *t = malloc(3 * (size_t)rounds * sizeof(double));
    double *rc = malloc((size_t)rounds * sizeof(double)), *ru = malloc((size_t)rounds * sizeof(double));
    if (!one || !forces || !status || !t || !rc || !ru || pm_servo_create(table, 1, &o1, &s1, err, sizeof err) ||
        pm_servo_create(table, n, &oc, &sc, err, sizeof err) || pm_servo_create(table, n, &ou, &su, err, sizeof err)) {
        fprintf(stderr, "ratio: %s\n", err);
        return 1;
    }
    for (int64_t k = 0; k < ticks; k++) memcpy(one + 3 * k, trace + 3 * (size_t)n * (size_t)k, 3 * sizeof(double));
    pass(s1, one, ticks, 1, forces, status); /* warm: the tables and the code in cache for all three */
    pass(sc, trace, ticks, n, forces, status);
    pass(su, trace, ticks, n, forces, status);
    for (long r = 0; r < rounds; r++) {
        double *tr = t + 3 * r;  /* one, coupled, independent */
        for (int j = 0; j < 3; j++) {
            int w = (int)((j + r) % 3);
            double best = 1e30;
            for (int q = 0; q < RATIO_PASSES; q++) {  /* a pass is ~1 ms: the least of a few drops preemptions */
                double x = w == 0 ? pass(s1, one, ticks, 1, forces, status)
                         : pass(w == 1 ? sc : su, trace, ticks, n, forces, status);
                if (x < best) best = x;
            }
            tr[w] = best;
        }
        rc[r] = tr[1] / tr[0];
        ru[r] = tr[2] / tr[0];
    }
    double *col = malloc((size_t)rounds * sizeof(double));
    if (!col) return 1;
    printf("\"ratio\": {\"rounds\": %ld, ", rounds);
    const char *names[3] = {"one_us", "coupled_us", "independent_us"};
    for (int j = 0; j < 3; j++) {
        for (long r = 0; r < rounds; r++) col[r] = 1e6 * t[3 * r + j];
        qsort(col, (size_t)rounds, sizeof(double), cmp);
        printf("\"%s\": %.4f, ", names[j], col[rounds / 2]);
    }
    ratio_stats("coupled_over_one", rc, (size_t)rounds, 1);
    ratio_stats("independent_over_one", ru, (size_t)rounds, 0);
    printf("}, ");
    free(col);
    free(one);
    free(forces);
    free(status);
    free(t);
    free(rc);
    free(ru);
    pm_servo_free(s1);
    pm_servo_free(sc);
    pm_servo_free(su);
    return 0;
}

int main(int argc, char **argv)
{
    if (argc < 4) {
        fprintf(stderr, "usage: %s TABLE TRACE N [--friction MU] [--paced TICKS] [--batch Q] [--reacquire C] "
                        "[--ratio ROUNDS]\n", argv[0]);
        return 2;
    }
    int32_t n = atoi(argv[3]);
    double friction = 0.0;
    long paced = 0, batch = 0, reacq = 0, rounds = 0;
    for (int i = 4; i + 1 < argc; i += 2) {
        if (!strcmp(argv[i], "--friction")) friction = atof(argv[i + 1]);
        else if (!strcmp(argv[i], "--paced")) paced = atol(argv[i + 1]);
        else if (!strcmp(argv[i], "--batch")) batch = atol(argv[i + 1]);
        else if (!strcmp(argv[i], "--reacquire")) reacq = atol(argv[i + 1]);
        else if (!strcmp(argv[i], "--ratio")) rounds = atol(argv[i + 1]);
    }
    char err[512];
    pm_table *table;
    if (pm_table_load(argv[1], &table, err, sizeof err)) {
        fprintf(stderr, "%s\n", err);
        return 1;
    }
    FILE *f = fopen(argv[2], "rb");
    int64_t ticks = 0;
    if (!f || fread(&ticks, 8, 1, f) != 1 || ticks <= 0) {
        fprintf(stderr, "cannot read the trace %s\n", argv[2]);
        return 1;
    }
    double *trace = malloc((size_t)ticks * 3 * (size_t)n * sizeof(double));
    if (!trace || fread(trace, sizeof(double), (size_t)ticks * 3 * (size_t)n, f) != (size_t)ticks * 3 * (size_t)n) {
        fprintf(stderr, "short trace\n");
        return 1;
    }
    fclose(f);
    pm_options opt;
    pm_options_default(table, &opt);
    opt.friction = opt.dynamic_friction = friction;
    if (getenv("PMASK_BENCH_UNCOUPLED")) opt.coupled = 0;  /* the s independent contacts, for comparison */
    pm_servo *servo;
    if (pm_servo_create(table, n, &opt, &servo, err, sizeof err)) {
        fprintf(stderr, "%s\n", err);
        return 1;
    }
    double *forces = malloc(3 * (size_t)n * sizeof(double));
    int32_t *status = malloc((size_t)n * sizeof(int32_t));
    double *t_step = malloc((size_t)ticks * sizeof(double));
    double *t_blend = malloc((size_t)ticks * sizeof(double));
    double *t_empty = malloc((size_t)ticks * sizeof(double));
    if (!forces || !status || !t_step || !t_blend || !t_empty) return 1;

    /* tight: the trace back to back; the blend at the same contact points, and the empty timer, interleaved */
    int64_t contact = 0, nb = 0;
    for (int64_t k = 0; k < ticks; k++) {
        double a = now_s();
        pm_servo_step(servo, trace + 3 * (size_t)n * (size_t)k, forces, status);
        double b = now_s();
        t_step[k] = b - a;
        contact += status[0] == PM_CONTACT;
        pm_contact_state cs;
        pm_servo_state(servo, 0, &cs);
        if (cs.triangle >= 0) {
            double K[9];
            a = now_s();
            pm_table_stiffness(table, 1, &cs.triangle, cs.bary, K);
            b = now_s();
            t_blend[nb] = b - a;
            a = now_s();
            b = now_s();
            t_empty[nb++] = b - a;
        }
    }
    printf("{\"ticks\": %lld, \"contacts\": %d, \"contact_fraction\": %.4f, \"kernel\": \"%s\", ", (long long)ticks,
           (int)n, (double)contact / (double)ticks, pm_servo_kernel(servo));
    stats("tight", t_step, (size_t)ticks, 1);
    stats("blend_tight", t_blend, (size_t)nb, 1);
    stats("empty_tight", t_empty, (size_t)nb, 1);

    if (paced > 0) {  /* 1 kHz on the wall clock: blocks of 500 ticks of the step, then 500 of the blend */
        const double T = 1e-3;
        pm_servo_reset(servo);
        int64_t ns = 0, nbl = 0, late = 0, k = 0;
        double next = now_s() + T;
        int64_t done = 0;
        pm_contact_state cs;
        memset(&cs, 0, sizeof cs);
        cs.triangle = -1;
        while (done < paced) {
            for (int phase = 0; phase < 2; phase++)
                for (int j = 0; j < 500 && done < paced; j++) {
                    sleep_until(next);
                    if (phase == 0) {
                        double a = now_s();
                        pm_servo_step(servo, trace + 3 * (size_t)n * (size_t)(k % ticks), forces, status);
                        double b = now_s();
                        t_step[ns++] = b - a;
                        if (b > next + T) late++;
                        pm_servo_state(servo, 0, &cs);
                        k++;
                        done++;
                    } else if (cs.triangle >= 0) {
                        double K[9];
                        double a = now_s();
                        pm_table_stiffness(table, 1, &cs.triangle, cs.bary, K);
                        double b = now_s();
                        t_blend[nbl] = b - a;
                        a = now_s();
                        b = now_s();
                        t_empty[nbl++] = b - a;
                    }
                    next += T;
                    double t = now_s();
                    if (t > next) next = t + T;  /* fell behind: restart the schedule */
                }
        }
        stats("paced", t_step, (size_t)ns, 1);
        stats("blend_paced", t_blend, (size_t)nbl, 1);
        stats("empty_paced", t_empty, (size_t)nbl, 1);
        printf("\"late\": %lld, \"paced_ticks\": %lld, ", (long long)late, (long long)ns);
    }
    if (batch > 0) {
        int64_t nt = pm_table_triangles(table);
        int64_t *tri = malloc((size_t)batch * sizeof(int64_t));
        double *bary = malloc((size_t)batch * 3 * sizeof(double));
        double *out = malloc((size_t)batch * 9 * sizeof(double));
        if (!tri || !bary || !out) return 1;
        for (long q = 0; q < batch; q++) {
            tri[q] = (int64_t)(urand() * (double)nt) % nt;
            double u = urand(), v = urand();
            if (u + v > 1.0) {
                u = 1.0 - u;
                v = 1.0 - v;
            }
            bary[3 * q] = 1.0 - u - v;
            bary[3 * q + 1] = u;
            bary[3 * q + 2] = v;
        }
        double best = 1e30;
        for (int r = 0; r < 7; r++) {
            double a = now_s();
            pm_table_stiffness(table, batch, tri, bary, out);
            double b = now_s();
            if (b - a < best) best = b - a;
        }
        /* the memory floor: the same bytes streamed by memset/memcpy (read the queries, write the results) */
        double fbest = 1e30;
        double *src = malloc((size_t)batch * 4 * sizeof(double));
        if (!src) return 1;
        memset(src, 0, (size_t)batch * 4 * sizeof(double));
        for (int r = 0; r < 7; r++) {
            double a = now_s();
            memcpy(out, src, (size_t)batch * 4 * sizeof(double));
            memset(out + 4 * batch, 0, (size_t)batch * 5 * sizeof(double));
            double b = now_s();
            if (b - a < fbest) fbest = b - a;
        }
        free(src);
        printf("\"batch_per_s\": %.1f, \"batch_floor_per_s\": %.1f, ", (double)batch / best, (double)batch / fbest);
        free(tri);
        free(bary);
        free(out);
    }
    if (reacq > 0 && n == 1) {
        /* ticks where tracking (re)starts: after a reset (as after a probe left the model's margin), a trace
           point near the surface: the grid's query and the walk to the projection */
        double *t_re = malloc((size_t)reacq * sizeof(double));
        if (!t_re) return 1;
        long m = 0;
        for (long r = 0; r < reacq; r++) {
            pm_servo_reset(servo);
            const double *p = trace + 3 * (size_t)((int64_t)(urand() * (double)ticks) % ticks);
            double a = now_s();
            pm_servo_step(servo, p, forces, status);
            double b = now_s();
            pm_contact_state cs;
            pm_servo_state(servo, 0, &cs);
            if (cs.triangle >= 0) t_re[m++] = b - a;
        }
        stats("reacquire", t_re, (size_t)m, 1);
        free(t_re);
    }
    if (rounds > 0 && n > 1 && ratio_rounds(table, &opt, trace, ticks, n, rounds)) return 1;
    printf("\"triangles\": %lld}\n", (long long)pm_table_triangles(table));
    pm_servo_free(servo);
    pm_table_free(table);
    free(trace);
    free(forces);
    free(status);
    free(t_step);
    free(t_blend);
    free(t_empty);
    return 0;
}
