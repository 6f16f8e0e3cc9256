// Compositing kernels of the ``simd`` backend: the ``cpu`` backend's forward and backward
// (``_kernels.forward`` / ``_kernels.backward``, same rules, same per-tile lists) with a tile
// row of 16 pixels in one vector of float32 lanes.
//
// Why: a box row inside a tile holds ~5.6 pixels and composites ~2.8 at 800x600 / 200k
// surfels; numba's scalar loops are at their throughput there and LLVM does not vectorise
// them (docs/rasterizer.md, "Explicit SIMD kernels, prototyped"). Arithmetic is float32 as in
// 2DGS's and gsplat's CUDA kernels, except the moments W, M1, M2 (float64: the distortion
// W M2 - M1^2 cancels) and the per-entry gradient sums (reduced across lanes into float64).
//
// Each call renders tiles of ``tile_order`` (largest first) until none is left, taking the next
// from a counter shared by the calls; the caller runs one call per thread. A tile is rendered
// by one call, sequentially in list order, so results do not depend on which thread renders it
// or on the number of threads. GCC / Clang vector extensions; AVX-512 for masks, compress and
// expand where the compiler targets it, a lane loop otherwise.
#include <stdint.h>
#include <string.h>

#include <type_traits>
#if defined(__AVX2__) || defined(__AVX512F__)
#include <immintrin.h>
#endif

