/* pmask servo core: thread mode (a thread of the servo's own runs the tick at a set rate), the hand-over of
 * probes from other threads, the tick-synchronous exchange, and the clock they use (pm_clock_now, also what
 * bench/servo_bench.c times with). */
#include "pm_internal.h"

#if PM_THREADS
#include <errno.h>
#include <sched.h>
#include <time.h>

double pm_clock_now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

void pm_clock_sleep_until(double t)
{
    if (!(t > 0.0) || !isfinite(t)) return;
    struct timespec ts;
    ts.tv_sec = (time_t)t;
    ts.tv_nsec = (long)((t - (double)ts.tv_sec) * 1e9);
    if (ts.tv_nsec >= 1000000000L) {
        ts.tv_sec += 1;
        ts.tv_nsec -= 1000000000L;
    }
    while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL) == EINTR) {
    }
}

/* the latest probes from pm_servo_set_probes (the consumer's side of the triple buffer): the middle buffer,
 * if a writer handed one over since the last tick, becomes the front one by an atomic exchange; a sample is
 * never torn and never older than the last complete one */
static void take_probes(pm_servo *s)
{
    if (__atomic_load_n(&s->tb_middle, __ATOMIC_ACQUIRE) & 4u) {
        uint32_t old = __atomic_exchange_n(&s->tb_middle, s->tb_front, __ATOMIC_ACQ_REL);
        s->tb_front = old & 3u;
    }
    memcpy(s->tick_probes, s->tb + 3 * (size_t)s->n * s->tb_front, 3 * (size_t)s->n * sizeof(double));
}

/* exchange mode: the oldest sample waiting, if any (the ring's consumer side) */
static int take_exchange(pm_servo *s, uint64_t *ticket)
{
    uint64_t tail = s->ring_tail;  /* only this thread writes it */
    if (tail >= __atomic_load_n(&s->ring_head, __ATOMIC_ACQUIRE)) return 0;
    memcpy(s->tick_probes, s->ring_in + (tail % PM_RING) * 3 * (size_t)s->n, 3 * (size_t)s->n * sizeof(double));
    *ticket = tail;
    __atomic_store_n(&s->ring_tail, tail + 1, __ATOMIC_RELEASE);
    return 1;
}

static void *servo_thread(void *arg)
{
    pm_servo *s = arg;
    const double T = s->period;
    double next = pm_clock_now() + T;
    const double spin = s->spin < T ? s->spin : 0.5 * T;
    const int32_t n = s->n;
    for (;;) {
        if (spin > 0.0) {  /* sleep to just before the tick, then spin to it */
            pm_clock_sleep_until(next - spin);
            while (pm_clock_now() < next) {
            }
        } else {
            pm_clock_sleep_until(next);
        }
        if (__atomic_load_n(&s->stop_flag, __ATOMIC_ACQUIRE)) break;
        double begin = pm_clock_now();
        int run = 1;
        uint64_t ticket = 0;
        if (s->has_io) {
            s->io.read(s->io.user, s->tick_probes);
        } else if (s->exchange) {
            run = take_exchange(s, &ticket);
        } else {
            take_probes(s);
        }
        if (run) {
            if (pm__step_inner(s, s->tick_probes))
                for (int32_t l = 0; l < n; l++) pm__hold(s, &s->st[l], PM_INTERNAL_ERROR);
            for (int32_t l = 0; l < n; l++) {
                s->tick_forces[3 * l] = s->st[l].force[0];
                s->tick_forces[3 * l + 1] = s->st[l].force[1];
                s->tick_forces[3 * l + 2] = s->st[l].force[2];
                s->tick_status[l] = s->st[l].status;
            }
            if (s->has_io) s->io.write(s->io.user, s->tick_forces, s->tick_status);
            if (s->exchange) {  /* the answer to that sample, then its ticket */
                size_t slot = (size_t)(ticket % PM_RING);
                memcpy(s->ring_out + slot * 3 * (size_t)n, s->tick_forces, 3 * (size_t)n * sizeof(double));
                memcpy(s->ring_status + slot * (size_t)n, s->tick_status, (size_t)n * sizeof(int32_t));
                __atomic_store_n(&s->ring_done, ticket + 1, __ATOMIC_RELEASE);
            }
        }
        double end = pm_clock_now();
        pm_tick_stats st = s->stats;  /* published with the state */
        st.ticks += 1;
        if (!run) st.idle += 1;
        double lateness = begin - next;
        if (end > next + T) st.late += 1;  /* the force was not ready within its own period */
        if (lateness > st.max_lateness) st.max_lateness = lateness;
        if (end - begin > st.step_max) st.step_max = end - begin;
        next += T;
        if (end > next) {  /* fell behind: skip the missed ticks (counted late), keep the schedule's phase */
            double behind = floor((end - next) / T) + 1.0;
            st.late += (int64_t)behind;
            next += behind * T;
        }
        pm__publish(s, &st);
    }
    return NULL;
}

