// Projection of Gaussians into the image (EWA local-affine approximation) with the hand-written backward.
#pragma once

#include "common.h"

// cam: [model(0 parallel,1 cone), sx, sy, fx, fy, cx, cy, W, H, lim_x, lim_y, R00..R22 (9), t0..t2, k2, near, cutoff]
// mode: 0 radiative, 1 unrectified, 2 alpha (rho is the opacity); mip: modes 1 and 2 apply sqrt(|S^|/|S^'|);
// fvar (3D filter variance) may be NULL.
template <typename T>
struct Cam {
    int cone; T sx, sy, fx, fy, cx, cy; int64_t W, H; T limx, limy, R[9], t[3], k2, near_, cut;
    explicit Cam(const double* c) {
        cone = c[0] > 0.5; sx = c[1]; sy = c[2]; fx = c[3]; fy = c[4]; cx = c[5]; cy = c[6];
        W = (int64_t)c[7]; H = (int64_t)c[8]; limx = c[9]; limy = c[10];
        for (int k = 0; k < 9; ++k) R[k] = c[11 + k];
        for (int k = 0; k < 3; ++k) t[k] = c[20 + k];
        k2 = c[23]; near_ = c[24]; cut = c[25];
    }
};


template <typename T>
static inline void rotmat(const T* qn, T* Rq) {
    const T w = qn[0], x = qn[1], y = qn[2], z = qn[3];
    Rq[0] = 1 - 2 * (y * y + z * z); Rq[1] = 2 * (x * y - w * z); Rq[2] = 2 * (x * z + w * y);
    Rq[3] = 2 * (x * y + w * z); Rq[4] = 1 - 2 * (x * x + z * z); Rq[5] = 2 * (y * z - w * x);
    Rq[6] = 2 * (x * z - w * y); Rq[7] = 2 * (y * z + w * x); Rq[8] = 1 - 2 * (x * x + y * y);
}

// the unit quaternion qn of q (norm floored at 1e-12) and its rotation matrix Rq; returns the norm used
template <typename T>
static inline T unit_rotmat(const T* q, T* qn, T* Rq) {
    T nq = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    if (nq < (T)1e-12) nq = (T)1e-12;
    for (int k = 0; k < 4; ++k) qn[k] = q[k] / nq;
    rotmat(qn, Rq);
    return nq;
}

// |T diag(s) T^T| for the 2x3 T (row-major) by Cauchy-Binet, sum_{j<k} s_j s_k m_jk^2 with m_jk the 2x2 minors of
// T: a sum of non-negative terms, so it keeps its relative precision for needle-like Gaussians, where
// c00 c11 - c01^2 of the rounded entries cancels to noise (or below zero) in float32. V: a scalar or v8f.
template <typename V>
static inline V det_cb(const V* t, const V* s) {
    const V m01 = t[0] * t[4] - t[1] * t[3], m02 = t[0] * t[5] - t[2] * t[3], m12 = t[1] * t[5] - t[2] * t[4];
    return s[0] * s[1] * m01 * m01 + s[0] * s[2] * m02 * m02 + s[1] * s[2] * m12 * m12;
}

// adds g * d det_cb / d t to gT and g * d det_cb / d s to gs
template <typename V>
static inline void det_cb_bwd(const V* t, const V* s, V g, V* gT, V* gs) {
    const V m01 = t[0] * t[4] - t[1] * t[3], m02 = t[0] * t[5] - t[2] * t[3], m12 = t[1] * t[5] - t[2] * t[4];
    const V a01 = g * s[0] * s[1] * m01, a02 = g * s[0] * s[2] * m02, a12 = g * s[1] * s[2] * m12;
    const V b0 = a01 * t[4] + a02 * t[5], b1 = a12 * t[5] - a01 * t[3], b2 = a02 * t[3] + a12 * t[4];
    const V b3 = a01 * t[1] + a02 * t[2], b4 = a01 * t[0] - a12 * t[2], b5 = a02 * t[0] + a12 * t[1];
    gT[0] += b0 + b0; gT[1] += b1 + b1; gT[2] -= b2 + b2;
    gT[3] -= b3 + b3; gT[4] += b4 + b4; gT[5] += b5 + b5;
    gs[0] += g * (s[1] * m01 * m01 + s[2] * m02 * m02);
    gs[1] += g * (s[0] * m01 * m01 + s[2] * m12 * m12);
    gs[2] += g * (s[0] * m02 * m02 + s[1] * m12 * m12);
}

// everything the forward computes for one Gaussian (also recomputed by the backward)
template <typename T>
struct PState {
    T qn[4], qnorm, Rq[9], M[9], s2[3], s2f[3], xc[3], z, tx, ty, r, clx, cly; int unclx, uncly;
    T J2[6], Tm[6], c00, c01, c11, f00, f01, f11, cb, D, dh, rho, ampn, amp, u, v, detJ; int valid;
};

