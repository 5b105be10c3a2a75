/* pmask servo core (see pmask_servo.h).
 *
 * Written operation for operation like pmask.runtime.haptics (the Python reference): the same
 * expressions in the same order, Python's min/max as PYMIN/PYMAX, and the divisions that raise
 * ZeroDivisionError in Python turned into the same INTERNAL_ERROR hold.  Compile without contraction
 * of multiply-adds (-ffp-contract=off; setup.py and the example's build pass it), or the last bits of
 * the forces differ from the Python step's.
 */
#define _POSIX_C_SOURCE 200809L
#include "pmask_servo.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#if !defined(_WIN32)
#include <errno.h>
#include <pthread.h>
#include <time.h>
#define PM_THREADS 1
#else
#define PM_THREADS 0
#endif

/* ------------------------------------------------------------------ constants (haptics.py's) */
#define GS_SWEEPS 60
#define FAR_FACTOR 10.0
#define PASSIVITY_SLACK 0.10
#define VELOCITY_FILTER 0.1
#define PC_DAMPING_MAX 1.0
#define PC_RAMP_TICKS 50.0

/* Python's max(a, b) and min(a, b): the first argument unless the second is larger (smaller) */
#define PYMAX(a, b) ((b) > (a) ? (b) : (a))
#define PYMIN(a, b) ((b) < (a) ? (b) : (a))

/* ------------------------------------------------------------------ the table */
struct pm_table {
    int64_t nv, nt, nc;           /* surface vertices, triangles, contact vertices (ζ table rows / 3) */
    const double *P, *frames, *N, *K, *taper, *grad;
    const int64_t *T, *nb;
    /* the bounding-volume hierarchy of the triangles, built at load (pm_table_nearest) */
    double *box;                  /* per node: lower corner, upper corner */
    int64_t *node;                /* per node: left child, or -1 - (first index into order) for a leaf */
    int64_t *leaf_count;          /* per node: triangles in a leaf, 0 for an inner node */
    int64_t *order;               /* triangles, leaves' runs */
    int64_t nnodes;
    double lo[3], hi[3], mean_edge, diag;
    const int64_t *row;           /* surface vertex -> contact row, -1 (NULL without ζ) */
    const double *zeta;           /* (3 nc, 3 nc): rows 3m..3m+2 = ζ_mᵀ (NULL without) */
    char *meta;
    unsigned char *blob;
    size_t size;
};

static void fmt(char *err, size_t errlen, const char *msg, const char *a, long long x, long long y)
{
    if (err && errlen) {
        char buf[512];
        snprintf(buf, sizeof buf, msg, a ? a : "", x, y);
        snprintf(err, errlen, "%s", buf);
    }
}

