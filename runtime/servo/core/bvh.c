/* pmask servo core: the nearest triangle to a point, which restarts contact tracking (pm_table_nearest). */
#include "pm_internal.h"

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

void pm__free_bvh(pm_table *t)
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

int pm__build_bvh(pm_table *t)
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
