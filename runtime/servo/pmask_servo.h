/* pmask servo core: haptic contact with precomputed Green's functions and pressure masks, in C99.
 *
 * The same algorithm as pmask.runtime.haptics (the Python reference; a test requires both to give the
 * same statuses and forces to 1e-12 on recorded probe traces): proxies that follow the probe's Phong
 * projection along the surface (by dead reckoning past half the radius of curvature), the frictionless normal
 * law k δ with the tangential term ½ δ² (I − δ S)⁻¹ ∇k (past δ_t the increments keep the stiffness where they
 * began; PM_DEEP past δ_lin), friction between the stuck (K̃ ū) and the frictionless force on the cone's edge,
 * several contacts coupled through the Green's functions by block Gauss-Seidel, zero-order-hold
 * compensation, viscous damping and a passivity observer/controller.
 *
 * A runtime table (``pmask export-table ARTIFACT -o FILE``; format in pmask/runtime/table.py) carries
 * everything the step reads: the mesh, contact normals, per-vertex rendered stiffness K_i, taper λ, normal
 * stiffness k and ∇k, the shape operator S, δ_lin, triangle frames and neighbours, and optionally the ζ table
 * for coupling and deformation.  Its
 * layout (little-endian): a 64-byte header ("PMASKTBL", major, minor, size, section count, a CRC-32 of
 * header and directory), a directory of named sections with a CRC-32 each, the sections.  A foreign,
 * truncated or corrupt file, a 1.0 table (without the 1.1 law's sections), a newer major version and
 * stiffnesses that are not positive definite are refused with a message.  Loading builds a bounding-volume
 * hierarchy of the triangles, which restarts contact tracking in O(log n) whatever the probe's depth.
 *
 * Threads: a table is read-only after loading and may be shared.  A servo (contact state for n
 * instruments) is used by one thread at a time, except in thread mode (pm_servo_start,
 * pm_servo_start_exchange), where its own thread runs the step at a set rate and any other threads call
 * pm_servo_set_probes, pm_servo_exchange, pm_servo_read, pm_servo_state and pm_servo_deformation.  Inside the
 * tick there is no lock, no wait and no allocation: results are published under a sequence lock whose payload
 * is copied with atomic word loads and stores, probes arrive through a triple buffer and exchanged samples
 * through a ring (the callers' side of those may take a mutex; the tick's never does).
 *
 * The sources: this header and core/ (one C99 file per step of the contact algorithm, pm_internal.h shared
 * between them).  Compile every .c file of core/ into your application (pmask.runtime.servo.sources() lists them).
 *
 * Indices are int64_t and sizes size_t throughout (no `long`: Windows is LLP64).
 */
#ifndef PMASK_SERVO_H
#define PMASK_SERVO_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#if defined(_WIN32) && defined(PMASK_SERVO_SHARED)
#define PM_API __declspec(dllexport)
#else
#define PM_API
#endif

#define PM_TABLE_MAJOR 1
#define PM_TABLE_MINOR 5

/* contact statuses (the values of pmask.runtime.Status) */
enum {
    PM_NO_CONTACT = 0,
    PM_CONTACT = 1,
    PM_BAD_SAMPLE = 2,
    PM_JUMP = 3,
    PM_OUTSIDE_REGION = 4,
    PM_FAR_OUTSIDE = 5,
    PM_REGION_EDGE = 6,
    PM_INTERNAL_ERROR = 7,
    PM_DEEP = 8               /* deeper than the linear contact is meaningful: the force keeps growing along the
                                 proxy's normal (see the haptics guide) */
};

typedef struct pm_table pm_table;
typedef struct pm_servo pm_servo;

/* The contact options (pmask.runtime.Contacts's keyword arguments); pm_options_default fills the
 * defaults, some of which come from the table (max_jump, slip_length: from the mean edge length). */
typedef struct {
    double friction;          /* static Coulomb coefficient μ_s (0: frictionless) */
    double dynamic_friction;  /* μ_d */
    double damping;           /* viscous damping b_v [N s/m] */
    double tool_radius;       /* radius of the spherical tip [model units] */
    double slip_length;       /* μ weakens from μ_s to μ_d over this much slip */
    double rate;              /* servo rate [Hz] (velocities) */
    double max_jump;          /* largest plausible probe move per tick */
    double decay;             /* per-tick factor on the last good force while samples are bad */
    double proxy_speed;       /* the proxy moves at most this many times the probe's motion per tick */
    int32_t reset_after;      /* implausible samples in a row before tracking restarts */
    int32_t max_walk;         /* triangle steps per walk */
    int32_t passivity;        /* the passivity observer/controller */
    int32_t coupled;          /* several contacts solved together (needs the ζ table, or a pair function:
                                 pm_servo_create_paired); -1: when n > 1 and the table has one */
} pm_options;