template <typename T>
static inline void proj_one(const Cam<T>& cam, const T* m, const T* s2in, const T* q, T rho, T fv, int mode, int mip,
                            int has_f, PState<T>& S) {
    S.qnorm = unit_rotmat(q, S.qn, S.Rq);
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            S.M[3 * i + j] = cam.R[3 * i] * S.Rq[j] + cam.R[3 * i + 1] * S.Rq[3 + j] + cam.R[3 * i + 2] * S.Rq[6 + j];
    for (int k = 0; k < 3; ++k) { S.s2[k] = s2in[k]; S.s2f[k] = S.s2[k] + (has_f ? fv : (T)0); }
    for (int i = 0; i < 3; ++i)
        S.xc[i] = cam.R[3 * i] * m[0] + cam.R[3 * i + 1] * m[1] + cam.R[3 * i + 2] * m[2] + cam.t[i];
    S.z = S.xc[2];
    if (!cam.cone) {
        S.valid = 1;
        S.u = S.xc[0] / cam.sx + cam.cx; S.v = S.xc[1] / cam.sy + cam.cy;
        S.J2[0] = 1 / cam.sx; S.J2[1] = 0; S.J2[2] = 0; S.J2[3] = 0; S.J2[4] = 1 / cam.sy; S.J2[5] = 0;
        S.detJ = 1 / (cam.sx * cam.sy);
    } else {
        S.valid = S.z > cam.near_;
        const T zs = S.valid ? S.z : (T)1;
        S.z = zs;
        S.u = cam.fx * S.xc[0] / zs + cam.cx; S.v = cam.fy * S.xc[1] / zs + cam.cy;
        T rx = S.xc[0] / zs, ry = S.xc[1] / zs;
        S.unclx = rx >= -cam.limx && rx <= cam.limx; S.uncly = ry >= -cam.limy && ry <= cam.limy;
        S.clx = rx < -cam.limx ? -cam.limx : (rx > cam.limx ? cam.limx : rx);
        S.cly = ry < -cam.limy ? -cam.limy : (ry > cam.limy ? cam.limy : ry);
        S.tx = zs * S.clx; S.ty = zs * S.cly;
        S.r = std::sqrt(S.tx * S.tx + S.ty * S.ty + zs * zs);
        S.J2[0] = cam.fx / zs; S.J2[1] = 0; S.J2[2] = -cam.fx * S.tx / (zs * zs);
        S.J2[3] = 0; S.J2[4] = cam.fy / zs; S.J2[5] = -cam.fy * S.ty / (zs * zs);
        S.detJ = cam.fx * cam.fy * S.r / (zs * zs * zs);
    }
    for (int i = 0; i < 2; ++i)
        for (int j = 0; j < 3; ++j)
            S.Tm[3 * i + j] = S.J2[3 * i] * S.M[j] + S.J2[3 * i + 1] * S.M[3 + j] + S.J2[3 * i + 2] * S.M[6 + j];
    S.c00 = S.c01 = S.c11 = 0;
    for (int k = 0; k < 3; ++k) {
        S.c00 += S.Tm[k] * S.Tm[k] * S.s2f[k];
        S.c01 += S.Tm[k] * S.Tm[3 + k] * S.s2f[k];
        S.c11 += S.Tm[3 + k] * S.Tm[3 + k] * S.s2f[k];
    }
    S.f00 = S.c00 + cam.k2; S.f01 = S.c01; S.f11 = S.c11 + cam.k2;
    S.cb = det_cb(S.Tm, S.s2f);  // |S^|
    S.D = S.cb + cam.k2 * (S.c00 + S.c11) + cam.k2 * cam.k2;  // |S^ + k2 I|
    S.dh = S.cb < (T)1e-20 ? (T)1e-20 : S.cb;
    S.rho = rho;  // mode 2 (alpha): opacity
    // ampn = amplitude per unit density/opacity (so the backward never divides by rho, which may underflow)
    if (mode == 0) {
        // rho sqrt(2 pi |J|^2 prod(s2f) / D) * sqrt(prod(s2)/prod(s2f)) = rho sqrt(2 pi prod(s2) / D) |J|
        S.ampn = std::sqrt((T)6.283185307179586 / S.D * (S.s2[0] * S.s2[1] * S.s2[2])) * S.detJ;
    } else {
        T a = 1;
        if (has_f) a *= std::sqrt((S.s2[0] / S.s2f[0]) * (S.s2[1] / S.s2f[1]) * (S.s2[2] / S.s2f[2]));
        if (mip) a *= std::sqrt(S.dh / S.D);
        S.ampn = a;
    }
    S.amp = S.rho * S.ampn;
}

