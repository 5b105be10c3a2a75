/* pmask servo core: a compressed Ξ's own sections in a runtime table (table 1.4; 1.5 as the artifact stores
 * them), and the coupling blocks of a pair of mesh triangles formed from them
 * (pmask.runtime.compressed.MaskedXi.block, ContactSurface.pair_blocks).
 *
 * A table exported from a compressed artifact has no ζ table (as large as dense Ξ: 28 GiB at 20,000 contact
 * vertices) but Ξ as the artifact stores it: the contact vertices in cluster order, blocks over pairs of leaf
 * clusters, the dense ones pair by pair (the pairs within r_max exact, the others as 16-bit multiples of a scale
 * per column; from table 1.5 the exact ones in 48-bit fixed point, as format 1.7 stores them), the far ones as
 * U Vᵀ (float32 or float64; from table 1.5 int16 words times a float32 scale per column of each block, as format
 * 1.8 stores them), and a lookup from a pair of leaves to its block; with the core masks ρ^m by contact vertex.
 * When two coupled contacts land on a new pair of triangles the servo asks for their nine vertex-pair blocks
 * (pm_servo_create_paired's pair function); this one reads ζ_m(i) = Σ_j ρ^m_j Ξ_ij (eq. 13) for each, the mask's
 * size in 3x3 blocks of Ξ, whatever n.  Everything is checked at load, so that a lookup can only land in the
 * block that holds the pair. */
#include "pm_internal.h"

static int bad(char *err, size_t errlen, const char *what)
{
    if (err && errlen)
        snprintf(err, errlen, "corrupt runtime table: the compressed Green's functions %s (export it again)", what);
    return -1;
}

static int popcount8(unsigned char b) { return __builtin_popcount((unsigned)b); }

/* exact pairs in bytes [from, to) of the pair masks */
static int64_t ones(const unsigned char *m, int64_t from, int64_t to)
{
    int64_t k = 0;
    for (int64_t i = from; i < to; i++) k += popcount8(m[i]);
    return k;
}

/* factor value i, in column j of its block, whose column scales (item 2) start at sc: a 16-bit word times its
 * column's scale in float32, then widened, as pmask.runtime.compressed.Far16 decodes it (numpy's int16 x float32
 * is a float32 product: the same number, bit for bit; -ffp-contract=off keeps it a product) */
static double factor(const pm_greens *x, const unsigned char *base, const unsigned char *sc, int64_t i, int64_t j)
{
    if (x->item == 2) {
        float f;
        memcpy(&f, sc + 4 * j, 4);
        int16_t q;
        memcpy(&q, base + 2 * i, 2);
        const float v = (float)q * f;
        return (double)v;
    }
    if (x->item == 4) {
        float f;
        memcpy(&f, base + 4 * i, 4);
        return (double)f;
    }
    double d;
    memcpy(&d, base + 8 * i, 8);
    return d;
}

/* the nine values of exact pair k (pmask.runtime.compressed.unpack_exact, bit for bit): each a 48-bit integer
 * (three little-endian words, sign-extended) times 2^(e - 46), e the pair's 28th word as int16; an integer below
 * 2^48 is a double exactly and ldexp's power of two is exact where the result is normal, and rounds as numpy's
 * ldexp where it is not */
#define EXACT_BITS 46
#define PAIR_WORDS 28
/* the exponents a pair's 28th word may hold (pmask.runtime.compressed.EXACT_EXPONENTS) */
#define EXACT_EMIN (-1074)
#define EXACT_EMAX 1023
static void exact_pair(const pm_greens *x, int64_t k, double *out)
{
    const unsigned char *w = x->exact48 + 2 * PAIR_WORDS * k;
    int16_t e;
    memcpy(&e, w + 2 * 27, 2);
    for (int v = 0; v < 9; v++) {
        const unsigned char *b = w + 6 * v;
        uint64_t u = (uint64_t)b[0] | (uint64_t)b[1] << 8 | (uint64_t)b[2] << 16 | (uint64_t)b[3] << 24 |
                     (uint64_t)b[4] << 32 | (uint64_t)b[5] << 40;
        if (u >> 47) u |= 0xFFFF000000000000u;  /* the sign of the 48-bit integer */
        int64_t m;
        memcpy(&m, &u, 8);
        out[v] = ldexp((double)m, (int)e - EXACT_BITS);
    }
}

