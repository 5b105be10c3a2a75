/* pmask servo core: a servo's state and options, the tick (the four steps in order), and publishing its
 * results to other threads (pmask.runtime.haptics.Contacts). */
#include "pm_internal.h"

#if PM_THREADS
#include <sched.h>
#endif

/* the published payload is copied in 64-bit words */
typedef char pm_state_is_whole_words[(sizeof(pm_contact_state) % 8 == 0) ? 1 : -1];

void pm__state_reset(cstate *s)
{
    memset(s, 0, sizeof *s);
    s->tri = -1;
    s->b[0] = 1.0;
    s->hold_scale = 1.0;
    s->status = PM_NO_CONTACT;
}

void pm_options_default(const pm_table *t, pm_options *o)
{
    memset(o, 0, sizeof *o);
    o->friction = 0.0;
    o->dynamic_friction = 0.0;
    o->damping = 0.0;
    o->tool_radius = 0.0;
    o->slip_length = 0.25 * t->mean_edge;
    o->rate = 1000.0;
    o->max_jump = 5.0 * t->mean_edge;
    o->decay = 0.9;
    o->proxy_speed = PROXY_SPEED;
    o->reset_after = 50;
    o->max_walk = 24;
    o->passivity = 1;
    o->coupled = -1;
}

static int bad_option(char *err, size_t errlen, const char *name, double v, const char *rule)
{
    if (err && errlen) snprintf(err, errlen, "%s must be %s, got %g", name, rule, v);
    return -1;
}

#define ALLOC(ptr, count)                                                                 \
    do {                                                                                  \
        size_t count_ = (size_t)(count);                                                  \
        (ptr) = calloc(count_ ? count_ : 1, sizeof *(ptr));                               \
        if (!(ptr)) {                                                                     \
            if (err && errlen) snprintf(err, errlen, "out of memory creating the servo"); \
            pm_servo_free(s);                                                             \
            return -1;                                                                    \
        }                                                                                 \
    } while (0)

int pm_servo_create(const pm_table *t, int32_t n, const pm_options *opt, pm_servo **out, char *err, size_t errlen)
{
    return pm_servo_create_paired(t, n, opt, NULL, NULL, out, err, errlen);
}

