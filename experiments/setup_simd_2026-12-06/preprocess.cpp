// Prototype (2026-12-06, not in the package): _kernels.preprocess for float32 surfels, 8
// surfels per step in float64 lanes. The same operations in the same order as the numba
// kernel, no fused multiply-adds (the function's own fp-contract=off), glibc's log and sqrt,
// so every output is bit for bit the numba kernel's (compare.py checks it). Built with
// -fno-math-errno so that the square roots vectorise.
#include <math.h>
#include <stdint.h>

typedef double vd __attribute__((vector_size(64)));
typedef int64_t vl __attribute__((vector_size(64)));
constexpr int L = 8;
enum { GEO_AX = 0, GEO_AY = 3, GEO_A0 = 6, GEO_DET = 9, GEO_CX = 10, GEO_CY = 11, GEO_RHO_MAX = 12,
       GEO_OPACITY = 13, GEO_INV_DET = 14, GEO_INV_ZC = 15, GEO_SIZE = 16 };
constexpr double RHO_SLACK = 1e-6, RHO_CUT_MAX = 9.0;

static inline vd splat(double a) { return (vd){} + a; }
static inline vd f32(vd a) { return __builtin_convertvector(__builtin_convertvector(a, float __attribute__((vector_size(32)))), vd); }
// Python's min / max, as numba compiles them: the first argument unless the second is strictly
// smaller (larger).
static inline vd vmin(vd a, vd b) { return b < a ? b : a; }
static inline vd vmax(vd a, vd b) { return b > a ? b : a; }
static inline vd vsqrt(vd a) {
    for (int l = 0; l < L; l++) a[l] = sqrt(a[l]);
    return a;
}