// activations of a block of Gaussians in separate loops that vectorise (libmvec exp / log1p), so the scalar
// per-Gaussian code below has no transcendental calls left but one sqrt: s2 = exp(2 log s) (3 per Gaussian),
// rho = softplus(raw) (mode 2: sigmoid) and d rho / d raw
constexpr int64_t ACT_BLOCK = 512;
template <typename T>
static void activations(int64_t m, const T* __restrict ls, const T* __restrict draw, int mode, T* __restrict s2,
                        T* __restrict rho, T* __restrict drho) {
    for (int64_t k = 0; k < 3 * m; ++k) s2[k] = ex_(2 * ls[k]);
    if (mode == 2) {
        for (int64_t k = 0; k < m; ++k) {
            const T x = draw[k] < -80 ? (T)(-80) : (draw[k] > 80 ? (T)80 : draw[k]);  // exp stays finite
            const T r = 1 / (1 + ex_(-x));
            rho[k] = r; drho[k] = r * (1 - r);
        }
    } else {
        for (int64_t k = 0; k < m; ++k) {
            const T x = draw[k];
            const T sp = log1p_(ex_(x < 20 ? x : (T)20));
            rho[k] = x > 20 ? x : sp;
            drho[k] = 1 / (1 + ex_(x < -80 ? (T)80 : -x));
        }
    }
}

// ---------------------------------------------------------------- projection, float32: 8 Gaussians per pass
// The algebra of proj_one / proj_bwd lane-wise (same formulas; data-dependent branches become selects): one
// Gaussian's chain of ~200 dependent operations is latency-bound, eight side by side are not.
#if defined(__AVX__)
static inline v8f vsqrt8(v8f x) { return __builtin_ia32_sqrtps256(x); }
#else
static inline v8f vsqrt8(v8f x) { for (int k = 0; k < 8; ++k) x[k] = std::sqrt(x[k]); return x; }
#endif
static inline v8f sel8(v8i m, v8f a, v8f b) { return (v8f)(((v8i)a & m) | ((v8i)b & ~m)); }
static inline v8f max8(v8f a, v8f b) { return sel8(a > b, a, b); }
static inline v8f min8(v8f a, v8f b) { return sel8(a < b, a, b); }
static inline v8f gat8(const float* p, int64_t i, int stride, int off) {
    v8f r;
    for (int k = 0; k < 8; ++k) r[k] = p[(i + k) * stride + off];
    return r;
}
static inline void sct8(float* p, int64_t i, int stride, int off, v8f v) {
    for (int k = 0; k < 8; ++k) p[(i + k) * stride + off] = v[k];
}

struct PState8 {
    v8f qn[4], nq, M[9], s2[3], s2f[3], xc[3], zs, tx, ty, r, clx, cly, J2[6], Tm[6], c00, c01, c11, f00, f01, f11,
        D, dh, ampn, amp;
    v8i valid, unclx, uncly, dh_raw_ok;
};