int pm_servo_create_paired(const pm_table *t, int32_t n, const pm_options *opt, pm_pair_fn pairs, void *user,
                           pm_servo **out, char *err, size_t errlen)
{
    *out = NULL;
    pm_options o;
    if (opt) o = *opt; else pm_options_default(t, &o);
    if (n < 1 || n > 64) {
        if (err && errlen) snprintf(err, errlen, "n must be between 1 and 64 instruments, got %d", (int)n);
        return -1;
    }
#define FIN(x) isfinite(x)
    if (!(FIN(o.friction) && o.friction >= 0.0))
        return bad_option(err, errlen, "friction", o.friction, "finite and >= 0");
    if (!(FIN(o.dynamic_friction) && o.dynamic_friction >= 0.0))
        return bad_option(err, errlen, "dynamic_friction", o.dynamic_friction, "finite and >= 0");
    if (!(FIN(o.damping) && o.damping >= 0.0)) return bad_option(err, errlen, "damping", o.damping, "finite and >= 0");
    if (!(FIN(o.tool_radius) && o.tool_radius >= 0.0 && o.tool_radius <= 0.5 * t->diag))
        return bad_option(err, errlen, "tool_radius", o.tool_radius, "finite, >= 0 and at most half the model's size");
    if (!(FIN(o.slip_length) && o.slip_length > 0.0))
        return bad_option(err, errlen, "slip_length", o.slip_length, "finite and > 0");
    if (!(FIN(o.rate) && o.rate > 0.0)) return bad_option(err, errlen, "rate", o.rate, "finite and > 0");
    if (!(FIN(o.max_jump) && o.max_jump > 0.0))
        return bad_option(err, errlen, "max_jump", o.max_jump, "finite and > 0");
    if (!(FIN(o.decay) && o.decay >= 0.0 && o.decay < 1.0))
        return bad_option(err, errlen, "decay", o.decay, "in [0, 1)");
    if (!(FIN(o.proxy_speed) && o.proxy_speed >= 1.0))
        return bad_option(err, errlen, "proxy_speed", o.proxy_speed, "finite and >= 1");
    if (o.reset_after < 1) return bad_option(err, errlen, "reset_after", o.reset_after, ">= 1");
    if (o.max_walk < 1) return bad_option(err, errlen, "max_walk", o.max_walk, ">= 1");
#undef FIN
    if (!t->zeta && !pairs && t->xi.n) {  /* a compressed Ξ's sections: the core forms the blocks itself */
        pairs = pm__greens_pairs;
        user = (void *)t;
    }
    if (o.coupled < 0) o.coupled = ((t->zeta != NULL || pairs != NULL) && n > 1);
    if (o.coupled && !t->zeta && !pairs) {
        if (err && errlen)
            snprintf(err, errlen, "coupled contacts need the table's zeta section (export it with the zeta table) or "
                     "a pair function (pm_servo_create_paired)");
        return -1;
    }
    pm_servo *s = calloc(1, sizeof *s);
    if (!s) {
        if (err && errlen) snprintf(err, errlen, "out of memory creating the servo");
        return -1;
    }
    s->tab = t;
    s->n = n;
    s->o = o;
    s->o.coupled = o.coupled ? 1 : 0;
    s->pairs = t->zeta ? NULL : pairs;
    s->pairs_user = user;
    s->o.passivity = o.passivity ? 1 : 0;
    s->frictionless = (o.friction == 0.0 && o.dynamic_friction == 0.0);
    s->block_sum = pm__block_sum_kernel();
    s->margin = 2.0 * o.max_jump + o.tool_radius;
    ALLOC(s->st, n);
    ALLOC(s->probe, 3 * n);
    ALLOC(s->ok, n);
    ALLOC(s->geo, n);
    ALLOC(s->ubar, 3 * n);
    ALLOC(s->active, n);
    ALLOC(s->res, n);
    ALLOC(s->gsf, 3 * n);
    ALLOC(s->cpl, (size_t)n * n * 9);
    ALLOC(s->pair_tri, (size_t)n * n * 2);
    ALLOC(s->pair_P, (size_t)n * n * 81);
    if (s->pairs) {
        ALLOC(s->given_tri, 2 * PM_PAIR_CACHE);
        ALLOC(s->given_P, 81 * PM_PAIR_CACHE);
        for (int k = 0; k < 2 * PM_PAIR_CACHE; k++) s->given_tri[k] = -1;
    }
    for (size_t k = 0; k < (size_t)n * n * 2; k++) s->pair_tri[k] = -1;
    ALLOC(s->nA, (size_t)n * n);
    ALLOC(s->nr, n);
    ALLOC(s->nx, n);
    ALLOC(s->nW, (size_t)n * n);
    ALLOC(s->nwr, n);
    ALLOC(s->nsol, n);
    ALLOC(s->npress, n);
    ALLOC(s->nidx, n);
    ALLOC(s->dC, (size_t)9 * n * n);
    ALLOC(s->du, 3 * n);
    ALLOC(s->dact, n);
    ALLOC(s->dsnap, n);
    if (t->xi.n) {  /* the deformation from a compressed Ξ's sections */
        ALLOC(s->dx, 3 * t->xi.n);
        ALLOC(s->dy, 3 * t->xi.n);
        ALLOC(s->gw.xs, 3 * t->xi.n);
        ALLOC(s->gw.ys, 3 * t->xi.n);
        ALLOC(s->gw.as, t->xi.n);
        ALLOC(s->gw.tk, t->xi.maxrank);
        ALLOC(s->gw.nz, t->xi.n + 1);
    }
    s->pub.nwords = sizeof(pm_tick_stats) / 8 + 3 * (size_t)n + ((size_t)n + 1) / 2 + (size_t)n * PUB_STATE_WORDS;
    ALLOC(s->pub.words, s->pub.nwords);
    ALLOC(s->pub.stage, s->pub.nwords);
    ALLOC(s->tb, 9 * n);
    ALLOC(s->ring_in, (size_t)PM_RING * 3 * n);
    ALLOC(s->ring_out, (size_t)PM_RING * 3 * n);
    ALLOC(s->ring_status, (size_t)PM_RING * n);
    ALLOC(s->tick_probes, 3 * n);
    ALLOC(s->tick_forces, 3 * n);
    ALLOC(s->tick_status, n);
    for (int32_t i = 0; i < 9 * n; i++) s->tb[i] = NAN;  /* no probe set yet: a bad sample, no contact */
    for (int32_t i = 0; i < 3 * n; i++) s->tick_probes[i] = NAN;
    s->tb_back = 0;
    s->tb_middle = 1;
    s->tb_front = 2;
#if PM_THREADS
    if (pthread_mutex_init(&s->in_lock, NULL)) {
        if (err && errlen) snprintf(err, errlen, "could not create the servo's input lock");
        pm_servo_free(s);
        return -1;
    }
    if (pthread_mutex_init(&s->display_lock, NULL)) {
        pthread_mutex_destroy(&s->in_lock);
        if (err && errlen) snprintf(err, errlen, "could not create the servo's display lock");
        pm_servo_free(s);
        return -1;
    }
    s->lock_ok = 1;
#endif
    pm_servo_reset(s);
    *out = s;
    return 0;
}