extern "C" __attribute__((optimize("fp-contract=off"))) void simd_preprocess(
    const float *means, const float *quats, const float *scales, const float *opac, const double *K,
    const double *Rwc, const double *twc, int64_t width, int64_t height, double near, double far, float *Tm,
    float *nrm, double *geo, double *depth, int64_t *box, int32_t *radii, float *centre, int64_t begin,
    int64_t end) {
    const double fx = K[0], sk = K[1], cx0 = K[2], fy = K[4], cy0 = K[5];
    const double big = 4.0 * (double)(width > height ? width : height);
    for (int64_t i0 = begin; i0 < end; i0 += L) {
        const int n = end - i0 < L ? (int)(end - i0) : L;
        vd w, x, y, z, s0, s1, m0, m1, m2, o;
        for (int l = 0; l < L; l++) {
            const int64_t i = i0 + (l < n ? l : 0);
            w[l] = quats[i * 4], x[l] = quats[i * 4 + 1], y[l] = quats[i * 4 + 2], z[l] = quats[i * 4 + 3];
            s0[l] = scales[i * 2], s1[l] = scales[i * 2 + 1];
            m0[l] = means[i * 3], m1[l] = means[i * 3 + 1], m2[l] = means[i * 3 + 2];
            o[l] = opac[i];
        }
        // numba types float() of a float32 as float32: the squared norm and its root are float32.
        typedef float vf8 __attribute__((vector_size(32)));
        const vf8 wf = __builtin_convertvector(w, vf8), xf = __builtin_convertvector(x, vf8);
        const vf8 yf = __builtin_convertvector(y, vf8), zf = __builtin_convertvector(z, vf8);
        vf8 nn = wf * wf + xf * xf + yf * yf + zf * zf;
        for (int l = 0; l < L; l++) nn[l] = sqrtf(nn[l]);
        const vd inv = 1.0 / __builtin_convertvector(nn, vd);
        w = w * inv, x = x * inv, y = y * inv, z = z * inv;
        vd R[3][3];
        R[0][0] = 1 - 2 * (y * y + z * z), R[0][1] = 2 * (x * y - w * z), R[0][2] = 2 * (x * z + w * y);
        R[1][0] = 2 * (x * y + w * z), R[1][1] = 1 - 2 * (x * x + z * z), R[1][2] = 2 * (y * z - w * x);
        R[2][0] = 2 * (x * z - w * y), R[2][1] = 2 * (y * z + w * x), R[2][2] = 1 - 2 * (x * x + y * y);
        vd M[3][3], nv[3];
        for (int r = 0; r < 3; r++) {
            const double a = Rwc[r * 3], b = Rwc[r * 3 + 1], c = Rwc[r * 3 + 2];
            M[r][0] = s0 * (a * R[0][0] + b * R[1][0] + c * R[2][0]);
            M[r][1] = s1 * (a * R[0][1] + b * R[1][1] + c * R[2][1]);
            M[r][2] = a * m0 + b * m1 + c * m2 + twc[r];
            nv[r] = a * R[0][2] + b * R[1][2] + c * R[2][2];
        }
        const vd d = nv[0] * M[0][2] + nv[1] * M[1][2] + nv[2] * M[2][2];
        const vd sgn = d > 0 ? splat(-1.0) : (d < 0 ? splat(1.0) : splat(0.0));
        vd T[3][3];
        for (int c = 0; c < 3; c++) {
            T[0][c] = fx * M[0][c] + sk * M[1][c] + cx0 * M[2][c];
            T[1][c] = fy * M[1][c] + cy0 * M[2][c];
            T[2][c] = M[2][c];
        }
        // Round to the storage dtype so the geometry matches what the backward sees.
        for (int r = 0; r < 3; r++)
            for (int c = 0; c < 3; c++) T[r][c] = f32(T[r][c]);
        auto cross = [](vd a0, vd a1, vd a2, vd b0, vd b1, vd b2, vd *out) {
            out[0] = a1 * b2 - a2 * b1, out[1] = a2 * b0 - a0 * b2, out[2] = a0 * b1 - a1 * b0;
        };
        vd ax[3], ay[3], a0[3];
        cross(T[1][0], T[1][1], T[1][2], T[2][0], T[2][1], T[2][2], ax);
        cross(T[2][0], T[2][1], T[2][2], T[0][0], T[0][1], T[0][2], ay);
        cross(T[0][0], T[0][1], T[0][2], T[1][0], T[1][1], T[1][2], a0);
        const vd zc = T[2][2];
        vd rho_cut;
        for (int l = 0; l < L; l++) {  // glibc's log, as numba calls it
            const double v = 2.0 * log(255.0 * o[l]);
            rho_cut[l] = o[l] > 0 ? (v < RHO_CUT_MAX ? v : RHO_CUT_MAX) : -1.0;
        }
        const vd det = T[2][0] * a0[0] + T[2][1] * a0[1] + T[2][2] * a0[2];
        const vd inv_det = det != 0.0 ? 1.0 / (det != 0.0 ? det : 1.0) : 0.0;
        const vd inv_zc = zc != 0.0 ? 1.0 / (zc != 0.0 ? zc : 1.0) : 0.0;
        const vd rho_max = rho_cut * (1.0 + RHO_SLACK) + RHO_SLACK;
        const vl drawn = (zc >= near) & (zc <= far) & (rho_cut >= 0.0);
        const vd pcx = drawn ? T[0][2] / zc : 0.0, pcy = drawn ? T[1][2] / zc : 0.0;
        // Support box (see the numba kernel).
        const vd r2 = rho_cut;
        const vd c22 = r2 * (T[2][0] * T[2][0] + T[2][1] * T[2][1]) - T[2][2] * T[2][2];
        const vd d2 = vsqrt(vmax(r2, splat(0.0)) / 2.0);
        vd lo_x = splat(-big), hi_x = splat(big), lo_y = splat(-big), hi_y = splat(big);
        const vl ell = c22 < 0;
        {
            const vd den = ell ? c22 : -1.0;
            const vd c02 = r2 * (T[0][0] * T[2][0] + T[0][1] * T[2][1]) - T[0][2] * T[2][2];
            const vd c12 = r2 * (T[1][0] * T[2][0] + T[1][1] * T[2][1]) - T[1][2] * T[2][2];
            const vd c00 = r2 * (T[0][0] * T[0][0] + T[0][1] * T[0][1]) - T[0][2] * T[0][2];
            const vd c11 = r2 * (T[1][0] * T[1][0] + T[1][1] * T[1][1]) - T[1][2] * T[1][2];
            const vd xc = c02 / den, yc = c12 / den;
            const vd hx = vsqrt(vmax(xc * xc - c00 / den, splat(0.0)));
            const vd hy = vsqrt(vmax(yc * yc - c11 / den, splat(0.0)));
            const vd lx = vmin(xc - hx, pcx - d2), hx2 = vmax(xc + hx, pcx + d2);
            const vd ly = vmin(yc - hy, pcy - d2), hy2 = vmax(yc + hy, pcy + d2);
            const vd inf = splat(INFINITY);
            const vl fin = (lx > -inf) & (lx < inf) & (hx2 > -inf) & (hx2 < inf) & (ly > -inf) & (ly < inf) &
                           (hy2 > -inf) & (hy2 < inf);
            const vl use = ell & fin;
            lo_x = use ? lx : lo_x, hi_x = use ? hx2 : hi_x, lo_y = use ? ly : lo_y, hi_y = use ? hy2 : hi_y;
        }
        const vd rad = vmax(vmax(hi_x - pcx, pcx - lo_x), vmax(hi_y - pcy, pcy - lo_y));
        for (int l = 0; l < n; l++) {
            const int64_t i = i0 + l;
            float *tm = Tm + i * 9;
            for (int r = 0; r < 3; r++)
                for (int c = 0; c < 3; c++) tm[3 * r + c] = (float)T[r][c][l];
            for (int r = 0; r < 3; r++) nrm[i * 3 + r] = (float)(sgn[l] * nv[r][l]);
            depth[i] = zc[l];
            double *g = geo + i * GEO_SIZE;
            for (int c = 0; c < 3; c++) g[GEO_AX + c] = ax[c][l], g[GEO_AY + c] = ay[c][l], g[GEO_A0 + c] = a0[c][l];
            g[GEO_DET] = det[l];
            g[GEO_INV_DET] = inv_det[l];
            g[GEO_INV_ZC] = inv_zc[l];
            g[GEO_RHO_MAX] = rho_max[l];
            g[GEO_OPACITY] = o[l];
            g[GEO_CX] = pcx[l];
            g[GEO_CY] = pcy[l];
            centre[i * 2] = (float)pcx[l];
            centre[i * 2 + 1] = (float)pcy[l];
            radii[i] = 0;
            int64_t *b = box + i * 4;
            b[0] = 0, b[1] = -1, b[2] = 0, b[3] = -1;
            if (!drawn[l]) continue;
            const double fw = (double)width, fh = (double)height;
            const double ex0 = lo_x[l] - 0.5, ex1 = hi_x[l] + 0.5, ey0 = lo_y[l] - 0.5, ey1 = hi_y[l] + 0.5;
            int64_t xmin = (int64_t)ceil(ex0 > -1.0 ? ex0 : -1.0), xmax = (int64_t)floor(ex1 < fw ? ex1 : fw);
            int64_t ymin = (int64_t)ceil(ey0 > -1.0 ? ey0 : -1.0), ymax = (int64_t)floor(ey1 < fh ? ey1 : fh);
            xmin = xmin > 0 ? xmin : 0, ymin = ymin > 0 ? ymin : 0;
            xmax = xmax < width - 1 ? xmax : width - 1, ymax = ymax < height - 1 ? ymax : height - 1;
            if (xmin <= xmax && ymin <= ymax) {
                b[0] = xmin, b[1] = xmax, b[2] = ymin, b[3] = ymax;
                const double rc = rad[l] > 0.0 ? rad[l] : 0.0;
                const int64_t rr = (int64_t)ceil(rc < big ? rc : big);
                radii[i] = (int32_t)(rr > 1 ? rr : 1);
            }
        }
    }
}
