// Prototype: the cpu backend's backward compositing, 8 float64 lanes = 8 records of one entry.
#include <stdint.h>
#include <string.h>
#include <immintrin.h>
#define TILE 16
#define NPX (TILE * TILE)
enum { GEO_AX = 0, GEO_AY = 3, GEO_A0 = 6, GEO_DET = 9, GEO_CX = 10, GEO_CY = 11, GEO_RHO_MAX = 12, GEO_OPACITY = 13,
       GEO_INV_DET = 14, GEO_INV_ZC = 15, E_ZC = 16, E_NRM = 17, E_BOX = 20, E_FEAT = 24 };
enum { S_AX = 0, S_AY = 3, S_A0 = 6, S_DET = 9, S_CX = 10, S_CY = 11, S_TW2 = 12, S_OPACITY = 13, S_NORMAL = 14, S_FEATURE = 17 };
enum { PX_GA = 0, PX_GD, PX_GN, PX_GN1, PX_GN2, PX_W, PX_M1, PX_M2, PX_GMED, PX_MED, PX_FEAT };
#define MAXC 8
typedef double v8d __attribute__((vector_size(64)));
typedef int64_t v8l __attribute__((vector_size(64)));
static inline v8d G(const double *base, v8l idx) { return (v8d)_mm512_i64gather_pd((__m512i)idx, base, 8); }
static inline double hsum(v8d a) { return _mm512_reduce_add_pd((__m512d)a); }