static inline void proj8(const Cam<float>& cam, const float* means, const float* s2b, const float* quats,
                         const float* rhob, const float* fvar, int mode, int mip, int64_t i, int64_t j, PState8& S) {
    const v8f q0 = gat8(quats, i, 4, 0), q1 = gat8(quats, i, 4, 1);
    const v8f q2 = gat8(quats, i, 4, 2), q3 = gat8(quats, i, 4, 3);
    S.nq = max8(vsqrt8(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3), bc8(1e-12f));
    const v8f w = q0 / S.nq, x = q1 / S.nq, y = q2 / S.nq, z = q3 / S.nq;
    S.qn[0] = w; S.qn[1] = x; S.qn[2] = y; S.qn[3] = z;
    const v8f one = bc8(1.f), two = bc8(2.f), zero = bc8(0.f);
    v8f Rq[9];
    Rq[0] = one - two * (y * y + z * z); Rq[1] = two * (x * y - w * z); Rq[2] = two * (x * z + w * y);
    Rq[3] = two * (x * y + w * z); Rq[4] = one - two * (x * x + z * z); Rq[5] = two * (y * z - w * x);
    Rq[6] = two * (x * z - w * y); Rq[7] = two * (y * z + w * x); Rq[8] = one - two * (x * x + y * y);
    for (int a = 0; a < 3; ++a)
        for (int b = 0; b < 3; ++b)
            S.M[3 * a + b] = bc8(cam.R[3 * a]) * Rq[b] + bc8(cam.R[3 * a + 1]) * Rq[3 + b]
                             + bc8(cam.R[3 * a + 2]) * Rq[6 + b];
    const v8f fv = fvar ? gat8(fvar, i, 1, 0) : zero;
    for (int k = 0; k < 3; ++k) { S.s2[k] = gat8(s2b, j, 3, k); S.s2f[k] = S.s2[k] + fv; }
    const v8f m0 = gat8(means, i, 3, 0), m1 = gat8(means, i, 3, 1), m2 = gat8(means, i, 3, 2);
    for (int a = 0; a < 3; ++a)
        S.xc[a] = bc8(cam.R[3 * a]) * m0 + bc8(cam.R[3 * a + 1]) * m1 + bc8(cam.R[3 * a + 2]) * m2 + bc8(cam.t[a]);
    v8f detJ;
    if (!cam.cone) {
        S.valid = (v8i)(zero == zero);
        S.zs = S.xc[2];
        S.J2[0] = bc8(1.f / cam.sx); S.J2[1] = zero; S.J2[2] = zero;
        S.J2[3] = zero; S.J2[4] = bc8(1.f / cam.sy); S.J2[5] = zero;
        detJ = bc8(1.f / (cam.sx * cam.sy));
    } else {
        S.valid = S.xc[2] > bc8(cam.near_);
        const v8f zs = sel8(S.valid, S.xc[2], one);
        S.zs = zs;
        const v8f rx = S.xc[0] / zs, ry = S.xc[1] / zs, lx = bc8(cam.limx), ly = bc8(cam.limy);
        S.unclx = (rx >= -lx) & (rx <= lx);
        S.uncly = (ry >= -ly) & (ry <= ly);
        S.clx = min8(max8(rx, -lx), lx);
        S.cly = min8(max8(ry, -ly), ly);
        S.tx = zs * S.clx; S.ty = zs * S.cly;
        S.r = vsqrt8(S.tx * S.tx + S.ty * S.ty + zs * zs);
        const v8f fx = bc8(cam.fx), fy = bc8(cam.fy);
        S.J2[0] = fx / zs; S.J2[1] = zero; S.J2[2] = -fx * S.tx / (zs * zs);
        S.J2[3] = zero; S.J2[4] = fy / zs; S.J2[5] = -fy * S.ty / (zs * zs);
        detJ = fx * fy * S.r / (zs * zs * zs);
    }
    for (int a = 0; a < 2; ++a)
        for (int b = 0; b < 3; ++b)
            S.Tm[3 * a + b] = S.J2[3 * a] * S.M[b] + S.J2[3 * a + 1] * S.M[3 + b] + S.J2[3 * a + 2] * S.M[6 + b];
    S.c00 = zero; S.c01 = zero; S.c11 = zero;
    for (int k = 0; k < 3; ++k) {
        S.c00 += S.Tm[k] * S.Tm[k] * S.s2f[k];
        S.c01 += S.Tm[k] * S.Tm[3 + k] * S.s2f[k];
        S.c11 += S.Tm[3 + k] * S.Tm[3 + k] * S.s2f[k];
    }
    const v8f k2 = bc8(cam.k2);
    S.f00 = S.c00 + k2; S.f01 = S.c01; S.f11 = S.c11 + k2;
    const v8f dh = det_cb(S.Tm, S.s2f);
    S.D = dh + k2 * (S.c00 + S.c11) + k2 * k2;
    S.dh_raw_ok = dh >= bc8(1e-20f);
    S.dh = max8(dh, bc8(1e-20f));
    if (mode == 0) {
        S.ampn = vsqrt8(bc8(6.283185307179586f) / S.D * (S.s2[0] * S.s2[1] * S.s2[2])) * detJ;
    } else {
        v8f a = one;
        if (fvar) a *= vsqrt8((S.s2[0] / S.s2f[0]) * (S.s2[1] / S.s2f[1]) * (S.s2[2] / S.s2f[2]));
        if (mip) a *= vsqrt8(S.dh / S.D);
        S.ampn = a;
    }
    v8f rho;
    std::memcpy(&rho, rhob + j, sizeof rho);
    S.amp = rho * S.ampn;
}

static inline void proj8_fwd(const Cam<float>& cam, const float* means, const float* s2b, const float* quats,
                             const float* rhob, const float* fvar, int mode, int mip, int64_t i, int64_t j,
                             float* m2d, float* con, float* amp, float* depth, uint8_t* valid, float* hxb,
                             float* hyb) {
    PState8 S;
    proj8(cam, means, s2b, quats, rhob, fvar, mode, mip, i, j, S);
    v8f u, v;
    if (!cam.cone) {
        u = S.xc[0] / bc8(cam.sx) + bc8(cam.cx); v = S.xc[1] / bc8(cam.sy) + bc8(cam.cy);
    } else {
        u = bc8(cam.fx) * S.xc[0] / S.zs + bc8(cam.cx); v = bc8(cam.fy) * S.xc[1] / S.zs + bc8(cam.cy);
    }
    sct8(m2d, i, 2, 0, u); sct8(m2d, i, 2, 1, v);
    sct8(con, i, 3, 0, S.f11 / S.D); sct8(con, i, 3, 1, -S.f01 / S.D); sct8(con, i, 3, 2, S.f00 / S.D);
    sct8(amp, i, 1, 0, S.amp); sct8(depth, i, 1, 0, S.xc[2]);
    for (int k = 0; k < 8; ++k) valid[i + k] = (uint8_t)(S.valid[k] != 0);
    const v8f cut = bc8(cam.cut), zero = bc8(0.f);
    const v8f hx = cut * vsqrt8(max8(S.f00, zero)), hy = cut * vsqrt8(max8(S.f11, zero));
    std::memcpy(hxb + j, &hx, sizeof hx);
    std::memcpy(hyb + j, &hy, sizeof hy);
}

