// Prototype: the cpu backend's forward compositing with 8 float64 lanes over a tile row half.
#include <stdint.h>
#include <math.h>
#include <string.h>
#include <omp.h>
#include <immintrin.h>

#define TILE 16
#define GEO_AX 0
#define GEO_AY 3
#define GEO_A0 6
#define GEO_DET 9
#define GEO_CX 10
#define GEO_CY 11
#define GEO_RHO_MAX 12
#define GEO_OPACITY 13
#define GEO_INV_DET 14
#define GEO_INV_ZC 15
#define E_ZC 16
#define E_NRM 17
#define E_BOX 20
#define E_FEAT 24
#define MAXC 8

static const double ALPHA_MIN = 1.0 / 255.0, ALPHA_MAX = 0.99, T_MIN = 1e-4, UV_MAX = 1e6;

typedef double v8d __attribute__((vector_size(64)));
typedef int64_t v8l __attribute__((vector_size(64)));

static inline bool any(v8l m) { return _mm512_test_epi64_mask((__m512i)m, (__m512i)m) != 0; }
static inline v8d sel(v8l m, v8d a, v8d b) { return m ? a : b; }
static inline v8d vabs(v8d a) { return a < 0 ? -a : a; }
static inline v8d vmax(v8d a, v8d b) { return a > b ? a : b; }
static inline v8d vmin(v8d a, v8d b) { return a < b ? a : b; }

// exp(x) for x in [-708, 0]: x = k ln2 + r, |r| <= ln2/2, degree-13 Taylor of e^r, 2^k by exponent bits.
static inline v8d vexp(v8d x) {
    const double LOG2E = 1.4426950408889634, LN2_HI = 6.93147180369123816490e-01, LN2_LO = 1.90821492927058770002e-10;
    x = vmax(x, (v8d){} - 700.0);
    const double RND = 6755399441055744.0;
    v8d k = (x * LOG2E + RND) - RND;
    v8d r = x - k * LN2_HI - k * LN2_LO;
    v8d p = (v8d){} + 1.0 / 6227020800.0;
    p = p * r + 1.0 / 479001600.0;
    p = p * r + 1.0 / 39916800.0;
    p = p * r + 1.0 / 3628800.0;
    p = p * r + 1.0 / 362880.0;
    p = p * r + 1.0 / 40320.0;
    p = p * r + 1.0 / 5040.0;
    p = p * r + 1.0 / 720.0;
    p = p * r + 1.0 / 120.0;
    p = p * r + 1.0 / 24.0;
    p = p * r + 1.0 / 6.0;
    p = p * r + 0.5;
    p = p * r + 1.0;
    p = p * r + 1.0;
    v8l ki = __builtin_convertvector(k, v8l);
    v8l bits = (ki + 1023) << 52;
    v8d scale;
    memcpy(&scale, &bits, 64);
    return p * scale;
}