extern "C" void backward(const int64_t *tile_start, const int64_t *slot_of_entry, const int64_t *worker_start,
    const int64_t *worker_tiles, int64_t n_workers, const double *ent, int64_t es, int64_t C, const double *Rwc,
    int64_t width, int64_t height, int64_t n_tx, double near, double far, double depth_eps, const double *aux_T,
    const double *aux_D, const double *aux_W, const double *aux_M1, const double *aux_M2, const int32_t *med_local,
    const float *rec, const int64_t *rec_start, const int64_t *rec_count, const float *g_feat, const float *g_alpha,
    const float *g_depth, const float *g_med, const float *g_ncam, const float *g_nworld, const float *g_dist,
    double *slots, int64_t RS) {
    const double mscale = far / (far - near);
    const int64_t ss = 17 + C;
#pragma omp parallel for schedule(static, 1) num_threads(n_workers)
    for (int64_t wk = 0; wk < n_workers; wk++) {
        double tab[(PX_FEAT + MAXC) * NPX] __attribute__((aligned(64)));
        double B[NPX] __attribute__((aligned(64)));
        for (int64_t it = worker_start[wk]; it < worker_start[wk + 1]; it++) {
            int64_t t = worker_tiles[it];
            int64_t ty = t / n_tx, x0 = (t - ty * n_tx) * TILE, y0 = ty * TILE;
            int64_t x1 = x0 + TILE < width ? x0 + TILE : width, y1 = y0 + TILE < height ? y0 + TILE : height;
            memset(B, 0, sizeof B);
            for (int64_t py = y0; py < y1; py++)
                for (int64_t px = x0; px < x1; px++) {
                    int64_t p = (py - y0) * TILE + px - x0, o = py * width + px;
                    double inv = 1.0 / (1.0 - aux_T[o] + depth_eps);
                    double ge = g_depth[o], gd = g_dist[o];
                    tab[PX_GD * NPX + p] = ge * inv;
                    tab[PX_GA * NPX + p] = (double)g_alpha[o] - ge * aux_D[o] * inv * inv;
                    for (int k = 0; k < 3; k++)
                        tab[(PX_GN + k) * NPX + p] = (double)g_ncam[o * 3 + k] + (Rwc[k * 3 + 0] * g_nworld[o * 3] + Rwc[k * 3 + 1] * g_nworld[o * 3 + 1] + Rwc[k * 3 + 2] * g_nworld[o * 3 + 2]);
                    tab[PX_W * NPX + p] = gd * aux_W[o];
                    tab[PX_M1 * NPX + p] = gd * aux_M1[o];
                    tab[PX_M2 * NPX + p] = gd * aux_M2[o];
                    tab[PX_GMED * NPX + p] = g_med[o];
                    tab[PX_MED * NPX + p] = med_local[o];
                    for (int c = 0; c < C; c++) tab[(PX_FEAT + c) * NPX + p] = g_feat[o * C + c];
                }
            int64_t start = tile_start[t];
            for (int64_t j = tile_start[t + 1] - 1; j >= start; j--) {
                const double *e = ent + j * es;
                double li = (double)(j - start);
                v8d gax0 = {}, gax1 = {}, gax2 = {}, gay0 = {}, gay1 = {}, gay2 = {}, g00 = {}, g01 = {}, g02 = {};
                v8d gdet = {}, gcx = {}, gcy = {}, gtw2 = {}, gop = {}, gn0 = {}, gn1 = {}, gn2 = {};
                v8d gfe[MAXC];
                for (int c = 0; c < C; c++) gfe[c] = (v8d){};
                double cx = e[GEO_CX], cy = e[GEO_CY];
                double ax0 = e[GEO_AX], ax1 = e[GEO_AX + 1], ax2 = e[GEO_AX + 2];
                double ay0 = e[GEO_AY], ay1 = e[GEO_AY + 1], ay2 = e[GEO_AY + 2];
                double a00 = e[GEO_A0], a01 = e[GEO_A0 + 1], a02 = e[GEO_A0 + 2];
                double det = e[GEO_DET], inv_det = e[GEO_INV_DET], zc = e[E_ZC], inv_zc = e[GEO_INV_ZC];
                double inv_o = 1.0 / e[GEO_OPACITY];
                double n0 = e[E_NRM], n1 = e[E_NRM + 1], n2 = e[E_NRM + 2];
                int64_t r0 = rec_start[j], rn = rec_count[j];
                // Each pixel appears once per entry, so lanes never collide on B.
                for (int64_t k = 0; k < rn; k += 8) {
                    int64_t nl = rn - k < 8 ? rn - k : 8;
                    __mmask8 km = (__mmask8)((1u << nl) - 1);
                    v8l valid = (v8l)_mm512_movm_epi64(km);
                    v8d fl = (v8d)_mm512_maskz_cvtps_pd(km, _mm256_maskz_loadu_ps(km, rec + r0 + k));
                    v8d T = (v8d)_mm512_maskz_cvtps_pd(km, _mm256_maskz_loadu_ps(km, rec + RS + r0 + k));
                    v8d a = (v8d)_mm512_maskz_cvtps_pd(km, _mm256_maskz_loadu_ps(km, rec + 2 * RS + r0 + k));
                    v8l flags = __builtin_convertvector(fl, v8l);
                    v8l p = flags & 255;
                    v8l use3 = (flags & 256) != 0;
                    v8l uncapped = (flags & 512) == 0;
                    v8d x = __builtin_convertvector(p & (TILE - 1), v8d) + (double)x0;
                    v8d y = __builtin_convertvector(p >> 4, v8d) + (double)y0;
                    v8d q0 = x * ax0 + (y * ay0 + a00), q1 = x * ax1 + (y * ay1 + a01), q2 = x * ax2 + (y * ay2 + a02);
                    v8d inv = use3 ? 1.0 / (use3 ? q2 : 1.0) : 0.0;
                    v8d u = q0 * inv, v = q1 * inv;
                    v8d z = use3 ? det * inv : zc;
                    v8d iz = use3 ? q2 * inv_det : inv_zc;
                    v8d w = a * T;
                    v8d m = mscale * (1.0 - near * iz);
                    v8d gq0 = G(tab + PX_GN * NPX, p), gq1 = G(tab + PX_GN1 * NPX, p), gq2 = G(tab + PX_GN2 * NPX, p);
                    v8d gDp = G(tab + PX_GD * NPX, p), gdW = G(tab + PX_W * NPX, p), gdM1 = G(tab + PX_M1 * NPX, p);
                    v8d vsum = G(tab + PX_GA * NPX, p) + gDp * z + gq0 * n0 + gq1 * n1 + gq2 * n2;
                    vsum += m * m * gdW - 2.0 * m * gdM1 + G(tab + PX_M2 * NPX, p);
                    for (int c = 0; c < C; c++) {
                        v8d gf = G(tab + (PX_FEAT + c) * NPX, p);
                        vsum += gf * e[E_FEAT + c];
                        gfe[c] += gf * w;
                    }
                    gn0 += gq0 * w; gn1 += gq1 * w; gn2 += gq2 * w;
                    v8d Bp = G(B, p);
                    v8d dL_da = T * (vsum - Bp);
                    _mm512_mask_i64scatter_pd(B, km, (__m512i)p, (__m512d)(a * vsum + (1.0 - a) * Bp), 8);
                    v8d dz = gDp * w + 2.0 * w * (m * gdW - gdM1) * mscale * near * iz * iz;
                    v8l ismed = G(tab + PX_MED * NPX, p) == li;
                    dz += ismed ? G(tab + PX_GMED * NPX, p) : 0.0;
                    dz = valid ? dz : 0.0;
                    v8d drho = uncapped ? -0.5 * a * dL_da : 0.0;
                    gop += uncapped ? dL_da * a * inv_o : 0.0;
                    v8d dq0 = 2.0 * drho * u * inv, dq1 = 2.0 * drho * v * inv;
                    v8d dq2 = -(2.0 * drho * (u * u + v * v) + dz * z) * inv;
                    dq0 = use3 ? dq0 : 0.0; dq1 = use3 ? dq1 : 0.0; dq2 = use3 ? dq2 : 0.0;
                    gax0 += x * dq0; gax1 += x * dq1; gax2 += x * dq2;
                    gay0 += y * dq0; gay1 += y * dq1; gay2 += y * dq2;
                    g00 += dq0; g01 += dq1; g02 += dq2;
                    gdet += use3 ? dz * inv : 0.0;
                    gcx += use3 ? 0.0 : -4.0 * (x - cx) * drho;
                    gcy += use3 ? 0.0 : -4.0 * (y - cy) * drho;
                    gtw2 += use3 ? 0.0 : dz;
                    (void)valid;
                }
                double *sl = slots + slot_of_entry[j] * ss;
                sl[S_AX] = hsum(gax0); sl[S_AX + 1] = hsum(gax1); sl[S_AX + 2] = hsum(gax2);
                sl[S_AY] = hsum(gay0); sl[S_AY + 1] = hsum(gay1); sl[S_AY + 2] = hsum(gay2);
                sl[S_A0] = hsum(g00); sl[S_A0 + 1] = hsum(g01); sl[S_A0 + 2] = hsum(g02);
                sl[S_DET] = hsum(gdet); sl[S_CX] = hsum(gcx); sl[S_CY] = hsum(gcy); sl[S_TW2] = hsum(gtw2);
                sl[S_OPACITY] = hsum(gop);
                sl[S_NORMAL] = hsum(gn0); sl[S_NORMAL + 1] = hsum(gn1); sl[S_NORMAL + 2] = hsum(gn2);
                for (int c = 0; c < C; c++) sl[S_FEATURE + c] = hsum(gfe[c]);
            }
        }
    }
}
