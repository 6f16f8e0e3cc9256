import math
import numpy as np
from numba import njit, prange
from pipeline.rasterizer._kernels import (_CHUNK, _CONTRACT, _cross, S_AX, S_AY, S_A0, S_DET, S_CX, S_CY, S_TW2,
                                          S_OPACITY, S_NORMAL, S_FEATURE)


@njit(parallel=True, cache=True, error_model="numpy", fastmath=_CONTRACT)
def reduce_and_chain2(
    emit_start, slots, quats, scales, means, Tm, nrm, K, Rwc,
    d_means, d_quats, d_scales, d_opac, d_feat, d_means2d,
):  # fmt: skip
    G = slots.shape[1]
    C = d_feat.shape[1]
    P = means.shape[0]
    k00, k01, k02, k11, k12 = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    for chunk in prange(-(-P // _CHUNK)):
        g = np.zeros((_CHUNK, G))
        lo = chunk * _CHUNK
        hi = min(P, lo + _CHUNK)
        for i in range(lo, hi):
            for e in range(emit_start[i], emit_start[i + 1]):
                for k in range(G):
                    g[i - lo, k] += slots[e, k]
        for i in range(lo, hi):
            if emit_start[i] == emit_start[i + 1]:  # never drawn: zero gradients
                d_means[i, :] = 0.0
                d_quats[i, :] = 0.0
                d_scales[i, :] = 0.0
                d_opac[i] = 0.0
                d_feat[i, :] = 0.0
                d_means2d[i, :] = 0.0
                continue
            gi = g[i - lo]
            Tu0, Tu1, Tu2 = float(Tm[i, 0]), float(Tm[i, 1]), float(Tm[i, 2])
            Tv0, Tv1, Tv2 = float(Tm[i, 3]), float(Tm[i, 4]), float(Tm[i, 5])
            Tw0, Tw1, Tw2 = float(Tm[i, 6]), float(Tm[i, 7]), float(Tm[i, 8])
            gx0, gx1, gx2 = gi[S_AX], gi[S_AX + 1], gi[S_AX + 2]
            gy0, gy1, gy2 = gi[S_AY], gi[S_AY + 1], gi[S_AY + 2]
            g00, g01, g02 = gi[S_A0], gi[S_A0 + 1], gi[S_A0 + 2]
            gdet = gi[S_DET]
            ax0, ax1, ax2 = _cross(Tv0, Tv1, Tv2, Tw0, Tw1, Tw2)
            ay0, ay1, ay2 = _cross(Tw0, Tw1, Tw2, Tu0, Tu1, Tu2)
            az0, az1, az2 = _cross(Tu0, Tu1, Tu2, Tv0, Tv1, Tv2)
            r10, r11, r12 = _cross(gy0, gy1, gy2, Tw0, Tw1, Tw2)
            r20, r21, r22 = _cross(Tv0, Tv1, Tv2, g00, g01, g02)
            r30, r31, r32 = _cross(Tw0, Tw1, Tw2, gx0, gx1, gx2)
            r40, r41, r42 = _cross(g00, g01, g02, Tu0, Tu1, Tu2)
            r50, r51, r52 = _cross(gx0, gx1, gx2, Tv0, Tv1, Tv2)
            r60, r61, r62 = _cross(Tu0, Tu1, Tu2, gy0, gy1, gy2)
            gcx, gcy = gi[S_CX], gi[S_CY]
            dT0 = r10 + r20 + gdet * ax0
            dT1 = r11 + r21 + gdet * ax1
            dT2 = r12 + r22 + gdet * ax2
            dT3 = r30 + r40 + gdet * ay0
            dT4 = r31 + r41 + gdet * ay1
            dT5 = r32 + r42 + gdet * ay2
            dT6 = r50 + r60 + gdet * az0
            dT7 = r51 + r61 + gdet * az1
            dT8 = r52 + r62 + gdet * az2
            dT2 += gcx / Tw2
            dT5 += gcy / Tw2
            dT8 += gi[S_TW2] - (gcx * Tu2 + gcy * Tv2) / (Tw2 * Tw2)
            d_means2d[i, 0] = dT0 * Tw0 + dT1 * Tw1 + dT2 * Tw2
            d_means2d[i, 1] = dT3 * Tw0 + dT4 * Tw1 + dT5 * Tw2
            d_opac[i] = gi[S_OPACITY]
            for c in range(C):
                d_feat[i, c] = gi[S_FEATURE + c]
            dM00, dM01, dM02 = k00 * dT0, k00 * dT1, k00 * dT2
            dM10, dM11, dM12 = k01 * dT0 + k11 * dT3, k01 * dT1 + k11 * dT4, k01 * dT2 + k11 * dT5
            dM20 = k02 * dT0 + k12 * dT3 + dT6
            dM21 = k02 * dT1 + k12 * dT4 + dT7
            dM22 = k02 * dT2 + k12 * dT5 + dT8
            w, x, y, z = float(quats[i, 0]), float(quats[i, 1]), float(quats[i, 2]), float(quats[i, 3])
            qn = math.sqrt(w * w + x * x + y * y + z * z)
            w, x, y, z = w / qn, x / qn, y / qn, z / qn
            R00, R01, R02 = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
            R10, R11, R12 = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
            R20, R21, R22 = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
            s0, s1 = float(scales[i, 0]), float(scales[i, 1])
            sgn = 0.0
            for r in range(3):
                sgn += float(nrm[i, r]) * (Rwc[r, 0] * R02 + Rwc[r, 1] * R12 + Rwc[r, 2] * R22)
            sgn = 1.0 if sgn > 0.5 else (-1.0 if sgn < -0.5 else 0.0)
            gn0, gn1, gn2 = gi[S_NORMAL], gi[S_NORMAL + 1], gi[S_NORMAL + 2]
            # r = 0, 1, 2 unrolled: the columns of R_wc^T
            dc0 = Rwc[0, 0] * dM00 + Rwc[1, 0] * dM10 + Rwc[2, 0] * dM20
            dc1 = Rwc[0, 0] * dM01 + Rwc[1, 0] * dM11 + Rwc[2, 0] * dM21
            dn = Rwc[0, 0] * gn0 + Rwc[1, 0] * gn1 + Rwc[2, 0] * gn2
            dR00, dR01, dR02 = s0 * dc0, s1 * dc1, sgn * dn
            ds0 = 0.0 + dc0 * R00
            ds1 = 0.0 + dc1 * R01
            d_means[i, 0] = Rwc[0, 0] * dM02 + Rwc[1, 0] * dM12 + Rwc[2, 0] * dM22
            dc0 = Rwc[0, 1] * dM00 + Rwc[1, 1] * dM10 + Rwc[2, 1] * dM20
            dc1 = Rwc[0, 1] * dM01 + Rwc[1, 1] * dM11 + Rwc[2, 1] * dM21
            dn = Rwc[0, 1] * gn0 + Rwc[1, 1] * gn1 + Rwc[2, 1] * gn2
            dR10, dR11, dR12 = s0 * dc0, s1 * dc1, sgn * dn
            ds0 += dc0 * R10
            ds1 += dc1 * R11
            d_means[i, 1] = Rwc[0, 1] * dM02 + Rwc[1, 1] * dM12 + Rwc[2, 1] * dM22
            dc0 = Rwc[0, 2] * dM00 + Rwc[1, 2] * dM10 + Rwc[2, 2] * dM20
            dc1 = Rwc[0, 2] * dM01 + Rwc[1, 2] * dM11 + Rwc[2, 2] * dM21
            dn = Rwc[0, 2] * gn0 + Rwc[1, 2] * gn1 + Rwc[2, 2] * gn2
            dR20, dR21, dR22 = s0 * dc0, s1 * dc1, sgn * dn
            ds0 += dc0 * R20
            ds1 += dc1 * R21
            d_means[i, 2] = Rwc[0, 2] * dM02 + Rwc[1, 2] * dM12 + Rwc[2, 2] * dM22
            d_scales[i, 0] = ds0
            d_scales[i, 1] = ds1
            dw = 2 * (-z * dR01 + y * dR02 + z * dR10 - x * dR12 - y * dR20 + x * dR21)
            dx = 2 * (y * dR01 + z * dR02 + y * dR10 - 2 * x * dR11 - w * dR12
                      + z * dR20 + w * dR21 - 2 * x * dR22)  # fmt: skip
            dy = 2 * (-2 * y * dR00 + x * dR01 + w * dR02 + x * dR10 + z * dR12
                      - w * dR20 + z * dR21 - 2 * y * dR22)  # fmt: skip
            dz = 2 * (-2 * z * dR00 - w * dR01 + x * dR02 + w * dR10 - 2 * z * dR11
                      + y * dR12 + x * dR20 + y * dR21)  # fmt: skip
            dot = w * dw + x * dx + y * dy + z * dz
            d_quats[i, 0] = (dw - w * dot) / qn
            d_quats[i, 1] = (dx - x * dot) / qn
            d_quats[i, 2] = (dy - y * dot) / qn
            d_quats[i, 3] = (dz - z * dot) / qn