extern "C" void forward(const int64_t *tile_start, const int64_t *worker_start, const int64_t *worker_tiles, int64_t n_workers,
             const double *ent, int64_t es, int64_t C, const double *Rwc, int64_t width, int64_t height, int64_t n_tx,
             double near, double far, double depth_eps, float *out_feat, float *out_alpha, float *out_depth,
             float *out_med, float *out_ncam, float *out_nworld, float *out_dist, double *aux_T, double *aux_D,
             double *aux_W, double *aux_M1, double *aux_M2, int32_t *med_local, const int64_t *rec_tile_start,
             float *rec, int64_t *rec_start, int64_t *rec_count) {
    const double mscale = far / (far - near);
    const int64_t RS = rec_tile_start[n_tx * ((height + TILE - 1) / TILE)] + 16;
#pragma omp parallel for schedule(static, 1) num_threads(n_workers)
    for (int64_t wk = 0; wk < n_workers; wk++) {
        double Tr[TILE * TILE] __attribute__((aligned(64)));
        double Ws[TILE * TILE] __attribute__((aligned(64)));
        double M1[TILE * TILE] __attribute__((aligned(64)));
        double M2[TILE * TILE] __attribute__((aligned(64)));
        double D[TILE * TILE] __attribute__((aligned(64)));
        double med[TILE * TILE] __attribute__((aligned(64)));
        double F[MAXC][TILE * TILE] __attribute__((aligned(64)));
        double Nn[3][TILE * TILE] __attribute__((aligned(64)));
        int64_t medi[TILE * TILE] __attribute__((aligned(64)));
        int64_t done[TILE * TILE] __attribute__((aligned(64)));
        const v8d lane = {0, 1, 2, 3, 4, 5, 6, 7};
        for (int64_t it = worker_start[wk]; it < worker_start[wk + 1]; it++) {
            int64_t t = worker_tiles[it];
            int64_t ty = t / n_tx, x0 = (t - ty * n_tx) * TILE, y0 = ty * TILE;
            int64_t x1 = x0 + TILE < width ? x0 + TILE : width, y1 = y0 + TILE < height ? y0 + TILE : height;
            int64_t npx = (x1 - x0) * (y1 - y0);
            for (int i = 0; i < TILE * TILE; i++) {
                Tr[i] = 1.0; Ws[i] = M1[i] = M2[i] = D[i] = med[i] = 0.0;
                for (int c = 0; c < C; c++) F[c][i] = 0.0;
                Nn[0][i] = Nn[1][i] = Nn[2][i] = 0.0;
                medi[i] = -1; done[i] = 0;
            }
            int64_t n_done = 0, start = tile_start[t], r = rec_tile_start[t];
            for (int64_t j = start; j < tile_start[t + 1]; j++) { rec_start[j] = r; rec_count[j] = 0; }
            for (int64_t j = start; j < tile_start[t + 1]; j++) {
                if (n_done == npx) break;
                rec_start[j] = r;
                const double *e = ent + j * es;
                double ax0 = e[GEO_AX], ax1 = e[GEO_AX + 1], ax2 = e[GEO_AX + 2];
                double ay0 = e[GEO_AY], ay1 = e[GEO_AY + 1], ay2 = e[GEO_AY + 2];
                double a00 = e[GEO_A0], a01 = e[GEO_A0 + 1], a02 = e[GEO_A0 + 2];
                double det = e[GEO_DET], cx = e[GEO_CX], cy = e[GEO_CY], rho_max = e[GEO_RHO_MAX], o = e[GEO_OPACITY];
                double inv_det = e[GEO_INV_DET], inv_zc = e[GEO_INV_ZC], zc = e[E_ZC];
                double n0 = e[E_NRM], n1 = e[E_NRM + 1], n2 = e[E_NRM + 2];
                int64_t bx0 = (int64_t)e[E_BOX], bx1 = (int64_t)e[E_BOX + 1], by0 = (int64_t)e[E_BOX + 2], by1 = (int64_t)e[E_BOX + 3];
                int64_t xa = bx0 > x0 ? bx0 : x0, xb = bx1 < x1 - 1 ? bx1 : x1 - 1;
                int64_t ya = by0 > y0 ? by0 : y0, yb = by1 < y1 - 1 ? by1 : y1 - 1;
                int64_t ha = (xa - x0) >> 3, hb = (xb - x0) >> 3;
                for (int64_t py = ya; py <= yb; py++) {
                    double y = (double)py, dy = y - cy, dy2 = dy * dy;
                    double qr0 = y * ay0 + a00, qr1 = y * ay1 + a01, qr2 = y * ay2 + a02;
                    int64_t row = (py - y0) * TILE;
                    for (int64_t h = ha; h <= hb; h++) {
                        int64_t p = row + 8 * h;
                        v8d x = lane + (double)(x0 + 8 * h);
                        v8l m = (x >= (double)xa) & (x <= (double)xb);
                        v8l dn = *(v8l *)(done + p);
                        m &= ~dn;
                        v8d q0 = x * ax0 + qr0, q1 = x * ax1 + qr1, q2 = x * ax2 + qr2;
                        v8d dx = x - cx;
                        v8d rho2 = 2.0 * (dx * dx + dy2);
                        v8l in3 = (vabs(q2) * UV_MAX > vmax(vabs(q0), vabs(q1))) & (q0 * q0 + q1 * q1 <= rho_max * (q2 * q2));
                        m &= in3 | (rho2 <= rho_max);
                        if (!any(m)) continue;
                        v8d inv = sel(in3, 1.0 / sel(in3, q2, (v8d){} + 1.0), (v8d){});
                        v8d u = q0 * inv, v = q1 * inv, r3 = u * u + v * v;
                        v8l use3 = in3 & (r3 <= rho2);
                        v8d rho = sel(use3, r3, rho2);
                        v8d z = sel(use3, det * inv, (v8d){} + zc);
                        v8d iz = sel(use3, q2 * inv_det, (v8d){} + inv_zc);
                        m &= (rho <= rho_max) & (z >= near);
                        if (!any(m)) continue;
                        v8d G = vexp(-0.5 * vmin(rho, (v8d){} + 1400.0));
                        v8d a_raw = o * G;
                        v8d a = vmin((v8d){} + ALPHA_MAX, a_raw);
                        m &= a >= ALPHA_MIN;
                        v8d T = *(v8d *)(Tr + p);
                        v8d Tn = T * (1.0 - a);
                        v8l stop = m & (Tn < T_MIN);
                        if (any(stop)) {
                            *(v8l *)(done + p) = dn | stop;
                            for (int l = 0; l < 8; l++) n_done += stop[l] != 0;
                            m &= ~stop;
                        }
                        if (!any(m)) continue;
                        v8d w = sel(m, a * T, (v8d){});
                        for (int c = 0; c < C; c++) *(v8d *)(F[c] + p) += w * e[E_FEAT + c];
                        *(v8d *)(Nn[0] + p) += w * n0;
                        *(v8d *)(Nn[1] + p) += w * n1;
                        *(v8d *)(Nn[2] + p) += w * n2;
                        *(v8d *)(D + p) += w * z;
                        v8d mm = mscale * (1.0 - near * iz);
                        *(v8d *)(Ws + p) += w;
                        *(v8d *)(M1 + p) += w * mm;
                        *(v8d *)(M2 + p) += w * mm * mm;
                        v8l md = m & (T > 0.5);
                        *(v8d *)(med + p) = sel(md, z, *(v8d *)(med + p));
                        *(v8l *)(medi + p) = md ? (j - start) : *(v8l *)(medi + p);
                        *(v8d *)(Tr + p) = sel(m, Tn, T);
                        v8l capped = a_raw >= ALPHA_MAX;
#ifndef NOREC
                        {
                            __mmask8 km = _mm512_test_epi64_mask((__m512i)m, (__m512i)m);
                            v8d fl = (v8d){0, 1, 2, 3, 4, 5, 6, 7} + (double)p + sel(use3, (v8d){} + 256.0, (v8d){}) + sel(a_raw >= ALPHA_MAX, (v8d){} + 512.0, (v8d){});
                            _mm256_storeu_ps(rec + r, _mm256_maskz_compress_ps(km, _mm512_cvtpd_ps((__m512d)fl)));
                            _mm256_storeu_ps(rec + RS + r, _mm256_maskz_compress_ps(km, _mm512_cvtpd_ps((__m512d)T)));
                            _mm256_storeu_ps(rec + 2 * RS + r, _mm256_maskz_compress_ps(km, _mm512_cvtpd_ps((__m512d)a)));
                            r += __builtin_popcount(km);
                        }
#endif
                    }
                }
                rec_count[j] = r - rec_start[j];
            }
            for (int64_t py = y0; py < y1; py++)
                for (int64_t px = x0; px < x1; px++) {
                    int64_t p = (py - y0) * TILE + px - x0, o_ = py * width + px;
                    for (int c = 0; c < C; c++) out_feat[o_ * C + c] = (float)F[c][p];
                    for (int k = 0; k < 3; k++) {
                        out_ncam[o_ * 3 + k] = (float)Nn[k][p];
                        out_nworld[o_ * 3 + k] = (float)(Rwc[0 * 3 + k] * Nn[0][p] + Rwc[1 * 3 + k] * Nn[1][p] + Rwc[2 * 3 + k] * Nn[2][p]);
                    }
                    double A = 1.0 - Tr[p];
                    out_alpha[o_] = (float)A;
                    out_depth[o_] = (float)(D[p] / (A + depth_eps));
                    out_med[o_] = (float)med[p];
                    double dist = Ws[p] * M2[p] - M1[p] * M1[p];
                    out_dist[o_] = (float)(dist > 0 ? dist : 0.0);
                    aux_T[o_] = Tr[p]; aux_D[o_] = D[p]; aux_W[o_] = Ws[p]; aux_M1[o_] = M1[p]; aux_M2[o_] = M2[p];
                    med_local[o_] = (int32_t)medi[p];
                }
        }
    }
}