/* One contact after a step (pmask.runtime.HapticContact's attributes). */
typedef struct {
    double force[3];      /* on the user */
    double body_force[3]; /* on the body (what the device holds during the next tick, negated) */
    double u_bar[3];      /* the surface's displacement at the contact (the law's, plus what the other
                             contacts move it): what the displayed deformation meets */
    double bary[3];       /* proxy barycentrics */
    double point[3];      /* proxy position */
    double depth, taper;
    int64_t triangle;     /* proxy triangle, -1 when not tracking */
    int32_t status, in_contact, sliding, pad;
} pm_contact_state;

/* Timing of thread mode (pm_servo_start, pm_servo_start_exchange). */
typedef struct {
    int64_t ticks;        /* ticks run */
    int64_t late;         /* ticks whose force was not ready within their own period (finished after
                             scheduled start + period), and ticks skipped because the loop fell behind */
    double max_lateness;  /* [s] */
    double step_max;      /* longest step [s] */
    int64_t idle;         /* exchange mode: ticks at which no sample was waiting (no step ran, the force held) */
} pm_tick_stats;

/* Load a table from a file, or from memory (copied).  0 on success; otherwise a message in err. */
PM_API int pm_table_load(const char *path, pm_table **out, char *err, size_t errlen);
PM_API int pm_table_from_memory(const void *data, size_t size, pm_table **out, char *err, size_t errlen);
/* A table over arrays the caller owns (no copy, no file: how an application that computes its own stiffness,
 * or the Python binding, hands its arrays to the core).  The sections are those a table file holds, by name
 * ("points", "triangles", ..., optionally "zeta" or "xi_*" and "contact_row", "display_*", "meta";
 * pmask/runtime/table.py),
 * each row-major and C-contiguous, doubles and int64 aligned to 8 bytes.  The same checks as a file apart from
 * checksums (types, shapes, indices in range, finite numbers, positive definite stiffness).  The arrays must stay
 * alive and unchanged until pm_table_free; the section list itself may be freed on return. */
enum { PM_SECTION_F64 = 1, PM_SECTION_I64 = 2, PM_SECTION_BYTES = 3 };
typedef struct {
    const char *name;    /* at most 31 characters */
    int32_t dtype;       /* PM_SECTION_F64, PM_SECTION_I64, or PM_SECTION_BYTES ("meta": JSON text, cols 1) */
    int64_t rows, cols;
    const void *data;
} pm_section;
PM_API int pm_table_from_sections(const pm_section *sections, int32_t n, pm_table **out, char *err,
                                  size_t errlen);
PM_API void pm_table_free(pm_table *table);
/* The model's surface mesh (the finite-element one: the deformation's n_vertices); the contact itself runs on its
 * Loop subdivision surface (table 1.3), which the table carries beside it. */
PM_API int64_t pm_table_vertices(const pm_table *table);
PM_API int64_t pm_table_triangles(const pm_table *table);
/* Those vertices at rest where the contact surface has them (3 x pm_table_vertices doubles, owned by the table):
 * the mesh's own points, except near a crease, which the contact surface rounds.  Draw pm_servo_deformation on
 * these and the shown surface meets every instrument. */
PM_API const double *pm_table_points(const pm_table *table);
PM_API int32_t pm_table_has_zeta(const pm_table *table);
/* Whether the table can couple contacts: its ζ table, or (table 1.4, exported from a compressed artifact) Ξ's
 * compressed sections, from which the core forms the blocks of the vertices a pair of contacts touches. */
PM_API int32_t pm_table_has_greens(const pm_table *table);
/* The coupling blocks of mesh triangles ta and tb as the servo reads them (pm_servo_create_paired's P: 81 doubles),
 * from the ζ table or formed from Ξ's compressed sections.  0, or -1 for a table without either or a triangle
 * out of range. */
PM_API int pm_table_pair_blocks(const pm_table *table, int64_t ta, int64_t tb, double *P);
/* The model's bounding box (lower and upper corner). */
PM_API void pm_table_bounds(const pm_table *table, double *lo, double *hi);
/* The table's metadata: a JSON object (mask, radius, k_rigid, units, source artifact). */
PM_API const char *pm_table_meta(const pm_table *table);