static inline void proj8_bwd(const Cam<float>& cam, const float* means, const float* s2b, const float* quats,
                             const float* rhob, const float* drhob, const float* fvar, int mode, int mip, int64_t i,
                             int64_t j, const float* gm2d, const float* gcon, const float* gamp, float* gmeans,
                             float* gls, float* gq, float* gdraw) {
    PState8 S;
    proj8(cam, means, s2b, quats, rhob, fvar, mode, mip, i, j, S);
    const v8f zero = bc8(0.f), two = bc8(2.f), half = bc8(0.5f);
    v8f g_ls[3] = {zero, zero, zero}, g_s2f[3] = {zero, zero, zero}, g_xc[3] = {zero, zero, zero};
    v8f g_logdetJ = zero, gD = zero, gdh = zero;
    const v8f ga = gat8(gamp, i, 1, 0);
    v8f drho;
    std::memcpy(&drho, drhob + j, sizeof drho);
    const v8f g_rho = ga * S.ampn, gaa = ga * S.amp;
    if (mode == 0) {
        for (int k = 0; k < 3; ++k) g_ls[k] += gaa;
        g_logdetJ += gaa;
        gD += -half * gaa / S.D;
    } else {
        if (fvar)
            for (int k = 0; k < 3; ++k) g_ls[k] += gaa;
        if (mip) {
            gD += -half * gaa / S.D;
            gdh += sel8(S.dh_raw_ok, half * gaa / S.dh, zero);
        }
        if (fvar)
            for (int k = 0; k < 3; ++k) g_s2f[k] += -half * gaa / S.s2f[k];
    }
    sct8(gdraw, i, 1, 0, g_rho * drho);
    const v8f gA = gat8(gcon, i, 3, 0), gB = gat8(gcon, i, 3, 1), gC = gat8(gcon, i, 3, 2), D = S.D;
    gD += -(gA * S.f11 - gB * S.f01 + gC * S.f00) / (D * D);
    // D = |S^| + k2 (c00 + c11) + k2^2 with |S^| = det_cb (gdh is zero where the floor holds)
    const v8f k2 = bc8(cam.k2);
    const v8f g_c00 = gC / D + gD * k2, g_c11 = gA / D + gD * k2, g_c01 = -gB / D;
    v8f gT[6];
    for (int k = 0; k < 3; ++k) {
        gT[k] = (two * g_c00 * S.Tm[k] + g_c01 * S.Tm[3 + k]) * S.s2f[k];
        gT[3 + k] = (two * g_c11 * S.Tm[3 + k] + g_c01 * S.Tm[k]) * S.s2f[k];
        g_s2f[k] += g_c00 * S.Tm[k] * S.Tm[k] + g_c01 * S.Tm[k] * S.Tm[3 + k] + g_c11 * S.Tm[3 + k] * S.Tm[3 + k];
    }
    det_cb_bwd(S.Tm, S.s2f, gD + gdh, gT, g_s2f);
    for (int k = 0; k < 3; ++k) g_ls[k] += two * S.s2[k] * g_s2f[k];
    v8f gJ2[6], gM[9], gRq[9];
    for (int a = 0; a < 2; ++a)
        for (int b = 0; b < 3; ++b)
            gJ2[3 * a + b] = gT[3 * a] * S.M[3 * b] + gT[3 * a + 1] * S.M[3 * b + 1] + gT[3 * a + 2] * S.M[3 * b + 2];
    for (int a = 0; a < 3; ++a)
        for (int b = 0; b < 3; ++b) gM[3 * a + b] = S.J2[a] * gT[b] + S.J2[3 + a] * gT[3 + b];
    for (int a = 0; a < 3; ++a)
        for (int b = 0; b < 3; ++b)
            gRq[3 * a + b] = bc8(cam.R[a]) * gM[b] + bc8(cam.R[3 + a]) * gM[3 + b] + bc8(cam.R[6 + a]) * gM[6 + b];
    const v8f w = S.qn[0], x = S.qn[1], y = S.qn[2], z = S.qn[3];
    v8f gqn[4];
    gqn[0] = two * (-z * gRq[1] + y * gRq[2] + z * gRq[3] - x * gRq[5] - y * gRq[6] + x * gRq[7]);
    gqn[1] = two * (y * gRq[1] + z * gRq[2] + y * gRq[3] - two * x * gRq[4] - w * gRq[5] + z * gRq[6] + w * gRq[7]
                    - two * x * gRq[8]);
    gqn[2] = two * (-two * y * gRq[0] + x * gRq[1] + w * gRq[2] + x * gRq[3] + z * gRq[5] - w * gRq[6] + z * gRq[7]
                    - two * y * gRq[8]);
    gqn[3] = two * (-two * z * gRq[0] - w * gRq[1] + x * gRq[2] + w * gRq[3] - two * z * gRq[4] + y * gRq[5]
                    + x * gRq[6] + y * gRq[7]);
    const v8f dotq = gqn[0] * w + gqn[1] * x + gqn[2] * y + gqn[3] * z;
    for (int k = 0; k < 4; ++k) sct8(gq, i, 4, k, (gqn[k] - S.qn[k] * dotq) / S.nq);
    const v8f gu = gat8(gm2d, i, 2, 0), gv = gat8(gm2d, i, 2, 1);
    if (!cam.cone) {
        g_xc[0] += gu / bc8(cam.sx); g_xc[1] += gv / bc8(cam.sy);
    } else {
        const v8f fx = bc8(cam.fx), fy = bc8(cam.fy), zs = S.zs, z2 = zs * zs, z3 = z2 * zs;
        v8f d0 = gu * fx / zs, d1 = gv * fy / zs, d2 = -gu * fx * S.xc[0] / z2 - gv * fy * S.xc[1] / z2;
        v8f gz = -gJ2[0] * fx / z2 + two * gJ2[2] * fx * S.tx / z3 - gJ2[4] * fy / z2 + two * gJ2[5] * fy * S.ty / z3;
        v8f gtx = -gJ2[2] * fx / z2, gty = -gJ2[5] * fy / z2;
        const v8f r2 = S.r * S.r;
        gtx += g_logdetJ * S.tx / r2; gty += g_logdetJ * S.ty / r2; gz += g_logdetJ * (zs / r2 - bc8(3.f) / zs);
        d0 += sel8(S.unclx, gtx, zero); gz += sel8(S.unclx, zero, gtx * S.clx);
        d1 += sel8(S.uncly, gty, zero); gz += sel8(S.uncly, zero, gty * S.cly);
        d2 += gz;
        g_xc[0] += sel8(S.valid, d0, zero); g_xc[1] += sel8(S.valid, d1, zero); g_xc[2] += sel8(S.valid, d2, zero);
    }
    for (int k = 0; k < 3; ++k) sct8(gls, i, 3, k, g_ls[k]);
    for (int k = 0; k < 3; ++k)
        sct8(gmeans, i, 3, k, bc8(cam.R[k]) * g_xc[0] + bc8(cam.R[3 + k]) * g_xc[1] + bc8(cam.R[6 + k]) * g_xc[2]);
}

