/* pmask servo core: loading and checking a runtime table (format in pmask/runtime/table.py). */
#include "pm_internal.h"

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

enum { DT_F64 = PM_SECTION_F64, DT_I64 = PM_SECTION_I64, DT_BYTES = PM_SECTION_BYTES };
#define HEADER_SIZE 64
#define ENTRY_SIZE 64
#define NAME_SIZE 32

static int find_section(const pm_section *secs, int32_t nsec, const char *name, section *out)
{
    memset(out, 0, sizeof *out);
    for (int32_t i = 0; i < nsec; i++) {
        if (secs[i].name && strncmp(secs[i].name, name, NAME_SIZE) == 0) {
            out->dtype = (uint32_t)secs[i].dtype;
            out->data = (const unsigned char *)secs[i].data;
            out->rows = (uint64_t)secs[i].rows;
            out->cols = (uint64_t)secs[i].cols;
            out->found = 1;
            return 1;
        }
    }
    return 0;
}

/* a required (or, with optional, possibly absent) section of the given type and shape; rows < 0: any */
int pm__want(const pm_section *secs, int32_t nsec, const char *name, uint32_t dtype, int64_t rows, int64_t cols,
             int optional, section *s, char *err, size_t errlen)
{
    if (!find_section(secs, nsec, name, s)) {
        if (optional) return 0;
        fmt(err, errlen, "not a complete runtime table: section '%s' is missing (a table from an older pmask, or a "
            "damaged one: export it again with `pmask export-table`)", name, 0, 0);
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




static int assign(const pm_section *secs, int32_t nsec, unsigned char *blob, size_t size, pm_table **out,
                  char *err, size_t errlen);

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
    /* the directory as sections (names copied: a directory entry's name need not end in a zero) */
    pm_section *secs = calloc(nsec ? nsec : 1, sizeof *secs);
    char *names = calloc(nsec ? nsec : 1, NAME_SIZE + 1);
    if (!secs || !names) {
        free(secs);
        free(names);
        fmt(err, errlen, "out of memory loading the runtime table", NULL, 0, 0);
        return -1;
    }
    for (uint32_t i = 0; i < nsec; i++) {
        const unsigned char *e = blob + HEADER_SIZE + (size_t)i * ENTRY_SIZE;
        char *name = names + (size_t)i * (NAME_SIZE + 1);
        memcpy(name, e, NAME_SIZE);
        secs[i].name = name;
        secs[i].dtype = (int32_t)rd32(e + 32);
        secs[i].data = blob + rd64(e + 40);
        secs[i].rows = (int64_t)rd64(e + 48);
        secs[i].cols = (int64_t)rd64(e + 56);
    }
    int rc = assign(secs, (int32_t)nsec, blob, size, out, err, errlen);
    free(secs);
    free(names);
    return rc;
}

/* the table's fields from its sections, each checked (types, shapes, indices in range, finite numbers,
 * positive definite K); blob (may be NULL) becomes the table's on success */
static int assign(const pm_section *secs, int32_t nsec, unsigned char *blob, size_t size, pm_table **out,
                  char *err, size_t errlen)
{
    pm_table *t = calloc(1, sizeof *t);
    if (!t) {
        fmt(err, errlen, "out of memory loading the runtime table", NULL, 0, 0);
        return -1;
    }
    section s;
    t->blob = blob;
    t->size = size;
#define NEED(name, dt, r, cl, opt) \
    if (pm__want(secs, nsec, name, dt, r, cl, opt, &s, err, errlen)) goto bad
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
    NEED("normal_stiffness", DT_F64, t->nv, 1, 0);
    t->kn = (const double *)s.data;
    NEED("gradient", DT_F64, t->nv, 1 * 3, 0);
    t->grad = (const double *)s.data;
    NEED("shape", DT_F64, t->nv, 9, 0);
    t->shape = (const double *)s.data;
    NEED("linear_depth", DT_F64, t->nv, 1, 0);
    t->dlin = (const double *)s.data;
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
        !all_finite(t->kn, (uint64_t)t->nv) || !all_finite(t->shape, 9 * (uint64_t)t->nv) ||
        !all_finite(t->dlin, (uint64_t)t->nv) ||
        !all_finite(t->lo, 3) || !all_finite(t->hi, 3) || !all_finite(&t->mean_edge, 1) || !all_finite(&t->diag, 1)) {
        fmt(err, errlen, "corrupt runtime table: a non-finite number", NULL, 0, 0);
        goto bad;
    }
    for (int64_t v = 0; v < t->nv; v++) {
        if (t->taper[v] < 0.0 || t->taper[v] > 1.0) {
            fmt(err, errlen, "corrupt runtime table: taper outside [0, 1] at vertex %s%lld", NULL, (long long)v, 0);
            goto bad;
        }
        if (t->kn[v] < 0.0 || !(t->dlin[v] > 0.0)) {
            fmt(err, errlen, "corrupt runtime table: a negative normal stiffness or a linear depth that is not "
                "positive (vertex %s%lld)", NULL, (long long)v, 0);
            goto bad;
        }
        if (!spd3(t->K + 9 * v)) {
            fmt(err, errlen, "runtime table: the stiffness at surface vertex %s%lld is not positive definite (a "
                "corrupt or hand-edited table; export it again from a checked artifact)", NULL, (long long)v, 0);
            goto bad;
        }
    }
    t->nm = t->nv;
    t->nmt = t->nt;
    t->mT = t->T;
    if (pm__want(secs, nsec, "mesh_triangles", DT_I64, -1, 3, 1, &s, err, errlen)) goto bad;
    if (s.found) {  /* a subdivided contact surface: its map to the mesh, checked */
        t->nmt = (int64_t)s.rows;
        t->mT = (const int64_t *)s.data;
        NEED("parent", DT_I64, t->nt, 1, 0);
        t->parent = (const int64_t *)s.data;
        NEED("corners", DT_F64, t->nt, 9, 0);
        t->corners = (const double *)s.data;
        if (t->nmt < 1 || !in_range(t->mT, 3 * (uint64_t)t->nmt, 0, INT64_MAX) ||
            !in_range(t->parent, (uint64_t)t->nt, 0, t->nmt)) {
            fmt(err, errlen, "corrupt runtime table: a mesh triangle index is out of range", NULL, 0, 0);
            goto bad;
        }
        int64_t top = 0;
        for (int64_t i = 0; i < 3 * t->nmt; i++)
            if (t->mT[i] > top) top = t->mT[i];
        t->nm = top + 1;
        for (int64_t i = 0; i < t->nt; i++) {
            const double *c = t->corners + 9 * i;
            for (int k = 0; k < 3; k++) {
                const double sum = c[3 * k] + c[3 * k + 1] + c[3 * k + 2];
                int ok = fabs(sum - 1.0) <= 1e-8;
                for (int j = 0; j < 3; j++) ok = ok && c[3 * k + j] >= 0.0 && c[3 * k + j] <= 1.0;
                if (!ok) {
                    fmt(err, errlen, "corrupt runtime table: the corners' barycentrics are not in [0, 1] summing "
                        "to 1", NULL, 0, 0);
                    goto bad;
                }
            }
        }
    } else {
        for (int i = 0; i < 2; i++) {
            const char *name = i ? "corners" : "parent";
            if (pm__want(secs, nsec, name, i ? DT_F64 : DT_I64, -1, -1, 1, &s, err, errlen)) goto bad;
            if (s.found) {
                fmt(err, errlen, "not a complete runtime table: 'mesh_triangles', 'parent' and 'corners' go "
                    "together (export it again)", NULL, 0, 0);
                goto bad;
            }
        }
    }
    if (pm__want(secs, nsec, "zeta", DT_F64, -1, -1, 1, &s, err, errlen)) goto bad;
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
    } else {  /* a compressed Ξ's own sections instead (table 1.4), when present */
        if (pm__greens_assign(t, secs, nsec, err, errlen)) goto bad;
        t->nc = t->xi.n;
    }
    if (t->zeta || t->xi.n) {
        NEED("contact_row", DT_I64, t->nm, 1, 0);
        t->row = (const int64_t *)s.data;
        if (!in_range(t->row, (uint64_t)t->nm, -1, t->nc)) {
            fmt(err, errlen, "corrupt runtime table: a contact row is out of range", NULL, 0, 0);
            goto bad;
        }
    }
    if (pm__want(secs, nsec, "display_points", DT_F64, -1, 3, 1, &s, err, errlen)) goto bad;
    if (s.found) {  /* the display surface (optional): all five sections, checked */
        t->nd = (int64_t)s.rows;
        t->dP = (const double *)s.data;
        NEED("display_triangles", DT_I64, -1, 3, 0);
        t->ndt = (int64_t)s.rows;
        t->dT = (const int64_t *)s.data;
        NEED("display_vertices", DT_I64, t->nd, 3, 0);
        t->dV = (const int64_t *)s.data;
        NEED("display_bary", DT_F64, t->nd, 3, 0);
        t->dbary = (const double *)s.data;
        NEED("display_lift", DT_F64, t->nd, 3, 0);
        t->dlift = (const double *)s.data;
        if (!in_range(t->dT, 3 * (uint64_t)t->ndt, 0, t->nd) || !in_range(t->dV, 3 * (uint64_t)t->nd, 0, t->nm)) {
            fmt(err, errlen, "corrupt runtime table: a display index is out of range", NULL, 0, 0);
            goto bad;
        }
        if (!all_finite(t->dP, 3 * (uint64_t)t->nd) || !all_finite(t->dbary, 3 * (uint64_t)t->nd) ||
            !all_finite(t->dlift, 3 * (uint64_t)t->nd)) {
            fmt(err, errlen, "corrupt runtime table: a non-finite number in the display surface", NULL, 0, 0);
            goto bad;
        }
    }
    if (pm__want(secs, nsec, "meta", DT_BYTES, -1, 1, 1, &s, err, errlen)) goto bad;
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
    if (pm__build_bvh(t)) {
        fmt(err, errlen, "out of memory building the runtime table's spatial index", NULL, 0, 0);
        goto bad;
    }
    *out = t;
    return 0;
