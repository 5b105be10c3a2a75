/* A 1 kHz haptic loop in C over a runtime table, with a simulated 3-DOF device.
 *
 *   pmask export-table artifacts/kidney.h5 -o kidney.tbl
 *   cc -std=c99 -O2 -ffp-contract=off -I$(pmask c-core --include) examples/c/haptic_loop.c \
 *      $(pmask c-core --sources) -lm -lpthread -o haptic_loop
 *   ./haptic_loop kidney.tbl                 # as fast as it runs (a scripted 4.5 s session)
 *   ./haptic_loop kidney.tbl --realtime      # paced at 1 kHz on the wall clock, the loop in main()
 *   ./haptic_loop kidney.tbl --thread        # the library's own servo thread, the device in its callbacks
 *   ./haptic_loop kidney.tbl --trace out.csv # every tick: probe, force, status
 *
 * The device: a 0.1 kg point mass with 0.05 N·s/m of damping, held by a hand through a spring-damper grip
 * (200 N/m, 2 N·s/m) that follows a scripted path: from 5 mm above the top of the model down to 4 mm
 * below its highest point, a hold, a 5 mm circle at that depth, a hold, and up again.  The rendered force
 * acts on the mass for the whole tick (a zero-order hold), as on a real device.
 *
 * It prints the table's metadata, how many ticks were in contact, the largest force, the force and the
 * grip's pull at the end of the last hold (their sum is what is left of the motion: ~0 at rest), and the
 * step's timing (median, 99.9th percentile, largest).
 */
#define _POSIX_C_SOURCE 200809L
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "pmask_servo.h"

#define RATE 1000.0
#define MASS 0.1
#define DEVICE_DAMPING 0.05
#define GRIP_K 200.0
#define GRIP_B 2.0
#define TICKS 4500

typedef struct {
    double x[3], v[3];          /* device position and velocity */
    double hand[3], hand_v[3];  /* the scripted hand */
    double top[3];              /* the model's highest point (from the table's bounds) */
    int64_t tick;               /* ticks simulated (in thread mode only the servo's thread touches it) */
    int64_t done;               /* thread mode: the same count, published to main() with atomics */
    double force[3];            /* rendered force, held during the tick */
    int32_t status;
} sim;

/* the hand's path at tick k (positions in metres relative to the model's top) */
static void hand_at(const sim *s, int64_t k, double *h)
{
    double t = (double)k / RATE;
    double z, x = 0.0, y = 0.0;
    if (t < 0.5) {
        z = 0.005 - 0.018 * t;                        /* +5 mm -> -4 mm in 0.5 s */
    } else if (t < 1.5) {
        z = -0.004;                                   /* hold */
    } else if (t < 3.5) {
        double a = 2.0 * 3.14159265358979323846 * (t - 1.5) / 2.0;
        x = 0.0025 * (1.0 - cos(a));                  /* a 5 mm circle */
        y = 0.0025 * sin(a);
        z = -0.004;
    } else if (t < 4.0) {
        z = -0.004;                                   /* hold */
    } else {
        z = -0.004 + 0.018 * (t - 4.0);               /* up again */
    }
    h[0] = s->top[0] + x;
    h[1] = s->top[1] + y;
    h[2] = s->top[2] + z;
}

/* one period of the device under the held force (semi-implicit Euler, 10 substeps) */
static void device_advance(sim *s)
{
    double h[3], hn[3];
    hand_at(s, s->tick, h);
    hand_at(s, s->tick + 1, hn);
    const int sub = 10;
    const double dt = 1.0 / RATE / sub;
    for (int i = 0; i < sub; i++) {
        for (int a = 0; a < 3; a++) {
            double ha = h[a] + (hn[a] - h[a]) * (i + 0.5) / sub, hv = (hn[a] - h[a]) * RATE;
            double f = s->force[a] + GRIP_K * (ha - s->x[a]) + GRIP_B * (hv - s->v[a]) - DEVICE_DAMPING * s->v[a];
            s->v[a] += dt * f / MASS;
            s->x[a] += dt * s->v[a];
        }
    }
    memcpy(s->hand, hn, sizeof hn);
    s->tick += 1;
}