template <typename T>
static void proj_fwd(int64_t n, const T* means, const T* ls, const T* quats, const T* draw, const T* fvar,
                     const double* camp, int mode, int mip, T* m2d, T* con, T* amp, T* depth, int64_t* bb,
                     int32_t* radii, uint8_t* valid, uint8_t* visible, int32_t* bad, int nt) {
    const Cam<T> cam(camp);
    // blocks of Gaussians in separate passes: each loop is short and independent across Gaussians, so the
    // out-of-order core overlaps them (a single fused loop is latency-bound: ~100 ns per Gaussian)
    parallel_for(n, nt, [&](int64_t i0, int64_t i1, int) {
    bool any_bad = false;
    T s2b[3 * ACT_BLOCK], rhob[ACT_BLOCK], drhob[ACT_BLOCK], hxb[ACT_BLOCK], hyb[ACT_BLOCK];
    for (int64_t b0 = i0; b0 < i1; b0 += ACT_BLOCK) {
        const int64_t m = i1 - b0 < ACT_BLOCK ? i1 - b0 : ACT_BLOCK;
        activations(m, ls + 3 * b0, draw + b0, mode, s2b, rhob, drhob);
        // non-finite parameters: flagged here, named by the caller (cheaper than torch reductions per view)
        for (int64_t i = b0; i < b0 + m; ++i) {
            bool ok = finite_((double)draw[i]) && (fvar == nullptr || (finite_((double)fvar[i]) && fvar[i] >= 0));
            for (int k = 0; k < 3; ++k) ok = ok && finite_((double)means[3 * i + k]) && finite_((double)ls[3 * i + k]);
            for (int k = 0; k < 4; ++k) ok = ok && finite_((double)quats[4 * i + k]);
            any_bad = any_bad || !ok;
        }
        for (int64_t j = 0; j < m; ++j) {
            const int64_t i = b0 + j;
            if constexpr (std::is_same<T, float>::value) {
                if (j + 8 <= m) {
                    proj8_fwd(cam, means, s2b, quats, rhob, fvar, mode, mip, i, j, m2d, con, amp, depth, valid, hxb,
                              hyb);
                    j += 7;
                    continue;
                }
            }
            PState<T> S;
            proj_one(cam, means + 3 * i, s2b + 3 * j, quats + 4 * i, rhob[j], fvar ? fvar[i] : (T)0, mode, mip,
                     fvar != nullptr, S);
            m2d[2 * i] = S.u; m2d[2 * i + 1] = S.v;
            con[3 * i] = S.f11 / S.D; con[3 * i + 1] = -S.f01 / S.D; con[3 * i + 2] = S.f00 / S.D;
            amp[i] = S.amp; depth[i] = S.xc[2];
            valid[i] = (uint8_t)S.valid;
            hxb[j] = cam.cut * std::sqrt(S.f00 > 0 ? S.f00 : (T)0);
            hyb[j] = cam.cut * std::sqrt(S.f11 > 0 ? S.f11 : (T)0);
        }
        // bounding boxes: pixel centres (i + 0.5) inside [m - h, m + h], clipped to the image; empty if culled
        const T Wt = (T)cam.W, Ht = (T)cam.H;
        auto cl = [](T x, T lo, T hi) { return x < lo ? lo : (x > hi ? hi : x); };
        for (int64_t j = 0; j < m; ++j) {
            const int64_t i = b0 + j;
            const T u = m2d[2 * i], v = m2d[2 * i + 1], hx = hxb[j], hy = hyb[j];
            int64_t u0 = 0, u1 = 0, v0 = 0, v1 = 0;
            if (valid[i] && finite_((double)u) && finite_((double)v) && finite_((double)hx) && finite_((double)hy)) {
                u0 = (int64_t)cl(std::ceil(cl(u - hx - (T)0.5, (T)-2, Wt + 2)), 0, Wt);
                u1 = (int64_t)cl(std::floor(cl(u + hx - (T)0.5, (T)-2, Wt + 2)) + 1, 0, Wt);
                v0 = (int64_t)cl(std::ceil(cl(v - hy - (T)0.5, (T)-2, Ht + 2)), 0, Ht);
                v1 = (int64_t)cl(std::floor(cl(v + hy - (T)0.5, (T)-2, Ht + 2)) + 1, 0, Ht);
                if (u1 < u0) u1 = u0;
                if (v1 < v0) v1 = v0;
            }
            bb[4 * i] = u0; bb[4 * i + 1] = u1; bb[4 * i + 2] = v0; bb[4 * i + 3] = v1;
            const bool vis = u1 > u0 && v1 > v0;
            visible[i] = (uint8_t)vis;
            radii[i] = vis ? (int32_t)((u1 - u0 > v1 - v0 ? u1 - u0 : v1 - v0) / 2 + 1) : 0;
        }
    }
    if (any_bad) __atomic_store_n(bad, 1, __ATOMIC_RELAXED);
    });
}