/* The display surface at the scan's resolution (a table exported from an artifact that has one; 0 vertices
 * otherwise): its points (m x 3) and triangles (k x 3) as stored, and its deformation for the surface
 * displacement u (n_vertices x 3, e.g. pm_servo_deformation's): out (m x 3) = x_d + Σ b_k u_{v_k} − w_d ℓ_d,
 * w_d = max over the n_contacts proxy points p_c of smoothstep(1 − |x_d − p_c| / radius) (pmask.runtime.display).
 * Allocates nothing; out may not alias u. */
PM_API int64_t pm_display_vertices(const pm_table *table);
PM_API int64_t pm_display_triangles(const pm_table *table);
PM_API const double *pm_display_points(const pm_table *table);
PM_API const int64_t *pm_display_triangle_indices(const pm_table *table);
PM_API void pm_display_deform(const pm_table *table, const double *u, int32_t n_contacts, const double *contacts,
                              double radius, double *out);

/* K(x) = Σ b_k K_{t_k} (eq. 15) for n points: out (n x 9, row-major 3x3 each).  No validation. */
PM_API void pm_table_stiffness(const pm_table *table, int64_t n, const int64_t *triangles, const double *bary,
                               double *out);
/* The triangle whose barycentric-clamped projection is nearest a point (the bounding-volume hierarchy;
 * ties: the smallest index, as the Python engine's grid). */
PM_API int64_t pm_table_nearest(const pm_table *table, const double *point);
/* The ζ table's rows for a table of one's own (Stiffness.zeta_table's loop): out (n_rows x width, row-major) row
 * centres[k] = Σ values[p] xi_rows[indices[p]] for p in indptr[k] .. indptr[k + 1] - 1, the masks in compressed
 * rows; other rows of out are left as they are.  0, or -1 and a message when an index is out of range. */
PM_API int pm_zeta_rows(int64_t n_rows, int64_t width, const double *xi_rows, int64_t n_masks, const int64_t *centres,
                        const int64_t *indptr, int64_t nnz, const int64_t *indices, const double *values, double *out,
                        char *err, size_t errlen);

PM_API void pm_options_default(const pm_table *table, pm_options *options);
/* A servo for n instruments: all memory the step needs is allocated here.  0 or a message. */
PM_API int pm_servo_create(const pm_table *table, int32_t n, const pm_options *options, pm_servo **out,
                           char *err, size_t errlen);
/* Coupled contacts without the table's ζ section (an artifact whose Ξ is compressed: its ζ table would be as
 * large as dense Ξ; a table exported from one carries Ξ's compressed sections, from which pm_servo_create forms
 * the blocks itself).  `pairs(user, ta, tb, P)` fills P (81 doubles) with the nine vertex-pair blocks of mesh
 * triangles ta and tb, for vertex x of ta and y of tb (x outer) P_xy = ½ (ζ_y(x) + ζ_x(y)ᵀ) row-major, zero where
 * either vertex has no row (pmask.runtime.contact.surface.ContactSurface.pair_blocks), and returns 0; anything
 * else, or a non-finite block, fails that tick's step (PM_INTERNAL_ERROR, the last force held).  The core calls it
 * on the step's thread, only when a pair of coupled contacts first lands on a pair of triangles (it keeps each
 * pair's blocks while both stay there), so it may take longer than a tick: that tick is late by as much.  With a
 * ζ section it is not called; NULL is pm_servo_create. */
typedef int (*pm_pair_fn)(void *user, int64_t ta, int64_t tb, double *P);
PM_API int pm_servo_create_paired(const pm_table *table, int32_t n, const pm_options *options, pm_pair_fn pairs,
                                  void *user, pm_servo **out, char *err, size_t errlen);
PM_API void pm_servo_free(pm_servo *servo);
PM_API void pm_servo_reset(pm_servo *servo);
/* One tick: probes (3n; a non-finite coordinate is a bad sample) -> forces on the users (3n), statuses (n).
 * Allocates nothing, takes no lock, never fails. */
PM_API void pm_servo_step(pm_servo *servo, const double *probes, double *forces, int32_t *status);
/* Contact k after the last tick (a consistent copy, also while the servo's thread runs). */
PM_API void pm_servo_state(pm_servo *servo, int32_t k, pm_contact_state *out);
PM_API int32_t pm_servo_count(const pm_servo *servo);
/* the kernel this servo's coupled pairs sum their blocks with, chosen by the CPU at creation: "avx2", or
 * "baseline" (SSE2; also where the environment's PMASK_DISABLE_CPU_FEATURES names AVX2).  Both give the same
 * forces to the bit. */