static uint32_t rd32(const unsigned char *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

static uint64_t rd64(const unsigned char *p) { return (uint64_t)rd32(p) | ((uint64_t)rd32(p + 4) << 32); }

/* CRC-32 (IEEE 802.3, zlib's crc32), slicing by 8 */
static void crc_tables(uint32_t tab[8][256])
{
    for (uint32_t i = 0; i < 256; i++) {
        uint32_t c = i;
        for (int k = 0; k < 8; k++) c = (c & 1u) ? 0xEDB88320u ^ (c >> 1) : c >> 1;
        tab[0][i] = c;
    }
    for (uint32_t i = 0; i < 256; i++)
        for (int s = 1; s < 8; s++) tab[s][i] = (tab[s - 1][i] >> 8) ^ tab[0][tab[s - 1][i] & 0xFFu];
}

static uint32_t crc32_update(uint32_t tab[8][256], uint32_t crc, const unsigned char *p, size_t n)
{
    uint32_t c = ~crc;
    while (n >= 8) {
        uint32_t a = c ^ rd32(p), b = rd32(p + 4);
        c = tab[7][a & 0xFF] ^ tab[6][(a >> 8) & 0xFF] ^ tab[5][(a >> 16) & 0xFF] ^ tab[4][a >> 24] ^
            tab[3][b & 0xFF] ^ tab[2][(b >> 8) & 0xFF] ^ tab[1][(b >> 16) & 0xFF] ^ tab[0][b >> 24];
        p += 8;
        n -= 8;
    }
    while (n--) c = tab[0][(c ^ *p++) & 0xFF] ^ (c >> 8);
    return ~c;
}

enum { DT_F64 = 1, DT_I64 = 2, DT_BYTES = 3 };
#define HEADER_SIZE 64
#define ENTRY_SIZE 64
#define NAME_SIZE 32

typedef struct {
    const unsigned char *data;
    uint64_t rows, cols;
    uint32_t dtype;
    int found;
} section;

static int find_section(const unsigned char *blob, uint32_t nsec, const char *name, section *out)
{
    memset(out, 0, sizeof *out);
    for (uint32_t i = 0; i < nsec; i++) {
        const unsigned char *e = blob + HEADER_SIZE + (size_t)i * ENTRY_SIZE;
        if (strncmp((const char *)e, name, NAME_SIZE) == 0) {
            out->dtype = rd32(e + 32);
            out->data = blob + rd64(e + 40);
            out->rows = rd64(e + 48);
            out->cols = rd64(e + 56);
            out->found = 1;
            return 1;
        }
    }
    return 0;
}

/* a required (or, with optional, possibly absent) section of the given type and shape; rows < 0: any */
static int want(const unsigned char *blob, uint32_t nsec, const char *name, uint32_t dtype, int64_t rows,
                int64_t cols, int optional, section *s, char *err, size_t errlen)
{
    if (!find_section(blob, nsec, name, s)) {
        if (optional) return 0;
        fmt(err, errlen, "not a complete runtime table: section '%s' is missing (export it again)", name, 0, 0);
        return -1;
    }
    if (s->dtype != dtype || (rows >= 0 && s->rows != (uint64_t)rows) || (cols >= 0 && s->cols != (uint64_t)cols)) {
        fmt(err, errlen, "corrupt runtime table: section '%s' has the wrong type or shape (%lld x %lld)", name,
            (long long)s->rows, (long long)s->cols);
        return -1;
    }
    return 0;
}

static int all_finite(const double *x, uint64_t n)
{
    for (uint64_t i = 0; i < n; i++)
        if (!isfinite(x[i])) return 0;
    return 1;
}

static int in_range(const int64_t *x, uint64_t n, int64_t lo, int64_t hi)
{
    for (uint64_t i = 0; i < n; i++)
        if (x[i] < lo || x[i] >= hi) return 0;
    return 1;
}

/* positive definite symmetric part (Cholesky of (K + Kᵀ)/2), as the Python loader checks */
static int spd3(const double *K)
{
    double a = K[0], b = 0.5 * (K[1] + K[3]), c = 0.5 * (K[2] + K[6]);
    double d = K[4], e = 0.5 * (K[5] + K[7]), f = K[8];
    if (!(a > 0.0)) return 0;
    double l11 = sqrt(a), l21 = b / l11, l31 = c / l11;
    double d2 = d - l21 * l21;
    if (!(d2 > 0.0)) return 0;
    double l22 = sqrt(d2), l32 = (e - l31 * l21) / l22;
    double d3 = f - l31 * l31 - l32 * l32;
    return d3 > 0.0;
}

static int host_little_endian(void)
{
    const uint32_t one = 1;
    unsigned char c;
    memcpy(&c, &one, 1);
    return c == 1;
}

static int build_bvh(pm_table *t);
static void free_bvh(pm_table *t);

/* parse and check a table held in blob (owned by the table on success) */
static int parse(unsigned char *blob, size_t size, pm_table **out, char *err, size_t errlen)
{
    if (!host_little_endian()) {
        fmt(err, errlen, "runtime tables are little-endian; this host is big-endian (unsupported)", NULL, 0, 0);
        return -1;
    }
    if (size < HEADER_SIZE || memcmp(blob, "PMASKTBL", 8) != 0) {
        fmt(err, errlen, "not a pmask runtime table (no PMASKTBL header); write one with `pmask export-table "
            "ARTIFACT -o FILE`", NULL, 0, 0);
        return -1;
    }
    uint32_t major = rd32(blob + 8), minor = rd32(blob + 12);
    if (major > PM_TABLE_MAJOR || major == 0) {
        fmt(err, errlen, "runtime table format %s%lld.%lld is not one this library reads (1.x): export the table "
            "with this version of pmask, or update the library", NULL, (long long)major, (long long)minor);
        return -1;
    }
    uint64_t fsize = rd64(blob + 16), dir = rd64(blob + 24);
    uint32_t nsec = rd32(blob + 32), hcrc = rd32(blob + 36);
    if (fsize != (uint64_t)size) {
        fmt(err, errlen, "corrupt runtime table: truncated or padded (the header says %s%lld bytes, there are %lld)",
            NULL, (long long)fsize, (long long)size);
        return -1;
    }
    if (dir != HEADER_SIZE || nsec > 4096 || HEADER_SIZE + (uint64_t)nsec * ENTRY_SIZE > size) {
        fmt(err, errlen, "corrupt runtime table: bad section directory", NULL, 0, 0);
        return -1;
    }
    uint32_t tab[8][256];   /* 8 KB, ~10 µs: per load, so that loading is thread-safe */
    crc_tables(tab);
    unsigned char head[HEADER_SIZE];
    memcpy(head, blob, HEADER_SIZE);
    memset(head + 36, 0, 4);
    uint32_t c = crc32_update(tab, 0, head, HEADER_SIZE);
    c = crc32_update(tab, c, blob + HEADER_SIZE, (size_t)nsec * ENTRY_SIZE);
    if (c != hcrc) {
        fmt(err, errlen, "corrupt runtime table: the header's checksum does not match", NULL, 0, 0);
        return -1;
    }
    for (uint32_t i = 0; i < nsec; i++) {
        const unsigned char *e = blob + HEADER_SIZE + (size_t)i * ENTRY_SIZE;
        char name[NAME_SIZE + 1];
        memcpy(name, e, NAME_SIZE);
        name[NAME_SIZE] = 0;
        uint32_t dt = rd32(e + 32), scrc = rd32(e + 36);
        uint64_t off = rd64(e + 40), rows = rd64(e + 48), cols = rd64(e + 56);
        uint64_t item = dt == DT_BYTES ? 1 : 8;
        if (cols != 0 && rows > UINT64_MAX / cols / 8) {
            fmt(err, errlen, "corrupt runtime table: section '%s' is too large", name, 0, 0);
            return -1;
        }
        uint64_t bytes = rows * cols * item;
        if (off % 8 != 0 || off > size || bytes > size - off) {
            fmt(err, errlen, "corrupt runtime table: section '%s' lies outside the file", name, 0, 0);
            return -1;
        }
        if (crc32_update(tab, 0, blob + off, (size_t)bytes) != scrc) {
            fmt(err, errlen, "corrupt runtime table: section '%s' fails its checksum", name, 0, 0);
            return -1;
        }
    }
    pm_table *t = calloc(1, sizeof *t);
    if (!t) {
        fmt(err, errlen, "out of memory loading the runtime table", NULL, 0, 0);
        return -1;
    }
    section s;
    t->blob = blob;
    t->size = size;
#define NEED(name, dt, r, cl, opt) \
    if (want(blob, nsec, name, dt, r, cl, opt, &s, err, errlen)) goto bad
    NEED("points", DT_F64, -1, 3, 0);
    t->nv = (int64_t)s.rows;
    t->P = (const double *)s.data;
    NEED("triangles", DT_I64, -1, 3, 0);
    t->nt = (int64_t)s.rows;
    t->T = (const int64_t *)s.data;
    if (t->nv < 3 || t->nt < 1) {
        fmt(err, errlen, "runtime table without a surface (%s%lld vertices, %lld triangles)", NULL, (long long)t->nv,
            (long long)t->nt);
        goto bad;
    }
    NEED("neighbours", DT_I64, t->nt, 3, 0);
    t->nb = (const int64_t *)s.data;
    NEED("frames", DT_F64, t->nt, 12, 0);
    t->frames = (const double *)s.data;
    NEED("normals", DT_F64, t->nv, 3, 0);
    t->N = (const double *)s.data;
    NEED("stiffness", DT_F64, t->nv, 9, 0);
    t->K = (const double *)s.data;
    NEED("taper", DT_F64, t->nv, 1, 0);
    t->taper = (const double *)s.data;
    NEED("gradient", DT_F64, t->nv, 1 * 3, 0);
    t->grad = (const double *)s.data;
    NEED("bounds", DT_F64, 2, 3, 0);
    memcpy(t->lo, s.data, 3 * sizeof(double));
    memcpy(t->hi, s.data + 24, 3 * sizeof(double));
    NEED("lengths", DT_F64, 1, 2, 0);
    memcpy(&t->mean_edge, s.data, sizeof(double));
    memcpy(&t->diag, s.data + 8, sizeof(double));
    if (!in_range(t->T, 3 * (uint64_t)t->nt, 0, t->nv) || !in_range(t->nb, 3 * (uint64_t)t->nt, -1, t->nt)) {
        fmt(err, errlen, "corrupt runtime table: a triangle or neighbour index is out of range", NULL, 0, 0);
        goto bad;
    }
    if (!all_finite(t->P, 3 * (uint64_t)t->nv) || !all_finite(t->frames, 12 * (uint64_t)t->nt) ||
        !all_finite(t->N, 3 * (uint64_t)t->nv) || !all_finite(t->K, 9 * (uint64_t)t->nv) ||
        !all_finite(t->taper, (uint64_t)t->nv) || !all_finite(t->grad, 3 * (uint64_t)t->nv) ||
        !all_finite(t->lo, 3) || !all_finite(t->hi, 3) || !all_finite(&t->mean_edge, 1) || !all_finite(&t->diag, 1)) {
        fmt(err, errlen, "corrupt runtime table: a non-finite number", NULL, 0, 0);
        goto bad;
    }
    for (int64_t v = 0; v < t->nv; v++) {
        if (t->taper[v] < 0.0 || t->taper[v] > 1.0) {
            fmt(err, errlen, "corrupt runtime table: taper outside [0, 1] at vertex %s%lld", NULL, (long long)v, 0);
            goto bad;
        }
        if (!spd3(t->K + 9 * v)) {
            fmt(err, errlen, "runtime table: the stiffness at surface vertex %s%lld is not positive definite (a "
                "corrupt or hand-edited table; export it again from a checked artifact)", NULL, (long long)v, 0);
            goto bad;
        }
    }
    if (want(blob, nsec, "zeta", DT_F64, -1, -1, 1, &s, err, errlen)) goto bad;
    if (s.found) {
        if (s.rows != s.cols || s.rows % 3 != 0) {
            fmt(err, errlen, "corrupt runtime table: the zeta table is not square", NULL, 0, 0);
            goto bad;
        }
        t->nc = (int64_t)s.rows / 3;
        t->zeta = (const double *)s.data;
        if (!all_finite(t->zeta, s.rows * s.cols)) {
            fmt(err, errlen, "corrupt runtime table: a non-finite number in the zeta table", NULL, 0, 0);
            goto bad;
        }
        NEED("contact_row", DT_I64, t->nv, 1, 0);
        t->row = (const int64_t *)s.data;
        if (!in_range(t->row, (uint64_t)t->nv, -1, t->nc)) {
            fmt(err, errlen, "corrupt runtime table: a contact row is out of range", NULL, 0, 0);
            goto bad;
        }
    }
    if (want(blob, nsec, "meta", DT_BYTES, -1, 1, 1, &s, err, errlen)) goto bad;
    t->meta = malloc(s.found ? (size_t)s.rows + 1 : 3);
    if (!t->meta) {
        fmt(err, errlen, "out of memory loading the runtime table", NULL, 0, 0);
        goto bad;
    }
    if (s.found) {
        memcpy(t->meta, s.data, (size_t)s.rows);
        t->meta[s.rows] = 0;
    } else {
        strcpy(t->meta, "{}");
    }
#undef NEED
    if (build_bvh(t)) {
        fmt(err, errlen, "out of memory building the runtime table's spatial index", NULL, 0, 0);
        goto bad;
    }
    *out = t;
    return 0;
bad:
    t->blob = NULL;  /* the caller frees the blob */
    free_bvh(t);
    free(t->meta);
    free(t);
    return -1;
}

int pm_table_from_memory(const void *data, size_t size, pm_table **out, char *err, size_t errlen)
{
    *out = NULL;
    unsigned char *blob = malloc(size ? size : 1);
    if (!blob) {
        fmt(err, errlen, "out of memory: the runtime table needs %s%lld bytes", NULL, (long long)size, 0);
        return -1;
    }
    memcpy(blob, data, size);
    if (parse(blob, size, out, err, errlen)) {
        free(blob);
        return -1;
    }
    return 0;
}

int pm_table_load(const char *path, pm_table **out, char *err, size_t errlen)
{
    *out = NULL;
    FILE *f = fopen(path, "rb");
    if (!f) {
        fmt(err, errlen, "cannot open the runtime table %s", path, 0, 0);
        return -1;
    }
    unsigned char *blob = NULL;
    size_t size = 0, cap = 0;
    for (;;) {
        if (size == cap) {
            size_t ncap = cap ? 2 * cap : (size_t)1 << 20;
            unsigned char *nb = realloc(blob, ncap);
            if (!nb) {
                free(blob);
                fclose(f);
                fmt(err, errlen, "out of memory reading the runtime table %s", path, 0, 0);
                return -1;
            }
            blob = nb;
            cap = ncap;
        }
        size_t got = fread(blob + size, 1, cap - size, f);
        size += got;
        if (got == 0) break;
    }
    int bad = ferror(f);
    fclose(f);
    if (bad) {
        free(blob);
        fmt(err, errlen, "cannot read the runtime table %s", path, 0, 0);
        return -1;
    }
    if (parse(blob, size, out, err, errlen)) {
        free(blob);
        return -1;
    }
    return 0;
}

void pm_table_free(pm_table *t)
{
    if (!t) return;
    free_bvh(t);
    free(t->blob);
    free(t->meta);
    free(t);
}

int64_t pm_table_vertices(const pm_table *t) { return t->nv; }
int64_t pm_table_triangles(const pm_table *t) { return t->nt; }
int32_t pm_table_has_zeta(const pm_table *t) { return t->zeta != NULL; }
const char *pm_table_meta(const pm_table *t) { return t->meta; }

void pm_table_bounds(const pm_table *t, double *lo, double *hi)
{
    memcpy(lo, t->lo, sizeof t->lo);
    memcpy(hi, t->hi, sizeof t->hi);
}

void pm_table_stiffness(const pm_table *t, int64_t n, const int64_t *tri, const double *bary, double *out)
{
    const double *K = t->K;
    const int64_t *T = t->T;
    for (int64_t q = 0; q < n; q++) {
#if defined(__GNUC__)
        /* random queries over a large mesh wait on memory: fetch a later query's triangle, then its rows */
        if (q + 16 < n) __builtin_prefetch(T + 3 * tri[q + 16]);
        if (q + 8 < n) {
            const int64_t *w = T + 3 * tri[q + 8];
            __builtin_prefetch(K + 9 * w[0]);
            __builtin_prefetch(K + 9 * w[0] + 8);
            __builtin_prefetch(K + 9 * w[1]);
            __builtin_prefetch(K + 9 * w[1] + 8);
            __builtin_prefetch(K + 9 * w[2]);
            __builtin_prefetch(K + 9 * w[2] + 8);
        }
#endif
        const int64_t *v = T + 3 * tri[q];
        const double *k0 = K + 9 * v[0], *k1 = K + 9 * v[1], *k2 = K + 9 * v[2];
        const double b0 = bary[3 * q], b1 = bary[3 * q + 1], b2 = bary[3 * q + 2];
        double *o = out + 9 * q;
        for (int i = 0; i < 9; i++) o[i] = b0 * k0[i] + b1 * k1[i] + b2 * k2[i];
    }
}

/* ------------------------------------------------------------------ nearest triangle */
/* squared distance from p to triangle t's barycentric-clamped flat projection (spatial.py's distance) */
static double tri_distance2(const pm_table *tb, int64_t t, const double *p)
{
    const double *F = tb->frames + 12 * t;
    const int64_t *v = tb->T + 3 * t;
    const double *P0 = tb->P + 3 * v[0], *P1 = tb->P + 3 * v[1], *P2 = tb->P + 3 * v[2];
    double dx = p[0] - F[0], dy = p[1] - F[1], dz = p[2] - F[2];
    double b1 = F[3] * dx + F[4] * dy + F[5] * dz;
    double b2 = F[6] * dx + F[7] * dy + F[8] * dz;
    double b0 = 1.0 - b1 - b2;
    b0 = PYMAX(b0, 0.0);
    b1 = PYMAX(b1, 0.0);
    b2 = PYMAX(b2, 0.0);
    double tot = b0 + b1 + b2;
    b0 = b0 / tot;
    b1 = b1 / tot;
    b2 = b2 / tot;
    double ex = b0 * P0[0] + b1 * P1[0] + b2 * P2[0] - p[0];
    double ey = b0 * P0[1] + b1 * P1[1] + b2 * P2[1] - p[1];
    double ez = b0 * P0[2] + b1 * P1[2] + b2 * P2[2] - p[2];
    return ex * ex + ey * ey + ez * ez;
}

/* A bounding-volume hierarchy of the triangles (median splits of the centroids along the box's longest
 * axis, leaves of up to 4), built once at load.  The query is a best-first descent that prunes a box whose
 * distance exceeds the best found; it returns the lexicographic minimum of (distance, index) over all
 * triangles, which is exactly what the Python engine's uniform grid returns, at a cost that does not grow
 * with the probe's depth below the surface (a grid's ring search visits (depth / cell)^3 cells). */
#define BVH_LEAF 4
#define BVH_STACK 128

static void free_bvh(pm_table *t)
{
    free(t->box);
    free(t->node);
    free(t->leaf_count);
    free(t->order);
    t->box = NULL;
    t->node = t->leaf_count = t->order = NULL;
}

static void tri_box(const pm_table *t, int64_t tri, double *lo, double *hi)
{
    const int64_t *v = t->T + 3 * tri;
    for (int a = 0; a < 3; a++) {
        double x = t->P[3 * v[0] + a], y = t->P[3 * v[1] + a], z = t->P[3 * v[2] + a];
        lo[a] = fmin(x, fmin(y, z));
        hi[a] = fmax(x, fmax(y, z));
    }
}

/* partial sort of order[lo, hi) so that the element at k has its rank by key (quickselect) */
static void select_k(int64_t *order, const double *key, int64_t lo, int64_t hi, int64_t k)
{
    while (hi - lo > 1) {
        double pivot = key[order[lo + (hi - lo) / 2]];
        int64_t i = lo, j = hi - 1;
        while (i <= j) {
            while (key[order[i]] < pivot) i++;
            while (key[order[j]] > pivot) j--;
            if (i <= j) {
                int64_t tmp = order[i];
                order[i] = order[j];
                order[j] = tmp;
                i++;
                j--;
            }
        }
        if (k <= j) hi = j + 1;
        else if (k >= i) lo = i;
        else return;
    }
}

static int build_bvh(pm_table *t)
{
    const int64_t n = t->nt;
    const int64_t cap = n + 2;  /* leaves hold >= 2 triangles (a split of > 4 leaves >= 2 each): < n nodes */
    t->box = malloc((size_t)cap * 6 * sizeof(double));
    t->node = malloc((size_t)cap * sizeof(int64_t));
    t->leaf_count = malloc((size_t)cap * sizeof(int64_t));
    t->order = malloc((size_t)n * sizeof(int64_t));
    double *cent = malloc((size_t)n * 3 * sizeof(double));
    double *key = malloc((size_t)n * sizeof(double));
    int64_t *stack = malloc((size_t)cap * 3 * sizeof(int64_t));
    if (!t->box || !t->node || !t->leaf_count || !t->order || !cent || !key || !stack) {
        free(cent);
        free(key);
        free(stack);
        return -1;
    }
    for (int64_t i = 0; i < n; i++) {
        t->order[i] = i;
        double lo[3], hi[3];
        tri_box(t, i, lo, hi);
        for (int a = 0; a < 3; a++) cent[3 * i + a] = 0.5 * (lo[a] + hi[a]);
    }
    /* explicit stack of (node, first, count) */
    int64_t nn = 1, sp = 0;
    stack[0] = 0;
    stack[1] = 0;
    stack[2] = n;
    sp = 1;
    while (sp > 0) {
        sp--;
        int64_t id = stack[3 * sp], first = stack[3 * sp + 1], count = stack[3 * sp + 2];
        double *bx = t->box + 6 * id;
        for (int a = 0; a < 3; a++) {
            bx[a] = INFINITY;
            bx[3 + a] = -INFINITY;
        }
        for (int64_t i = first; i < first + count; i++) {
            double lo[3], hi[3];
            tri_box(t, t->order[i], lo, hi);
            for (int a = 0; a < 3; a++) {
                bx[a] = fmin(bx[a], lo[a]);
                bx[3 + a] = fmax(bx[3 + a], hi[a]);
            }
        }
        if (count <= BVH_LEAF || nn + 2 > cap) {
            t->node[id] = -1 - first;
            t->leaf_count[id] = count;
            continue;
        }
        int axis = 0;
        for (int a = 1; a < 3; a++)
            if (bx[3 + a] - bx[a] > bx[3 + axis] - bx[axis]) axis = a;
        for (int64_t i = first; i < first + count; i++) key[t->order[i]] = cent[3 * t->order[i] + axis];
        int64_t half = count / 2;
        select_k(t->order, key, first, first + count, first + half);
        int64_t left = nn, right = nn + 1;
        nn += 2;
        t->node[id] = left;
        t->leaf_count[id] = 0;
        stack[3 * sp] = left;
        stack[3 * sp + 1] = first;
        stack[3 * sp + 2] = half;
        sp++;
        stack[3 * sp] = right;
        stack[3 * sp + 1] = first + half;
        stack[3 * sp + 2] = count - half;
        sp++;
    }
    t->nnodes = nn;
    free(cent);
    free(key);
    free(stack);
    return 0;
}

static double box_distance2(const double *bx, const double *p)
{
    double d = 0.0;
    for (int a = 0; a < 3; a++) {
        double e = bx[a] - p[a];
        if (e < 0.0) e = p[a] - bx[3 + a];
        if (e > 0.0) d += e * e;
    }
    return d;
}

int64_t pm_table_nearest(const pm_table *tb, const double *p)
{
    int64_t stack[BVH_STACK];
    double dstack[BVH_STACK];
    int sp = 0;
    int64_t best = -1;
    double best_d2 = INFINITY;
    stack[sp] = 0;
    dstack[sp++] = box_distance2(tb->box, p);
    while (sp > 0) {
        sp--;
        int64_t id = stack[sp];
        if (dstack[sp] > best_d2) continue;
        if (tb->leaf_count[id] > 0) {
            int64_t first = -1 - tb->node[id];
            for (int64_t i = first; i < first + tb->leaf_count[id]; i++) {
                int64_t t = tb->order[i];
                double d = tri_distance2(tb, t, p);
                if (d < best_d2 || (d == best_d2 && t < best)) {
                    best = t;
                    best_d2 = d;
                }
            }
            continue;
        }
        int64_t l = tb->node[id], r = l + 1;
        double dl = box_distance2(tb->box + 6 * l, p), dr = box_distance2(tb->box + 6 * r, p);
        if (sp + 2 > BVH_STACK) continue;  /* cannot happen for a median-split tree (depth ~ log2 n) */
        if (dl <= dr) {   /* the nearer child on top */
            stack[sp] = r;
            dstack[sp++] = dr;
            stack[sp] = l;
            dstack[sp++] = dl;
        } else {
            stack[sp] = l;
            dstack[sp++] = dl;
            stack[sp] = r;
            dstack[sp++] = dr;
        }
    }
    return best;
}

/* ------------------------------------------------------------------ the servo */
typedef struct {
    int64_t tri;
    double b[3];
    int has_anchor;
    double anchor[3];
    int in_contact, above, sliding;
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

typedef struct {   /* step 2's inputs at the proxy (_geometry's first result) */
    double N[3], K[9], Ki[9], lam, g[3];
} geom;

typedef struct {   /* _local's result and the displacement left to the contact */
    double f[3], u2[3];
    int sliding;
    double delta;
    double ueff[3];
    double total[3];  /* the surface's displacement at the contact: u2 + (ū − ueff) */
} lres;

struct pm_servo {
    const pm_table *tab;
    int32_t n;
    pm_options o;
    int frictionless;
    double margin, energy, pc_damping;
    int far_warned, far_pending;
    double far_probe[3];
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
    double *nA, *nr, *nx;  /* the frictionless start's normal system (n*n, n, n) */
    /* display solve */
    double *dC, *du;
    int64_t *dpiv;
    int32_t *dact;
    /* the published results: a sequence lock (odd while the tick writes) */
    uint64_t out_seq;
    pm_contact_state *pub;
    double *pub_forces;
    int32_t *pub_status;
    pm_tick_stats stats;
    /* thread mode */
    uint64_t in_seq;
    double *in_probes;
    double *tick_probes, *tick_forces;
    int32_t *tick_status;
    pm_io io;
    int has_io;
    double period, spin;
    int running;
    int stop_flag;
#if PM_THREADS
    pthread_t thread;
#endif
};

static void state_reset(cstate *s)
{
    memset(s, 0, sizeof *s);
    s->tri = -1;
    s->b[0] = 1.0;
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
    o->proxy_speed = 1.25;
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

#define ALLOC(ptr, count)                                                           \
    do {                                                                            \
        (ptr) = calloc((size_t)(count), sizeof *(ptr)); /* count >= 1: n >= 1 */     \
        if (!(ptr)) {                                                               \
            if (err && errlen) snprintf(err, errlen, "out of memory creating the servo"); \
            pm_servo_free(s);                                                       \
            return -1;                                                              \
        }                                                                           \
    } while (0)

int pm_servo_create(const pm_table *t, int32_t n, const pm_options *opt, pm_servo **out, char *err, size_t errlen)
{
    *out = NULL;
    pm_options o;
    if (opt) o = *opt; else pm_options_default(t, &o);
    if (n < 1 || n > 64) {
        if (err && errlen) snprintf(err, errlen, "n must be between 1 and 64 instruments, got %d", (int)n);
        return -1;
    }
#define FIN(x) isfinite(x)
    if (!(FIN(o.friction) && o.friction >= 0.0)) return bad_option(err, errlen, "friction", o.friction, "finite and >= 0");
    if (!(FIN(o.dynamic_friction) && o.dynamic_friction >= 0.0))
        return bad_option(err, errlen, "dynamic_friction", o.dynamic_friction, "finite and >= 0");
    if (!(FIN(o.damping) && o.damping >= 0.0)) return bad_option(err, errlen, "damping", o.damping, "finite and >= 0");
    if (!(FIN(o.tool_radius) && o.tool_radius >= 0.0 && o.tool_radius <= 0.5 * t->diag))
        return bad_option(err, errlen, "tool_radius", o.tool_radius, "finite, >= 0 and at most half the model's size");
    if (!(FIN(o.slip_length) && o.slip_length > 0.0))
        return bad_option(err, errlen, "slip_length", o.slip_length, "finite and > 0");
    if (!(FIN(o.rate) && o.rate > 0.0)) return bad_option(err, errlen, "rate", o.rate, "finite and > 0");
    if (!(FIN(o.max_jump) && o.max_jump > 0.0)) return bad_option(err, errlen, "max_jump", o.max_jump, "finite and > 0");
    if (!(FIN(o.decay) && o.decay >= 0.0 && o.decay < 1.0)) return bad_option(err, errlen, "decay", o.decay, "in [0, 1)");
    if (!(FIN(o.proxy_speed) && o.proxy_speed >= 1.0))
        return bad_option(err, errlen, "proxy_speed", o.proxy_speed, "finite and >= 1");
    if (o.reset_after < 1) return bad_option(err, errlen, "reset_after", o.reset_after, ">= 1");
    if (o.max_walk < 1) return bad_option(err, errlen, "max_walk", o.max_walk, ">= 1");
#undef FIN
    if (o.coupled < 0) o.coupled = (t->zeta != NULL && n > 1);
    if (o.coupled && !t->zeta) {
        if (err && errlen) snprintf(err, errlen, "coupled contacts need the table's zeta section (export it with the zeta table)");
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
    s->o.passivity = o.passivity ? 1 : 0;
    s->frictionless = (o.friction == 0.0 && o.dynamic_friction == 0.0);
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
    ALLOC(s->nA, (size_t)n * n);
    ALLOC(s->nr, n);
    ALLOC(s->nx, n);
    ALLOC(s->dC, (size_t)9 * n * n);
    ALLOC(s->du, 3 * n);
    ALLOC(s->dpiv, 3 * n);
    ALLOC(s->dact, n);
    ALLOC(s->pub, n);
    ALLOC(s->pub_forces, 3 * n);
    ALLOC(s->pub_status, n);
    ALLOC(s->in_probes, 3 * n);
    ALLOC(s->tick_probes, 3 * n);
    ALLOC(s->tick_forces, 3 * n);
    ALLOC(s->tick_status, n);
    for (int32_t i = 0; i < 3 * n; i++) s->in_probes[i] = NAN;
    pm_servo_reset(s);
    *out = s;
    return 0;
}

void pm_servo_free(pm_servo *s)
{
    if (!s) return;
    pm_servo_stop(s);
    free(s->st);
    free(s->probe);
    free(s->ok);
    free(s->geo);
    free(s->ubar);
    free(s->active);
    free(s->res);
    free(s->gsf);
    free(s->cpl);
    free(s->nA);
    free(s->nr);
    free(s->nx);
    free(s->dC);
    free(s->du);
    free(s->dpiv);
    free(s->dact);
    free(s->pub);
    free(s->pub_forces);
    free(s->pub_status);
    free(s->in_probes);
    free(s->tick_probes);
    free(s->tick_forces);
    free(s->tick_status);
    free(s);
}

/* ---------------------------------------------------------------- publishing (sequence lock) */
static void publish(pm_servo *s);
static void read_published(pm_servo *s, int32_t k, pm_contact_state *one, double *forces, int32_t *status,
                           pm_tick_stats *stats);

void pm_servo_reset(pm_servo *s)
{
    if (s->running) return;  /* only between runs of the thread */
    for (int32_t l = 0; l < s->n; l++) state_reset(&s->st[l]);
    s->energy = 0.0;
    s->pc_damping = 0.0;
    publish(s);
}

int32_t pm_servo_take_far_warning(pm_servo *s, double *probe)
{
    int32_t w = s->far_pending;
    if (w && probe) memcpy(probe, s->far_probe, sizeof s->far_probe);
    s->far_pending = 0;
    return w;
}

/* ------------------------------------------------------------------ geometry (haptics.py's) */
static void project(const pm_table *tb, int64_t t, const double *p, double *b0o, double *b1o, double *b2o, double *so)
{
    const double *F = tb->frames + 12 * t;
    const double ox = F[0], oy = F[1], oz = F[2], ax = F[3], ay = F[4], az = F[5], bx = F[6], by = F[7], bz = F[8];
    const double nx = F[9], ny = F[10], nz = F[11];
    const int64_t *v = tb->T + 3 * t;
    const double *n0 = tb->N + 3 * v[0], *n1 = tb->N + 3 * v[1], *n2 = tb->N + 3 * v[2];
    double dx = p[0] - ox, dy = p[1] - oy, dz = p[2] - oz;
    double h = nx * dx + ny * dy + nz * dz;
    double b1 = ax * dx + ay * dy + az * dz;
    double b2 = bx * dx + by * dy + bz * dz;
    double s = h;
    for (int it = 0; it < 2; it++) {
        double b0 = 1.0 - b1 - b2;
        double Nx = b0 * n0[0] + b1 * n1[0] + b2 * n2[0];
        double Ny = b0 * n0[1] + b1 * n1[1] + b2 * n2[1];
        double Nz = b0 * n0[2] + b1 * n1[2] + b2 * n2[2];
        double hn = Nx * nx + Ny * ny + Nz * nz;
        if (hn < 0.1) break;
        s = h / hn;
        double qx = dx - s * Nx, qy = dy - s * Ny, qz = dz - s * Nz;
        b1 = ax * qx + ay * qy + az * qz;
        b2 = bx * qx + by * qy + bz * qz;
    }
    *b0o = 1.0 - b1 - b2;
    *b1o = b1;
    *b2o = b2;
    *so = s;
}

typedef struct {
    int64_t t;
    double b0, b1, b2, s;
} located;

/* 0, or -1 where the Python raises (ZeroDivisionError) */
static int locate(const pm_servo *S, int64_t t, const double *p, int retry, located *out)
{
    const pm_table *tb = S->tab;
    int64_t prev = -1;
    double b0 = 0, b1 = 0, b2 = 0, s = 0;
    int spent = 1;
    for (int32_t it = 0; it < S->o.max_walk; it++) {
        project(tb, t, p, &b0, &b1, &b2, &s);
        if (b0 >= 0.0 && b1 >= 0.0 && b2 >= 0.0) {
            out->t = t;
            out->b0 = b0;
            out->b1 = b1;
            out->b2 = b2;
            out->s = s;
            return 0;
        }
        int k = (b0 <= b1 && b0 <= b2) ? 0 : (b1 <= b2 ? 1 : 2);
        int64_t nb = tb->nb[3 * t + k];
        if (nb < 0 || nb == prev) {
            if (retry) {
                int64_t near = pm_table_nearest(tb, p);
                if (near != t && near != prev) return locate(S, near, p, 0, out);
            }
            spent = 0;
            break;
        }
        prev = t;
        t = nb;
    }
    if (spent) project(tb, t, p, &b0, &b1, &b2, &s);
    b0 = PYMAX(b0, 0.0);
    b1 = PYMAX(b1, 0.0);
    b2 = PYMAX(b2, 0.0);
    double tot = b0 + b1 + b2;
    if (tot == 0.0) return -1;
    out->t = t;
    out->b0 = b0 / tot;
    out->b1 = b1 / tot;
    out->b2 = b2 / tot;
    out->s = s;
    return 0;
}

static void point_at(const pm_table *tb, int64_t t, const double *b, double *x)
{
    const int64_t *v = tb->T + 3 * t;
    const double *a = tb->P + 3 * v[0], *bb = tb->P + 3 * v[1], *c = tb->P + 3 * v[2];
    x[0] = b[0] * a[0] + b[1] * bb[0] + b[2] * c[0];
    x[1] = b[0] * a[1] + b[1] * bb[1] + b[2] * c[1];
    x[2] = b[0] * a[2] + b[1] * bb[2] + b[2] * c[2];
}

static int normal_at(const pm_table *tb, int64_t t, const double *b, double *N)
{
    const int64_t *v = tb->T + 3 * t;
    const double *a = tb->N + 3 * v[0], *bb = tb->N + 3 * v[1], *c = tb->N + 3 * v[2];
    double x = b[0] * a[0] + b[1] * bb[0] + b[2] * c[0];
    double y = b[0] * a[1] + b[1] * bb[1] + b[2] * c[1];
    double z = b[0] * a[2] + b[1] * bb[2] + b[2] * c[2];
    double r = sqrt(x * x + y * y + z * z);
    if (r == 0.0) return -1;
    N[0] = x / r;
    N[1] = y / r;
    N[2] = z / r;
    return 0;
}

static void inverse3(const double *K, double *out)
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

/* ------------------------------------------------------------------ the tick */
static void hold(const pm_servo *S, cstate *st, int32_t status)
{
    double d = S->o.decay;
    for (int a = 0; a < 3; a++) {
        st->good_force[a] = st->good_force[a] * d;
        st->force[a] = st->good_force[a];
        st->body_force[a] = -st->force[a];
    }
    st->status = status;
}

static void none(cstate *st, int32_t status)
{
    for (int a = 0; a < 3; a++) {
        st->force[a] = st->good_force[a] = st->body_force[a] = st->law_force[a] = 0.0;
        st->u_bar[a] = 0.0;
    }
    st->depth = 0.0;
    st->taper = 0.0;
    st->sliding = 0;
    st->has_anchor = 0;
    st->slip = 0.0;
    st->status = status;
}

static double norm3(const double *v) { return sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]); }

static int move_proxy(const pm_servo *S, cstate *st, const double *target, double limit)
{
    const pm_table *tb = S->tab;
    int64_t t = st->tri;
    double b0 = st->b[0], b1 = st->b[1], b2 = st->b[2];
    double remaining = limit;
    for (int32_t it = 0; it < S->o.max_walk; it++) {
        const double *F = tb->frames + 12 * t;
        double dx = target[0] - F[0], dy = target[1] - F[1], dz = target[2] - F[2];
        double q1 = F[3] * dx + F[4] * dy + F[5] * dz;
        double q2 = F[6] * dx + F[7] * dy + F[8] * dz;
        double d0 = (1.0 - q1 - q2) - b0, d1 = q1 - b1, d2 = q2 - b2;
        const int64_t *v = tb->T + 3 * t;
        const double *v0 = tb->P + 3 * v[0], *v1 = tb->P + 3 * v[1], *v2 = tb->P + 3 * v[2];
        double ex = d0 * v0[0] + d1 * v1[0] + d2 * v2[0];
        double ey = d0 * v0[1] + d1 * v1[1] + d2 * v2[1];
        double ez = d0 * v0[2] + d1 * v1[2] + d2 * v2[2];
        double dist = sqrt(ex * ex + ey * ey + ez * ez);
        if (dist <= 0.0 || remaining <= 0.0) break;
        double a = PYMIN(1.0, remaining / dist);
        int exit_k = -1;
        double exit_a = a;
        const double bk[3] = {b0, b1, b2}, dk[3] = {d0, d1, d2};
        for (int k = 0; k < 3; k++)
            if (dk[k] < 0.0 && bk[k] + exit_a * dk[k] < 0.0) {
                exit_a = -bk[k] / dk[k];
                exit_k = k;
            }
        b0 = b0 + exit_a * d0;
        b1 = b1 + exit_a * d1;
        b2 = b2 + exit_a * d2;
        remaining -= exit_a * dist;
        if (exit_k < 0) break;
        int64_t nb = tb->nb[3 * t + exit_k];
        if (nb < 0) break;
        double bs[3] = {b0, b1, b2};
        bs[exit_k] = 0.0;
        const int64_t *w = tb->T + 3 * nb;
        double nbv[3];
        for (int j = 0; j < 3; j++) {
            double val = 0.0;
            for (int k = 0; k < 3; k++)
                if (v[k] == w[j]) val = bs[k];
            nbv[j] = val;
        }
        t = nb;
        b0 = nbv[0];
        b1 = nbv[1];
        b2 = nbv[2];
    }
    b0 = PYMAX(b0, 0.0);
    b1 = PYMAX(b1, 0.0);
    b2 = PYMAX(b2, 0.0);
    double tot = b0 + b1 + b2;
    if (tot == 0.0) return -1;
    st->tri = t;
    st->b[0] = b0 / tot;
    st->b[1] = b1 / tot;
    st->b[2] = b2 / tot;
    return 0;
}

/* step 1 for one contact: returns 1 when active (probe in p), 0 when not, -1 on an internal error */
static int prepare(pm_servo *S, cstate *st, const double *sample, double *p)
{
    const pm_table *tb = S->tab;
    double px = sample[0], py = sample[1], pz = sample[2];
    if (!(isfinite(px) && isfinite(py) && isfinite(pz))) {
        hold(S, st, PM_BAD_SAMPLE);
        return 0;
    }
    if (st->has_last) {
        double dx = fabs(px - st->last[0]), dy = fabs(py - st->last[1]), dz = fabs(pz - st->last[2]);
        double mj = S->o.max_jump;
        if (dx > mj || dy > mj || dz > mj || dx * dx + dy * dy + dz * dz > mj * mj) {
            st->bad += 1;
            if (st->bad <= S->o.reset_after) {
                hold(S, st, PM_JUMP);
                return 0;
            }
            state_reset(st);
        }
    }
    st->bad = 0;
    double gx = PYMAX(PYMAX(tb->lo[0] - px, px - tb->hi[0]), 0.0);
    double gy = PYMAX(PYMAX(tb->lo[1] - py, py - tb->hi[1]), 0.0);
    double gz = PYMAX(PYMAX(tb->lo[2] - pz, pz - tb->hi[2]), 0.0);
    if (st->has_last) {
        st->move[0] = px - st->last[0];
        st->move[1] = py - st->last[1];
        st->move[2] = pz - st->last[2];
    } else {
        st->move[0] = st->move[1] = st->move[2] = 0.0;
    }
    double a = VELOCITY_FILTER;
    for (int k = 0; k < 3; k++) st->vel[k] = st->vel[k] + a * (st->move[k] - st->vel[k]);
    st->has_last = 1;
    st->last[0] = px;
    st->last[1] = py;
    st->last[2] = pz;
    st->has_target = 0;
    double far = FAR_FACTOR * tb->diag;
    if (gx > far || gy > far || gz > far || gx * gx + gy * gy + gz * gz > far * far) {
        if (!S->far_warned) {
            S->far_warned = 1;
            S->far_pending = 1;
            S->far_probe[0] = px;
            S->far_probe[1] = py;
            S->far_probe[2] = pz;
        }
        st->tri = -1;
        st->in_contact = 0;
        st->above = 0;
        none(st, PM_FAR_OUTSIDE);
        return 0;
    }
    double m = S->margin;
    if (gx > m || gy > m || gz > m) {
        st->tri = -1;
        st->in_contact = 0;
        st->above = 0;
        none(st, PM_NO_CONTACT);
        return 0;
    }
    double r = S->o.tool_radius;
    double pp[3] = {px, py, pz};
    located L;
    if (st->tri < 0) {
        int64_t t = pm_table_nearest(tb, pp);
        if (locate(S, t, pp, 1, &L)) return -1;
        st->tri = L.t;
        st->b[0] = L.b0;
        st->b[1] = L.b1;
        st->b[2] = L.b2;
        st->above = L.s >= r;
        none(st, PM_NO_CONTACT);
        return 0;
    }
    if (locate(S, st->tri, pp, 1, &L)) return -1;
    if (!st->in_contact) {
        st->tri = L.t;
        st->b[0] = L.b0;
        st->b[1] = L.b1;
        st->b[2] = L.b2;
        if (L.s >= r || !st->above) {
            st->above = st->above || L.s >= r;
            none(st, PM_NO_CONTACT);
            return 0;
        }
        st->in_contact = 1;
        st->sliding = 0;
        st->has_anchor = 0;
        st->slip = 0.0;
        st->body_force[0] = st->body_force[1] = st->body_force[2] = 0.0;
        p[0] = px;
        p[1] = py;
        p[2] = pz;
        return 1;
    }
    st->has_target = 1;
    st->target_t = L.t;
    st->target_b[0] = L.b0;
    st->target_b[1] = L.b1;
    st->target_b[2] = L.b2;
    p[0] = px;
    p[1] = py;
    p[2] = pz;
    return 1;
}

static double nkn_of(const double *N, const double *Ki)
{
    const double Nx = N[0], Ny = N[1], Nz = N[2];
    return (Nx * (Ki[0] * Nx + Ki[1] * Ny + Ki[2] * Nz) + Ny * (Ki[3] * Nx + Ki[4] * Ny + Ki[5] * Nz) +
            Nz * (Ki[6] * Nx + Ki[7] * Ny + Ki[8] * Nz));
}

/* the contact law (_local): 0, or -1 where the Python raises */
static int local_law(const pm_servo *S, const cstate *st, const geom *g, double ux, double uy, double uz, lres *R)
{
    const double Nx = g->N[0], Ny = g->N[1], Nz = g->N[2], lam = g->lam;
    const double *Ki = g->Ki;
    double delta = -(Nx * ux + Ny * uy + Nz * uz);
    if (delta <= 0.0 || lam <= 0.0) {
        R->f[0] = R->f[1] = R->f[2] = 0.0;
        R->u2[0] = ux;
        R->u2[1] = uy;
        R->u2[2] = uz;
        R->sliding = 0;
        R->delta = 0.0;
        return 0;
    }
    double nkn = nkn_of(g->N, Ki);
    if (nkn == 0.0) return -1;
    double fc = lam * delta / nkn;
    double fx = -fc * Nx, fy = -fc * Ny, fz = -fc * Nz;
    if (S->frictionless) {
        R->f[0] = fx;
        R->f[1] = fy;
        R->f[2] = fz;
        R->u2[0] = -delta * Nx;
        R->u2[1] = -delta * Ny;
        R->u2[2] = -delta * Nz;
        R->sliding = 1;
        R->delta = delta;
        return 0;
    }
    double wx = ux + delta * Nx, wy = uy + delta * Ny, wz = uz + delta * Nz;
    double den = Ki[0] + Ki[4] + Ki[8] - nkn;
    if (den == 0.0) return -1;
    double kt = 2.0 * lam / den;
    double tx = kt * wx, ty = kt * wy, tz = kt * wz;
    double ft = sqrt(tx * tx + ty * ty + tz * tz);
    double mu = st->sliding ? S->o.dynamic_friction + (S->o.friction - S->o.dynamic_friction) *
                                                         exp(-st->slip / S->o.slip_length)
                            : S->o.friction;
    if (ft <= mu * fc) {
        R->f[0] = fx + tx;
        R->f[1] = fy + ty;
        R->f[2] = fz + tz;
        R->u2[0] = ux;
        R->u2[1] = uy;
        R->u2[2] = uz;
        R->sliding = 0;
        R->delta = delta;
        return 0;
    }
    double c = mu * fc / ft;
    tx = c * tx;
    ty = c * ty;
    tz = c * tz;
    if (kt == 0.0) return -1;
    R->f[0] = fx + tx;
    R->f[1] = fy + ty;
    R->f[2] = fz + tz;
    R->u2[0] = -delta * Nx + tx / kt;
    R->u2[1] = -delta * Ny + ty / kt;
    R->u2[2] = -delta * Nz + tz / kt;
    R->sliding = 1;
    R->delta = delta;
    return 0;
}

/* _geometry: N, K, K⁻¹, λ, ∇k_n at the proxy and ū; 0 or -1 */
static int geometry(const pm_servo *S, cstate *st, const double *p, geom *g, double *u)
{
    const pm_table *tb = S->tab;
    int64_t t = st->tri;
    const double *b = st->b;
    if (normal_at(tb, t, b, g->N)) return -1;
    const double Nx = g->N[0], Ny = g->N[1], Nz = g->N[2];
    const int64_t *v = tb->T + 3 * t;
    const double *k0 = tb->K + 9 * v[0], *k1 = tb->K + 9 * v[1], *k2 = tb->K + 9 * v[2];
    for (int i = 0; i < 9; i++) g->K[i] = b[0] * k0[i] + b[1] * k1[i] + b[2] * k2[i];
    const double *g0 = tb->grad + 3 * v[0], *g1 = tb->grad + 3 * v[1], *g2 = tb->grad + 3 * v[2];
    double gx = b[0] * g0[0] + b[1] * g1[0] + b[2] * g2[0];
    double gy = b[0] * g0[1] + b[1] * g1[1] + b[2] * g2[1];
    double gz = b[0] * g0[2] + b[1] * g1[2] + b[2] * g2[2];
    g->lam = b[0] * tb->taper[v[0]] + b[1] * tb->taper[v[1]] + b[2] * tb->taper[v[2]];
    inverse3(g->K, g->Ki);
    double gn = gx * Nx + gy * Ny + gz * Nz;
    double c[3];
    point_at(tb, t, b, c);
    if (st->has_anchor) {
        double ax = st->anchor[0], ay = st->anchor[1], az = st->anchor[2];
        double an = Nx * (ax - c[0]) + Ny * (ay - c[1]) + Nz * (az - c[2]);
        c[0] = ax - an * Nx;
        c[1] = ay - an * Ny;
        c[2] = az - an * Nz;
        st->anchor[0] = c[0];
        st->anchor[1] = c[1];
        st->anchor[2] = c[2];
    }
    double r = S->o.tool_radius;
    g->g[0] = gx - gn * Nx;
    g->g[1] = gy - gn * Ny;
    g->g[2] = gz - gn * Nz;
    u[0] = p[0] - r * Nx - c[0];
    u[1] = p[1] - r * Ny - c[1];
    u[2] = p[2] - r * Nz - c[2];
    return 0;
}

/* Σ_i Σ_m φ_i(x_a) φ_m(x_b) ζ_m(i) (9 row-major): displacement at a per unit force at b */
static void compliance(const pm_table *tb, int64_t ta, const double *ba, int64_t tbi, const double *bb, double *C)
{
    const int64_t n3 = 3 * tb->nc;
    for (int k = 0; k < 9; k++) C[k] = 0.0;
    const int64_t *ia = tb->T + 3 * ta, *ib = tb->T + 3 * tbi;
    for (int x = 0; x < 3; x++) {
        double pi = ba[x];
        int64_t ri = tb->row[ia[x]];
        if (pi == 0.0 || ri < 0) continue;
        for (int y = 0; y < 3; y++) {
            double pm = bb[y];
            int64_t rm = tb->row[ib[y]];
            if (pm == 0.0 || rm < 0) continue;
            double w = pi * pm;
            const double *blk = tb->zeta + 3 * rm * n3 + 3 * ri;   /* blk[c][r] = blk[c * n3 + r] */
            for (int r = 0; r < 3; r++)
                for (int c = 0; c < 3; c++) C[3 * r + c] += w * blk[c * n3 + r];
        }
    }
}

static void coupling_blocks(pm_servo *S, const int32_t *act, int32_t na)
{
    const pm_table *tb = S->tab;
    const int32_t n = S->n;
    for (int32_t x = 0; x < na; x++)
        for (int32_t y = 0; y < na; y++) {
            int32_t a = act[x], b = act[y];
            if (a < b) {
                double C[9], Ct[9];
                compliance(tb, S->st[a].tri, S->st[a].b, S->st[b].tri, S->st[b].b, C);
                compliance(tb, S->st[b].tri, S->st[b].b, S->st[a].tri, S->st[a].b, Ct);
                double *Sab = S->cpl + 9 * ((size_t)a * n + b), *Sba = S->cpl + 9 * ((size_t)b * n + a);
                for (int i = 0; i < 3; i++)
                    for (int j = 0; j < 3; j++) Sab[3 * i + j] = 0.5 * (C[3 * i + j] + Ct[3 * j + i]);
                for (int i = 0; i < 3; i++)
                    for (int j = 0; j < 3; j++) Sba[3 * i + j] = Sab[3 * j + i];
            }
        }
}

/* x with A x = r, Gaussian elimination without pivoting (A s x s row-major, SPD), in place: 0, or -1 when a
 * pivot is not positive (haptics.py's _solve_spd) */
static int solve_spd(double *A, double *r, double *x, int32_t s)
{
    for (int32_t k = 0; k < s; k++) {
        double p = A[k * s + k];
        if (!(p > 0.0)) return -1;
        for (int32_t i = k + 1; i < s; i++) {
            double q = A[i * s + k] / p;
            for (int32_t j = k + 1; j < s; j++) A[i * s + j] = A[i * s + j] - q * A[k * s + j];
            r[i] = r[i] - q * r[k];
        }
    }
    for (int32_t i = s - 1; i >= 0; i--) {
        double acc = r[i];
        for (int32_t j = i + 1; j < s; j++) acc = acc - A[i * s + j] * x[j];
        x[i] = acc / A[i * s + i];
    }
    return 0;
}

/* the frictionless start: the coupled normal problem with every active contact pressing (_normal_start) */
static void normal_start(pm_servo *S, const int32_t *act, int32_t na)
{
    const int32_t n = S->n;
    double *A = S->nA, *r = S->nr, *x = S->nx;
    for (int32_t a = 0; a < na; a++) {
        int32_t l = act[a];
        const geom *g = &S->geo[l];
        const double Nx = g->N[0], Ny = g->N[1], Nz = g->N[2];
        for (int32_t b = 0; b < na; b++) A[a * na + b] = 0.0;
        A[a * na + a] = nkn_of(g->N, g->Ki) / g->lam;
        const double *u = S->ubar + 3 * l;
        r[a] = -(Nx * u[0] + Ny * u[1] + Nz * u[2]);
        for (int32_t b = 0; b < na; b++) {
            int32_t k = act[b];
            if (k == l) continue;
            const double *C = S->cpl + 9 * ((size_t)l * n + k);
            const double Mx = S->geo[k].N[0], My = S->geo[k].N[1], Mz = S->geo[k].N[2];
            double cx = C[0] * Mx + C[1] * My + C[2] * Mz;
            double cy = C[3] * Mx + C[4] * My + C[5] * Mz;
            double cz = C[6] * Mx + C[7] * My + C[8] * Mz;
            A[a * na + b] = Nx * cx + Ny * cy + Nz * cz;
        }
    }
    int ok = solve_spd(A, r, x, na) == 0;
    for (int32_t a = 0; a < na; a++) {
        int32_t l = act[a];
        double p = ok ? PYMAX(x[a], 0.0) : 0.0;
        const double *N = S->geo[l].N;
        S->gsf[3 * l] = -p * N[0];
        S->gsf[3 * l + 1] = -p * N[1];
        S->gsf[3 * l + 2] = -p * N[2];
    }
}

static int solve(pm_servo *S, const int32_t *act, int32_t na)
{
    const int coupled = S->o.coupled && na > 1;
    const int32_t n = S->n;
    if (coupled) coupling_blocks(S, act, na);
    if (coupled && S->frictionless) {
        normal_start(S, act, na);
    } else {
        for (int32_t x = 0; x < na; x++) {  /* warm start: last tick's forces */
            int32_t l = act[x];
            S->gsf[3 * l] = S->st[l].law_force[0];
            S->gsf[3 * l + 1] = S->st[l].law_force[1];
            S->gsf[3 * l + 2] = S->st[l].law_force[2];
        }
    }
    int sweeps = coupled ? GS_SWEEPS : 1;
    for (int sw = 0; sw < sweeps; sw++) {
        double change = 0.0, size = 0.0;
        for (int32_t x = 0; x < na; x++) {
            int32_t l = act[x];
            double ux = S->ubar[3 * l], uy = S->ubar[3 * l + 1], uz = S->ubar[3 * l + 2];
            if (coupled) {
                for (int32_t y = 0; y < na; y++) {
                    int32_t k = act[y];
                    if (k == l) continue;
                    const double *C = S->cpl + 9 * ((size_t)l * n + k), *g = S->gsf + 3 * k;
                    const double gx = g[0], gy = g[1], gz = g[2];
                    ux -= C[0] * gx + C[1] * gy + C[2] * gz;
                    uy -= C[3] * gx + C[4] * gy + C[5] * gz;
                    uz -= C[6] * gx + C[7] * gy + C[8] * gz;
                }
            }
            lres *R = &S->res[l];
            if (local_law(S, &S->st[l], &S->geo[l], ux, uy, uz, R)) return -1;
            R->ueff[0] = ux;
            R->ueff[1] = uy;
            R->ueff[2] = uz;
            double *old = S->gsf + 3 * l;
            double c0 = fabs(R->f[0] - old[0]), c1 = fabs(R->f[1] - old[1]), c2 = fabs(R->f[2] - old[2]);
            old[0] = R->f[0];
            old[1] = R->f[1];
            old[2] = R->f[2];
            change = PYMAX(PYMAX(PYMAX(change, c0), c1), c2);
            size = PYMAX(PYMAX(PYMAX(size, fabs(R->f[0])), fabs(R->f[1])), fabs(R->f[2]));
        }
        if (change <= 1e-13 * size) break;
    }
    for (int32_t x = 0; x < na; x++) {
        int32_t l = act[x];
        memcpy(S->st[l].law_force, S->gsf + 3 * l, sizeof S->st[l].law_force);
    }
    return 0;
}

static int step_inner(pm_servo *S, const double *probes)
{
    const int32_t n = S->n;
    const pm_table *tb = S->tab;
    for (int32_t l = 0; l < n; l++) {
        int r = prepare(S, &S->st[l], probes + 3 * l, S->probe + 3 * l);
        if (r < 0) return -1;
        S->ok[l] = r;
    }
    const int frictionless = S->frictionless;
    int32_t na = 0;
    for (int32_t l = 0; l < n; l++) {
        if (!S->ok[l]) continue;
        cstate *st = &S->st[l];
        if (st->has_target) {
            double x[3];
            point_at(tb, st->target_t, st->target_b, x);
            if (move_proxy(S, st, x, S->o.proxy_speed * norm3(st->move))) return -1;
        }
        if (!frictionless && !st->has_anchor) {
            point_at(tb, st->tri, st->b, st->anchor);
            st->has_anchor = 1;
        }
        if (geometry(S, st, S->probe + 3 * l, &S->geo[l], S->ubar + 3 * l)) return -1;
        if (S->geo[l].lam <= 0.0) {
            if (!frictionless && st->has_target) {
                double x[3];
                point_at(tb, st->target_t, st->target_b, x);
                if (move_proxy(S, st, x, S->o.proxy_speed * norm3(st->move))) return -1;
            }
            none(st, PM_OUTSIDE_REGION);
            continue;
        }
        S->active[na++] = l;
    }
    if (na == 0) {
        S->energy = 0.0;
        S->pc_damping = 0.0;
        return 0;
    }
    if (solve(S, S->active, na)) return -1;
    int32_t kept = 0;
    for (int32_t x = 0; x < na; x++) {
        int32_t l = S->active[x];
        if (S->res[l].delta <= 0.0) {
            cstate *st = &S->st[l];
            if (st->has_target) {
                st->tri = st->target_t;
                st->b[0] = st->target_b[0];
                st->b[1] = st->target_b[1];
                st->b[2] = st->target_b[2];
            }
            st->in_contact = 0;
            st->above = 1;
            none(st, PM_NO_CONTACT);
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
    /* each contact's displacement of the surface: the law's own plus what the others move it */
    for (int32_t x = 0; x < na; x++) {
        int32_t l = S->active[x];
        lres *R = &S->res[l];
        const double *u = S->ubar + 3 * l;
        for (int a = 0; a < 3; a++) R->total[a] = R->u2[a] + (u[a] - R->ueff[a]);
    }
    double stored = 0.0, work = 0.0, motion2 = 0.0;
    for (int32_t x = 0; x < na; x++) {
        int32_t l = S->active[x];
        const cstate *st = &S->st[l];
        const lres *R = &S->res[l];
        double dpx = st->move[0], dpy = st->move[1], dpz = st->move[2];
        double vx = st->vel[0], vy = st->vel[1], vz = st->vel[2];
        motion2 += vx * vx + vy * vy + vz * vz;
        const double *hb = st->body_force;
        work += hb[0] * dpx + hb[1] * dpy + hb[2] * dpz;
        stored += 0.5 * (R->f[0] * R->total[0] + R->f[1] * R->total[1] + R->f[2] * R->total[2]);
    }
    double slack = PASSIVITY_SLACK * stored;
    double energy = S->o.passivity ? PYMIN(S->energy + work, stored + slack) : stored;
    double deficit = stored - slack - energy;
    double rate = S->o.rate;
    if (S->o.passivity) {
        double need = motion2 <= 0.0 ? PC_DAMPING_MAX : PYMIN(PC_DAMPING_MAX, deficit * rate / motion2);
        double wantd = deficit > 0.0 ? need : 0.0;
        S->pc_damping += (wantd - S->pc_damping) / PC_RAMP_TICKS;
    }
    double bpc = S->pc_damping * rate;
    for (int32_t x = 0; x < na; x++) {
        int32_t l = S->active[x];
        cstate *st = &S->st[l];
        const lres *R = &S->res[l];
        const geom *g = &S->geo[l];
        const double Nx = g->N[0], Ny = g->N[1], Nz = g->N[2], lam = g->lam;
        const double *Ki = g->Ki;
        const double gx = g->g[0], gy = g->g[1], gz = g->g[2];
        const double *f = R->f, *u2 = R->u2;
        const double delta = R->delta;
        const int sliding = R->sliding;
        double dpx = st->vel[0], dpy = st->vel[1], dpz = st->vel[2];
        double bx = f[0], by = f[1], bz = f[2];
        double hd = 0.5 * delta * delta;
        bx = bx + hd * gx;
        by = by + hd * gy;
        bz = bz + hd * gz;
        double nkn = nkn_of(g->N, Ki);
        double dn = Nx * dpx + Ny * dpy + Nz * dpz;
        if (nkn == 0.0) return -1;
        double hz = 0.5 * lam / nkn * dn;
        double vx = hz * Nx, vy = hz * Ny, vz = hz * Nz;
        if (!sliding) {
            double den = Ki[0] + Ki[4] + Ki[8] - nkn;
            if (den == 0.0) return -1;
            double ht = lam / den;
            vx = vx + ht * (dpx - dn * Nx);
            vy = vy + ht * (dpy - dn * Ny);
            vz = vz + ht * (dpz - dn * Nz);
        }
        double bv = lam * S->o.damping * rate + bpc;
        vx = vx + bv * dpx;
        vy = vy + bv * dpy;
        vz = vz + bv * dpz;
        double vm = sqrt(vx * vx + vy * vy + vz * vz);
        double fm = 0.5 * sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2]);
        if (vm > fm) {
            double c = fm / vm;
            vx = c * vx;
            vy = c * vy;
            vz = c * vz;
        }
        bx = bx + vx;
        by = by + vy;
        bz = bz + vz;
        if (!(isfinite(bx) && isfinite(by) && isfinite(bz))) return -1;
        st->body_force[0] = bx;
        st->body_force[1] = by;
        st->body_force[2] = bz;
        st->force[0] = st->good_force[0] = -bx;
        st->force[1] = st->good_force[1] = -by;
        st->force[2] = st->good_force[2] = -bz;
        st->u_bar[0] = R->total[0];
        st->u_bar[1] = R->total[1];
        st->u_bar[2] = R->total[2];
        st->depth = delta;
        st->taper = lam;
        st->sliding = sliding;
        st->status = lam >= 1.0 - 1e-9 ? PM_CONTACT : PM_REGION_EDGE;
        if (sliding && !frictionless) {
            double mx = R->ueff[0] - u2[0], my = R->ueff[1] - u2[1], mz = R->ueff[2] - u2[2];
            double mn = mx * Nx + my * Ny + mz * Nz;
            mx = mx - mn * Nx;
            my = my - mn * Ny;
            mz = mz - mn * Nz;
            st->anchor[0] = st->anchor[0] + mx;
            st->anchor[1] = st->anchor[1] + my;
            st->anchor[2] = st->anchor[2] + mz;
            st->slip += sqrt(mx * mx + my * my + mz * mz);
        } else if (!sliding) {
            st->slip = 0.0;
        }
    }
    S->energy = energy;
    return 0;
}

static void seq_begin(uint64_t *seq)
{
    uint64_t s = __atomic_load_n(seq, __ATOMIC_RELAXED);
    __atomic_store_n(seq, s + 1, __ATOMIC_RELAXED);
    __atomic_thread_fence(__ATOMIC_RELEASE);
}

static void seq_end(uint64_t *seq)
{
    uint64_t s = __atomic_load_n(seq, __ATOMIC_RELAXED);
    __atomic_store_n(seq, s + 1, __ATOMIC_RELEASE);
}

static void publish_stats(pm_servo *s, const pm_tick_stats *stats)
{
    const pm_table *tb = s->tab;
    seq_begin(&s->out_seq);
    if (stats) s->stats = *stats;
    for (int32_t l = 0; l < s->n; l++) {
        const cstate *st = &s->st[l];
        pm_contact_state *o = &s->pub[l];
        for (int a = 0; a < 3; a++) {
            o->force[a] = st->force[a];
            o->body_force[a] = st->body_force[a];
            o->u_bar[a] = st->u_bar[a];
            o->bary[a] = st->b[a];
            s->pub_forces[3 * l + a] = st->force[a];
        }
        if (st->tri >= 0) {
            point_at(tb, st->tri, st->b, o->point);
        } else {
            o->point[0] = o->point[1] = o->point[2] = NAN;
        }
        o->depth = st->depth;
        o->taper = st->taper;
        o->triangle = st->tri;
        o->status = st->status;
        o->in_contact = st->in_contact;
        o->sliding = st->sliding;
        o->pad = 0;
        s->pub_status[l] = st->status;
    }
    seq_end(&s->out_seq);
}

static void publish(pm_servo *s) { publish_stats(s, NULL); }

void pm_servo_step(pm_servo *s, const double *probes, double *forces, int32_t *status)
{
    if (s->running) {  /* the servo's own thread runs the step: report its latest results instead */
        read_published(s, 0, NULL, forces, status, NULL);
        return;
    }
    if (step_inner(s, probes)) {
        for (int32_t l = 0; l < s->n; l++) hold(s, &s->st[l], PM_INTERNAL_ERROR);
    }
    for (int32_t l = 0; l < s->n; l++) {
        if (forces) {
            forces[3 * l] = s->st[l].force[0];
            forces[3 * l + 1] = s->st[l].force[1];
            forces[3 * l + 2] = s->st[l].force[2];
        }
        if (status) status[l] = s->st[l].status;
    }
    publish(s);
}

/* a consistent copy of the published results (never waits on the tick for long: it writes ~100 ns) */
static void read_published(pm_servo *s, int32_t k, pm_contact_state *one, double *forces, int32_t *status,
                           pm_tick_stats *stats)
{
    for (;;) {
        uint64_t a = __atomic_load_n(&s->out_seq, __ATOMIC_ACQUIRE);
        if (a & 1u) continue;
        if (one) memcpy(one, &s->pub[k], sizeof *one);
        if (forces) memcpy(forces, s->pub_forces, 3 * (size_t)s->n * sizeof(double));
        if (status) memcpy(status, s->pub_status, (size_t)s->n * sizeof(int32_t));
        if (stats) memcpy(stats, &s->stats, sizeof *stats);
        __atomic_thread_fence(__ATOMIC_ACQUIRE);
        if (__atomic_load_n(&s->out_seq, __ATOMIC_RELAXED) == a) return;
    }
}

void pm_servo_state(pm_servo *s, int32_t k, pm_contact_state *out)
{
    if (k < 0 || k >= s->n) {
        memset(out, 0, sizeof *out);
        out->triangle = -1;
        return;
    }
    read_published(s, k, out, NULL, NULL, NULL);
}

void pm_servo_read(pm_servo *s, double *forces, int32_t *status, pm_tick_stats *stats)
{
    read_published(s, 0, NULL, forces, status, stats);
}

void pm_servo_set_probes(pm_servo *s, const double *probes)
{
    seq_begin(&s->in_seq);
    memcpy(s->in_probes, probes, 3 * (size_t)s->n * sizeof(double));
    seq_end(&s->in_seq);
}

/* ------------------------------------------------------------------ display */
int pm_servo_deformation(pm_servo *s, double *out)
{
    const pm_table *tb = s->tab;
    if (!tb->zeta) return -1;
    const int32_t n = s->n;
    /* a snapshot of the published contacts (consistent per contact under the sequence lock) */
    int32_t na = 0;
    int64_t tri[64];
    double b[64][3], u[64][3], f[64][3];
    for (int32_t l = 0; l < n; l++) {
        pm_contact_state one;
        read_published(s, l, &one, NULL, NULL, NULL);
        if (one.status == PM_CONTACT || one.status == PM_REGION_EDGE) {
            tri[na] = one.triangle;
            memcpy(b[na], one.bary, sizeof b[na]);
            memcpy(u[na], one.u_bar, sizeof u[na]);
            f[na][0] = -one.force[0];
            f[na][1] = -one.force[1];
            f[na][2] = -one.force[2];
            na++;
        }
    }
    const int64_t nv = tb->nv;
    for (int64_t i = 0; i < 3 * nv; i++) out[i] = 0.0;
    if (na == 0) return 0;
    /* C_disp f = ū' (Gaussian elimination with partial pivoting), or the rendered forces if singular */
    const int64_t m = 3 * (int64_t)na;
    double *A = s->dC, *x = s->du;
    for (int32_t i = 0; i < na; i++)
        for (int32_t j = 0; j < na; j++) {
            double C[9];
            compliance(tb, tri[i], b[i], tri[j], b[j], C);
            for (int r = 0; r < 3; r++)
                for (int c = 0; c < 3; c++) A[(3 * i + r) * m + 3 * j + c] = C[3 * r + c];
        }
    for (int32_t i = 0; i < na; i++)
        for (int r = 0; r < 3; r++) x[3 * i + r] = u[i][r];
    int singular = 0;
    for (int64_t k = 0; k < m && !singular; k++) {
        int64_t piv = k;
        for (int64_t i = k + 1; i < m; i++)
            if (fabs(A[i * m + k]) > fabs(A[piv * m + k])) piv = i;
        if (A[piv * m + k] == 0.0) {
            singular = 1;
            break;
        }
        if (piv != k) {
            for (int64_t j = 0; j < m; j++) {
                double tmp = A[k * m + j];
                A[k * m + j] = A[piv * m + j];
                A[piv * m + j] = tmp;
            }
            double tmp = x[k];
            x[k] = x[piv];
            x[piv] = tmp;
        }
        for (int64_t i = k + 1; i < m; i++) {
            double q = A[i * m + k] / A[k * m + k];
            for (int64_t j = k; j < m; j++) A[i * m + j] -= q * A[k * m + j];
            x[i] -= q * x[k];
        }
    }
    if (!singular)
        for (int64_t i = m - 1; i >= 0; i--) {
            double acc = x[i];
            for (int64_t j = i + 1; j < m; j++) acc -= A[i * m + j] * x[j];
            x[i] = acc / A[i * m + i];
        }
    for (int64_t i = 0; i < m; i++)
        if (!isfinite(x[i])) singular = 1;
    if (singular)
        for (int32_t i = 0; i < na; i++)
            for (int r = 0; r < 3; r++) x[3 * i + r] = f[i][r];
    /* eq. 16: v(contact vertex) += Σ_loads Σ_k φ_k (f @ Zt[3 row_k : 3 row_k + 3]) */
    const int64_t n3 = 3 * tb->nc;
    for (int64_t v = 0; v < nv; v++) {
        int64_t rv = tb->row[v];
        if (rv < 0) continue;
        double acc[3] = {0.0, 0.0, 0.0};
        for (int32_t i = 0; i < na; i++) {
            const int64_t *tv = tb->T + 3 * tri[i];
            for (int k = 0; k < 3; k++) {
                int64_t rm = tb->row[tv[k]];
                double phi = b[i][k];
                if (phi == 0.0 || rm < 0) continue;
                const double *Z = tb->zeta + 3 * rm * n3 + 3 * rv;
                double fx = phi * x[3 * i], fy = phi * x[3 * i + 1], fz = phi * x[3 * i + 2];
                for (int c = 0; c < 3; c++) acc[c] += fx * Z[c] + fy * Z[n3 + c] + fz * Z[2 * n3 + c];
            }
        }
        out[3 * v] = acc[0];
        out[3 * v + 1] = acc[1];
        out[3 * v + 2] = acc[2];
    }
    return 0;
}

/* ------------------------------------------------------------------ thread mode */
#if PM_THREADS
static double now_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

static void sleep_until(double t)
{
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

static void *servo_thread(void *arg)
{
    pm_servo *s = arg;
    const double T = s->period;
    double next = now_s() + T;
    const double spin = s->spin < T ? s->spin : 0.5 * T;
    for (int64_t k = 0;; k++) {
        if (spin > 0.0) {  /* sleep to just before the tick, then spin to it */
            sleep_until(next - spin);
            while (now_s() < next) {
            }
        } else {
            sleep_until(next);
        }
        if (__atomic_load_n(&s->stop_flag, __ATOMIC_ACQUIRE)) break;
        double begin = now_s();
        if (s->has_io) {
            s->io.read(s->io.user, s->tick_probes);
        } else {  /* the probes last set: a consistent copy, or last tick's if a writer is mid-way */
            for (int attempt = 0; attempt < 4; attempt++) {
                uint64_t a = __atomic_load_n(&s->in_seq, __ATOMIC_ACQUIRE);
                if (a & 1u) continue;
                memcpy(s->tick_probes, s->in_probes, 3 * (size_t)s->n * sizeof(double));
                __atomic_thread_fence(__ATOMIC_ACQUIRE);
                if (__atomic_load_n(&s->in_seq, __ATOMIC_RELAXED) == a) break;
            }
        }
        if (step_inner(s, s->tick_probes))
            for (int32_t l = 0; l < s->n; l++) hold(s, &s->st[l], PM_INTERNAL_ERROR);
        for (int32_t l = 0; l < s->n; l++) {
            s->tick_forces[3 * l] = s->st[l].force[0];
            s->tick_forces[3 * l + 1] = s->st[l].force[1];
            s->tick_forces[3 * l + 2] = s->st[l].force[2];
            s->tick_status[l] = s->st[l].status;
        }
        if (s->has_io) s->io.write(s->io.user, s->tick_forces, s->tick_status);
        double end = now_s();
        /* the statistics are published with the state */
        pm_tick_stats st = s->stats;
        st.ticks += 1;
        double lateness = begin - next;
        if (end > next + T) st.late += 1;   /* the force was not ready within its own period */
        if (lateness > st.max_lateness) st.max_lateness = lateness;
        if (end - begin > st.step_max) st.step_max = end - begin;
        next += T;
        if (end > next) {  /* fell behind: skip the missed ticks (counted late), keep the schedule's phase */
            double behind = floor((end - next) / T) + 1.0;
            st.late += (int64_t)behind;
            next += behind * T;
        }
        publish_stats(s, &st);
    }
    return NULL;
}
#endif

int pm_servo_start(pm_servo *s, double rate, double spin, const pm_io *io)
{
#if PM_THREADS
    if (s->running) return -1;
    if (!(isfinite(rate) && rate > 0.0 && rate <= 100000.0 && isfinite(spin) && spin >= 0.0 && spin <= 0.01)) return -2;
    if (io && (!io->read || !io->write)) return -3;
    s->period = 1.0 / rate;
    s->spin = spin;
    s->has_io = io != NULL;
    if (io) s->io = *io;
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
    s->running = 1;
    return 0;
#else
    (void)s;
    (void)rate;
    (void)spin;
    (void)io;
    return -5;
#endif
}

void pm_servo_stop(pm_servo *s)
{
#if PM_THREADS
    if (!s->running) return;
    __atomic_store_n(&s->stop_flag, 1, __ATOMIC_RELEASE);
    pthread_join(s->thread, NULL);
    s->running = 0;
#else
    (void)s;
#endif
}

int32_t pm_servo_running(const pm_servo *s) { return s->running; }

int32_t pm_servo_count(const pm_servo *s) { return s->n; }