static int start(pm_servo *s, double rate, double spin, const pm_io *io, int exchange)
{
    if (pm_servo_running(s)) return -1;
    if (!(isfinite(rate) && rate > 0.0 && rate <= 100000.0 && isfinite(spin) && spin >= 0.0 && spin <= 0.01)) return -2;
    if (io && (!io->read || !io->write)) return -3;
    s->period = 1.0 / rate;
    s->spin = spin;
    s->has_io = io != NULL;
    if (io) s->io = *io;
    s->exchange = exchange;
    s->ring_head = s->ring_tail = s->ring_done = 0;
    memset(&s->stats, 0, sizeof s->stats);
    __atomic_store_n(&s->stop_flag, 0, __ATOMIC_RELEASE);
    pthread_attr_t attr;
    if (pthread_attr_init(&attr)) return -4;
    int rc = pthread_create(&s->thread, &attr, servo_thread, s);
    pthread_attr_destroy(&attr);
    if (rc) return -4;
    {   /* a real-time priority where the process may have one (root, rtprio limits); otherwise normal */
        struct sched_param sp;
        sp.sched_priority = sched_get_priority_min(SCHED_FIFO) + 10;
        (void)pthread_setschedparam(s->thread, SCHED_FIFO, &sp);
    }
    __atomic_store_n(&s->running, 1, __ATOMIC_RELEASE);
    return 0;
}

int pm_servo_start(pm_servo *s, double rate, double spin, const pm_io *io) { return start(s, rate, spin, io, 0); }

int pm_servo_start_exchange(pm_servo *s, double rate, double spin) { return start(s, rate, spin, NULL, 1); }

void pm_servo_stop(pm_servo *s)
{
    if (!pm_servo_running(s)) return;
    __atomic_store_n(&s->stop_flag, 1, __ATOMIC_RELEASE);
    pthread_join(s->thread, NULL);
    __atomic_store_n(&s->running, 0, __ATOMIC_RELEASE);
}

void pm_servo_set_probes(pm_servo *s, const double *probes)
{
    pthread_mutex_lock(&s->in_lock);  /* writers one at a time (never the servo thread: it does not wait) */
    memcpy(s->tb + 3 * (size_t)s->n * s->tb_back, probes, 3 * (size_t)s->n * sizeof(double));
    uint32_t old = __atomic_exchange_n(&s->tb_middle, s->tb_back | 4u, __ATOMIC_ACQ_REL);
    s->tb_back = old & 3u;
    pthread_mutex_unlock(&s->in_lock);
}

int pm_servo_exchange(pm_servo *s, const double *probes, double *forces, int32_t *status, double timeout)
{
    if (!pm_servo_running(s) || !s->exchange) return -2;
    const size_t n = (size_t)s->n;
    pthread_mutex_lock(&s->in_lock);
    uint64_t ticket = s->ring_head;  /* only exchange callers (one at a time) write it */
    int rc = 0;
    if (ticket - __atomic_load_n(&s->ring_done, __ATOMIC_ACQUIRE) >= PM_RING) {
        rc = -3;  /* PM_RING samples submitted and not answered: the servo thread is not taking them */
    } else {
        memcpy(s->ring_in + (ticket % PM_RING) * 3 * n, probes, 3 * n * sizeof(double));
        __atomic_store_n(&s->ring_head, ticket + 1, __ATOMIC_RELEASE);
        double deadline = pm_clock_now() + timeout;
        unsigned spins = 0;
        while (__atomic_load_n(&s->ring_done, __ATOMIC_ACQUIRE) <= ticket) {
            if (++spins > 200) {  /* a tick is at most a period away: spin briefly, then sleep in short steps */
                if (pm_clock_now() > deadline) {
                    rc = -1;
                    break;
                }
                struct timespec ts = {0, 20000};
                nanosleep(&ts, NULL);
            }
        }
        if (rc == 0) {
            size_t slot = (size_t)(ticket % PM_RING);
            if (forces) memcpy(forces, s->ring_out + slot * 3 * n, 3 * n * sizeof(double));
            if (status) memcpy(status, s->ring_status + slot * n, n * sizeof(int32_t));
        }
    }
    pthread_mutex_unlock(&s->in_lock);
    return rc;
}
#else
double pm_clock_now(void) { return 0.0; }
void pm_clock_sleep_until(double t) { (void)t; }
int pm_servo_start(pm_servo *s, double rate, double spin, const pm_io *io)
{
    (void)s, (void)rate, (void)spin, (void)io;
    return -5;
}
int pm_servo_start_exchange(pm_servo *s, double rate, double spin)
{
    (void)s, (void)rate, (void)spin;
    return -5;
}
void pm_servo_stop(pm_servo *s) { (void)s; }
void pm_servo_set_probes(pm_servo *s, const double *probes)
{
    memcpy(s->tb + 3 * (size_t)s->n * s->tb_back, probes, 3 * (size_t)s->n * sizeof(double));
    uint32_t old = s->tb_middle;
    s->tb_middle = s->tb_back | 4u;
    s->tb_back = old & 3u;
}
int pm_servo_exchange(pm_servo *s, const double *probes, double *forces, int32_t *status, double timeout)
{
    (void)s, (void)probes, (void)forces, (void)status, (void)timeout;
    return -2;
}
#endif

int32_t pm_servo_running(const pm_servo *s) { return __atomic_load_n(&s->running, __ATOMIC_ACQUIRE); }