void pm_servo_free(pm_servo *s)
{
    if (!s) return;
    pm_servo_stop(s);
#if PM_THREADS
    if (s->lock_ok) {
        pthread_mutex_destroy(&s->in_lock);
        pthread_mutex_destroy(&s->display_lock);
    }
#endif
    free(s->st);
    free(s->probe);
    free(s->ok);
    free(s->geo);
    free(s->ubar);
    free(s->active);
    free(s->res);
    free(s->gsf);
    free(s->cpl);
    free(s->pair_tri);
    free(s->pair_P);
    free(s->given_tri);
    free(s->given_P);
    free(s->nA);
    free(s->nr);
    free(s->nx);
    free(s->nW);
    free(s->nwr);
    free(s->nsol);
    free(s->npress);
    free(s->nidx);
    free(s->dC);
    free(s->du);
    free(s->dact);
    free(s->dsnap);
    free(s->dx);
    free(s->dy);
    free(s->gw.xs);
    free(s->gw.ys);
    free(s->gw.as);
    free(s->gw.tk);
    free(s->gw.nz);
    free(s->pub.words);
    free(s->pub.stage);
    free(s->tb);
    free(s->ring_in);
    free(s->ring_out);
    free(s->ring_status);
    free(s->tick_probes);
    free(s->tick_forces);
    free(s->tick_status);
    free(s);
}

void pm_servo_reset(pm_servo *s)
{
    if (pm_servo_running(s)) return;  /* only between runs of the thread */
    for (int32_t l = 0; l < s->n; l++) pm__state_reset(&s->st[l]);
    s->energy = 0.0;
    s->pc_damping = 0.0;
    pm__publish(s, NULL);
}

int32_t pm_servo_take_far_warning(pm_servo *s, double *probe)
{
    int32_t w = __atomic_exchange_n(&s->far_pending, 0, __ATOMIC_ACQ_REL);
    if (w && probe) memcpy(probe, s->far_probe, sizeof s->far_probe);  /* written before the flag was set */
    return w;
}

int32_t pm_servo_count(const pm_servo *s) { return s->n; }

const char *pm_servo_kernel(const pm_servo *s) { return pm__block_sum_is_avx2(s->block_sum) ? "avx2" : "baseline"; }

/* ------------------------------------------------------------------ a contact's state (state.py's) */
/* the last good force, decaying (state.hold) */
void pm__hold(const pm_servo *S, cstate *st, int32_t status)
{
    double d = S->o.decay;
    for (int a = 0; a < 3; a++) {
        st->good_force[a] = st->good_force[a] * d;
        st->force[a] = st->good_force[a];
        st->body_force[a] = -st->force[a];
    }
    st->status = status;
}

/* no force, tracking kept (state.release) */
void pm__release(cstate *st, int32_t status)
{
    for (int a = 0; a < 3; a++) {
        st->force[a] = st->good_force[a] = st->body_force[a] = st->law_force[a] = 0.0;
        st->u_bar[a] = 0.0;
    }
    st->depth = 0.0;
    st->taper = 0.0;
    st->sliding = 0;
    st->has_anchor = 0;
    st->frozen = 0;
    st->hold_scale = 1.0;
    st->hold_peak = 0.0;
    st->slip = 0.0;
    st->status = status;
}

