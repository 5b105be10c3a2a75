/* pmask servo core, table building: the ζ table's rows from Ξᵀ and the pressure masks
 * (pmask.runtime.stiffness.Stiffness.zeta_table, whose numpy loop this replaces where the core is built).
 *
 * Row m of the output is Σ_p values[p] · xi_rows[indices[p]] over the mask of centre m (p from indptr[k] to
 * indptr[k + 1], m = centres[k]): ζ_mᵀ = Σ_j ρ^m_j Ξ[:, j]ᵀ in the numpy twin's layout, three table rows per
 * vertex row.  Eight columns are summed in registers at a time, over ZETA_COLUMNS columns of every row
 * before the next, so that the rows of Ξᵀ that neighbouring masks share are read from cache (0.24 s for numpy's
 * loop against 0.09 s at the default kidney, by hand on one core). */
#include "pm_internal.h"

#define ZETA_COLUMNS 1024

static void msg(char *err, size_t errlen, const char *text)
{
    if (err && errlen) snprintf(err, errlen, "%s", text);
}

int pm_zeta_rows(int64_t n_rows, int64_t width, const double *xi_rows, int64_t n_masks, const int64_t *centres,
                 const int64_t *indptr, int64_t nnz, const int64_t *indices, const double *values, double *out,
                 char *err, size_t errlen)
{
    if (n_rows < 0 || width < 0 || n_masks < 0 || nnz < 0 || indptr[0] != 0 || indptr[n_masks] != nnz) {
        msg(err, errlen, "zeta rows: the masks' row pointers do not span their entries");
        return -1;
    }
    for (int64_t k = 0; k < n_masks; k++) {
        if (centres[k] < 0 || centres[k] >= n_rows || indptr[k + 1] < indptr[k]) {
            msg(err, errlen, "zeta rows: a mask centre out of range, or row pointers that decrease");
            return -1;
        }
    }
    for (int64_t p = 0; p < nnz; p++) {
        if (indices[p] < 0 || indices[p] >= n_rows) {
            msg(err, errlen, "zeta rows: a mask vertex out of range");
            return -1;
        }
    }
    for (int64_t a = 0; a < width; a += ZETA_COLUMNS) {
        const int64_t c = width - a < ZETA_COLUMNS ? width - a : ZETA_COLUMNS;
        for (int64_t k = 0; k < n_masks; k++) {
            double *o = out + centres[k] * width + a;
            const int64_t p0 = indptr[k], p1 = indptr[k + 1];
            int64_t j = 0;
            for (; j + 8 <= c; j += 8) {
                double s0 = 0.0, s1 = 0.0, s2 = 0.0, s3 = 0.0, s4 = 0.0, s5 = 0.0, s6 = 0.0, s7 = 0.0;
                for (int64_t p = p0; p < p1; p++) {
                    const double *x = xi_rows + indices[p] * width + a + j;
                    const double v = values[p];
                    s0 += v * x[0];
                    s1 += v * x[1];
                    s2 += v * x[2];
                    s3 += v * x[3];
                    s4 += v * x[4];
                    s5 += v * x[5];
                    s6 += v * x[6];
                    s7 += v * x[7];
                }
                o[j] = s0;
                o[j + 1] = s1;
                o[j + 2] = s2;
                o[j + 3] = s3;
                o[j + 4] = s4;
                o[j + 5] = s5;
                o[j + 6] = s6;
                o[j + 7] = s7;
            }
            for (; j < c; j++) {
                double s = 0.0;
                for (int64_t p = p0; p < p1; p++) s += values[p] * xi_rows[indices[p] * width + a + j];
                o[j] = s;
            }
        }
    }
    return 0;
}