namespace {

constexpr int TILE_SHIFT = 4, TILE = 1 << TILE_SHIFT, NPX = TILE * TILE, MAXC = 8;
// Columns of an entry row (``_kernels``: GEO_*, E_*) and of a gradient slot (S_*).
enum { GEO_AX = 0, GEO_AY = 3, GEO_A0 = 6, GEO_DET = 9, GEO_CX = 10, GEO_CY = 11, GEO_RHO_MAX = 12,
       GEO_OPACITY = 13, GEO_INV_DET = 14, GEO_INV_ZC = 15, E_ZC = 16, E_NRM = 17, E_BOX = 20, E_FEAT = 24 };
enum { S_AX = 0, S_AY = 3, S_A0 = 6, S_DET = 9, S_CX = 10, S_CY = 11, S_TW2 = 12, S_OPACITY = 13, S_NORMAL = 14,
       S_FEATURE = 17 };
// Per-pixel fields of the backward's tile table, one plane of NPX floats each.
enum { PX_GA = 0, PX_GD, PX_GN0, PX_GN1, PX_GN2, PX_W, PX_M1, PX_M2, PX_GMED, PX_MED, PX_DEXP, PX_FEAT };
// Per (entry, tile row): the lane masks of the composited pairs, of those on the ray-splat
// intersection branch (use3) and of those whose alpha is capped.
enum { RM_PAIR = 0, RM_USE3 = 1, RM_CAP = 2, RM_SIZE = 3 };

constexpr int PREFETCH = 4;  // entries ahead in the backward
constexpr float ALPHA_MIN = 1.0f / 255.0f, ALPHA_MAX = 0.99f, T_MIN = 1e-4f, UV_MAX = 1e6f;

typedef float vf __attribute__((vector_size(64)));
typedef int32_t vi __attribute__((vector_size(64)));
typedef double vd __attribute__((vector_size(64)));
typedef int64_t vl __attribute__((vector_size(64)));
// Half a tile row: an entry at most 8 pixels wide in its tile (83% of the box rows at 800x600 /
// 200k surfels) is evaluated on the 8 columns from ``window_column``'s, half the work on CPUs
// that split 512-bit operations. The operations per lane are the same, but the compiler may
// fuse multiply-adds differently at the two widths (with -ffp-contract=off the results are
// bitwise those of 16 lanes), so they can differ in the last bits; the width depends only on
// the entry's box.
typedef float vf8 __attribute__((vector_size(32)));
typedef int32_t vi8 __attribute__((vector_size(32)));

template <int L> struct Lanes;
template <> struct Lanes<16> {
    typedef vf F;
    typedef vi I;
};
template <> struct Lanes<8> {
    typedef vf8 F;
    typedef vi8 I;
};
template <int L> using Width = std::integral_constant<int, L>;

template <int L> inline typename Lanes<L>::F lane_index();
template <> inline vf lane_index<16>() { return (vf){0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15}; }
template <> inline vf8 lane_index<8>() { return (vf8){0, 1, 2, 3, 4, 5, 6, 7}; }

template <class F> inline F splat(float a) { return (F){} + a; }
// A vector from / to any address of its lane type: an entry's lanes start at any tile column.
template <class V, class T> inline V loadu(const T *src) {
    V v;
    memcpy(&v, src, sizeof v);
    return v;
}
template <class T, class V> inline void storeu(T *dst, V v) { memcpy(dst, &v, sizeof v); }
template <class F> inline F vmax(F a, F b) { return a > b ? a : b; }
template <class F> inline F vmin(F a, F b) { return a < b ? a : b; }
template <class F> inline F vabs(F a) { return a < 0 ? -a : a; }

// Per helper: the AVX-512 instruction where the compiler targets it, a lane loop otherwise.
// The lanes set in ``m`` as bits.
template <class I> inline uint32_t bits(I m) {
    constexpr int L = sizeof(I) / sizeof(int32_t);
#if defined(__AVX512F__)
    if constexpr (L == 16) return _mm512_test_epi32_mask((__m512i)m, (__m512i)m);
#endif
#if defined(__AVX512VL__)
    if constexpr (L == 8) return _mm256_test_epi32_mask((__m256i)m, (__m256i)m);
#endif
    uint32_t b = 0;
    for (int l = 0; l < L; l++) b |= (m[l] != 0 ? 1u : 0u) << l;
    return b;
}

// The inverse: a lane mask with the lanes of the bits of ``b`` set.
template <int L> inline typename Lanes<L>::I lanes_of(uint32_t b) {
    typedef typename Lanes<L>::I I;
#if defined(__AVX512F__) && defined(__AVX512DQ__)
    if constexpr (L == 16) return (I)_mm512_movm_epi32((__mmask16)b);
#endif
#if defined(__AVX512VL__) && defined(__AVX512DQ__)
    if constexpr (L == 8) return (I)_mm256_movm_epi32((__mmask8)b);
#endif
    I bit = {};
    for (int l = 0; l < L; l++) bit[l] = 1 << l;
    return ((I){} + (int32_t)b & bit) != 0;
}

// The 16 lanes as two float64 vectors (lanes 0-7, 8-15).
inline void widen(vf a, vd &lo, vd &hi) {
#if defined(__AVX512F__)
    lo = (vd)_mm512_cvtps_pd(_mm512_castps512_ps256((__m512)a));
    hi = (vd)_mm512_cvtps_pd(_mm256_castpd_ps(_mm512_extractf64x4_pd(_mm512_castps_pd((__m512)a), 1)));
#else
    for (int k = 0; k < 8; k++) {
        lo[k] = a[k];
        hi[k] = a[8 + k];
    }
#endif
}

// Store the lanes of ``v`` selected by ``b`` contiguously at ``dst`` (a whole vector is written:
// the caller leaves room behind the last record).
template <class F> inline void compress_store(float *dst, uint32_t b, F v) {
    constexpr int L = sizeof(F) / sizeof(float);
#if defined(__AVX512F__)
    if constexpr (L == 16) return _mm512_storeu_ps(dst, _mm512_maskz_compress_ps((__mmask16)b, (__m512)v));
#endif
#if defined(__AVX512VL__)
    if constexpr (L == 8) return _mm256_storeu_ps(dst, _mm256_maskz_compress_ps((__mmask8)b, (__m256)v));
#endif
    int k = 0;
    for (int l = 0; l < L; l++)
        if (b >> l & 1) dst[k++] = v[l];
}

// The inverse: consecutive floats at ``src`` into the lanes selected by ``b``, 0 elsewhere.
template <int L> inline typename Lanes<L>::F expand_load(const float *src, uint32_t b) {
    typedef typename Lanes<L>::F F;
#if defined(__AVX512F__)
    if constexpr (L == 16) return (F)_mm512_maskz_expand_ps((__mmask16)b, _mm512_loadu_ps(src));
#endif
#if defined(__AVX512VL__)
    if constexpr (L == 8) return (F)_mm256_maskz_expand_ps((__mmask8)b, _mm256_loadu_ps(src));
#endif
    F v = {};
    int k = 0;
    for (int l = 0; l < L; l++)
        if (b >> l & 1) v[l] = src[k++];
    return v;
}

// Two rows of 8 lanes as one vector of 16 (a row pair): lanes 0-7 the first, 8-15 the second.
#if defined(__has_builtin) && __has_builtin(__builtin_shufflevector)
template <class V8, class V16> inline V16 join(V8 a, V8 b) {
    return __builtin_shufflevector(a, b, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
}
template <class V16, class V8> inline V8 half(V16 v, int h) {
    return h ? __builtin_shufflevector(v, v, 8, 9, 10, 11, 12, 13, 14, 15) : __builtin_shufflevector(v, v, 0, 1, 2, 3, 4, 5, 6, 7);
}
#else
template <class V8, class V16> inline V16 join(V8 a, V8 b) {
    V16 v;
    memcpy(&v, &a, sizeof a);
    memcpy((char *)&v + sizeof a, &b, sizeof b);
    return v;
}
template <class V16, class V8> inline V8 half(V16 v, int h) {
    V8 a;
    memcpy(&a, (const char *)&v + h * sizeof a, sizeof a);
    return a;
}
#endif
// The 8-lane vector of V's lane type: one row of a row pair.
template <class V> using Half = std::conditional_t<std::is_same_v<V, Lanes<16>::F>, Lanes<8>::F, Lanes<8>::I>;
// A step's lanes of a tile plane from ``p``: one row, or (P) 8 lanes of a row and the 8 below.
template <class V, bool P, class T> inline V load_rows(const T *p) {
    if constexpr (P) {
        return join<Half<V>, V>(loadu<Half<V>>(p), loadu<Half<V>>(p + TILE));
    } else {
        return loadu<V>(p);
    }
}
template <bool P, class T, class V> inline void store_rows(T *p, V v) {
    if constexpr (P) {
        storeu(p, half<V, Half<V>>(v, 0));
        storeu(p + TILE, half<V, Half<V>>(v, 1));
    } else {
        storeu(p, v);
    }
}

// A per-row value on the lanes of a row pair, hidden from the compiler so that it forms
// the same multiply-adds as with the one row's value (a scalar) on 8 lanes.
inline vf rows_value(float a, float b) {
    vf v = join<vf8, vf>(splat<vf8>(a), splat<vf8>(b));
#if defined(__AVX512F__)
    asm("" : "+v"(v));
#else
    asm("" : "+m"(v));
#endif
    return v;
}

// Sum of 8 doubles in a fixed order.
inline double hsum8(vd s8) {
#if defined(__AVX512F__)
    const __m256d s4 = _mm256_add_pd(_mm512_castpd512_pd256((__m512d)s8), _mm512_extractf64x4_pd((__m512d)s8, 1));
    const __m128d s2 = _mm_add_pd(_mm256_castpd256_pd128(s4), _mm256_extractf128_pd(s4, 1));
    return _mm_cvtsd_f64(_mm_add_sd(s2, _mm_unpackhi_pd(s2, s2)));
#else
    const double s4[4] = {s8[0] + s8[4], s8[1] + s8[5], s8[2] + s8[6], s8[3] + s8[7]};
    const double s2[2] = {s4[0] + s4[2], s4[1] + s4[3]};
    return s2[0] + s2[1];
#endif
}

// Sum of the lanes in float64, in a fixed order: the two halves added first, so that 8 lanes
// give what 16 give when the other half is zero.
inline double hsum(vf a) {
    vd lo, hi;
    widen(a, lo, hi);
    return hsum8(lo + hi);
}
// The lanes of a window of 8 at tile column ``off``, summed as hsum sums the 16 of the tile row
// with zeros outside the window: the window holds each column k or k + 8 once, lane (k - off) mod 8.
inline double hsum(vf8 a, int64_t off) {
#if defined(__AVX2__)
    const __m256i rot = _mm256_and_si256(_mm256_sub_epi32(_mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7), _mm256_set1_epi32((int)off)), _mm256_set1_epi32(7));
    a = (vf8)_mm256_permutevar8x32_ps((__m256)a, rot);
#else
    vf8 r;
    for (int k = 0; k < 8; k++) r[k] = a[(k - off) & 7];
    a = r;
#endif
    return hsum8(__builtin_convertvector(a, vd));
}

// exp(x) for x <= 0 in float32: x = k ln2 + r, |r| <= ln2 / 2, Cephes' degree-7 polynomial, 2^k
// through the exponent bits; within 2 ulp of expf on [-87, 0] (tested).
template <int L> inline typename Lanes<L>::F vexp(typename Lanes<L>::F x) {
    typedef typename Lanes<L>::F F;
    typedef typename Lanes<L>::I I;
    const float LOG2E = 1.44269504f, LN2_HI = 0.693359375f, LN2_LO = -2.12194440e-4f, RND = 12582912.0f;
    x = vmax(x, splat<F>(-87.0f));
    F k = (x * LOG2E + RND) - RND;  // round to nearest
    F r = x - k * LN2_HI - k * LN2_LO;
    F p = splat<F>(1.9875691500e-4f);
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    p = p * r * r + r + 1.0f;
    I e = (__builtin_convertvector(k, I) + 127) << 23;
    F scale;
    memcpy(&scale, &e, sizeof scale);
    return p * scale;
}

struct Tile {
    int64_t x0, y0, x1, y1;
};

// The first of the 8 tile columns on which an entry spanning tile columns ``a``..``b`` is
// evaluated (0 or 8 when it lies in one half), -1 when it is wider than 8: the forward and the
// backward must choose alike.
inline int64_t window_column(int64_t a, int64_t b) {
    if (b - a >= 8) return -1;
    return b < 8 ? 0 : a < 8 ? a : 8;
}

inline Tile tile_bounds(int64_t t, int64_t n_tx, int64_t width, int64_t height) {
    int64_t ty = t / n_tx, x0 = (t - ty * n_tx) * TILE, y0 = ty * TILE;
    return {x0, y0, x0 + TILE < width ? x0 + TILE : width, y0 + TILE < height ? y0 + TILE : height};
}

// The forward of ``_kernels.forward`` for the tiles it takes from ``tile_order``; records as two
// planes (transmittance before the pair, alpha) plus ``rmask`` (n_entries x TILE x RM_SIZE; an
// entry's rows outside its box are left unwritten, and the backward reads only its box rows).
// The channel count is a template parameter: with it known, the features and their gradient
// sums stay in registers instead of a stack array zeroed and copied per entry.
template <int C>
void forward_tiles(const int64_t *tile_start, const int64_t *tile_order, int64_t n_tiles, int64_t *next_tile, const int32_t *tile_list,
                  const float *surf, int64_t surf_cols, const double *Rwc, int64_t width, int64_t height, int64_t n_tx,
                  double near, double far, double depth_eps, float *out_feat, float *out_alpha, float *out_depth,
                  float *out_med, float *out_ncam, float *out_nworld, float *out_dist, double *aux_T, double *aux_D,
                  double *aux_W, double *aux_M1, double *aux_M2, int32_t *med_local, const int64_t *rec_tile_start,
                  float *rec_T, float *rec_A, uint16_t *rmask, int64_t *rec_start, int64_t *rec_count) {
    const float mscale = (float)(far / (far - near)), nearf = (float)near;
    alignas(64) float Tr[NPX], D[NPX], med[NPX], Fe[MAXC][NPX], Nn[3][NPX];
    alignas(64) double Ws[NPX], M1[NPX], M2[NPX];
    alignas(64) int32_t medi[NPX], done[NPX];
    for (int64_t it; (it = __atomic_fetch_add(next_tile, 1, __ATOMIC_RELAXED)) < n_tiles;) {
        const int64_t t = tile_order[it];
        const Tile tb = tile_bounds(t, n_tx, width, height);
        const int64_t npx = (tb.x1 - tb.x0) * (tb.y1 - tb.y0);
        for (int i = 0; i < NPX; i++) {
            Tr[i] = 1.0f;
            D[i] = med[i] = 0.0f;
            Ws[i] = M1[i] = M2[i] = 0.0;
            for (int c = 0; c < C; c++) Fe[c][i] = 0.0f;
            Nn[0][i] = Nn[1][i] = Nn[2][i] = 0.0f;
            medi[i] = -1;
            done[i] = 0;
        }
        int64_t n_done = 0, r = rec_tile_start[t];
        const int64_t start = tile_start[t], end = tile_start[t + 1];
        for (int64_t j = start; j < end; j++) {
            rec_start[j] = r;
            rec_count[j] = 0;
        }
        for (int64_t j = start; j < end; j++) {
            if (n_done == npx) break;
            rec_start[j] = r;
            const float *e = surf + (int64_t)tile_list[j] * surf_cols;
            if (j + PREFETCH < end) {
                const char *ek = (const char *)(surf + (int64_t)tile_list[j + PREFETCH] * surf_cols);
                __builtin_prefetch(ek);
                __builtin_prefetch(ek + 64);
            }
            const float ax0 = e[GEO_AX], ax1 = e[GEO_AX + 1], ax2 = e[GEO_AX + 2];
            const float ay0 = e[GEO_AY], ay1 = e[GEO_AY + 1], ay2 = e[GEO_AY + 2];
            const float a00 = e[GEO_A0], a01 = e[GEO_A0 + 1], a02 = e[GEO_A0 + 2];
            const float det = e[GEO_DET], cx = e[GEO_CX], cy = e[GEO_CY], rho_max = e[GEO_RHO_MAX];
            const float o = e[GEO_OPACITY], inv_det = e[GEO_INV_DET], inv_zc = e[GEO_INV_ZC], zc = e[E_ZC];
            const float n0 = e[E_NRM], n1 = e[E_NRM + 1], n2 = e[E_NRM + 2];
            float fs[MAXC];
            for (int c = 0; c < C; c++) fs[c] = e[E_FEAT + c];
            const int64_t bx0 = (int64_t)e[E_BOX], bx1 = (int64_t)e[E_BOX + 1];
            const int64_t by0 = (int64_t)e[E_BOX + 2], by1 = (int64_t)e[E_BOX + 3];
            const int64_t xa = bx0 > tb.x0 ? bx0 : tb.x0, xb = bx1 < tb.x1 - 1 ? bx1 : tb.x1 - 1;
            const int64_t ya = by0 > tb.y0 ? by0 : tb.y0, yb = by1 < tb.y1 - 1 ? by1 : tb.y1 - 1;
            // One step of the entry's rows: tile row ``py`` on L lanes from tile column ``off``,
            // or (P) the row pair py, py + 1 on 8 lanes each from ``off``, as one vector of 16:
            // per lane the same operations, so the same results, in half the steps. ``xr`` and
            // ``in_box_r``: the pixels' x and whether they are in the box, on one row's lanes.
            auto step = [&](auto width, auto paired, int64_t off, int64_t py, auto xr, auto in_box_r) {
                constexpr int L = decltype(width)::value;
                constexpr bool P = decltype(paired)::value;
                typedef typename Lanes<L>::F F;
                typedef typename Lanes<L>::I I;
                typedef typename Lanes<P ? 8 : L>::F Fr;  // one row's lanes
                typedef typename Lanes<P ? 8 : L>::I Ir;
                const int64_t row = (py - tb.y0) * TILE + off;
                // A per-row value on the step's lanes.
                auto per_row = [&](float a, float b) {
                    if constexpr (P) return rows_value(a, b);
                    else return splat<F>(a);
                };
                F x;
                I in_box;
                if constexpr (P) {
                    x = join<Fr, F>(xr, xr);
                    in_box = join<Ir, I>(in_box_r, in_box_r);
                } else {
                    x = xr;
                    in_box = in_box_r;
                }
                uint16_t *rm = rmask + (j * TILE + (py - tb.y0)) * RM_SIZE;
                rm[RM_PAIR] = rm[RM_USE3] = rm[RM_CAP] = 0;
                if constexpr (P) rm[RM_SIZE + RM_PAIR] = rm[RM_SIZE + RM_USE3] = rm[RM_SIZE + RM_CAP] = 0;
                // The lanes of ``b`` into the rows' masks.
                auto set_rows = [&](int field, uint32_t b) {
                    if constexpr (P) {
                        rm[field] = (uint16_t)((b & 0xffu) << off);
                        rm[RM_SIZE + field] = (uint16_t)((b >> 8) << off);
                    } else {
                        rm[field] = (uint16_t)(b << off);
                    }
                };
                const float y0 = (float)py, y1 = (float)(py + P);
                const float dy0 = y0 - cy, dy1 = y1 - cy;
                const F dy2 = per_row(dy0 * dy0, dy1 * dy1);
                const F qr0 = per_row(y0 * ay0 + a00, y1 * ay0 + a00);
                const F qr1 = per_row(y0 * ay1 + a01, y1 * ay1 + a01);
                const F qr2 = per_row(y0 * ay2 + a02, y1 * ay2 + a02);
                const I dn = load_rows<I, P>(done + row);
                I m = in_box & ~dn;
                const F q0 = x * ax0 + qr0, q1 = x * ax1 + qr1, q2 = x * ax2 + qr2;
                const F dx = x - cx;
                const F rho2 = 2.0f * (dx * dx + dy2);
                const I in3 = (vabs(q2) * UV_MAX > vmax(vabs(q0), vabs(q1))) & (q0 * q0 + q1 * q1 <= rho_max * (q2 * q2));
                m &= in3 | (rho2 <= rho_max);
                if (!bits(m)) return;
                const F inv = in3 ? 1.0f / (in3 ? q2 : 1.0f) : 0.0f;
                const F u = q0 * inv, v = q1 * inv, r3 = u * u + v * v;
                const I use3 = in3 & (r3 <= rho2);
                const F rho = use3 ? r3 : rho2;
                const F z = use3 ? det * inv : zc;
                const F iz = use3 ? q2 * inv_det : inv_zc;
                m &= (rho <= rho_max) & (z >= nearf);
                if (!bits(m)) return;
                const F a_raw = o * vexp<L>(-0.5f * vmin(rho, splat<F>(170.0f)));
                const F a = vmin(splat<F>(ALPHA_MAX), a_raw);
                m &= a >= ALPHA_MIN;
                const F T = load_rows<F, P>(Tr + row);
                const F Tn = T * (1.0f - a);
                const I stop = m & (Tn < T_MIN);
                if (uint32_t sb = bits(stop)) {
                    store_rows<P>(done + row, dn | stop);
                    n_done += __builtin_popcount(sb);
                    m &= ~stop;
                }
                const uint32_t mb = bits(m);
                if (!mb) return;
                const F w = m ? a * T : 0.0f;
                for (int c = 0; c < C; c++) store_rows<P>(Fe[c] + row, load_rows<F, P>(Fe[c] + row) + w * fs[c]);
                store_rows<P>(Nn[0] + row, load_rows<F, P>(Nn[0] + row) + w * n0);
                store_rows<P>(Nn[1] + row, load_rows<F, P>(Nn[1] + row) + w * n1);
                store_rows<P>(Nn[2] + row, load_rows<F, P>(Nn[2] + row) + w * n2);
                store_rows<P>(D + row, load_rows<F, P>(D + row) + w * z);
                const F mm = mscale * (1.0f - nearf * iz);
                if constexpr (L == 16) {
                    vd wl[2], ml[2];
                    widen(w, wl[0], wl[1]);
                    widen(mm, ml[0], ml[1]);
                    for (int h = 0; h < 2; h++) {
                        const int64_t at = row + (P ? TILE : 8) * h;
                        const vd wm = wl[h] * ml[h];
                        storeu(Ws + at, loadu<vd>(Ws + at) + wl[h]);
                        storeu(M1 + at, loadu<vd>(M1 + at) + wm);
                        storeu(M2 + at, loadu<vd>(M2 + at) + wm * ml[h]);
                    }
                } else {
                    const vd wl = __builtin_convertvector(w, vd), ml = __builtin_convertvector(mm, vd);
                    const vd wm = wl * ml;
                    storeu(Ws + row, loadu<vd>(Ws + row) + wl);
                    storeu(M1 + row, loadu<vd>(M1 + row) + wm);
                    storeu(M2 + row, loadu<vd>(M2 + row) + wm * ml);
                }
                const I md = m & (T > 0.5f);
                store_rows<P>(med + row, md ? z : load_rows<F, P>(med + row));
                store_rows<P>(medi + row, md ? (int32_t)(j - start) : load_rows<I, P>(medi + row));
                store_rows<P>(Tr + row, m ? Tn : T);
                compress_store(rec_T + r, mb, T);
                compress_store(rec_A + r, mb, a);
                r += __builtin_popcount(mb);
                set_rows(RM_PAIR, mb);
                set_rows(RM_USE3, bits(use3) & mb);
                set_rows(RM_CAP, bits(a_raw >= ALPHA_MAX) & mb);
            };
            // An entry at most 8 pixels wide in this tile (83% of the box rows at 800x600 / 200k
            // surfels) takes its rows in pairs, on the 8 columns from window_column's.
            const int64_t off = window_column(xa - tb.x0, xb - tb.x0);
            if (off >= 0) {
                const vf8 xr = lane_index<8>() + (float)(tb.x0 + off);
                const vi8 in_box_r = (xr >= (float)xa) & (xr <= (float)xb);
                int64_t py = ya;
                for (; py + 1 <= yb; py += 2) step(Width<16>{}, std::true_type{}, off, py, xr, in_box_r);
                if (py <= yb) step(Width<8>{}, std::false_type{}, off, py, xr, in_box_r);
            } else {
                const vf xr = lane_index<16>() + (float)tb.x0;
                const vi in_box_r = (xr >= (float)xa) & (xr <= (float)xb);
                for (int64_t py = ya; py <= yb; py++) step(Width<16>{}, std::false_type{}, 0, py, xr, in_box_r);
            }
            rec_count[j] = r - rec_start[j];
        }
        for (int64_t py = tb.y0; py < tb.y1; py++) {
            const int64_t p0 = (py - tb.y0) * TILE, o0 = py * width + tb.x0;
            // The per-pixel maps of a whole tile row, 8 pixels at a time in float64: the same
            // operations as the pixel loop below.
            alignas(32) float nw[3][TILE];
            if (tb.x1 - tb.x0 == TILE)
                for (int h = 0; h < TILE; h += 8) {
                    const int64_t p = p0 + h, o = o0 + h;
                    const vd tr = __builtin_convertvector(*(const vf8 *)(Tr + p), vd);
                    const vd dd = __builtin_convertvector(*(const vf8 *)(D + p), vd);
                    const vd ws = *(const vd *)(Ws + p), m1 = *(const vd *)(M1 + p), m2 = *(const vd *)(M2 + p);
                    const vd A = 1.0 - tr;
                    const vd dist = ws * m2 - m1 * m1;
                    storeu(out_alpha + o, __builtin_convertvector(A, vf8));
                    storeu(out_depth + o, __builtin_convertvector(dd / (A + depth_eps), vf8));
                    storeu(out_med + o, *(const vf8 *)(med + p));
                    storeu(out_dist + o, __builtin_convertvector(dist > 0.0 ? dist : 0.0, vf8));
                    storeu(aux_T + o, tr);
                    storeu(aux_D + o, dd);
                    storeu(aux_W + o, ws);
                    storeu(aux_M1 + o, m1);
                    storeu(aux_M2 + o, m2);
                    storeu(med_local + o, *(const vi8 *)(medi + p));
                    const vd n0 = __builtin_convertvector(*(const vf8 *)(Nn[0] + p), vd);
                    const vd n1 = __builtin_convertvector(*(const vf8 *)(Nn[1] + p), vd);
                    const vd n2 = __builtin_convertvector(*(const vf8 *)(Nn[2] + p), vd);
                    // n_world = R_wc^T n_cam
                    for (int k = 0; k < 3; k++)
                        *(vf8 *)(nw[k] + h) = __builtin_convertvector(Rwc[k] * n0 + Rwc[3 + k] * n1 + Rwc[6 + k] * n2, vf8);
                }
            for (int64_t i = 0; i < tb.x1 - tb.x0; i++) {
                const int64_t p = p0 + i, o = o0 + i;
                for (int c = 0; c < C; c++) out_feat[o * C + c] = Fe[c][p];
                for (int k = 0; k < 3; k++) out_ncam[o * 3 + k] = Nn[k][p];
                if (tb.x1 - tb.x0 == TILE)
                    for (int k = 0; k < 3; k++) out_nworld[o * 3 + k] = nw[k][i];
            }
            if (tb.x1 - tb.x0 == TILE) continue;
            for (int64_t px = tb.x0; px < tb.x1; px++) {
                const int64_t p = p0 + px - tb.x0, o = py * width + px;
                for (int k = 0; k < 3; k++)
                    // n_world = R_wc^T n_cam
                    out_nworld[o * 3 + k] = (float)(Rwc[k] * Nn[0][p] + Rwc[3 + k] * Nn[1][p] + Rwc[6 + k] * Nn[2][p]);
                const double A = 1.0 - (double)Tr[p];
                out_alpha[o] = (float)A;
                out_depth[o] = (float)(D[p] / (A + depth_eps));
                out_med[o] = med[p];
                const double dist = Ws[p] * M2[p] - M1[p] * M1[p];
                out_dist[o] = (float)(dist > 0.0 ? dist : 0.0);
                aux_T[o] = Tr[p];
                aux_D[o] = D[p];
                aux_W[o] = Ws[p];
                aux_M1[o] = M1[p];
                aux_M2[o] = M2[p];
                med_local[o] = medi[p];
            }
        }
    }
}

// The backward of ``_kernels.backward`` for the tiles it takes from ``tile_order``, from
// ``simd_forward``'s records: per entry (in reverse list order) and tile row, the pairs'
// gradients in lanes, summed per entry into its slot.
template <int C>
void backward_tiles(const int64_t *tile_start, const int64_t *slot_of_entry, const int64_t *tile_order, int64_t n_tiles,
                   int64_t *next_tile, const int32_t *tile_list, const float *surf, int64_t surf_cols, const double *Rwc, int64_t width,
                   int64_t height, int64_t n_tx, double near, double far, double depth_eps, const double *aux_T,
                   const double *aux_D, const double *aux_W, const double *aux_M1, const double *aux_M2,
                   const int32_t *med_local, const float *rec_T, const float *rec_A, const uint16_t *rmask,
                   const int64_t *rec_start, const int64_t *rec_count, const float *g_feat, const float *g_alpha,
                   const float *g_depth, const float *g_med, const float *g_ncam, const float *g_nworld,
                   const float *g_dist, double *slots) {
    const float mscale = (float)(far / (far - near)), nearf = (float)near;
    const int64_t slot_cols = S_FEATURE + C;
    alignas(64) float tab[(PX_FEAT + MAXC) * NPX];
    alignas(64) float B[NPX];
    for (int64_t it; (it = __atomic_fetch_add(next_tile, 1, __ATOMIC_RELAXED)) < n_tiles;) {
        const int64_t t = tile_order[it];
        const Tile tb = tile_bounds(t, n_tx, width, height);
        memset(B, 0, sizeof B);
        // A full tile writes every pixel's table row below; an edge tile's lanes past the image
        // are read too (masked out, but they must be finite).
        if (tb.x1 - tb.x0 < TILE || tb.y1 - tb.y0 < TILE) memset(tab, 0, sizeof tab);
        for (int64_t py = tb.y0; py < tb.y1; py++)
            for (int64_t px = tb.x0; px < tb.x1; px++) {
                const int64_t p = (py - tb.y0) * TILE + px - tb.x0, o = py * width + px;
                const double inv = 1.0 / (1.0 - aux_T[o] + depth_eps);
                const double ge = g_depth[o], gd = g_dist[o];
                // dL/dA of D / (A + eps) enters as gD (z - D / (A + eps)): no cancellation in float32.
                tab[PX_GD * NPX + p] = (float)(ge * inv);
                tab[PX_DEXP * NPX + p] = (float)(aux_D[o] * inv);
                tab[PX_GA * NPX + p] = g_alpha[o];
                for (int k = 0; k < 3; k++)
                    tab[(PX_GN0 + k) * NPX + p] = (float)(g_ncam[o * 3 + k] + (Rwc[k * 3] * g_nworld[o * 3] + Rwc[k * 3 + 1] * g_nworld[o * 3 + 1] + Rwc[k * 3 + 2] * g_nworld[o * 3 + 2]));
                tab[PX_W * NPX + p] = (float)(gd * aux_W[o]);
                tab[PX_M1 * NPX + p] = (float)(gd * aux_M1[o]);
                tab[PX_M2 * NPX + p] = (float)(gd * aux_M2[o]);
                tab[PX_GMED * NPX + p] = g_med[o];
                tab[PX_MED * NPX + p] = (float)med_local[o];
                for (int c = 0; c < C; c++) tab[(PX_FEAT + c) * NPX + p] = g_feat[o * C + c];
            }
        const int64_t start = tile_start[t];
        for (int64_t j = tile_start[t + 1] - 1; j >= start; j--) {
            // The entries are read in the reverse of the order the forward wrote them, which
            // the hardware prefetcher does not follow: fetch an entry's data a few entries ahead.
            if (j - PREFETCH >= start) {
                const int64_t k = j - PREFETCH;
                const char *ek = (const char *)(surf + (int64_t)tile_list[k] * surf_cols), *mk = (const char *)(rmask + k * TILE * RM_SIZE);
                __builtin_prefetch(ek);
                __builtin_prefetch(ek + 64);
                __builtin_prefetch(mk);
                __builtin_prefetch(mk + 64);
                __builtin_prefetch(rec_T + rec_start[k]);
                __builtin_prefetch(rec_A + rec_start[k]);
                __builtin_prefetch(slots + slot_of_entry[k] * slot_cols, 1);
            }
            double *sl = slots + slot_of_entry[j] * slot_cols;
            if (rec_count[j] == 0) {
                memset(sl, 0, slot_cols * sizeof(double));
                continue;
            }
            const float *e = surf + (int64_t)tile_list[j] * surf_cols;
            const float li = (float)(j - start);
            const float cx = e[GEO_CX], cy = e[GEO_CY];
            const float ax0 = e[GEO_AX], ax1 = e[GEO_AX + 1], ax2 = e[GEO_AX + 2];
            const float ay0 = e[GEO_AY], ay1 = e[GEO_AY + 1], ay2 = e[GEO_AY + 2];
            const float a00 = e[GEO_A0], a01 = e[GEO_A0 + 1], a02 = e[GEO_A0 + 2];
            const float det = e[GEO_DET], inv_det = e[GEO_INV_DET], zc = e[E_ZC], inv_zc = e[GEO_INV_ZC];
            const float inv_o = (float)(1.0 / (double)e[GEO_OPACITY]);
            const float n0 = e[E_NRM], n1 = e[E_NRM + 1], n2 = e[E_NRM + 2];
            float fs[MAXC];
            for (int c = 0; c < C; c++) fs[c] = e[E_FEAT + c];
            const int64_t bx0 = (int64_t)e[E_BOX], bx1 = (int64_t)e[E_BOX + 1];
            const int64_t by0 = (int64_t)e[E_BOX + 2], by1 = (int64_t)e[E_BOX + 3];
            const int64_t xa = bx0 > tb.x0 ? bx0 : tb.x0, xb = bx1 < tb.x1 - 1 ? bx1 : tb.x1 - 1;
            const int64_t ry0 = (by0 > tb.y0 ? by0 : tb.y0) - tb.y0, ry1 = (by1 < tb.y1 - 1 ? by1 : tb.y1 - 1) - tb.y0;
            // The entry's pairs on L lanes starting at tile column ``off`` (as the forward chose).
            auto pairs = [&](auto width, int64_t off) {
                constexpr int L = decltype(width)::value;
                typedef typename Lanes<L>::F F;
                typedef typename Lanes<L>::I I;
                const uint32_t lane_bits = (1u << L) - 1;
                const F x = lane_index<L>() + (float)(tb.x0 + off);
                // Per-lane sums over the entry's pairs; the pixel-weighted ones about the centre
                // (x - cx, y - cy), which keeps them well conditioned in float32.
                F g0 = {}, g1 = {}, g2 = {}, gy0 = {}, gy1 = {}, gy2 = {};
                F gdet = {}, gdrho_lp = {}, gcy = {}, gtw2 = {}, gop = {}, gn0 = {}, gn1 = {}, gn2 = {};
                F gfe[C];
                for (int c = 0; c < C; c++) gfe[c] = (F){};
                int64_t r = rec_start[j];
                for (int64_t ry = ry0; ry <= ry1; ry++) {
                    const uint16_t *rm = rmask + (j * TILE + ry) * RM_SIZE;
                    const uint32_t mb = (uint32_t)rm[RM_PAIR] >> off & lane_bits;
                    if (!mb) continue;
                    const I m = lanes_of<L>(mb), use3 = lanes_of<L>((uint32_t)rm[RM_USE3] >> off & lane_bits);
                    const I lowpass = m & ~use3;
                    const I uncapped = m & ~lanes_of<L>((uint32_t)rm[RM_CAP] >> off & lane_bits);
                    const F T = expand_load<L>(rec_T + r, mb), a = expand_load<L>(rec_A + r, mb);
                    r += __builtin_popcount(mb);
                    const int64_t row = ry * TILE + off;
                    const float y = (float)(tb.y0 + ry);
                    const F q0 = x * ax0 + (y * ay0 + a00), q1 = x * ax1 + (y * ay1 + a01), q2 = x * ax2 + (y * ay2 + a02);
                    const F inv = use3 ? 1.0f / (use3 ? q2 : 1.0f) : 0.0f;
                    const F u = q0 * inv, v = q1 * inv;
                    const F z = use3 ? det * inv : zc;
                    const F iz = use3 ? q2 * inv_det : inv_zc;
                    const F w = a * T;
                    const F mm = mscale * (1.0f - nearf * iz);
#define ROW(f) loadu<F>(tab + (f) * NPX + row)
                    const F gq0 = ROW(PX_GN0), gq1 = ROW(PX_GN1), gq2 = ROW(PX_GN2);
                    const F gDp = ROW(PX_GD), gdW = ROW(PX_W), gdM1 = ROW(PX_M1);
                    F vsum = ROW(PX_GA) + gDp * (z - ROW(PX_DEXP)) + gq0 * n0 + gq1 * n1 + gq2 * n2;
                    vsum += mm * mm * gdW - 2.0f * mm * gdM1 + ROW(PX_M2);
                    for (int c = 0; c < C; c++) {
                        const F gf = ROW(PX_FEAT + c);
                        vsum += gf * fs[c];
                        gfe[c] += gf * w;
                    }
                    gn0 += gq0 * w;
                    gn1 += gq1 * w;
                    gn2 += gq2 * w;
                    const F Bp = loadu<F>(B + row);
                    const F dL_da = T * (vsum - Bp);
                    storeu(B + row, m ? a * vsum + (1.0f - a) * Bp : Bp);
                    F dz = gDp * w + 2.0f * w * (mm * gdW - gdM1) * mscale * nearf * iz * iz;
                    dz += (ROW(PX_MED) == li) ? ROW(PX_GMED) : 0.0f;
                    dz = m ? dz : 0.0f;
#undef ROW
                    // The cap alpha = 0.99 has zero derivative.
                    const F drho = uncapped ? -0.5f * a * dL_da : 0.0f;
                    gop += uncapped ? dL_da * a * inv_o : 0.0f;
                    // rho = (q0^2 + q1^2) / q2^2 and z = det / q2 on the intersection branch.
                    const F dq0 = use3 ? 2.0f * drho * u * inv : 0.0f;
                    const F dq1 = use3 ? 2.0f * drho * v * inv : 0.0f;
                    const F dq2 = use3 ? -(2.0f * drho * (u * u + v * v) + dz * z) * inv : 0.0f;
                    g0 += dq0;
                    g1 += dq1;
                    g2 += dq2;
                    gy0 += (y - cy) * dq0;
                    gy1 += (y - cy) * dq1;
                    gy2 += (y - cy) * dq2;
                    gdet += use3 ? dz * inv : 0.0f;
                    // rho2 = 2 |(x, y) - c|^2 and z = T_w2 on the low-pass branch.
                    gdrho_lp += lowpass ? drho : 0.0f;
                    gcy += lowpass ? -4.0f * (y - cy) * drho : 0.0f;
                    gtw2 += lowpass ? dz : 0.0f;
                }
                const F dxc = x - cx;
                // The lanes summed in float64 as the 16 of the tile row would be.
                auto sum = [&](F v) {
                    if constexpr (L == 8) return hsum(v, off);
                    else return hsum(v);
                };
                const double s0 = sum(g0), s1 = sum(g1), s2 = sum(g2);
                sl[S_AX] = sum(dxc * g0) + (double)cx * s0;
                sl[S_AX + 1] = sum(dxc * g1) + (double)cx * s1;
                sl[S_AX + 2] = sum(dxc * g2) + (double)cx * s2;
                sl[S_AY] = sum(gy0) + (double)cy * s0;
                sl[S_AY + 1] = sum(gy1) + (double)cy * s1;
                sl[S_AY + 2] = sum(gy2) + (double)cy * s2;
                sl[S_A0] = s0;
                sl[S_A0 + 1] = s1;
                sl[S_A0 + 2] = s2;
                sl[S_DET] = sum(gdet);
                sl[S_CX] = sum(-4.0f * dxc * gdrho_lp);
                sl[S_CY] = sum(gcy);
                sl[S_TW2] = sum(gtw2);
                sl[S_OPACITY] = sum(gop);
                sl[S_NORMAL] = sum(gn0);
                sl[S_NORMAL + 1] = sum(gn1);
                sl[S_NORMAL + 2] = sum(gn2);
                for (int c = 0; c < C; c++) sl[S_FEATURE + c] = sum(gfe[c]);
            };
            const int64_t off = window_column(xa - tb.x0, xb - tb.x0);
            if (off >= 0)
                pairs(Width<8>{}, off);
            else
                pairs(Width<16>{}, 0);
        }
    }
}

// ---- Per-surfel set-up: ``_kernels.preprocess`` for float32 surfels, 8 surfels per step in
// float64 lanes, writing each surfel's row of the kernels' table (GEO_*, E_ZC, E_NRM, E_BOX)
// in float32 where the numba kernel writes a float64 ``geo`` that was then packed. The same
// operations in the same order, no fused multiply-adds, glibc's log and sqrt: every output is
// bit for bit the numba kernel's (the tests compare them), so the two backends bin alike.
constexpr int PRE_LANES = 8;
constexpr double RHO_SLACK = 1e-6, RHO_CUT_MAX = 9.0;  // _kernels._RHO_SLACK, project.RHO_CUT_MAX
constexpr double OPACITY_AT_CUT_MAX = 0.3532;  // > exp(RHO_CUT_MAX / 2) / 255 = 0.35301

inline vd dsplat(double a) { return (vd){} + a; }
inline vd round_to_float(vd a) { return __builtin_convertvector(__builtin_convertvector(a, vf8), vd); }
// Python's min / max as numba compiles them: the first argument unless the second is strictly
// smaller (larger); differs from the compositing's vmin / vmax at signed zeros and NaN.
inline vd py_min(vd a, vd b) { return b < a ? b : a; }
inline vd py_max(vd a, vd b) { return b > a ? b : a; }
// IEEE square roots (correctly rounded: the same bits as glibc's sqrt, which numba calls).
inline vd lane_sqrt(vd a) {
#if defined(__AVX512F__)
    return (vd)_mm512_sqrt_pd((__m512d)a);
#else
    for (int l = 0; l < PRE_LANES; l++) a[l] = __builtin_sqrt(a[l]);
    return a;
#endif
}

#if defined(__clang__)
#define NO_CONTRACT
#else
#define NO_CONTRACT __attribute__((optimize("fp-contract=off", "no-math-errno")))
#endif

// ---- The binning's per-tile test (``_kernels.tile_conic``, ``tile_reached``: the same values in
// the same order, no fused multiply-add, so both backends list alike).
constexpr double CULL_MARGIN = 1e-3, WELL_POSED = 1e-4;

struct TileConic {
    double ax0, ax1, ax2, ay0, ay1, ay2, a00, a01, a02, r, cx, cy, s01, s02, s12, inv00, inv11, ex, ey;
    bool ellipse, well_posed;
};

NO_CONTRACT inline TileConic tile_conic(const float *row) {
#if defined(__clang__)
#pragma clang fp contract(off)
#endif
    TileConic c;
    c.ax0 = row[GEO_AX], c.ax1 = row[GEO_AX + 1], c.ax2 = row[GEO_AX + 2];
    c.ay0 = row[GEO_AY], c.ay1 = row[GEO_AY + 1], c.ay2 = row[GEO_AY + 2];
    c.a00 = row[GEO_A0], c.a01 = row[GEO_A0 + 1], c.a02 = row[GEO_A0 + 2];
    c.cx = row[GEO_CX], c.cy = row[GEO_CY];
    c.r = (double)row[GEO_RHO_MAX] * (1.0 + CULL_MARGIN);
    const double s00 = c.ax0 * c.ax0 + c.ax1 * c.ax1 - c.r * (c.ax2 * c.ax2);
    c.s01 = c.ax0 * c.ay0 + c.ax1 * c.ay1 - c.r * (c.ax2 * c.ay2);
    const double s11 = c.ay0 * c.ay0 + c.ay1 * c.ay1 - c.r * (c.ay2 * c.ay2);
    c.s02 = c.ax0 * c.a00 + c.ax1 * c.a01 - c.r * (c.ax2 * c.a02);
    c.s12 = c.ay0 * c.a00 + c.ay1 * c.a01 - c.r * (c.ay2 * c.a02);
    const double det2 = s00 * s11 - c.s01 * c.s01;
    c.ellipse = s00 > 0.0 && det2 > 0.0;
    c.ex = c.ey = c.inv00 = c.inv11 = 0.0;
    if (c.ellipse) {
        c.ex = (c.s01 * c.s12 - s11 * c.s02) / det2;
        c.ey = (c.s01 * c.s02 - s00 * c.s12) / det2;
        c.inv00 = 1.0 / s00;
        c.inv11 = 1.0 / s11;
    }
    c.well_posed = det2 > WELL_POSED * (s00 * s11);
    return c;
}

NO_CONTRACT inline double conic_value(const TileConic &c, double x, double y) {
#if defined(__clang__)
#pragma clang fp contract(off)
#endif
    const double q0 = x * c.ax0 + y * c.ay0 + c.a00, q1 = x * c.ax1 + y * c.ay1 + c.a01;
    const double q2 = x * c.ax2 + y * c.ay2 + c.a02;
    return q0 * q0 + q1 * q1 - c.r * (q2 * q2);
}

// numba's min and max of two floats (NO_CONTRACT as their callers: GCC inlines no function
// whose optimisation options differ from its caller's)
NO_CONTRACT inline double py_min(double a, double b) { return b < a ? b : a; }
NO_CONTRACT inline double py_max(double a, double b) { return b > a ? b : a; }
NO_CONTRACT inline double clamp_to(double v, double lo, double hi) { return py_min(py_max(v, lo), hi); }

NO_CONTRACT inline bool tile_reached(const TileConic &c, double xa, double xb, double ya, double yb) {
#if defined(__clang__)
#pragma clang fp contract(off)
#endif
    const double dx = py_max(py_max(xa - c.cx, 0.0), c.cx - xb), dy = py_max(py_max(ya - c.cy, 0.0), c.cy - yb);
    if (2.0 * (dx * dx + dy * dy) <= c.r || !c.ellipse) return true;
    if (xa <= c.ex && c.ex <= xb && ya <= c.ey && c.ey <= yb) return true;
    const bool every = !c.well_posed;
    if ((every || c.ey < ya) && conic_value(c, clamp_to(-(c.s01 * ya + c.s02) * c.inv00, xa, xb), ya) <= 0.0)
        return true;
    if ((every || c.ey > yb) && conic_value(c, clamp_to(-(c.s01 * yb + c.s02) * c.inv00, xa, xb), yb) <= 0.0)
        return true;
    if ((every || c.ex < xa) && conic_value(c, xa, clamp_to(-(c.s01 * xa + c.s12) * c.inv11, ya, yb)) <= 0.0)
        return true;
    if ((every || c.ex > xb) && conic_value(c, xb, clamp_to(-(c.s01 * xb + c.s12) * c.inv11, ya, yb)) <= 0.0)
        return true;
    return false;
}

// The pixel rows [ya, yb] of box ``b`` in tile row ``ty``, its columns [xa, xb] in tile column ``tx``.
NO_CONTRACT inline void box_in_tile(const int64_t *b, int64_t tx, int64_t ty, int64_t &xa, int64_t &xb, int64_t &ya, int64_t &yb) {
    xa = b[0] > tx * TILE ? b[0] : tx * TILE, xb = b[1] < tx * TILE + TILE - 1 ? b[1] : tx * TILE + TILE - 1;
    ya = b[2] > ty * TILE ? b[2] : ty * TILE, yb = b[3] < ty * TILE + TILE - 1 ? b[3] : ty * TILE + TILE - 1;
}

// The tiles of box ``b`` (row-major) that the surfel of ``row`` reaches, as bits, for a box of at
// most 64 tiles (one tile: reached, untested); all bits set for a larger box (its binning
// tests each tile itself).
NO_CONTRACT inline uint64_t reach_bits(const int64_t *b, const float *row) {
    const int64_t tx0 = b[0] >> TILE_SHIFT, tx1 = b[1] >> TILE_SHIFT, ty0 = b[2] >> TILE_SHIFT, ty1 = b[3] >> TILE_SHIFT;
    if (tx0 == tx1 && ty0 == ty1) return 1;
    if ((tx1 - tx0 + 1) * (ty1 - ty0 + 1) > 64) return ~(uint64_t)0;
    const TileConic conic = tile_conic(row);
    uint64_t bits = 0;
    int64_t i = 0;
    for (int64_t ty = ty0; ty <= ty1; ty++)
        for (int64_t tx = tx0; tx <= tx1; tx++, i++) {
            int64_t xa, xb, ya, yb;
            box_in_tile(b, tx, ty, xa, xb, ya, yb);
            if (tile_reached(conic, (double)xa, (double)xb, (double)ya, (double)yb)) bits |= (uint64_t)1 << i;
        }
    return bits;
}

// Whether tile ``i`` of box ``b`` (its (tx, ty)) is reached: from ``bits`` where the box has at
// most 64 tiles, else tested.
NO_CONTRACT inline bool tile_of_box_reached(uint64_t bits, int64_t n_box_tiles, int64_t i, const int64_t *b,
                                            const TileConic *conic, int64_t tx, int64_t ty) {
    if (n_box_tiles <= 64) return bits >> i & 1;
    int64_t xa, xb, ya, yb;
    box_in_tile(b, tx, ty, xa, xb, ya, yb);
    return tile_reached(*conic, (double)xa, (double)xb, (double)ya, (double)yb);
}

}  // namespace