/* ------------------------------------------------------------------ the tick (Contacts._step) */
int pm__step_inner(pm_servo *S, const double *probes)
{
    const int32_t n = S->n;
    const pm_table *tb = S->tab;
    for (int32_t l = 0; l < n; l++) {  /* step 1 */
        int r = pm__prepare(S, &S->st[l], probes + 3 * l, S->probe + 3 * l);
        if (r < 0) return -1;
        S->ok[l] = r;
    }
    const int frictionless = S->frictionless;
    int32_t na = 0;
    for (int32_t l = 0; l < n; l++) {
        if (!S->ok[l]) continue;
        cstate *st = &S->st[l];
        if (pm__follow(S, st)) return -1;
        if (!frictionless && !st->has_anchor) {
            pm__point_at(tb, st->tri, st->b, st->anchor);
            st->has_anchor = 1;
        }
        if (pm__geometry(S, st, S->probe + 3 * l, &S->geo[l], S->ubar + 3 * l)) return -1;
        if (S->geo[l].lam <= 0.0) {
            if (!frictionless && pm__follow(S, st)) return -1;
            pm__release(st, PM_OUTSIDE_REGION);
            continue;
        }
        S->active[na++] = l;
    }
    if (na == 0) {
        S->energy = 0.0;
        S->pc_damping = 0.0;
        return 0;
    }
    if (pm__solve(S, S->active, na)) return -1;  /* steps 2 and 3 */
    int32_t kept = 0;
    for (int32_t x = 0; x < na; x++) {
        int32_t l = S->active[x];
        const double *N = S->geo[l].N, *u = S->ubar + 3 * l;
        if (N[0] * u[0] + N[1] * u[1] + N[2] * u[2] >= 0.0) {  /* the tool is out at the proxy: the contact ends
                                                                  (one the others carried away stays, no force) */
            cstate *st = &S->st[l];
            if (st->has_target) {
                st->tri = st->target_t;
                st->b[0] = st->target_b[0];
                st->b[1] = st->target_b[1];
                st->b[2] = st->target_b[2];
            }
            st->in_contact = 0;
            st->above = 1;
            pm__release(st, PM_NO_CONTACT);
        } else {
            S->active[kept++] = l;
        }
    }
    na = kept;
    if (na == 0) {
        S->energy = 0.0;
        S->pc_damping = 0.0;
        return 0;
    }
    return pm__render(S, na);  /* step 4 */
}

/* ------------------------------------------------------------------ publishing (a sequence lock)
 * The writer (the tick) fills a staging copy, then makes the sequence odd, stores the copy word by word with
 * release stores, and makes the sequence even again with a release store.  A reader loads the sequence
 * (acquire), copies the words with acquire loads, and accepts the copy when the sequence was even and is
 * unchanged: a word from a write in progress carries the odd sequence with it (its release store follows the
 * odd store), so the second load sees that the sequence moved (Boehm, "Can seqlocks get along with
 * programming language memory models?", 2012, without fences, which ThreadSanitizer does not model).  No plain
 * access to the shared words ever races, and the tick never waits. */
#define STATS_WORDS (sizeof(pm_tick_stats) / 8)
typedef char pm_stats_are_whole_words[(sizeof(pm_tick_stats) % 8 == 0) ? 1 : -1];
static size_t pub_forces_at(void) { return STATS_WORDS; }
static size_t pub_status_at(const pm_servo *s) { return STATS_WORDS + 3 * (size_t)s->n; }
static size_t pub_states_at(const pm_servo *s) { return STATS_WORDS + 3 * (size_t)s->n + ((size_t)s->n + 1) / 2; }