/* the exact pairs' values from value offset off (a multiple of nine), pair by pair */
static void exact_values(const pm_greens *x, int64_t off, double *out)
{
    if (x->exact48)
        exact_pair(x, off / 9, out);
    else
        memcpy(out, x->exact + off, 9 * sizeof *out);
}

/* stored block b's column scales in U's or V's (16-bit factors), NULL for float factors */
static const unsigned char *far_scales(const pm_greens *x, const unsigned char *scales, int64_t b)
{
    return x->so ? scales + 4 * x->so[b - x->nd] : NULL;
}

static int16_t q16(const unsigned char *base, int64_t i)
{
    int16_t v;
    memcpy(&v, base + 2 * i, 2);
    return v;
}

static int finite_run(const double *a, uint64_t n)
{
    for (uint64_t i = 0; i < n; i++)
        if (!isfinite(a[i])) return 0;
    return 1;
}

/* a stored block's box: r0, r1, c0, c1 (positions) */
static const int64_t *box_of(const pm_greens *x, int64_t b)
{
    return b < x->nd ? x->dense_index + 5 * b : x->lowrank_index + 7 * (b - x->nd);
}

int pm__greens_assign(pm_table *t, const pm_section *secs, int32_t nsec, char *err, size_t errlen)
{
    pm_greens *x = &t->xi;
    memset(x, 0, sizeof *x);
    section s;
    if (pm__want(secs, nsec, "xi_info", PM_SECTION_I64, 1, 3, 1, &s, err, errlen)) return -1;
    if (!s.found) return 0;
    int64_t info[3];
    memcpy(info, s.data, sizeof info);
    const int64_t n = info[0];
    if (n < 1 || (info[1] != 2 && info[1] != 4 && info[1] != 8) || (info[2] != 0 && info[2] != 1))
        return bad(err, errlen, "have a bad header");
    x->item = info[1];
    x->symmetric = (int)info[2];
#define SEC(name, dt, rows, cols) \
    if (pm__want(secs, nsec, name, dt, rows, cols, 0, &s, err, errlen)) return -1
    SEC("xi_leaves", PM_SECTION_I64, -1, 1);
    x->leaves = (const int64_t *)s.data;
    x->nleaves = (int64_t)s.rows - 1;
    SEC("xi_scale", PM_SECTION_F64, x->symmetric ? n : 0, 1);
    x->scale = (const double *)s.data;
    SEC("xi_dense_index", PM_SECTION_I64, -1, 5);
    x->dense_index = (const int64_t *)s.data;
    x->nd = (int64_t)s.rows;
    SEC("xi_near_index", PM_SECTION_I64, x->nd, 3);
    x->near_index = (const int64_t *)s.data;
    SEC("xi_near_exact", PM_SECTION_F64, -1, 1);
    x->exact = (const double *)s.data;
    int64_t nexact = (int64_t)s.rows;
    section e48;  /* (table 1.5: the exact pairs in fixed point, in place of float64) */
    if (pm__want(secs, nsec, "xi_near_exact48", PM_SECTION_BYTES, -1, 1, 1, &e48, err, errlen)) return -1;
    x->exact48 = NULL;
    if (e48.found) {
        if (nexact || e48.rows % (2 * PAIR_WORDS)) return bad(err, errlen, "have a bad header");
        x->exact48 = e48.data;
        nexact = (int64_t)(e48.rows / (2 * PAIR_WORDS)) * 9;
    }
    SEC("xi_near_mask", PM_SECTION_BYTES, -1, 1);
    x->mask = s.data;
    const int64_t nmask = (int64_t)s.rows;
    SEC("xi_near_q", PM_SECTION_BYTES, -1, 1);
    x->q = s.data;
    const int64_t nq = (int64_t)s.rows / 2;
    SEC("xi_near_scale", PM_SECTION_F64, -1, 1);
    x->qscale = (const double *)s.data;
    const int64_t nqscale = (int64_t)s.rows;
    SEC("xi_lowrank_index", PM_SECTION_I64, -1, 7);
    x->lowrank_index = (const int64_t *)s.data;
    x->nl = (int64_t)s.rows;
    SEC("xi_U", PM_SECTION_BYTES, -1, 1);
    x->U = s.data;
    const int64_t nU = (int64_t)s.rows / x->item;
    if ((int64_t)s.rows % x->item) return bad(err, errlen, "have a bad header");
    SEC("xi_V", PM_SECTION_BYTES, -1, 1);
    x->V = s.data;
    const int64_t nV = (int64_t)s.rows / x->item;
    if ((int64_t)s.rows % x->item) return bad(err, errlen, "have a bad header");
    section us, vs;  /* (table 1.5: with 16-bit factors, their column scales) */
    if (pm__want(secs, nsec, "xi_U_scale", PM_SECTION_BYTES, -1, 1, 1, &us, err, errlen) ||
        pm__want(secs, nsec, "xi_V_scale", PM_SECTION_BYTES, -1, 1, 1, &vs, err, errlen))
        return -1;
    if (x->item == 2 && (!us.found || !vs.found)) {
        if (err && errlen)
            snprintf(err, errlen, "not a complete runtime table: section '%s' is missing (a damaged table: export it "
                     "again with `pmask export-table`)", us.found ? "xi_V_scale" : "xi_U_scale");
        return -1;
    }
    x->Us = us.found ? us.data : NULL;
    x->Vs = vs.found ? vs.data : NULL;
    SEC("xi_owner", PM_SECTION_I64, -1, 3);
    x->owner = (const int64_t *)s.data;
    x->nowner = (int64_t)s.rows;
    SEC("mask_ptr", PM_SECTION_I64, n + 1, 1);
    x->mask_ptr = (const int64_t *)s.data;
    SEC("mask_cols", PM_SECTION_I64, -1, 1);
    x->mask_cols = (const int64_t *)s.data;
    const int64_t ncols = (int64_t)s.rows;
    SEC("mask_weights", PM_SECTION_F64, ncols, 1);
    x->mask_w = (const double *)s.data;
    SEC("xi_perm", PM_SECTION_I64, n, 1);
    const int64_t *perm = (const int64_t *)s.data;
#undef SEC
    /* the permutation, and the leaves (increasing from 0 to n) */
    x->position = malloc((size_t)n * sizeof *x->position);
    x->leaf_of = malloc((size_t)n * sizeof *x->leaf_of);
    if (!x->position || !x->leaf_of) {
        if (err && errlen) snprintf(err, errlen, "out of memory loading the runtime table");
        return -1;
    }
    for (int64_t i = 0; i < n; i++) x->position[i] = -1;
    for (int64_t p = 0; p < n; p++) {
        if (perm[p] < 0 || perm[p] >= n || x->position[perm[p]] >= 0)
            return bad(err, errlen, "do not order their vertices");
        x->position[perm[p]] = p;
    }
    const int64_t L = x->nleaves;
    if (L < 1 || x->leaves[0] != 0 || x->leaves[L] != n) return bad(err, errlen, "do not cluster their vertices");
    for (int64_t l = 0; l < L; l++) {
        if (x->leaves[l + 1] <= x->leaves[l]) return bad(err, errlen, "do not cluster their vertices");
        for (int64_t p = x->leaves[l]; p < x->leaves[l + 1]; p++) x->leaf_of[p] = l;
    }
    /* every block inside the vertices, its values inside their arrays */
    for (int64_t b = 0; b < x->nd + x->nl; b++) {
        const int64_t *k = box_of(x, b);
        if (k[0] < 0 || k[1] > n || k[1] <= k[0] || k[2] < 0 || k[3] > n || k[3] <= k[2])
            return bad(err, errlen, "have a block outside their vertices");
        const int64_t m = k[1] - k[0], w = k[3] - k[2];
        if (b < x->nd) {
            const int64_t *ni = x->near_index + 3 * b, pairs = m * w, bytes = (pairs + 7) / 8;
            if (k[4] < 0 || ni[0] < 0 || ni[1] < 0 || ni[2] < 0 || ni[1] > nmask - bytes)
                return bad(err, errlen, "do not match their index");
            const int64_t e = ones(x->mask, ni[1], ni[1] + bytes);
            if (e > pairs || k[4] > nexact - 9 * e || ni[0] > nq - 9 * (pairs - e) || ni[2] > nqscale - 3 * w)
                return bad(err, errlen, "do not match their index");
        } else {
            if (k[4] > x->maxrank) x->maxrank = k[4];
            if (k[4] < 0 || k[5] < 0 || k[6] < 0 || k[5] > nU || k[6] > nV ||
                (k[4] > 0 && (3 * m > (nU - k[5]) / k[4] || 3 * w > (nV - k[6]) / k[4])))
                return bad(err, errlen, "do not match their index");
        }
    }
    /* 16-bit factors: each block's column scales, block after block (pmask.runtime.compressed.far_scale_offsets) */
    if (x->item == 2) {
        x->so = malloc((size_t)(x->nl > 0 ? x->nl : 1) * sizeof *x->so);
        if (!x->so) {
            if (err && errlen) snprintf(err, errlen, "out of memory loading the runtime table");
            return -1;
        }
        int64_t ks = 0;
        for (int64_t l = 0; l < x->nl; l++) {
            x->so[l] = ks;
            ks += x->lowrank_index[7 * l + 4];  /* (each rank at most nU, checked above) */
        }
        if ((int64_t)(us.rows % 4) || (int64_t)(vs.rows % 4) || (int64_t)(us.rows / 4) != ks ||
            (int64_t)(vs.rows / 4) != ks)
            return bad(err, errlen, "do not match their index");
    }
    /* finite values, positive scales */
    if (x->exact48) {  /* every pair's exponent one a double has (unpack_exact's check), every value finite: a
                          value m 2^(e - 46), |m| <= 2^47, can overflow only at e = EXACT_EMAX, so only those are
                          decoded */
        for (int64_t k = 0; k < nexact / 9; k++) {
            int16_t e;
            memcpy(&e, x->exact48 + 2 * PAIR_WORDS * k + 2 * 27, 2);
            if (e > EXACT_EMAX || e < EXACT_EMIN) return bad(err, errlen, "hold an exponent no float64 has");
            double v[9];
            if (e == EXACT_EMAX) {
                exact_pair(x, k, v);
                if (!finite_run(v, 9)) return bad(err, errlen, "hold a non-finite number");
            }
        }
    }
    if ((!x->exact48 && !finite_run(x->exact, (uint64_t)nexact)) || !finite_run(x->qscale, (uint64_t)nqscale) ||
        !finite_run(x->mask_w, (uint64_t)ncols))
        return bad(err, errlen, "hold a non-finite number");
    if (x->item == 2) {  /* every decoded value, as the Python loader checks them (a huge scale overflows) */
        for (int64_t l = 0; l < x->nl; l++) {
            const int64_t *k = x->lowrank_index + 7 * l, rank = k[4];
            const int64_t m = 3 * (k[1] - k[0]) * rank, w = 3 * (k[3] - k[2]) * rank;
            for (int64_t i = 0; i < m; i++)
                if (!isfinite(factor(x, x->U, x->Us + 4 * x->so[l], k[5] + i, i % rank)))
                    return bad(err, errlen, "hold a non-finite number");
            for (int64_t i = 0; i < w; i++)
                if (!isfinite(factor(x, x->V, x->Vs + 4 * x->so[l], k[6] + i, i % rank)))
                    return bad(err, errlen, "hold a non-finite number");
        }
    } else {
        for (int64_t i = 0; i < nU; i++)
            if (!isfinite(factor(x, x->U, NULL, i, 0))) return bad(err, errlen, "hold a non-finite number");
        for (int64_t i = 0; i < nV; i++)
            if (!isfinite(factor(x, x->V, NULL, i, 0))) return bad(err, errlen, "hold a non-finite number");
    }
    for (int64_t i = 0; x->symmetric && i < n; i++)
        if (!(isfinite(x->scale[i]) && x->scale[i] > 0.0)) return bad(err, errlen, "have a scale that is not positive");
    /* the masks: compressed rows by contact vertex, columns among the contact vertices */
    if (x->mask_ptr[0] != 0 || x->mask_ptr[n] != ncols) return bad(err, errlen, "have masks that do not match");
    for (int64_t i = 0; i < n; i++)
        if (x->mask_ptr[i + 1] < x->mask_ptr[i]) return bad(err, errlen, "have masks that do not match");
    for (int64_t j = 0; j < ncols; j++)
        if (x->mask_cols[j] < 0 || x->mask_cols[j] >= n) return bad(err, errlen, "have masks that do not match");
    /* the lookup (CompressedXi._leaf_rows): keys row * L + first leaf column, increasing; each leaf row's blocks
       tile its columns from the first to the last, each once, and hold the row; a flipped entry reads the stored
       block above the diagonal transposed */
#define LOOKUP "have a block lookup that does not match their blocks"
    int64_t row = -1, next = 0;
    for (int64_t e = 0; e < x->nowner; e++) {
        const int64_t *o = x->owner + 3 * e;
        if (o[0] < 0 || o[0] >= L * L || (e > 0 && o[0] <= o[-3]) || o[1] < 0 || o[1] >= x->nd + x->nl ||
            o[2] < 0 || o[2] > (int64_t)x->symmetric)
            return bad(err, errlen, LOOKUP);
        const int64_t r = o[0] / L, c = o[0] % L;
        const int64_t *k = box_of(x, o[1]);
        const int f = o[2] != 0;  /* flipped: the stored block's rows are the pair's columns */
        const int64_t r0 = k[2 * f], r1 = k[2 * f + 1], c0 = k[2 - 2 * f], c1 = k[3 - 2 * f];
        if (r != row) {
            if (r != row + 1 || (row >= 0 && next != n)) return bad(err, errlen, LOOKUP);
            row = r;
            next = 0;
        }
        if (c0 != x->leaves[c] || c0 != next || r0 > x->leaves[r] || r1 < x->leaves[r + 1])
            return bad(err, errlen, LOOKUP);
        next = c1;
    }
    if (row != L - 1 || next != n) return bad(err, errlen, LOOKUP);
#undef LOOKUP
    x->n = n;
    return 0;
}