template <typename T>
static void proj_bwd(int64_t n, const T* means, const T* ls, const T* quats, const T* draw, const T* fvar,
                     const double* camp, int mode, int mip, const T* gm2d, const T* gcon, const T* gamp,
                     T* gmeans, T* gls, T* gq, T* gdraw, int nt) {
    const Cam<T> cam(camp);
    parallel_for(n, nt, [&](int64_t i0, int64_t i1, int) {
    T s2b[3 * ACT_BLOCK], rhob[ACT_BLOCK], drhob[ACT_BLOCK];
    for (int64_t i = i0; i < i1; ++i) {
        const int64_t j = (i - i0) % ACT_BLOCK;
        if (j == 0) activations(i1 - i < ACT_BLOCK ? i1 - i : ACT_BLOCK, ls + 3 * i, draw + i, mode, s2b, rhob, drhob);
        if constexpr (std::is_same<T, float>::value) {
            if (i + 8 <= i1) {  // blocks are multiples of 8 long: a group of 8 never straddles two
                proj8_bwd(cam, means, s2b, quats, rhob, drhob, fvar, mode, mip, i, j, gm2d, gcon, gamp, gmeans, gls,
                          gq, gdraw);
                i += 7;
                continue;
            }
        }
        PState<T> S;
        const int has_f = fvar != nullptr;
        proj_one(cam, means + 3 * i, s2b + 3 * j, quats + 4 * i, rhob[j], has_f ? fvar[i] : (T)0, mode, mip, has_f, S);
        T g_ls[3] = {0, 0, 0}, g_s2f[3] = {0, 0, 0}, g_xc[3] = {0, 0, 0};
        T g_logdetJ = 0, gD = 0, gdh = 0;
        const T ga = gamp[i];
        // amplitude
        const T drho_draw = drhob[j];
        T g_rho = 0;
        if (mode == 0) {
            g_rho = ga * S.ampn;
            for (int k = 0; k < 3; ++k) g_ls[k] += ga * S.amp;
            g_logdetJ += ga * S.amp;
            gD += ga * S.amp * (T)(-0.5) / S.D;
        } else {
            g_rho = ga * S.ampn;
            if (has_f)
                for (int k = 0; k < 3; ++k) g_ls[k] += ga * S.amp;  // sqrt(prod s2): d/dls_k = 1
            if (mip) {
                gD += ga * S.amp * (T)(-0.5) / S.D;
                if (S.cb >= (T)1e-20) gdh += ga * S.amp * (T)0.5 / S.dh;
            }
            if (has_f)
                for (int k = 0; k < 3; ++k) g_s2f[k] += ga * S.amp * (T)(-0.5) / S.s2f[k];
        }
        gdraw[i] = g_rho * drho_draw;
        // conic = (f11, -f01, f00) / D
        const T gA = gcon[3 * i], gB = gcon[3 * i + 1], gC = gcon[3 * i + 2], D = S.D;
        gD += -(gA * S.f11 - gB * S.f01 + gC * S.f00) / (D * D);
        // D = |S^| + k2 (c00 + c11) + k2^2 with |S^| = det_cb (gdh is zero where the floor holds)
        const T g_c00 = gC / D + gD * cam.k2, g_c11 = gA / D + gD * cam.k2, g_c01 = -gB / D;
        // c = T diag(s2f) T^T
        T gT[6];
        for (int k = 0; k < 3; ++k) {
            gT[k] = (2 * g_c00 * S.Tm[k] + g_c01 * S.Tm[3 + k]) * S.s2f[k];
            gT[3 + k] = (2 * g_c11 * S.Tm[3 + k] + g_c01 * S.Tm[k]) * S.s2f[k];
            g_s2f[k] += g_c00 * S.Tm[k] * S.Tm[k] + g_c01 * S.Tm[k] * S.Tm[3 + k] + g_c11 * S.Tm[3 + k] * S.Tm[3 + k];
        }
        det_cb_bwd(S.Tm, S.s2f, gD + gdh, gT, g_s2f);
        for (int k = 0; k < 3; ++k) g_ls[k] += 2 * S.s2[k] * g_s2f[k];
        // T = J2 M  -> gJ2 = gT M^T, gM = J2^T gT
        T gJ2[6], gM[9];
        for (int a = 0; a < 2; ++a)
            for (int b = 0; b < 3; ++b)
                gJ2[3 * a + b] = gT[3 * a] * S.M[3 * b] + gT[3 * a + 1] * S.M[3 * b + 1]
                                 + gT[3 * a + 2] * S.M[3 * b + 2];
        for (int a = 0; a < 3; ++a)
            for (int b = 0; b < 3; ++b) gM[3 * a + b] = S.J2[a] * gT[b] + S.J2[3 + a] * gT[3 + b];
        // M = R Rq -> gRq = R^T gM
        T gRq[9];
        for (int a = 0; a < 3; ++a)
            for (int b = 0; b < 3; ++b)
                gRq[3 * a + b] = cam.R[a] * gM[b] + cam.R[3 + a] * gM[3 + b] + cam.R[6 + a] * gM[6 + b];
        // rotmat backward (w, x, y, z)
        const T w = S.qn[0], x = S.qn[1], y = S.qn[2], z = S.qn[3];
        T gqn[4];
        gqn[0] = 2 * (-z * gRq[1] + y * gRq[2] + z * gRq[3] - x * gRq[5] - y * gRq[6] + x * gRq[7]);
        gqn[1] = 2 * (y * gRq[1] + z * gRq[2] + y * gRq[3] - 2 * x * gRq[4] - w * gRq[5] + z * gRq[6] + w * gRq[7]
                      - 2 * x * gRq[8]);
        gqn[2] = 2 * (-2 * y * gRq[0] + x * gRq[1] + w * gRq[2] + x * gRq[3] + z * gRq[5] - w * gRq[6] + z * gRq[7]
                      - 2 * y * gRq[8]);
        gqn[3] = 2 * (-2 * z * gRq[0] - w * gRq[1] + x * gRq[2] + w * gRq[3] - 2 * z * gRq[4] + y * gRq[5]
                      + x * gRq[6] + y * gRq[7]);
        const T dotq = gqn[0] * w + gqn[1] * x + gqn[2] * y + gqn[3] * z;
        for (int k = 0; k < 4; ++k) gq[4 * i + k] = (gqn[k] - S.qn[k] * dotq) / S.qnorm;
        // means2d and J2 -> camera-frame mean
        const T gu = gm2d[2 * i], gv = gm2d[2 * i + 1];
        if (!cam.cone) {
            g_xc[0] += gu / cam.sx; g_xc[1] += gv / cam.sy;
        } else if (S.valid) {
            const T zs = S.z, z2 = zs * zs, z3 = z2 * zs;
            g_xc[0] += gu * cam.fx / zs; g_xc[2] -= gu * cam.fx * S.xc[0] / z2;
            g_xc[1] += gv * cam.fy / zs; g_xc[2] -= gv * cam.fy * S.xc[1] / z2;
            T gz = 0, gtx = 0, gty = 0;
            gz += -gJ2[0] * cam.fx / z2 + 2 * gJ2[2] * cam.fx * S.tx / z3 - gJ2[4] * cam.fy / z2
                  + 2 * gJ2[5] * cam.fy * S.ty / z3;
            gtx += -gJ2[2] * cam.fx / z2;
            gty += -gJ2[5] * cam.fy / z2;
            // log|J| = log(fx fy) + log r - 3 log z
            const T r2 = S.r * S.r;
            gtx += g_logdetJ * S.tx / r2; gty += g_logdetJ * S.ty / r2; gz += g_logdetJ * (zs / r2 - 3 / zs);
            // tx = z clamp(x / z)
            if (S.unclx) g_xc[0] += gtx; else gz += gtx * S.clx;
            if (S.uncly) g_xc[1] += gty; else gz += gty * S.cly;
            g_xc[2] += gz;
        }
        for (int k = 0; k < 3; ++k) gls[3 * i + k] = g_ls[k];
        for (int k = 0; k < 3; ++k)
            gmeans[3 * i + k] = cam.R[k] * g_xc[0] + cam.R[3 + k] * g_xc[1] + cam.R[6 + k] * g_xc[2];
    }
    });
}