void pm__publish(pm_servo *s, const pm_tick_stats *stats)
{
    const pm_table *tb = s->tab;
    uint64_t *w = s->pub.stage;
    if (stats) s->stats = *stats;
    memcpy(w, &s->stats, sizeof s->stats);
    int32_t *status = (int32_t *)(w + pub_status_at(s));
    double *forces = (double *)(w + pub_forces_at());
    for (int32_t l = 0; l < s->n; l++) {
        const cstate *st = &s->st[l];
        pm_contact_state o;
        memset(&o, 0, sizeof o);
        for (int a = 0; a < 3; a++) {
            o.force[a] = st->force[a];
            o.body_force[a] = st->body_force[a];
            o.u_bar[a] = st->u_bar[a];
            o.bary[a] = st->b[a];
            forces[3 * l + a] = st->force[a];
        }
        if (st->tri >= 0) {
            pm__point_at(tb, st->tri, st->b, o.point);
        } else {
            o.point[0] = o.point[1] = o.point[2] = NAN;
        }
        o.depth = st->depth;
        o.taper = st->taper;
        o.triangle = st->tri;
        o.status = st->status;
        o.in_contact = st->in_contact;
        o.sliding = st->sliding;
        status[l] = st->status;
        memcpy(w + pub_states_at(s) + (size_t)l * PUB_STATE_WORDS, &o, sizeof o);
    }
    uint64_t seq = __atomic_load_n(&s->pub.seq, __ATOMIC_RELAXED);  /* only the writer changes it */
    __atomic_store_n(&s->pub.seq, seq + 1, __ATOMIC_RELAXED);
    for (size_t i = 0; i < s->pub.nwords; i++) __atomic_store_n(&s->pub.words[i], w[i], __ATOMIC_RELEASE);
    __atomic_store_n(&s->pub.seq, seq + 2, __ATOMIC_RELEASE);
}

/* a consistent copy of the words [from, from + count) (never waits on the tick for long: it writes ~100 ns) */
static void read_words(pm_servo *s, size_t from, size_t count, uint64_t *out)
{
    for (unsigned tries = 0;; tries++) {
        uint64_t a = __atomic_load_n(&s->pub.seq, __ATOMIC_ACQUIRE);
        if (!(a & 1u)) {
            for (size_t i = 0; i < count; i++) out[i] = __atomic_load_n(&s->pub.words[from + i], __ATOMIC_ACQUIRE);
            if (__atomic_load_n(&s->pub.seq, __ATOMIC_ACQUIRE) == a) return;
        }
#if PM_THREADS
        if (tries > 64) sched_yield();  /* the writer was preempted mid-publish: let it finish */
#endif
    }
}

void pm__read_published(pm_servo *s, int32_t k, pm_contact_state *one, double *forces, int32_t *status,
                        pm_tick_stats *stats)
{
    /* one consistent copy of everything asked for: the whole payload is small (~20 words per contact) */
    uint64_t local[STATS_WORDS + 3 * 64 + 32 + 64 * PUB_STATE_WORDS];
    size_t nw = s->pub.nwords;
    read_words(s, 0, nw, local);
    if (stats) memcpy(stats, local, sizeof *stats);
    if (forces) memcpy(forces, local + pub_forces_at(), 3 * (size_t)s->n * sizeof(double));
    if (status) memcpy(status, local + pub_status_at(s), (size_t)s->n * sizeof(int32_t));
    if (one) memcpy(one, local + pub_states_at(s) + (size_t)k * PUB_STATE_WORDS, sizeof *one);
}

/* every contact's published state, in one consistent copy (the display's snapshot) */
void pm__read_states(pm_servo *s, pm_contact_state *out)
{
    uint64_t local[64 * PUB_STATE_WORDS];
    read_words(s, pub_states_at(s), (size_t)s->n * PUB_STATE_WORDS, local);
    memcpy(out, local, (size_t)s->n * sizeof *out);
}

void pm_servo_step(pm_servo *s, const double *probes, double *forces, int32_t *status)
{
    if (pm_servo_running(s)) {  /* the servo's own thread runs the step: report its latest results instead */
        pm__read_published(s, 0, NULL, forces, status, NULL);
        return;
    }
    if (pm__step_inner(s, probes)) {
        for (int32_t l = 0; l < s->n; l++) pm__hold(s, &s->st[l], PM_INTERNAL_ERROR);
    }
    for (int32_t l = 0; l < s->n; l++) {
        if (forces) {
            forces[3 * l] = s->st[l].force[0];
            forces[3 * l + 1] = s->st[l].force[1];
            forces[3 * l + 2] = s->st[l].force[2];
        }
        if (status) status[l] = s->st[l].status;
    }
    pm__publish(s, NULL);
}

void pm_servo_state(pm_servo *s, int32_t k, pm_contact_state *out)
{
    if (k < 0 || k >= s->n) {
        memset(out, 0, sizeof *out);
        out->triangle = -1;
        return;
    }
    pm__read_published(s, k, out, NULL, NULL, NULL);
}

void pm_servo_read(pm_servo *s, double *forces, int32_t *status, pm_tick_stats *stats)
{
    pm__read_published(s, 0, NULL, forces, status, stats);
}