extern "C" {

#define CHANNELS(F) F(1) F(2) F(3) F(4) F(5) F(6) F(7) F(8)

void simd_forward(const int64_t *tile_start, const int64_t *tile_order, int64_t n_tiles, int64_t *next_tile, const int32_t *tile_list,
                  const float *surf, int64_t surf_cols, int64_t C, const double *Rwc, int64_t width, int64_t height, int64_t n_tx,
                  double near, double far, double depth_eps, float *out_feat, float *out_alpha, float *out_depth,
                  float *out_med, float *out_ncam, float *out_nworld, float *out_dist, double *aux_T, double *aux_D,
                  double *aux_W, double *aux_M1, double *aux_M2, int32_t *med_local, const int64_t *rec_tile_start,
                  float *rec_T, float *rec_A, uint16_t *rmask, int64_t *rec_start, int64_t *rec_count) {
    switch (C) {
#define CASE(c)                                                                                                     \
    case c:                                                                                                         \
        return forward_tiles<c>(tile_start, tile_order, n_tiles, next_tile, tile_list, surf, surf_cols, Rwc, width, height, n_tx, near, \
                                far, depth_eps, out_feat, out_alpha, out_depth, out_med, out_ncam, out_nworld,     \
                                out_dist, aux_T, aux_D, aux_W, aux_M1, aux_M2, med_local, rec_tile_start, rec_T,   \
                                rec_A, rmask, rec_start, rec_count);
        CHANNELS(CASE)
#undef CASE
    }
}

void simd_backward(const int64_t *tile_start, const int64_t *slot_of_entry, const int64_t *tile_order, int64_t n_tiles,
                   int64_t *next_tile, const int32_t *tile_list, const float *surf, int64_t surf_cols, int64_t C, const double *Rwc, int64_t width,
                   int64_t height, int64_t n_tx, double near, double far, double depth_eps, const double *aux_T,
                   const double *aux_D, const double *aux_W, const double *aux_M1, const double *aux_M2,
                   const int32_t *med_local, const float *rec_T, const float *rec_A, const uint16_t *rmask,
                   const int64_t *rec_start, const int64_t *rec_count, const float *g_feat, const float *g_alpha,
                   const float *g_depth, const float *g_med, const float *g_ncam, const float *g_nworld,
                   const float *g_dist, double *slots) {
    switch (C) {
#define CASE(c)                                                                                                      \
    case c:                                                                                                          \
        return backward_tiles<c>(tile_start, slot_of_entry, tile_order, n_tiles, next_tile, tile_list, surf, surf_cols, Rwc, width,       \
                                 height, n_tx, near, far, depth_eps, aux_T, aux_D, aux_W, aux_M1, aux_M2, med_local, \
                                 rec_T, rec_A, rmask, rec_start, rec_count, g_feat, g_alpha, g_depth, g_med, g_ncam, \
                                 g_nworld, g_dist, slots);
        CHANNELS(CASE)
#undef CASE
    }
}

// ``_kernels.preprocess`` on surfels [begin, end), with each surfel's float32 row of the kernels'
// table, its ``n_feat`` features included, and the tiles of its box it reaches (``reach_bits``:
// the binning's test, run here in surfel order; in depth order its rows were cache misses).
// The caller runs one call per chunk of surfels, one per thread at a time.
NO_CONTRACT void simd_preprocess(const float *means, const float *quats, const float *scales, const float *opac,
                                 const double *K, const double *Rwc, const double *twc, int64_t width,
                                 int64_t height, double near, double far, float *Tm, float *nrm, double *depth,
                                 int64_t *box, int32_t *radii, float *centre, float *surf, int64_t surf_cols,
                                 const float *feat, int64_t n_feat, uint64_t *reached, int64_t begin, int64_t end) {
#if defined(__clang__)
#pragma clang fp contract(off)
#endif
    const double fx = K[0], sk = K[1], cx0 = K[2], fy = K[4], cy0 = K[5];
    const double big = 4.0 * (double)(width > height ? width : height);
    for (int64_t i0 = begin; i0 < end; i0 += PRE_LANES) {
        const int n = end - i0 < PRE_LANES ? (int)(end - i0) : PRE_LANES;
        vd w, x, y, z, s0, s1, m0, m1, m2, o;
        for (int l = 0; l < PRE_LANES; l++) {
            const int64_t i = i0 + (l < n ? l : 0);
            w[l] = quats[i * 4], x[l] = quats[i * 4 + 1], y[l] = quats[i * 4 + 2], z[l] = quats[i * 4 + 3];
            s0[l] = scales[i * 2], s1[l] = scales[i * 2 + 1];
            m0[l] = means[i * 3], m1[l] = means[i * 3 + 1], m2[l] = means[i * 3 + 2];
            o[l] = opac[i];
        }
        // numba types float() of a float32 as float32: the squared norm and its root are float32.
        const vf8 wf = __builtin_convertvector(w, vf8), xf = __builtin_convertvector(x, vf8);
        const vf8 yf = __builtin_convertvector(y, vf8), zf = __builtin_convertvector(z, vf8);
        vf8 norm = wf * wf + xf * xf + yf * yf + zf * zf;
        for (int l = 0; l < PRE_LANES; l++) norm[l] = __builtin_sqrtf(norm[l]);
        const vd inv = 1.0 / __builtin_convertvector(norm, vd);
        w = w * inv, x = x * inv, y = y * inv, z = z * inv;
        vd R[3][3];
        R[0][0] = 1 - 2 * (y * y + z * z), R[0][1] = 2 * (x * y - w * z), R[0][2] = 2 * (x * z + w * y);
        R[1][0] = 2 * (x * y + w * z), R[1][1] = 1 - 2 * (x * x + z * z), R[1][2] = 2 * (y * z - w * x);
        R[2][0] = 2 * (x * z - w * y), R[2][1] = 2 * (y * z + w * x), R[2][2] = 1 - 2 * (x * x + y * y);
        vd M[3][3], nv[3];  // camera-frame columns s_u t_u, s_v t_v, p_c; the normal
        for (int r = 0; r < 3; r++) {
            const double a = Rwc[r * 3], b = Rwc[r * 3 + 1], c = Rwc[r * 3 + 2];
            M[r][0] = s0 * (a * R[0][0] + b * R[1][0] + c * R[2][0]);
            M[r][1] = s1 * (a * R[0][1] + b * R[1][1] + c * R[2][1]);
            M[r][2] = a * m0 + b * m1 + c * m2 + twc[r];
            nv[r] = a * R[0][2] + b * R[1][2] + c * R[2][2];
        }
        const vd d = nv[0] * M[0][2] + nv[1] * M[1][2] + nv[2] * M[2][2];
        const vd sgn = d > 0 ? dsplat(-1.0) : (d < 0 ? dsplat(1.0) : dsplat(0.0));
        vd T[3][3];
        for (int c = 0; c < 3; c++) {
            T[0][c] = fx * M[0][c] + sk * M[1][c] + cx0 * M[2][c];
            T[1][c] = fy * M[1][c] + cy0 * M[2][c];
            T[2][c] = M[2][c];
        }
        for (int r = 0; r < 3; r++)  // the geometry of the stored (float32) ray transform
            for (int c = 0; c < 3; c++) T[r][c] = round_to_float(T[r][c]);
        auto cross = [](vd a0, vd a1, vd a2, vd b0, vd b1, vd b2, vd *out) {
            out[0] = a1 * b2 - a2 * b1, out[1] = a2 * b0 - a0 * b2, out[2] = a0 * b1 - a1 * b0;
        };
        vd ax[3], ay[3], a0[3];
        cross(T[1][0], T[1][1], T[1][2], T[2][0], T[2][1], T[2][2], ax);
        cross(T[2][0], T[2][1], T[2][2], T[0][0], T[0][1], T[0][2], ay);
        cross(T[0][0], T[0][1], T[0][2], T[1][0], T[1][1], T[1][2], a0);
        const vd zc = T[2][2];
        vd rho_cut;
        for (int l = 0; l < PRE_LANES; l++) {  // glibc's log, as numba calls it
            // From o >= OPACITY_AT_CUT_MAX, 2 ln(255 o) > 9.001: the cap, without the log.
            if (o[l] >= OPACITY_AT_CUT_MAX) {
                rho_cut[l] = RHO_CUT_MAX;
                continue;
            }
            const double v = 2.0 * __builtin_log(255.0 * o[l]);
            rho_cut[l] = o[l] > 0 ? (v < RHO_CUT_MAX ? v : RHO_CUT_MAX) : -1.0;
        }
        const vd det = T[2][0] * a0[0] + T[2][1] * a0[1] + T[2][2] * a0[2];
        const vd inv_det = det != 0.0 ? 1.0 / (det != 0.0 ? det : 1.0) : 0.0;
        const vd inv_zc = zc != 0.0 ? 1.0 / (zc != 0.0 ? zc : 1.0) : 0.0;
        const vd rho_max = rho_cut * (1.0 + RHO_SLACK) + RHO_SLACK;
        const vl drawn = (zc >= near) & (zc <= far) & (rho_cut >= 0.0);
        const vd pcx = drawn ? T[0][2] / zc : 0.0, pcy = drawn ? T[1][2] / zc : 0.0;
        // Support box: the disc's image through the dual conic, union the low-pass square
        // (the numba kernel's comments).
        const vd r2 = rho_cut;
        const vd c22 = r2 * (T[2][0] * T[2][0] + T[2][1] * T[2][1]) - T[2][2] * T[2][2];
        const vd d2 = lane_sqrt(py_max(r2, dsplat(0.0)) / 2.0);
        vd lo_x = dsplat(-big), hi_x = dsplat(big), lo_y = dsplat(-big), hi_y = dsplat(big);
        const vl ellipse = c22 < 0;
        {
            const vd den = ellipse ? c22 : -1.0;
            const vd c02 = r2 * (T[0][0] * T[2][0] + T[0][1] * T[2][1]) - T[0][2] * T[2][2];
            const vd c12 = r2 * (T[1][0] * T[2][0] + T[1][1] * T[2][1]) - T[1][2] * T[2][2];
            const vd c00 = r2 * (T[0][0] * T[0][0] + T[0][1] * T[0][1]) - T[0][2] * T[0][2];
            const vd c11 = r2 * (T[1][0] * T[1][0] + T[1][1] * T[1][1]) - T[1][2] * T[1][2];
            const vd xc = c02 / den, yc = c12 / den;
            const vd hx = lane_sqrt(py_max(xc * xc - c00 / den, dsplat(0.0)));
            const vd hy = lane_sqrt(py_max(yc * yc - c11 / den, dsplat(0.0)));
            const vd lx = py_min(xc - hx, pcx - d2), ux = py_max(xc + hx, pcx + d2);
            const vd ly = py_min(yc - hy, pcy - d2), uy = py_max(yc + hy, pcy + d2);
            const vd inf = dsplat(__builtin_inf());
            const vl finite = (lx > -inf) & (lx < inf) & (ux > -inf) & (ux < inf) & (ly > -inf) & (ly < inf) &
                              (uy > -inf) & (uy < inf);
            const vl use = ellipse & finite;
            lo_x = use ? lx : lo_x, hi_x = use ? ux : hi_x, lo_y = use ? ly : lo_y, hi_y = use ? uy : hi_y;
        }
        const vd rad = py_max(py_max(hi_x - pcx, pcx - lo_x), py_max(hi_y - pcy, pcy - lo_y));
        for (int l = 0; l < n; l++) {
            const int64_t i = i0 + l;
            float *tm = Tm + i * 9, *row = surf + i * surf_cols;
            for (int r = 0; r < 3; r++)
                for (int c = 0; c < 3; c++) tm[3 * r + c] = (float)T[r][c][l];
            for (int r = 0; r < 3; r++) nrm[i * 3 + r] = row[E_NRM + r] = (float)(sgn[l] * nv[r][l]);
            depth[i] = zc[l];
            row[E_ZC] = tm[8];
            for (int c = 0; c < 3; c++) {
                row[GEO_AX + c] = (float)ax[c][l];
                row[GEO_AY + c] = (float)ay[c][l];
                row[GEO_A0 + c] = (float)a0[c][l];
            }
            row[GEO_DET] = (float)det[l], row[GEO_INV_DET] = (float)inv_det[l], row[GEO_INV_ZC] = (float)inv_zc[l];
            row[GEO_RHO_MAX] = (float)rho_max[l], row[GEO_OPACITY] = (float)o[l];
            row[GEO_CX] = centre[i * 2] = (float)pcx[l];
            row[GEO_CY] = centre[i * 2 + 1] = (float)pcy[l];
            for (int64_t c = 0; c < n_feat; c++) row[E_FEAT + c] = feat[i * n_feat + c];
            int64_t b[4] = {0, -1, 0, -1};
            radii[i] = 0;
            if (drawn[l]) {
                const double fw = (double)width, fh = (double)height;
                const double ex0 = lo_x[l] - 0.5, ex1 = hi_x[l] + 0.5, ey0 = lo_y[l] - 0.5, ey1 = hi_y[l] + 0.5;
                int64_t xmin = (int64_t)__builtin_ceil(ex0 > -1.0 ? ex0 : -1.0);
                int64_t xmax = (int64_t)__builtin_floor(ex1 < fw ? ex1 : fw);
                int64_t ymin = (int64_t)__builtin_ceil(ey0 > -1.0 ? ey0 : -1.0);
                int64_t ymax = (int64_t)__builtin_floor(ey1 < fh ? ey1 : fh);
                xmin = xmin > 0 ? xmin : 0, ymin = ymin > 0 ? ymin : 0;
                xmax = xmax < width - 1 ? xmax : width - 1, ymax = ymax < height - 1 ? ymax : height - 1;
                if (xmin <= xmax && ymin <= ymax) {
                    b[0] = xmin, b[1] = xmax, b[2] = ymin, b[3] = ymax;
                    const double rc = rad[l] > 0.0 ? rad[l] : 0.0;
                    const int64_t rr = (int64_t)__builtin_ceil(rc < big ? rc : big);
                    radii[i] = (int32_t)(rr > 1 ? rr : 1);
                }
            }
            for (int k = 0; k < 4; k++) box[i * 4 + k] = b[k], row[E_BOX + k] = (float)b[k];
            reached[i] = radii[i] > 0 ? reach_bits(b, row) : 0;
        }
    }
}

// ---- Tile binning (``_kernels.bin_tiles``' two passes over one part of the depth order; the
// same lists and slots). The boxes are read in depth order, i.e. at scattered ids: fetched a
// few surfels ahead, which numba cannot ask for.
constexpr int BIN_AHEAD = 16;

// ``_kernels.bin_tiles``' count over entries [begin, end) of the depth order (``n`` long): each
// entry's tile range, its surfel's count of tiles reached (``reached``: the set-up's bits), and
// per tile the entries and their box pixels (added to ``counts`` and ``pixels``, one row per
// part of the order).
NO_CONTRACT void simd_bin_count(const int64_t *front_to_back, const int64_t *box, const uint64_t *reached,
                                const float *surf, int64_t surf_cols, int64_t begin, int64_t end, int64_t n,
                                int64_t n_tx, int32_t *tiles, int64_t *per_surfel, int64_t *counts, int64_t *pixels) {
    for (int64_t k = begin; k < end; k++) {
        if (k + BIN_AHEAD < n) {
            __builtin_prefetch(box + front_to_back[k + BIN_AHEAD] * 4);
            __builtin_prefetch(reached + front_to_back[k + BIN_AHEAD]);
        }
        const int64_t s = front_to_back[k];
        const int64_t *b = box + s * 4;
        const int64_t tx0 = b[0] >> TILE_SHIFT, tx1 = b[1] >> TILE_SHIFT, ty0 = b[2] >> TILE_SHIFT,
                      ty1 = b[3] >> TILE_SHIFT;
        int32_t *tk = tiles + k * 4;
        tk[0] = (int32_t)tx0, tk[1] = (int32_t)tx1, tk[2] = (int32_t)ty0, tk[3] = (int32_t)ty1;
        const int64_t n_box_tiles = (tx1 - tx0 + 1) * (ty1 - ty0 + 1);
        TileConic conic;
        if (n_box_tiles > 64) conic = tile_conic(surf + s * surf_cols);
        int64_t kept = 0, i = 0;
        for (int64_t ty = ty0; ty <= ty1; ty++) {
            const int64_t rows = (b[3] < ty * TILE + TILE - 1 ? b[3] : ty * TILE + TILE - 1) - (b[2] > ty * TILE ? b[2] : ty * TILE) + 1;
            for (int64_t tx = tx0; tx <= tx1; tx++, i++) {
                if (!tile_of_box_reached(reached[s], n_box_tiles, i, b, &conic, tx, ty)) continue;
                const int64_t x0 = tx * TILE, t = ty * n_tx + tx;
                counts[t] += 1;
                pixels[t] += rows * ((b[1] < x0 + TILE - 1 ? b[1] : x0 + TILE - 1) - (b[0] > x0 ? b[0] : x0) + 1);
                kept++;
            }
        }
        per_surfel[s + 1] = kept;
    }
}

// Its fill: each entry's surfel and gradient slot at its tile's ``cursor`` (advanced).
NO_CONTRACT void simd_bin_fill(const int64_t *front_to_back, const int64_t *box, const uint64_t *reached,
                               const float *surf, int64_t surf_cols, const int32_t *tiles, const int64_t *emit_start,
                               int64_t begin, int64_t end, int64_t n, int64_t n_tx, int64_t *cursor,
                               int32_t *tile_list, int64_t *slot_of_entry) {
    for (int64_t k = begin; k < end; k++) {
        if (k + BIN_AHEAD < n) {
            __builtin_prefetch(emit_start + front_to_back[k + BIN_AHEAD]);
            __builtin_prefetch(reached + front_to_back[k + BIN_AHEAD]);
        }
        const int64_t s = front_to_back[k];
        const int32_t *tk = tiles + k * 4;
        const int64_t n_box_tiles = (int64_t)(tk[1] - tk[0] + 1) * (tk[3] - tk[2] + 1);
        TileConic conic;
        if (n_box_tiles > 64) conic = tile_conic(surf + s * surf_cols);
        int64_t slot = emit_start[s], i = 0;
        for (int64_t ty = tk[2]; ty <= tk[3]; ty++)
            for (int64_t tx = tk[0]; tx <= tk[1]; tx++, i++) {
                if (!tile_of_box_reached(reached[s], n_box_tiles, i, box + s * 4, &conic, tx, ty)) continue;
                const int64_t j = cursor[ty * n_tx + tx]++;
                tile_list[j] = (int32_t)s;
                slot_of_entry[j] = slot++;
            }
    }
}

// The kernels' exp on n floats (tested against numpy's).
void simd_exp(const float *x, float *out, int64_t n) {
    for (int64_t i = 0; i < n; i += 16) {
        vf v = {};
        const int64_t k = n - i < 16 ? n - i : 16;
        for (int64_t l = 0; l < k; l++) v[l] = x[i + l];
        const vf e = vexp<16>(v);
        for (int64_t l = 0; l < k; l++) out[i + l] = e[l];
    }
}

}  // extern "C"
