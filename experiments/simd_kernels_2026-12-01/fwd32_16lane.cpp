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

static const float ALPHA_MIN = 1.0f / 255.0f, ALPHA_MAX = 0.99f, T_MIN = 1e-4f, UV_MAX = 1e6f;

typedef float v8d __attribute__((vector_size(64)));
typedef int32_t v8l __attribute__((vector_size(64)));

static inline bool any(v8l m) { return _mm512_test_epi32_mask((__m512i)m, (__m512i)m) != 0; }
static inline v8d sel(v8l m, v8d a, v8d b) { return m ? a : b; }
static inline v8d vabs(v8d a) { return a < 0 ? -a : a; }
static inline v8d vmax(v8d a, v8d b) { return a > b ? a : b; }
static inline v8d vmin(v8d a, v8d b) { return a < b ? a : b; }

// exp(x) for x in [-708, 0]: x = k ln2 + r, |r| <= ln2/2, degree-13 Taylor of e^r, 2^k by exponent bits.
static inline v8d vexp(v8d x) {
    const float LOG2E = 1.44269504f, LN2_HI = 0.693359375f, LN2_LO = -2.12194440e-4f;
    x = vmax(x, (v8d){} - 87.0f);
    const float RND = 12582912.0f;
    v8d k = (x * LOG2E + RND) - RND;
    v8d r = x - k * LN2_HI - k * LN2_LO;
    v8d p = (v8d){} + 1.9875691500E-4f;
    p = p * r + 1.3981999507E-3f;
    p = p * r + 8.3334519073E-3f;
    p = p * r + 4.1665795894E-2f;
    p = p * r + 1.6666665459E-1f;
    p = p * r + 5.0000001201E-1f;
    p = p * r * r + r + 1.0f;
    v8l ki = __builtin_convertvector(k, v8l);
    v8l bits = (ki + 127) << 23;
    v8d scale;
    memcpy(&scale, &bits, 64);
    return p * scale;
}