bad:
    t->blob = NULL;  /* the caller frees the blob */
    pm__free_bvh(t);
    pm__greens_free(t);
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

int pm_table_from_sections(const pm_section *sections, int32_t n, pm_table **out, char *err, size_t errlen)
{
    *out = NULL;
    if (!host_little_endian()) {
        fmt(err, errlen, "runtime tables are little-endian; this host is big-endian (unsupported)", NULL, 0, 0);
        return -1;
    }
    if (n < 0 || (n > 0 && !sections)) {
        fmt(err, errlen, "pm_table_from_sections: no sections given", NULL, 0, 0);
        return -1;
    }
    for (int32_t i = 0; i < n; i++) {
        const pm_section *s = sections + i;
        const char *name = s->name ? s->name : "(unnamed)";
        if (!s->name || strlen(s->name) >= NAME_SIZE) {
            fmt(err, errlen, "pm_table_from_sections: section %s%lld has no name of at most 31 characters", NULL,
                (long long)i, 0);
            return -1;
        }
        if (s->dtype != DT_F64 && s->dtype != DT_I64 && s->dtype != DT_BYTES) {
            fmt(err, errlen, "pm_table_from_sections: section '%s' has an unknown type %lld", name,
                (long long)s->dtype, 0);
            return -1;
        }
        uint64_t item = s->dtype == DT_BYTES ? 1 : 8;
        if (s->rows < 0 || s->cols < 0 ||
            (s->cols != 0 && (uint64_t)s->rows > (uint64_t)PTRDIFF_MAX / (uint64_t)s->cols / 8)) {
            fmt(err, errlen, "pm_table_from_sections: section '%s' has a bad shape (%lld x %lld)", name,
                (long long)s->rows, (long long)s->cols);
            return -1;
        }
        if ((uint64_t)s->rows * (uint64_t)s->cols * item > 0 && !s->data) {
            fmt(err, errlen, "pm_table_from_sections: section '%s' has no data", name, 0, 0);
            return -1;
        }
        if (item == 8 && (uintptr_t)s->data % 8 != 0) {
            fmt(err, errlen, "pm_table_from_sections: section '%s' is not aligned to 8 bytes", name, 0, 0);
            return -1;
        }
    }
    return assign(sections, n, NULL, 0, out, err, errlen);
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
    pm__free_bvh(t);
    pm__greens_free(t);
    free(t->blob);
    free(t->meta);
    free(t);
}

int64_t pm_table_vertices(const pm_table *t) { return t->nm; }
int64_t pm_table_triangles(const pm_table *t) { return t->nmt; }
const double *pm_table_points(const pm_table *t) { return t->P; }  /* the mesh's vertices come first (table 1.3) */
int32_t pm_table_has_zeta(const pm_table *t) { return t->zeta != NULL; }
int32_t pm_table_has_greens(const pm_table *t) { return t->zeta != NULL || t->xi.n > 0; }
int64_t pm_display_vertices(const pm_table *t) { return t->nd; }
int64_t pm_display_triangles(const pm_table *t) { return t->ndt; }
const double *pm_display_points(const pm_table *t) { return t->dP; }
const int64_t *pm_display_triangle_indices(const pm_table *t) { return t->dT; }
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