PM_API const char *pm_servo_kernel(const pm_servo *servo);
/* 1 once a probe came more than 10 model sizes from the model (wrong units?), with that probe in `probe`
 * (may be NULL); 0 afterwards (it is reported once per servo, as the Python engine logs it once). */
PM_API int32_t pm_servo_take_far_warning(pm_servo *servo, double *probe);
/* The surface displacement (n_vertices x 3) of eq. 16 for the contacts after the last step, with display
 * forces that make it meet every contact's displacement (on a subdivided contact surface the mesh point under a
 * contact moves by that plus the contact point's offset from it, so the mesh reaches where the contact surface
 * does): 0, or -1 without a ζ table or a compressed Ξ's sections
 * (pm_table_has_greens).  On the latter it takes one product with the blocks the loads reach (its time at organ
 * scale: the benchmarks page), allocation-free: its workspace comes with the servo. */
PM_API int pm_servo_deformation(pm_servo *servo, double *out);

/* Device input/output inside the tick (thread mode): read fills the probes (3n) before the step, write
 * receives the forces (3n) and statuses (n) right after it.  Both run on the servo's thread, so they must
 * not block (a device driver's non-blocking read and write). */
typedef struct {
    void (*read)(void *user, double *probes);
    void (*write)(void *user, const double *forces, const int32_t *status);
    void *user;
} pm_io;

/* Thread mode: a thread of the servo's own runs the step at `rate` Hz (absolute schedule, CLOCK_MONOTONIC;
 * a real-time priority where the process may have one), on the probes from `io` or, with io NULL, on the
 * probes last given to pm_servo_set_probes.  It sleeps to `spin` seconds before each tick and spins the
 * rest (PM_SPIN_DEFAULT, a fifth of a core at 1 kHz: on a loaded VM a wake-up from sleep came up to 10 ms
 * late, a spun one on time; 0 sleeps only).  While it runs, pm_servo_step returns the thread's latest
 * results and pm_servo_reset does nothing.  0, or < 0: already running (-1), bad rate or spin (-2), bad io
 * (-3), no thread (-4), no threads on this platform (-5).  POSIX only. */
#define PM_SPIN_DEFAULT 2e-4
PM_API int pm_servo_start(pm_servo *servo, double rate, double spin, const pm_io *io);
PM_API void pm_servo_stop(pm_servo *servo);
PM_API int32_t pm_servo_running(const pm_servo *servo);
/* The probes (3n) the thread uses from its next tick: any thread, any time (callers take turns on a mutex;
 * the servo's thread takes the latest complete set without waiting, never a torn one).  Before the first
 * call every probe is NaN (a bad sample). */
PM_API void pm_servo_set_probes(pm_servo *servo, const double *probes);

/* Tick-synchronous exchange, for a loop that reads its device on its own schedule but wants the servo's
 * timing: pm_servo_start_exchange runs the thread at `rate` on the samples given to pm_servo_exchange, each
 * used by exactly one tick, in order (a tick with no sample waiting runs no step and counts as idle).
 * pm_servo_exchange queues one sample (3n), waits (without the GIL, from Python) for the tick that uses it and
 * returns that tick's forces (3n) and statuses (n): the sequence of forces is the one pm_servo_step gives on
 * the same sequence of samples.  Returns 0; -1 when no tick answered within `timeout` seconds; -2 when the
 * thread does not run in exchange mode; -3 when 64 samples wait unanswered.  From one thread at a time (callers
 * take turns on a mutex). */
PM_API int pm_servo_start_exchange(pm_servo *servo, double rate, double spin);
PM_API int pm_servo_exchange(pm_servo *servo, const double *probes, double *forces, int32_t *status, double timeout);

/* The clock the thread schedules by: CLOCK_MONOTONIC in seconds, and a sleep to an absolute time on it
 * (POSIX; 0 and a no-op elsewhere).  A device loop in C can pace itself with them as the thread does. */
PM_API double pm_clock_now(void);
PM_API void pm_clock_sleep_until(double t);
/* The latest forces (3n), statuses (n) and timing; any pointer may be NULL. */
PM_API void pm_servo_read(pm_servo *servo, double *forces, int32_t *status, pm_tick_stats *stats);

#ifdef __cplusplus
}
#endif
#endif