extern "C" void forward(const int64_t *tile_start, const int64_t *worker_start, const int64_t *worker_tiles, int64_t n_workers,
             const double *ent, int64_t es, int64_t C, const double *Rwc, int64_t width, int64_t height, int64_t n_tx,
             double near, double far, double depth_eps, float *out_feat, float *out_alpha, float *out_depth,
             float *out_med, float *out_ncam, float *out_nworld, float *out_dist, double *aux_T, double *aux_D,
             double *aux_W, double *aux_M1, double *aux_M2, int32_t *med_local, const int64_t *rec_tile_start,
             float *rec, int64_t *rec_start, int64_t *rec_count, uint16_t *rmask) {
    const double mscale = far / (far - near);
    const int64_t RS = rec_tile_start[n_tx * ((height + TILE - 1) / TILE)] + 16;
#pragma omp parallel for schedule(static, 1) num_threads(n_workers)
    for (int64_t wk = 0; wk < n_workers; wk++) {
        float Tr[TILE * TILE] __attribute__((aligned(64)));
        double Ws[TILE * TILE] __attribute__((aligned(64)));
        double M1[TILE * TILE] __attribute__((aligned(64)));
        double M2[TILE * TILE] __attribute__((aligned(64)));
        float D[TILE * TILE] __attribute__((aligned(64)));
        float med[TILE * TILE] __attribute__((aligned(64)));
        float F[MAXC][TILE * TILE] __attribute__((aligned(64)));
        float Nn[3][TILE * TILE] __attribute__((aligned(64)));
        int32_t medi[TILE * TILE] __attribute__((aligned(64)));
        int32_t done[TILE * TILE] __attribute__((aligned(64)));
        const v8d lane = {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15};
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
                memset(rmask + j * 48, 0, 96);
                const double *e = ent + j * es;
                float ax0 = e[GEO_AX], ax1 = e[GEO_AX + 1], ax2 = e[GEO_AX + 2];
                float ay0 = e[GEO_AY], ay1 = e[GEO_AY + 1], ay2 = e[GEO_AY + 2];
                float a00 = e[GEO_A0], a01 = e[GEO_A0 + 1], a02 = e[GEO_A0 + 2];
                float det = e[GEO_DET], cx = e[GEO_CX], cy = e[GEO_CY], rho_max = e[GEO_RHO_MAX], o = e[GEO_OPACITY];
                float inv_det = e[GEO_INV_DET], inv_zc = e[GEO_INV_ZC], zc = e[E_ZC];
                float n0 = e[E_NRM], n1 = e[E_NRM + 1], n2 = e[E_NRM + 2];
                int64_t bx0 = (int64_t)e[E_BOX], bx1 = (int64_t)e[E_BOX + 1], by0 = (int64_t)e[E_BOX + 2], by1 = (int64_t)e[E_BOX + 3];
                int64_t xa = bx0 > x0 ? bx0 : x0, xb = bx1 < x1 - 1 ? bx1 : x1 - 1;
                int64_t ya = by0 > y0 ? by0 : y0, yb = by1 < y1 - 1 ? by1 : y1 - 1;
                int64_t ha = 0, hb = 0;
                for (int64_t py = ya; py <= yb; py++) {
                    float y = (float)py, dy = y - cy, dy2 = dy * dy;
                    float qr0 = y * ay0 + a00, qr1 = y * ay1 + a01, qr2 = y * ay2 + a02;
                    int64_t row = (py - y0) * TILE;
                    for (int64_t h = ha; h <= hb; h++) {
                        int64_t p = row;
                        v8d x = lane + (float)x0;
                        v8l m = (x >= (float)xa) & (x <= (float)xb);
                        v8l dn = *(v8l *)(done + p);
                        m &= ~dn;
                        v8d q0 = x * ax0 + qr0, q1 = x * ax1 + qr1, q2 = x * ax2 + qr2;
                        v8d dx = x - cx;
                        v8d rho2 = 2.0f * (dx * dx + dy2);
                        v8l in3 = (vabs(q2) * UV_MAX > vmax(vabs(q0), vabs(q1))) & (q0 * q0 + q1 * q1 <= (float)rho_max * (q2 * q2));
                        m &= in3 | (rho2 <= (float)rho_max);
                        if (!any(m)) continue;
                        v8d inv = sel(in3, 1.0f / sel(in3, q2, (v8d){} + 1.0f), (v8d){});
                        v8d u = q0 * inv, v = q1 * inv, r3 = u * u + v * v;
                        v8l use3 = in3 & (r3 <= rho2);
                        v8d rho = sel(use3, r3, rho2);
                        v8d z = sel(use3, det * inv, (v8d){} + (float)zc);
                        v8d iz = sel(use3, q2 * inv_det, (v8d){} + (float)inv_zc);
                        m &= (rho <= (float)rho_max) & (z >= (float)near);
                        if (!any(m)) continue;
                        v8d G = vexp(-0.5f * vmin(rho, (v8d){} + 170.0f));
                        v8d a_raw = (float)o * G;
                        v8d a = vmin((v8d){} + ALPHA_MAX, a_raw);
                        m &= a >= ALPHA_MIN;
                        v8d T = *(v8d *)(Tr + p);
                        v8d Tn = T * (1.0f - a);
                        v8l stop = m & (Tn < T_MIN);
                        if (any(stop)) {
                            *(v8l *)(done + p) = dn | stop;
                            n_done += __builtin_popcount(_mm512_test_epi32_mask((__m512i)stop, (__m512i)stop));
                            m &= ~stop;
                        }
                        if (!any(m)) continue;
                        v8d w = sel(m, a * T, (v8d){});
                        for (int c = 0; c < C; c++) *(v8d *)(F[c] + p) += w * (float)e[E_FEAT + c];
                        *(v8d *)(Nn[0] + p) += w * n0;
                        *(v8d *)(Nn[1] + p) += w * n1;
                        *(v8d *)(Nn[2] + p) += w * n2;
                        *(v8d *)(D + p) += w * z;
                        v8d mm = (float)mscale * (1.0f - (float)near * iz);
                        {
                            // The moments in float64: the distortion W M2 - M1^2 cancels.
                            __m512d wl = _mm512_cvtps_pd(_mm512_castps512_ps256((__m512)w));
                            __m512d wh = _mm512_cvtps_pd(_mm512_extractf32x8_ps((__m512)w, 1));
                            __m512d ml = _mm512_cvtps_pd(_mm512_castps512_ps256((__m512)mm));
                            __m512d mh = _mm512_cvtps_pd(_mm512_extractf32x8_ps((__m512)mm, 1));
                            __m512d *W0 = (__m512d *)(Ws + p), *A0 = (__m512d *)(M1 + p), *B0 = (__m512d *)(M2 + p);
                            __m512d wml = _mm512_mul_pd(wl, ml), wmh = _mm512_mul_pd(wh, mh);
                            W0[0] = _mm512_add_pd(W0[0], wl); W0[1] = _mm512_add_pd(W0[1], wh);
                            A0[0] = _mm512_add_pd(A0[0], wml); A0[1] = _mm512_add_pd(A0[1], wmh);
                            B0[0] = _mm512_fmadd_pd(wml, ml, B0[0]); B0[1] = _mm512_fmadd_pd(wmh, mh, B0[1]);
                        }
                        v8l md = m & (T > 0.5f);
                        *(v8d *)(med + p) = sel(md, z, *(v8d *)(med + p));
                        *(v8l *)(medi + p) = md ? (int32_t)(j - start) : *(v8l *)(medi + p);
                        *(v8d *)(Tr + p) = sel(m, Tn, T);
                        v8l capped = a_raw >= ALPHA_MAX;
#ifndef NOREC
                        {
                            __mmask16 km = _mm512_test_epi32_mask((__m512i)m, (__m512i)m);
                            v8d fl = lane + (float)p + sel(use3, (v8d){} + 256.0f, (v8d){}) + sel(a_raw >= ALPHA_MAX, (v8d){} + 512.0f, (v8d){});
                            _mm512_storeu_ps(rec + r, _mm512_maskz_compress_ps(km, (__m512)fl));
                            _mm512_storeu_ps(rec + RS + r, _mm512_maskz_compress_ps(km, (__m512)T));
                            _mm512_storeu_ps(rec + 2 * RS + r, _mm512_maskz_compress_ps(km, (__m512)a));
                            r += __builtin_popcount(km);
                            uint16_t *rm = rmask + j * 48 + 3 * (py - y0);
                            rm[0] = km; rm[1] = _mm512_test_epi32_mask((__m512i)use3, (__m512i)use3); rm[2] = _mm512_test_epi32_mask((__m512i)capped, (__m512i)capped);
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