static int cmp(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

/* thread mode: the device's read and write run inside the library's tick */
static void io_read(void *user, double *probes)
{
    sim *s = user;
    memcpy(probes, s->x, sizeof s->x);
}

static void io_write(void *user, const double *forces, const int32_t *status)
{
    sim *s = user;
    memcpy(s->force, forces, sizeof s->force);
    s->status = status[0];
    if (s->tick < TICKS) device_advance(s);
    __atomic_store_n(&s->done, s->tick, __ATOMIC_RELEASE);
}

int main(int argc, char **argv)
{
    if (argc < 2) {
        fprintf(stderr, "usage: %s TABLE [--realtime | --thread] [--trace FILE]\n", argv[0]);
        return 2;
    }
    const char *trace_path = NULL;
    int realtime = 0, threaded = 0;
    for (int i = 2; i < argc; i++) {
        if (strcmp(argv[i], "--realtime") == 0) realtime = 1;
        else if (strcmp(argv[i], "--thread") == 0) threaded = 1;
        else if (strcmp(argv[i], "--trace") == 0 && i + 1 < argc) trace_path = argv[++i];
        else {
            fprintf(stderr, "unknown argument %s\n", argv[i]);
            return 2;
        }
    }
    char err[512];
    pm_table *table;
    if (pm_table_load(argv[1], &table, err, sizeof err)) {
        fprintf(stderr, "error: %s\n", err);
        return 1;
    }
    printf("table: %lld vertices, %lld triangles, zeta %s\nmeta: %s\n", (long long)pm_table_vertices(table),
           (long long)pm_table_triangles(table), pm_table_has_zeta(table) ? "yes" : "no", pm_table_meta(table));
    pm_options opt;
    pm_options_default(table, &opt);
    opt.friction = 0.4;
    opt.dynamic_friction = 0.3;
    pm_servo *servo;
    if (pm_servo_create(table, 1, &opt, &servo, err, sizeof err)) {
        fprintf(stderr, "error: %s\n", err);
        pm_table_free(table);
        return 1;
    }

    /* the model's top: the surface point under the bounds' top centre, where tracking starts */
    sim s;
    memset(&s, 0, sizeof s);
    {
        double lo[3], hi[3], f[3];
        int32_t st;
        pm_contact_state cs;
        pm_table_bounds(table, lo, hi);
        double p[3] = {0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), hi[2] + 0.001 * (hi[2] - lo[2])};
        pm_servo_step(servo, p, f, &st);
        pm_servo_state(servo, 0, &cs);
        if (cs.triangle < 0) {
            fprintf(stderr, "error: tracking did not start above the model\n");
            pm_servo_free(servo);
            pm_table_free(table);
            return 1;
        }
        memcpy(s.top, cs.point, sizeof s.top);
        pm_servo_reset(servo);
    }
    hand_at(&s, 0, s.hand);
    memcpy(s.x, s.hand, sizeof s.x);
    printf("top of the model: (%.4f, %.4f, %.4f)\n", s.top[0], s.top[1], s.top[2]);

    FILE *trace = NULL;
    if (trace_path && !(trace = fopen(trace_path, "w"))) {
        fprintf(stderr, "error: cannot write %s\n", trace_path);
        pm_servo_free(servo);
        pm_table_free(table);
        return 1;
    }
    if (trace) fprintf(trace, "tick,px,py,pz,fx,fy,fz,status\n");
    double *step_time = malloc(TICKS * sizeof(double));
    int rc = 0;
    if (!step_time) {
        fprintf(stderr, "error: out of memory\n");
        rc = 1;
        goto done;
    }
    int64_t contact = 0, late = 0;
    double fmax = 0.0, f_hold[3] = {0, 0, 0}, grip_hold[3] = {0, 0, 0};

    if (threaded) {
        pm_io io = {io_read, io_write, &s};
        int started = pm_servo_start(servo, RATE, PM_SPIN_DEFAULT, &io);
        if (started) {
            fprintf(stderr, "error: the servo thread did not start (%d)\n", started);
            rc = 1;
            goto done;
        }
        struct timespec ts = {0, 50000000L};
        while (__atomic_load_n(&s.done, __ATOMIC_ACQUIRE) < TICKS) nanosleep(&ts, NULL);
        pm_servo_stop(servo);
        pm_tick_stats stats;
        pm_servo_read(servo, NULL, NULL, &stats);
        printf("thread: %lld ticks, %lld late, largest lateness %.1f us, longest step %.2f us\n",
               (long long)stats.ticks, (long long)stats.late, 1e6 * stats.max_lateness, 1e6 * stats.step_max);
    } else {
        double next = pm_clock_now();
        for (int64_t k = 0; k < TICKS; k++) {
            if (realtime) {  /* the library's clock: the schedule its own thread keeps */
                next += 1.0 / RATE;
                pm_clock_sleep_until(next);
            }
            double probe[3];
            memcpy(probe, s.x, sizeof probe);   /* read the device */
            double t0 = pm_clock_now();
            pm_servo_step(servo, probe, s.force, &s.status);
            double t1 = pm_clock_now();
            step_time[k] = t1 - t0;
            if (realtime && t1 > next + 1.0 / RATE) late++;
            if (trace)
                fprintf(trace, "%lld,%.17g,%.17g,%.17g,%.17g,%.17g,%.17g,%d\n", (long long)k, probe[0], probe[1],
                        probe[2], s.force[0], s.force[1], s.force[2], (int)s.status);
            if (s.status == PM_CONTACT || s.status == PM_REGION_EDGE || s.status == PM_DEEP) contact++;
            double fm = sqrt(s.force[0] * s.force[0] + s.force[1] * s.force[1] + s.force[2] * s.force[2]);
            if (fm > fmax) fmax = fm;
            if (k == 3999) {   /* the end of the last hold */
                for (int a = 0; a < 3; a++) {
                    f_hold[a] = s.force[a];
                    grip_hold[a] = GRIP_K * (s.hand[a] - s.x[a]);
                }
            }
            device_advance(&s);   /* write the force: it acts until the next tick */
        }
        qsort(step_time, TICKS, sizeof(double), cmp);
        printf("contact ticks: %lld of %d; largest force %.4f N\n", (long long)contact, TICKS, fmax);
        printf("end of hold: force (%.6f, %.6f, %.6f) N, grip (%.6f, %.6f, %.6f) N\n", f_hold[0], f_hold[1],
               f_hold[2], grip_hold[0], grip_hold[1], grip_hold[2]);
        printf("step: median %.3f us, p99.9 %.3f us, max %.3f us%s\n", 1e6 * step_time[TICKS / 2],
               1e6 * step_time[(int)(0.999 * TICKS)], 1e6 * step_time[TICKS - 1],
               realtime ? "" : " (unpaced)");
        if (realtime) printf("paced: %lld late ticks of %d\n", (long long)late, TICKS);
    }
done:
    if (trace) fclose(trace);
    free(step_time);
    pm_servo_free(servo);
    pm_table_free(table);
    return rc;
}