void pm__greens_free(pm_table *t)
{
    free(t->xi.position);
    free(t->xi.leaf_of);
    free(t->xi.so);
    t->xi.position = t->xi.leaf_of = NULL;
    t->xi.so = NULL;
    t->xi.n = 0;
}

/* Ξ at positions (p, q) from stored block b (cluster order), row-major (CompressedXi._stored and _pairs) */
static void stored(const pm_greens *x, int64_t p, int64_t q, int64_t b, double *out)
{
    if (b < x->nd) {
        const int64_t *k = x->dense_index + 5 * b, *ni = x->near_index + 3 * b;
        const int64_t w = k[3] - k[2], t = (p - k[0]) * w + (q - k[2]), g = 8 * ni[1] + t;
        const unsigned char byte = x->mask[g >> 3];
        const int bit = (int)(g & 7);
        const int64_t before = ones(x->mask, ni[1], g >> 3) + (bit ? popcount8((unsigned char)(byte >> (8 - bit))) : 0);
        if ((byte >> (7 - bit)) & 1) {
            exact_values(x, k[4] + 9 * before, out);
        } else {
            const int64_t at = ni[0] + 9 * (t - before);
            const double *sc = x->qscale + ni[2] + 3 * (q - k[2]);
            for (int r = 0; r < 3; r++)
                for (int c = 0; c < 3; c++) out[3 * r + c] = (double)q16(x->q, at + 3 * r + c) * sc[c];
        }
        return;
    }
    const int64_t *k = x->lowrank_index + 7 * (b - x->nd);
    const int64_t rank = k[4];
    const int64_t u = k[5] + 3 * (p - k[0]) * rank, v = k[6] + 3 * (q - k[2]) * rank;
    const unsigned char *us = far_scales(x, x->Us, b), *vs = far_scales(x, x->Vs, b);
    for (int r = 0; r < 3; r++)
        for (int c = 0; c < 3; c++) {
            double acc = 0.0;
            for (int64_t j = 0; j < rank; j++)
                acc += factor(x, x->U, us, u + r * rank + j, j) * factor(x, x->V, vs, v + c * rank + j, j);
            out[3 * r + c] = acc;
        }
}

/* Ξ_ij (3x3, row-major) for contact vertices i, j (CompressedXi.blocks): the block that holds the pair found from
 * the pair's leaves; below a symmetric form's diagonal, Ξ_ij = (a_j / a_i) Ξ_jiᵀ */
static void xi_block(const pm_greens *x, int64_t i, int64_t j, double *out)
{
    const int64_t p = x->position[i], q = x->position[j], key = x->leaf_of[p] * x->nleaves + x->leaf_of[q];
    int64_t lo = 0, hi = x->nowner - 1;  /* the last entry whose key is at most the pair's (checked at load) */
    while (lo < hi) {
        const int64_t mid = lo + (hi - lo + 1) / 2;
        if (x->owner[3 * mid] <= key) lo = mid; else hi = mid - 1;
    }
    const int64_t *o = x->owner + 3 * lo;
    if (!o[2]) {
        stored(x, p, q, o[1], out);
        return;
    }
    double B[9];
    stored(x, q, p, o[1], B);
    const double s = x->scale[j] / x->scale[i];
    for (int r = 0; r < 3; r++)
        for (int c = 0; c < 3; c++) out[3 * r + c] = B[3 * c + r] * s;
}

/* ζ_m(i) = Σ_j ρ^m_j Ξ_ij (3x3, row-major; MaskedXi.block's transpose), zero where m has no mask */
void pm__greens_zeta(const pm_greens *x, int64_t m, int64_t i, double *Z)
{
    for (int k = 0; k < 9; k++) Z[k] = 0.0;
    double B[9];
    for (int64_t e = x->mask_ptr[m]; e < x->mask_ptr[m + 1]; e++) {
        xi_block(x, i, x->mask_cols[e], B);
        const double w = x->mask_w[e];
        for (int k = 0; k < 9; k++) Z[k] += w * B[k];
    }
}

int pm__greens_pairs(void *user, int64_t ta, int64_t tb, double *P)
{
    const pm_table *t = user;
    if (ta < 0 || ta >= t->nmt || tb < 0 || tb >= t->nmt) return -1;
    pm__triangle_pairs(t, ta, tb, -1, -1, P);
    return 0;
}

int pm_table_pair_blocks(const pm_table *t, int64_t ta, int64_t tb, double *P)
{
    if (ta < 0 || ta >= t->nmt || tb < 0 || tb >= t->nmt) return -1;
    if (!t->zeta && !t->xi.n) return -1;
    pm__triangle_pairs(t, ta, tb, -1, -1, P);
    return 0;
}

/* y += B v for a 3x3 block B (row-major), and y += (Bᵀ v) s */
static inline void add_block(const double *B, const double *v, double *y)
{
    for (int r = 0; r < 3; r++) y[r] += B[3 * r] * v[0] + B[3 * r + 1] * v[1] + B[3 * r + 2] * v[2];
}

static inline void add_block_t(const double *B, const double *v, double s, double *y)
{
    for (int c = 0; c < 3; c++) y[c] += (B[c] * v[0] + B[3 + c] * v[1] + B[6 + c] * v[2]) * s;
}

/* stored block b's product with the loaded part of xs (cluster order) into ys: forward (Ξ_IJ x_J) where its
 * columns hold load, and (symmetric, off the diagonal) the block below, Ξ_JI x_I = diag(a_J)⁻¹ Ξ_IJᵀ diag(a_I) x_I,
 * where its rows do (CompressedXi.matvec, pair by pair) */
static void block_product(const pm_greens *x, int64_t b, const double *xs, const int64_t *nz, const double *as,
                          double *tk, double *ys)
{
    const int64_t *k = b < x->nd ? x->dense_index + 5 * b : x->lowrank_index + 7 * (b - x->nd);
    const int64_t r0 = k[0], r1 = k[1], c0 = k[2], c1 = k[3];
    const int fwd = nz[c1] > nz[c0], back = x->symmetric && r0 != c0 && nz[r1] > nz[r0];
    if (!fwd && !back) return;
    if (b < x->nd) {  /* pair by pair in the stored order: exact where the mask's bit is set, else 16 bits */
        const int64_t *ni = x->near_index + 3 * b;
        int64_t e = 0, qn = 0, t = 0;
        for (int64_t p = r0; p < r1; p++)
            for (int64_t q = c0; q < c1; q++, t++) {
                const int64_t g = 8 * ni[1] + t;
                const int exact = (x->mask[g >> 3] >> (7 - (g & 7))) & 1;
                const int use_f = fwd && nz[q + 1] > nz[q], use_b = back && nz[p + 1] > nz[p];
                if (use_f || use_b) {
                    double B[9];
                    if (exact) {
                        exact_values(x, k[4] + 9 * e, B);
                    } else {
                        const int64_t at = ni[0] + 9 * qn;
                        const double *sc = x->qscale + ni[2] + 3 * (q - c0);
                        for (int r = 0; r < 3; r++)
                            for (int c = 0; c < 3; c++) B[3 * r + c] = (double)q16(x->q, at + 3 * r + c) * sc[c];
                    }
                    if (use_f) add_block(B, xs + 3 * q, ys + 3 * p);
                    if (use_b) add_block_t(B, xs + 3 * p, as[p] / as[q], ys + 3 * q);
                }
                if (exact) e++; else qn++;
            }
        return;
    }
    const int64_t rank = k[4], m = 3 * (r1 - r0), w = 3 * (c1 - c0);
    const unsigned char *us = far_scales(x, x->Us, b), *vs = far_scales(x, x->Vs, b);
    if (fwd) {  /* U (Vᵀ x_J) */
        for (int64_t j = 0; j < rank; j++) tk[j] = 0.0;
        for (int64_t c = 0; c < w; c++) {
            const double v = xs[3 * c0 + c];
            if (v != 0.0)
                for (int64_t j = 0; j < rank; j++) tk[j] += factor(x, x->V, vs, k[6] + c * rank + j, j) * v;
        }
        for (int64_t r = 0; r < m; r++) {
            double acc = 0.0;
            for (int64_t j = 0; j < rank; j++) acc += factor(x, x->U, us, k[5] + r * rank + j, j) * tk[j];
            ys[3 * r0 + r] += acc;
        }
    }
    if (back) {  /* diag(a_J)⁻¹ V (Uᵀ diag(a_I) x_I) */
        for (int64_t j = 0; j < rank; j++) tk[j] = 0.0;
        for (int64_t r = 0; r < m; r++) {
            const double v = xs[3 * r0 + r] * as[r0 + r / 3];
            if (v != 0.0)
                for (int64_t j = 0; j < rank; j++) tk[j] += factor(x, x->U, us, k[5] + r * rank + j, j) * v;
        }
        for (int64_t c = 0; c < w; c++) {
            double acc = 0.0;
            for (int64_t j = 0; j < rank; j++) acc += factor(x, x->V, vs, k[6] + c * rank + j, j) * tk[j];
            ys[3 * c0 + c] += acc / as[c0 + c / 3];
        }
    }
}

void pm__greens_matvec(const pm_table *t, const double *x, double *y, pm_greens_work *wk)
{
    const pm_greens *g = &t->xi;
    const int64_t n = g->n;
    for (int64_t i = 0; i < n; i++) {
        const int64_t p = g->position[i];
        for (int a = 0; a < 3; a++) wk->xs[3 * p + a] = x[3 * i + a];
        wk->as[p] = g->symmetric ? g->scale[i] : 1.0;
    }
    wk->nz[0] = 0;
    for (int64_t p = 0; p < n; p++)
        wk->nz[p + 1] = wk->nz[p] + (wk->xs[3 * p] != 0.0 || wk->xs[3 * p + 1] != 0.0 || wk->xs[3 * p + 2] != 0.0);
    for (int64_t i = 0; i < 3 * n; i++) wk->ys[i] = 0.0;
    for (int64_t b = 0; b < g->nd + g->nl; b++) block_product(g, b, wk->xs, wk->nz, wk->as, wk->tk, wk->ys);
    for (int64_t i = 0; i < n; i++) {
        const int64_t p = g->position[i];
        for (int a = 0; a < 3; a++) y[3 * i + a] = wk->ys[3 * p + a];
    }
}
