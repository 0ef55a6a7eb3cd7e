"""Fused CPU kernels for the additive (radiative) compositors: projection + rasteriser, hand-written backward.

Two ``torch.autograd.Function`` s, chained exactly like the reference path so that ``means2d`` stays a real graph
node (its ``.grad`` feeds densification):

* :class:`ProjectAdditive` -- :func:`ctsplat.render.project` for ``radiative`` / ``radiative_unrectified`` (same
  formulas, same 3D filter / 2D mip / ``EPS_2D`` handling, same bounding boxes) in one pass over the Gaussians;
  its backward re-computes the forward per Gaussian and applies the chain rule by hand (quaternion
  normalisation, ``R S² Rᵀ``, the cone Jacobian with the 3DGS clamp, ``log|J|``, conic inversion, softplus).
* :class:`SplatAdditive` -- for every Gaussian ``i`` and every pixel ``p`` of its bounding box,
  ``img[p] += a_i exp(q_i(p))``, ``q = -½ (A dx² + C dy²) - B dx dy``, ``dx = u_p + 0.5 - m_x``,
  ``dy = v_p + 0.5 - m_y``. Backward, with ``g = ∂L/∂img[p]`` and ``e = exp(q)``::

      ∂L/∂a   = Σ_p g e
      ∂L/∂m_x = a Σ_p g e (A dx + B dy),   ∂L/∂m_y = a Σ_p g e (B dx + C dy)
      ∂L/∂A   = -½ a Σ_p g e dx²,  ∂L/∂B = -a Σ_p g e dx dy,  ∂L/∂C = -½ a Σ_p g e dy²

Both are tested against the autograd reference (values and gradients, float32 and float64) and by gradcheck.
The float32 rasteriser cuts each footprint row into 8-lane chunks (GCC/Clang vector extensions, the last chunk
masked) with an inline vector ``exp`` (Cody-Waite reduction + Cephes polynomial, about 1 ulp): footprint rows are
~8 px long, too short for auto-vectorised loops. The projection runs in blocks of separate short passes
(activations through libmvec, finiteness, per-Gaussian algebra, boxes); in float32 its algebra, forward and
backward, runs on 8 Gaussians side by side (``proj8``: one Gaussian's chain of dependent operations is
latency-bound). float64 keeps the scalar code (gradcheck, the exactness tests), the float32 path is tested
against it.
The C++ source (no torch headers) is compiled on first use with the system compiler
(``c++ -O3 -ffast-math -march=native``; other loops vectorise with glibc's libmvec ``exp``) into
``$CTSPLAT_CACHE`` (default ``~/.cache/ctsplat``), keyed by the source and the CPU, and loaded with ``ctypes``;
compiling takes a few seconds. Threads: ``torch.get_num_threads()`` ``std::thread`` s over static blocks of
Gaussians (no OpenMP runtime that would spin against torch's); the forward gives each thread its own image
buffer and sums them in a fixed order, so results are deterministic for a fixed thread count. Without a
compiler (or with ``CTSPLAT_NO_KERNEL=1``) :func:`available` is False and the renderer uses the reference.
"""

from __future__ import annotations

import contextlib
import ctypes
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

import torch

__all__ = ["available", "splat_additive_kernel", "SplatAdditive", "ProjectAdditive", "AlphaComposite", "VoxelizeKernel",
           "camera_vector"]

_SRC = r"""
#include <math.h>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <thread>
#include <type_traits>
#include <vector>

// static block partition of [0, n) over nt std::threads (no OpenMP: it would spin against torch's own pool)
template <typename F>
static void parallel_for(int64_t n, int nt, F fn) {
    if (nt < 1) nt = 1;
    if (n < 4096 || nt == 1) { fn((int64_t)0, n, 0); return; }
    std::vector<std::thread> pool;
    for (int k = 1; k < nt; ++k)
        pool.emplace_back([=]() { fn(n * k / nt, n * (k + 1) / nt, k); });
    fn((int64_t)0, n / nt, 0);
    for (auto& th : pool) th.join();
}

// C exp/expf (not std::) so that -ffast-math can vectorise the pixel loops with glibc's libmvec
static inline float ex_(float x) { return expf(x); }
static inline double ex_(double x) { return exp(x); }
// finiteness by bits (the build uses -ffast-math, under which std::isfinite may be folded to true)
static inline bool finite_(double x) { uint64_t b; std::memcpy(&b, &x, 8); return ((b >> 52) & 0x7ff) != 0x7ff; }

// one image row of one Gaussian: row[k] += a exp(-A/2 dx^2 + by dx + cy), dx = x0 + k
template <typename T>
static inline void row_fwd(T* __restrict row, int len, T x0, T A, T by, T cy, T a) {
    const T h = (T)(-0.5) * A;
    for (int k = 0; k < len; ++k) {
        const T dx = x0 + (T)k;
        row[k] += a * ex_(h * dx * dx + by * dx + cy);
    }
}

// backward of row_fwd without the amplitude: sums of g e, g e dx, g e dx^2
template <typename T>
static inline void row_bwd(const T* __restrict g, int len, T x0, T A, T by, T cy, T* out3) {
    const T h = (T)(-0.5) * A;
    T r_e = 0, r_x = 0, r_xx = 0;
    for (int k = 0; k < len; ++k) {
        const T dx = x0 + (T)k;
        const T ge = g[k] * ex_(h * dx * dx + by * dx + cy);
        r_e += ge; r_x += ge * dx; r_xx += ge * dx * dx;
    }
    out3[0] = r_e; out3[1] = r_x; out3[2] = r_xx;
}

// ---------------------------------------------------------------- additive rasteriser
template <typename T>
static void splat_fwd(int64_t n, const T* mean, const T* con, const T* amp, const int64_t* bb, int64_t H, int64_t W,
                      T* out, int nthreads) {
    int nt = nthreads < 1 ? 1 : nthreads;
    if (n < 4096) nt = 1;
    const int64_t npx = H * W;
    std::memset(out, 0, sizeof(T) * (size_t)npx);
    std::vector<T> bufs(nt > 1 ? (size_t)(nt - 1) * (size_t)npx : 0, (T)0);
    parallel_for(n, nt, [&](int64_t i0, int64_t i1, int tid) {
        T* img = tid == 0 ? out : bufs.data() + (size_t)(tid - 1) * (size_t)npx;
        for (int64_t i = i0; i < i1; ++i) {
            const int64_t u0 = bb[4 * i], u1 = bb[4 * i + 1], v0 = bb[4 * i + 2], v1 = bb[4 * i + 3];
            if (u1 <= u0 || v1 <= v0) continue;
            const T mx = mean[2 * i], my = mean[2 * i + 1];
            const T A = con[3 * i], B = con[3 * i + 1], C = con[3 * i + 2], a = amp[i];
            for (int64_t v = v0; v < v1; ++v) {
                const T dy = (T)v + (T)0.5 - my;
                const T cy = (T)(-0.5) * C * dy * dy;
                const T by = -B * dy;
                row_fwd<T>(img + v * W + u0, (int)(u1 - u0), (T)u0 + (T)0.5 - mx, A, by, cy, a);
            }
        }
    });
    for (int k = 1; k < nt; ++k) {
        const T* b = bufs.data() + (size_t)(k - 1) * (size_t)npx;
        for (int64_t p = 0; p < npx; ++p) out[p] += b[p];
    }
}

template <typename T>
static void splat_bwd(int64_t n, const T* mean, const T* con, const T* amp, const int64_t* bb, int64_t /*H*/,
                      int64_t W, const T* gimg, T* gmean, T* gcon, T* gamp, int nthreads) {
    parallel_for(n, nthreads, [&](int64_t i0, int64_t i1, int) {
    for (int64_t i = i0; i < i1; ++i) {
        const int64_t u0 = bb[4 * i], u1 = bb[4 * i + 1], v0 = bb[4 * i + 2], v1 = bb[4 * i + 3];
        T s_e = 0, s_x = 0, s_y = 0, s_xx = 0, s_xy = 0, s_yy = 0;
        const T mx = mean[2 * i], my = mean[2 * i + 1];
        const T A = con[3 * i], B = con[3 * i + 1], C = con[3 * i + 2];
        if (u1 > u0 && v1 > v0) {
            for (int64_t v = v0; v < v1; ++v) {
                const T dy = (T)v + (T)0.5 - my;
                const T cy = (T)(-0.5) * C * dy * dy;
                const T by = -B * dy;
                T r3[3];
                row_bwd<T>(gimg + v * W + u0, (int)(u1 - u0), (T)u0 + (T)0.5 - mx, A, by, cy, r3);
                const T r_e = r3[0], r_x = r3[1], r_xx = r3[2];
                s_e += r_e; s_x += r_x; s_xx += r_xx;
                s_y += r_e * dy; s_xy += r_x * dy; s_yy += r_e * dy * dy;
            }
        }
        const T a = amp[i];
        gamp[i] = s_e;
        gmean[2 * i] = a * (A * s_x + B * s_y);
        gmean[2 * i + 1] = a * (B * s_x + C * s_y);
        gcon[3 * i] = (T)(-0.5) * a * s_xx;
        gcon[3 * i + 1] = -a * s_xy;
        gcon[3 * i + 2] = (T)(-0.5) * a * s_yy;
    }
    });
}

// ---------------------------------------------------------------- additive rasteriser, float32: 8 lanes
// GCC/Clang vector extensions (AVX2 here, SSE or NEON pairs elsewhere). A footprint row is ~8 px wide, too short
// for the compiler's auto-vectorised libmvec loop (mostly scalar remainder), so each row is cut into 8-lane
// chunks, the last one masked; buffers carry 8 floats of padding so a chunk never leaves them.
typedef float v8f __attribute__((vector_size(32)));
typedef int32_t v8i __attribute__((vector_size(32)));
static inline v8f bc8(float s) { return (v8f){s, s, s, s, s, s, s, s}; }
static inline v8f ld8(const float* p) { v8f v; std::memcpy(&v, p, sizeof v); return v; }
static inline void st8(float* p, v8f v) { std::memcpy(p, &v, sizeof v); }
static inline v8f keep8(v8f a, v8i m) { return (v8f)((v8i)a & m); }
static inline float hsum8(v8f a) { return ((a[0] + a[1]) + (a[2] + a[3])) + ((a[4] + a[5]) + (a[6] + a[7])); }
static const v8f IOTA8 = {0.f, 1.f, 2.f, 3.f, 4.f, 5.f, 6.f, 7.f};

// exp of 8 floats: x = n ln2 + r with |r| <= ln2/2 (n = floor(x log2 e + 1/2), ln2 split in two for the
// reduction), exp(r) by Cephes' degree-7 minimax polynomial (about 1 ulp), 2^n added to the exponent bits.
// exp(x) = 0 below -86 (near FLT_MIN); x is clamped at 88.
static inline v8f vexp8(v8f x) {
    const v8i under = x < bc8(-86.0f), over = x > bc8(88.0f);
    x = (v8f)(((v8i)x & ~over) | ((v8i)bc8(88.0f) & over));
    x = (v8f)(((v8i)x & ~under) | ((v8i)bc8(-86.0f) & under));
    const v8f fx = x * bc8(1.44269504088896341f) + bc8(0.5f);
    v8i n = __builtin_convertvector(fx, v8i);              // truncation towards zero ...
    n += (v8i)(__builtin_convertvector(n, v8f) > fx);       // ... to floor (a true comparison is -1)
    const v8f nf = __builtin_convertvector(n, v8f);
    const v8f r = (x - nf * bc8(0.693359375f)) + nf * bc8(2.12194440e-4f);
    v8f p = bc8(1.9875691500e-4f);
    p = p * r + bc8(1.3981999507e-3f);
    p = p * r + bc8(8.3334519073e-3f);
    p = p * r + bc8(4.1665795894e-2f);
    p = p * r + bc8(1.6666665459e-1f);
    p = p * r + bc8(5.0000001201e-1f);
    const v8f y = (p * r) * r + r + bc8(1.0f);
    return keep8((v8f)((v8i)y + (n << 23)), ~under);
}

static void splat_fwd(int64_t n, const float* mean, const float* con, const float* amp, const int64_t* bb,
                      int64_t H, int64_t W, float* out, int nthreads) {
    int nt = nthreads < 1 ? 1 : nthreads;
    if (n < 4096) nt = 1;
    const int64_t npx = H * W, stride = npx + 8;
    std::vector<float> bufs((size_t)nt * (size_t)stride, 0.f);
    parallel_for(n, nt, [&](int64_t i0, int64_t i1, int tid) {
        float* img = bufs.data() + (size_t)tid * (size_t)stride;
        for (int64_t i = i0; i < i1; ++i) {
            const int64_t u0 = bb[4 * i], u1 = bb[4 * i + 1], v0 = bb[4 * i + 2], v1 = bb[4 * i + 3];
            if (u1 <= u0 || v1 <= v0) continue;
            const int len = (int)(u1 - u0);
            const float mx = mean[2 * i], my = mean[2 * i + 1];
            const float B = con[3 * i + 1], C = con[3 * i + 2];
            const v8f h = bc8(-0.5f * con[3 * i]), a = bc8(amp[i]);
            const float x0 = (float)u0 + 0.5f - mx;
            // rows have the same number of chunks: full ones, then one masked (no data-dependent branch per row)
            const int last = 8 * ((len - 1) / 8);
            const v8i tail = IOTA8 < bc8((float)(len - last));
            const v8f dx_last = bc8(x0 + (float)last) + IOTA8;
            for (int64_t v = v0; v < v1; ++v) {
                const float dy = (float)v + 0.5f - my;
                const v8f cy = bc8(-0.5f * C * dy * dy), by = bc8(-B * dy);
                float* row = img + v * W + u0;
                for (int k = 0; k < last; k += 8) {
                    const v8f dx = bc8(x0 + (float)k) + IOTA8;
                    st8(row + k, ld8(row + k) + a * vexp8((h * dx + by) * dx + cy));
                }
                const v8f e = keep8(a * vexp8((h * dx_last + by) * dx_last + cy), tail);
                st8(row + last, ld8(row + last) + e);
            }
        }
    });
    for (int64_t p = 0; p < npx; ++p) {
        float s = bufs[(size_t)p];
        for (int k = 1; k < nt; ++k) s += bufs[(size_t)k * (size_t)stride + (size_t)p];
        out[p] = s;
    }
}

static void splat_bwd(int64_t n, const float* mean, const float* con, const float* amp, const int64_t* bb,
                      int64_t H, int64_t W, const float* gimg, float* gmean, float* gcon, float* gamp, int nthreads) {
    std::vector<float> gpad((size_t)(H * W + 8), 0.f);  // padded copy: the last row's chunk may read past W
    std::memcpy(gpad.data(), gimg, sizeof(float) * (size_t)(H * W));
    const float* g = gpad.data();
    parallel_for(n, nthreads, [&](int64_t i0, int64_t i1, int) {
    for (int64_t i = i0; i < i1; ++i) {
        const int64_t u0 = bb[4 * i], u1 = bb[4 * i + 1], v0 = bb[4 * i + 2], v1 = bb[4 * i + 3];
        const float mx = mean[2 * i], my = mean[2 * i + 1];
        const float A = con[3 * i], B = con[3 * i + 1], C = con[3 * i + 2];
        const v8f zero = bc8(0.f);
        v8f s_e = zero, s_x = zero, s_y = zero, s_xx = zero, s_xy = zero, s_yy = zero;
        if (u1 > u0 && v1 > v0) {
            const int len = (int)(u1 - u0);
            const v8f h = bc8(-0.5f * A);
            const float x0 = (float)u0 + 0.5f - mx;
            const int last = 8 * ((len - 1) / 8);
            const v8i tail = IOTA8 < bc8((float)(len - last));
            const v8f dx_last = bc8(x0 + (float)last) + IOTA8;
            for (int64_t v = v0; v < v1; ++v) {
                const float dy = (float)v + 0.5f - my;
                const v8f cy = bc8(-0.5f * C * dy * dy), by = bc8(-B * dy), dyv = bc8(dy);
                const float* grow = g + v * W + u0;
                const v8f ge_l = keep8(ld8(grow + last), tail) * vexp8((h * dx_last + by) * dx_last + cy);
                const v8f gx_l = ge_l * dx_last;
                v8f r_e = ge_l, r_x = gx_l, r_xx = gx_l * dx_last;
                for (int k = 0; k < last; k += 8) {
                    const v8f dx = bc8(x0 + (float)k) + IOTA8;
                    const v8f ge = ld8(grow + k) * vexp8((h * dx + by) * dx + cy);
                    const v8f gx = ge * dx;
                    r_e += ge; r_x += gx; r_xx += gx * dx;
                }
                s_e += r_e; s_x += r_x; s_xx += r_xx;
                s_y += r_e * dyv; s_xy += r_x * dyv; s_yy += (r_e * dyv) * dyv;
            }
        }
        const float a = amp[i];
        const float se = hsum8(s_e), sx = hsum8(s_x), sy = hsum8(s_y);
        gamp[i] = se;
        gmean[2 * i] = a * (A * sx + B * sy);
        gmean[2 * i + 1] = a * (B * sx + C * sy);
        gcon[3 * i] = -0.5f * a * hsum8(s_xx);
        gcon[3 * i + 1] = -a * hsum8(s_xy);
        gcon[3 * i + 2] = -0.5f * a * hsum8(s_yy);
    }
    });
}

// ---------------------------------------------------------------- projection (per Gaussian)
// cam: [model(0 parallel,1 cone), sx, sy, fx, fy, cx, cy, W, H, lim_x, lim_y, R00..R22 (9), t0..t2, k2, near, cutoff]
// mode: 0 radiative, 1 unrectified; mip: unrectified applies sqrt(|S^|/|S^'|); fvar may be NULL.
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

// everything the forward computes for one Gaussian (also recomputed by the backward)
template <typename T>
struct PState {
    T qn[4], qnorm, Rq[9], M[9], s2[3], s2f[3], xc[3], z, tx, ty, r, clx, cly; int unclx, uncly;
    T J2[6], Tm[6], c00, c01, c11, f00, f01, f11, D, dh, rho, ampn, amp, u, v, detJ; int valid;
};

template <typename T>
static inline void proj_one(const Cam<T>& cam, const T* m, const T* s2in, const T* q, T rho, T fv, int mode, int mip,
                            int has_f, PState<T>& S) {
    T nq = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    if (nq < (T)1e-12) nq = (T)1e-12;
    S.qnorm = nq;
    for (int k = 0; k < 4; ++k) S.qn[k] = q[k] / nq;
    rotmat(S.qn, S.Rq);
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
    S.D = S.f00 * S.f11 - S.f01 * S.f01;
    S.dh = S.c00 * S.c11 - S.c01 * S.c01;
    if (S.dh < (T)1e-20) S.dh = (T)1e-20;
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

static inline float log1p_(float x) { return log1pf(x); }
static inline double log1p_(double x) { return log1p(x); }

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
    S.f00 = S.c00 + bc8(cam.k2); S.f01 = S.c01; S.f11 = S.c11 + bc8(cam.k2);
    S.D = S.f00 * S.f11 - S.f01 * S.f01;
    const v8f dh = S.c00 * S.c11 - S.c01 * S.c01;
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
    const v8f g_f00 = gC / D + gD * S.f11, g_f11 = gA / D + gD * S.f00, g_f01 = -gB / D - two * gD * S.f01;
    const v8f g_c00 = g_f00 + gdh * S.c11, g_c11 = g_f11 + gdh * S.c00, g_c01 = g_f01 - two * gdh * S.c01;
    v8f gT[6];
    for (int k = 0; k < 3; ++k) {
        gT[k] = (two * g_c00 * S.Tm[k] + g_c01 * S.Tm[3 + k]) * S.s2f[k];
        gT[3 + k] = (two * g_c11 * S.Tm[3 + k] + g_c01 * S.Tm[k]) * S.s2f[k];
        g_s2f[k] += g_c00 * S.Tm[k] * S.Tm[k] + g_c01 * S.Tm[k] * S.Tm[3 + k] + g_c11 * S.Tm[3 + k] * S.Tm[3 + k];
    }
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
    // out-of-order core overlaps them (one fused loop was latency-bound: ~100 ns per Gaussian)
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
                const T raw_dh = S.c00 * S.c11 - S.c01 * S.c01;
                if (raw_dh >= (T)1e-20) gdh += ga * S.amp * (T)0.5 / S.dh;
            }
            if (has_f)
                for (int k = 0; k < 3; ++k) g_s2f[k] += ga * S.amp * (T)(-0.5) / S.s2f[k];
        }
        gdraw[i] = g_rho * drho_draw;
        // conic = (f11, -f01, f00) / D
        const T gA = gcon[3 * i], gB = gcon[3 * i + 1], gC = gcon[3 * i + 2], D = S.D;
        gD += -(gA * S.f11 - gB * S.f01 + gC * S.f00) / (D * D);
        T g_f00 = gC / D + gD * S.f11;
        T g_f11 = gA / D + gD * S.f00;
        T g_f01 = -gB / D - 2 * gD * S.f01;
        T g_c00 = g_f00 + gdh * S.c11, g_c11 = g_f11 + gdh * S.c00, g_c01 = g_f01 - 2 * gdh * S.c01;
        // c = T diag(s2f) T^T
        T gT[6];
        for (int k = 0; k < 3; ++k) {
            gT[k] = (2 * g_c00 * S.Tm[k] + g_c01 * S.Tm[3 + k]) * S.s2f[k];
            gT[3 + k] = (2 * g_c11 * S.Tm[3 + k] + g_c01 * S.Tm[k]) * S.s2f[k];
            g_s2f[k] += g_c00 * S.Tm[k] * S.Tm[k] + g_c01 * S.Tm[k] * S.Tm[3 + k] + g_c11 * S.Tm[3 + k] * S.Tm[3 + k];
        }
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

// ---------------------------------------------------------------- alpha compositing (front to back)
// per-pixel lists of Gaussians in depth order: counting sort by pixel, filled in depth order
static void alpha_lists(int64_t n, const int64_t* order, const int64_t* bb, int64_t H, int64_t W,
                        int64_t* offsets, int32_t* ids) {
    const int64_t npx = H * W;
    for (int64_t p = 0; p <= npx; ++p) offsets[p] = 0;
    for (int64_t i = 0; i < n; ++i)
        for (int64_t v = bb[4 * i + 2]; v < bb[4 * i + 3]; ++v)
            for (int64_t u = bb[4 * i]; u < bb[4 * i + 1]; ++u) offsets[v * W + u + 1] += 1;
    for (int64_t p = 0; p < npx; ++p) offsets[p + 1] += offsets[p];
    std::vector<int64_t> fill(offsets, offsets + npx);
    for (int64_t k = 0; k < n; ++k) {
        const int64_t i = order[k];
        for (int64_t v = bb[4 * i + 2]; v < bb[4 * i + 3]; ++v)
            for (int64_t u = bb[4 * i]; u < bb[4 * i + 1]; ++u) ids[fill[v * W + u]++] = (int32_t)i;
    }
}

template <typename T>
static inline T alpha_of(const T* mean, const T* con, const T* op, int32_t i, T px, T py, T& e, T& dx, T& dy) {
    dx = px - mean[2 * i]; dy = py - mean[2 * i + 1];
    e = ex_((T)(-0.5) * (con[3 * i] * dx * dx + con[3 * i + 2] * dy * dy) - con[3 * i + 1] * dx * dy);
    const T a = op[i] * e;
    return a < (T)0.99 ? a : (T)0.99;
}

template <typename T>
static void alpha_fwd(int64_t H, int64_t W, int C, const int64_t* offsets, const int32_t* ids, const T* mean,
                      const T* con, const T* op, const T* col, T* out, T* alphas, int nt) {
    parallel_for(H * W, nt, [&](int64_t p0, int64_t p1, int) {
        for (int64_t p = p0; p < p1; ++p) {
            const T px = (T)(p % W) + (T)0.5, py = (T)(p / W) + (T)0.5;
            T Tr = 1;
            for (int c = 0; c < C; ++c) out[p * C + c] = 0;
            for (int64_t k = offsets[p]; k < offsets[p + 1]; ++k) {
                const int32_t i = ids[k];
                T e, dx, dy;
                const T a = alpha_of(mean, con, op, i, px, py, e, dx, dy);
                alphas[k] = a;  // kept for the backward (no exp there)
                for (int c = 0; c < C; ++c) out[p * C + c] += Tr * a * col[i * C + c];
                Tr *= 1 - a;
            }
        }
    });
}

template <typename T>
static void alpha_bwd(int64_t n, int64_t H, int64_t W, int C, const int64_t* offsets, const int32_t* ids,
                      const T* alphas, const T* mean, const T* con, const T* op, const T* col, const T* gout,
                      T* gmean, T* gcon, T* gop, T* gcol, int nthreads) {
    int nt = nthreads < 1 ? 1 : nthreads;
    if (H * W < 4096) nt = 1;
    const int64_t stride = 6 + C;  // per Gaussian: gmx, gmy, gA, gB, gC, gop, gcol[C]
    std::vector<T> acc((size_t)nt * (size_t)n * (size_t)stride, (T)0);
    parallel_for(H * W, nt, [&](int64_t p0, int64_t p1, int tid) {
        T* g = acc.data() + (size_t)tid * (size_t)n * (size_t)stride;
        std::vector<T> Ts, suffix(C);
        for (int64_t p = p0; p < p1; ++p) {
            const int64_t k0 = offsets[p], k1 = offsets[p + 1];
            if (k1 == k0) continue;
            const T px = (T)(p % W) + (T)0.5, py = (T)(p / W) + (T)0.5;
            Ts.resize(k1 - k0);
            T Tr = 1;
            for (int64_t k = k0; k < k1; ++k) {
                Ts[k - k0] = Tr;
                Tr *= 1 - alphas[k];
            }
            for (int c = 0; c < C; ++c) suffix[c] = 0;  // sum_{j>i} c_j a_j T_j
            const T* go = gout + p * C;
            for (int64_t k = k1 - 1; k >= k0; --k) {
                const int32_t i = ids[k];
                const T Ti = Ts[k - k0], a = alphas[k];
                T gdot = 0, sdot = 0;
                for (int c = 0; c < C; ++c) {
                    gdot += go[c] * col[i * C + c];
                    sdot += go[c] * suffix[c];
                    g[(size_t)i * stride + 6 + c] += go[c] * a * Ti;
                    suffix[c] += col[i * C + c] * a * Ti;
                }
                const T ga = Ti * gdot - sdot / (1 - a);
                if (a >= (T)0.99) continue;  // clamped: no gradient to opacity / footprint
                const T dx = px - mean[2 * i], dy = py - mean[2 * i + 1];
                T* gi = g + (size_t)i * stride;
                gi[5] += op[i] > 0 ? ga * a / op[i] : (T)0;  // a = o e  ->  d a / d o = e
                const T gq = ga * a;  // d alpha / d q = o e
                const T A = con[3 * i], B = con[3 * i + 1], Cc = con[3 * i + 2];
                gi[0] += gq * (A * dx + B * dy);
                gi[1] += gq * (B * dx + Cc * dy);
                gi[2] += gq * (T)(-0.5) * dx * dx;
                gi[3] += gq * (-dx * dy);
                gi[4] += gq * (T)(-0.5) * dy * dy;
            }
        }
    });
    for (int64_t i = 0; i < n; ++i) {
        T s[64];
        const int64_t m = stride < 64 ? stride : 64;
        for (int64_t k = 0; k < m; ++k) s[k] = 0;
        for (int t = 0; t < nt; ++t)
            for (int64_t k = 0; k < m; ++k) s[k] += acc[((size_t)t * (size_t)n + (size_t)i) * (size_t)stride + k];
        gmean[2 * i] = s[0]; gmean[2 * i + 1] = s[1];
        gcon[3 * i] = s[2]; gcon[3 * i + 1] = s[3]; gcon[3 * i + 2] = s[4];
        gop[i] = s[5];
        for (int c = 0; c < C; ++c) gcol[i * C + c] = s[6 + c];
    }
}

extern "C" void alpha_lists_c(int64_t n, const int64_t* order, const int64_t* bb, int64_t H, int64_t W,
                              int64_t* offsets, int32_t* ids) { alpha_lists(n, order, bb, H, W, offsets, ids); }

// ---------------------------------------------------------------- voxelizer (mu on a grid)
// affine: A (row-major 3x3) then b (3), voxel (i,j,k) -> A (i,j,k) + b; rows along k are contiguous in the output
// one Gaussian's box, row by row along k (the k axis w = A[:, 2] in mm): for voxel row (i, j) with d = x(i, j, k0) - m
// the quadratic form along the row is q(c) = q0 + q1 c + wPw c², c = 0 .. ext_k - 1; calls row(flat, d, q0, q1)
// with flat the output index of (i, j, k0). Shared by the forward and the backward so both walk the same voxels.
template <typename T>
struct VoxAxis {
    T w[3], Pw[3], wPw;
    VoxAxis(const T* P, const double* aff) {
        w[0] = (T)aff[2]; w[1] = (T)aff[5]; w[2] = (T)aff[8];
        Pw[0] = P[0] * w[0] + P[3] * w[1] + P[4] * w[2];
        Pw[1] = P[3] * w[0] + P[1] * w[1] + P[5] * w[2];
        Pw[2] = P[4] * w[0] + P[5] * w[1] + P[2] * w[2];
        wPw = w[0] * Pw[0] + w[1] * Pw[1] + w[2] * Pw[2];
    }
};

template <typename T, typename F>
static inline void vox_rows(int64_t i, const T* means, const T* P, const VoxAxis<T>& ax, const int64_t* lo,
                            const int64_t* ext, const double* aff, const int64_t* origin, const int64_t* shape,
                            F&& row) {
    for (int64_t a = 0; a < ext[3 * i]; ++a)
        for (int64_t b = 0; b < ext[3 * i + 1]; ++b) {
            const int64_t ii = lo[3 * i] + a, jj = lo[3 * i + 1] + b, kk = lo[3 * i + 2];
            T d[3];
            for (int r = 0; r < 3; ++r)
                d[r] = (T)(aff[3 * r] * ii + aff[3 * r + 1] * jj + aff[3 * r + 2] * kk + aff[9 + r]) - means[3 * i + r];
            const T q0 = P[0] * d[0] * d[0] + P[1] * d[1] * d[1] + P[2] * d[2] * d[2]
                         + 2 * (P[3] * d[0] * d[1] + P[4] * d[0] * d[2] + P[5] * d[1] * d[2]);
            const T q1 = 2 * (d[0] * ax.Pw[0] + d[1] * ax.Pw[1] + d[2] * ax.Pw[2]);
            row(((ii - origin[0]) * shape[1] + (jj - origin[1])) * shape[2] + (kk - origin[2]), d, q0, q1);
        }
}

template <typename T>
static void vox_fwd(int64_t n, const T* means, const T* p6, const T* dens, const int64_t* lo, const int64_t* ext,
                    const double* aff, const int64_t* origin, const int64_t* shape, T* out, int nthreads) {
    int nt = nthreads < 1 ? 1 : nthreads;
    const int64_t nvox = shape[0] * shape[1] * shape[2];
    if (n < 4096 || nvox > ((int64_t)1 << 27)) nt = 1;  // per-thread grids only while they are small
    std::vector<T> bufs(nt > 1 ? (size_t)(nt - 1) * (size_t)nvox : 0, (T)0);
    parallel_for(n, nt, [&](int64_t i0, int64_t i1, int tid) {
        T* grid = tid == 0 ? out : bufs.data() + (size_t)(tid - 1) * (size_t)nvox;
        for (int64_t i = i0; i < i1; ++i) {
            const T* P = p6 + 6 * i;
            const VoxAxis<T> ax(P, aff);
            vox_rows(i, means, P, ax, lo, ext, aff, origin, shape, [&](int64_t flat, const T*, T q0, T q1) {
                // value = rho exp(-q/2)
                row_fwd<T>(grid + flat, (int)ext[3 * i + 2], (T)0, ax.wPw, (T)(-0.5) * q1, (T)(-0.5) * q0, dens[i]);
            });
        }
    });
    for (int k = 1; k < nt; ++k) {
        const T* b = bufs.data() + (size_t)(k - 1) * (size_t)nvox;
        for (int64_t p = 0; p < nvox; ++p) out[p] += b[p];
    }
}

template <typename T>
static void vox_bwd(int64_t n, const T* means, const T* p6, const T* dens, const int64_t* lo, const int64_t* ext,
                    const double* aff, const int64_t* origin, const int64_t* shape, const T* gout, T* gmeans, T* gp6,
                    T* gdens, int nt) {
    parallel_for(n, nt, [&](int64_t i0, int64_t i1, int) {
        for (int64_t i = i0; i < i1; ++i) {
            const T* P = p6 + 6 * i;
            const VoxAxis<T> ax(P, aff);
            const T* w = ax.w;
            double S = 0, Sd[3] = {0, 0, 0}, Sdd[6] = {0, 0, 0, 0, 0, 0};  // sums of g e, g e d, g e d d^T
            vox_rows(i, means, P, ax, lo, ext, aff, origin, shape, [&](int64_t flat, const T* d, T q0, T q1) {
                T r3[3];  // sums over c of g e, g e c, g e c^2
                row_bwd<T>(gout + flat, (int)ext[3 * i + 2], (T)0, ax.wPw, (T)(-0.5) * q1, (T)(-0.5) * q0, r3);
                const double s0 = r3[0], s1 = r3[1], s2 = r3[2];
                S += s0;
                for (int r = 0; r < 3; ++r) Sd[r] += s0 * d[r] + s1 * w[r];
                const int pr[6][2] = {{0, 0}, {1, 1}, {2, 2}, {0, 1}, {0, 2}, {1, 2}};
                for (int e = 0; e < 6; ++e) {
                    const int x = pr[e][0], y = pr[e][1];
                    Sdd[e] += s0 * d[x] * d[y] + s1 * (d[x] * w[y] + w[x] * d[y]) + s2 * w[x] * w[y];
                }
            });
            const double rho = dens[i];
            gdens[i] = (T)S;
            // v = rho exp(-q/2), q = d^T P d, d = x - m:  dv/dm = rho e P d ; dv/dP_xy = -rho e d_x d_y (x != y: twice)
            gmeans[3 * i] = (T)(rho * (P[0] * Sd[0] + P[3] * Sd[1] + P[4] * Sd[2]));
            gmeans[3 * i + 1] = (T)(rho * (P[3] * Sd[0] + P[1] * Sd[1] + P[5] * Sd[2]));
            gmeans[3 * i + 2] = (T)(rho * (P[4] * Sd[0] + P[5] * Sd[1] + P[2] * Sd[2]));
            for (int e = 0; e < 6; ++e) gp6[6 * i + e] = (T)(-0.5 * rho * Sdd[e] * (e < 3 ? 1.0 : 2.0));
        }
    });
}

#define EXPORT(T, SUF)                                                                                          \
extern "C" void splat_fwd_##SUF(int64_t n, const T* m, const T* c, const T* a, const int64_t* bb, int64_t H,     \
                                int64_t W, T* out, int nt) { splat_fwd(n, m, c, a, bb, H, W, out, nt); }         \
extern "C" void splat_bwd_##SUF(int64_t n, const T* m, const T* c, const T* a, const int64_t* bb, int64_t H,     \
                                int64_t W,                                                                      \
                                const T* g, T* gm, T* gc, T* ga, int nt) {                                      \
    splat_bwd(n, m, c, a, bb, H, W, g, gm, gc, ga, nt); }                                                       \
extern "C" void proj_fwd_##SUF(int64_t n, const T* means, const T* ls, const T* q, const T* d, const T* fv,       \
                               const double* cam, int mode, int mip, T* m2d, T* con, T* amp, T* depth,          \
                               int64_t* bb, int32_t* radii, uint8_t* valid, uint8_t* visible, int32_t* bad,     \
                               int nt) {                                                                        \
    proj_fwd<T>(n, means, ls, q, d, fv, cam, mode, mip, m2d, con, amp, depth, bb, radii, valid, visible, bad, nt); } \
extern "C" void proj_bwd_##SUF(int64_t n, const T* means, const T* ls, const T* q, const T* d, const T* fv,       \
                               const double* cam, int mode, int mip, const T* gm2d, const T* gcon,              \
                               const T* gamp, T* gmeans, T* gls, T* gq, T* gd, int nt) {                        \
    proj_bwd<T>(n, means, ls, q, d, fv, cam, mode, mip, gm2d, gcon, gamp, gmeans, gls, gq, gd, nt); }           \
extern "C" void alpha_fwd_##SUF(int64_t H, int64_t W, int C, const int64_t* off, const int32_t* ids, const T* m, \
                                const T* con, const T* op, const T* col, T* out, T* al, int nt) {               \
    alpha_fwd<T>(H, W, C, off, ids, m, con, op, col, out, al, nt); }                                            \
extern "C" void alpha_bwd_##SUF(int64_t n, int64_t H, int64_t W, int C, const int64_t* off, const int32_t* ids,  \
                                const T* al, const T* m, const T* con, const T* op, const T* col, const T* g,   \
                                T* gm, T* gc, T* gop, T* gcol, int nt) {                                        \
    alpha_bwd<T>(n, H, W, C, off, ids, al, m, con, op, col, g, gm, gc, gop, gcol, nt); }                        \
extern "C" void vox_fwd_##SUF(int64_t n, const T* m, const T* p6, const T* d, const int64_t* lo, const int64_t* ext, \
                              const double* aff, const int64_t* org, const int64_t* shp, T* out, int nt) {      \
    vox_fwd<T>(n, m, p6, d, lo, ext, aff, org, shp, out, nt); }                                                 \
extern "C" void vox_bwd_##SUF(int64_t n, const T* m, const T* p6, const T* d, const int64_t* lo, const int64_t* ext, \
                              const double* aff, const int64_t* org, const int64_t* shp, const T* g, T* gm,     \
                              T* gp6, T* gd, int nt) {                                                          \
    vox_bwd<T>(n, m, p6, d, lo, ext, aff, org, shp, g, gm, gp6, gd, nt); }

EXPORT(float, f32)
EXPORT(double, f64)
"""

# tried in order; the first set the compiler accepts is used (some compilers lack -march=native)
_FLAG_SETS = (["-march=native"], [])

_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_failed: str | None = None


def _cache_dir() -> Path:
    return Path(os.environ.get("CTSPLAT_CACHE", Path.home() / ".cache" / "ctsplat"))


def _build() -> ctypes.CDLL:
    # -march=native: the build is specific to this CPU, so the cache key includes the machine and CPU model
    cpu = platform.machine() + platform.processor()
    with contextlib.suppress(OSError):
        cpu += next((ln for ln in Path("/proc/cpuinfo").read_text().splitlines() if ln.startswith("flags")), "")
    tag = hashlib.sha256((_SRC + cpu + repr(_FLAG_SETS)).encode()).hexdigest()[:16]
    out = _cache_dir() / f"render_{tag}.so"
    if not out.exists():
        cxx = os.environ.get("CXX") or shutil.which("c++") or shutil.which("g++") or shutil.which("clang++")
        if cxx is None:
            raise RuntimeError("no C++ compiler found (c++, g++ or clang++)")
        out.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
            src = Path(tmp) / "render.cpp"
            src.write_text(_SRC)
            so = Path(tmp) / "render.so"
            base = [cxx, "-O3", "-std=c++17", "-ffast-math", "-fPIC", "-shared", str(src), "-o", str(so), "-pthread"]
            for extra in _FLAG_SETS:  # the first set the compiler accepts
                res = subprocess.run(base[:1] + extra + base[1:], capture_output=True, text=True)
                if res.returncode == 0:
                    break
            if res.returncode != 0:
                raise RuntimeError(f"render kernel compilation failed: {res.stderr.strip()[:500]}")
            os.replace(so, out)
    lib = ctypes.CDLL(str(out))
    lib.alpha_lists_c.restype = None
    for suf in ("f32", "f64"):
        for name in ("splat_fwd", "splat_bwd", "proj_fwd", "proj_bwd", "alpha_fwd", "alpha_bwd", "vox_fwd", "vox_bwd"):
            getattr(lib, f"{name}_{suf}").restype = None
    return lib


def _get_lib() -> ctypes.CDLL | None:
    global _lib, _failed
    if _lib is not None or _failed is not None:
        return _lib
    with _lock:
        if _lib is None and _failed is None:
            if os.environ.get("CTSPLAT_NO_KERNEL"):
                _failed = "disabled by CTSPLAT_NO_KERNEL"
            else:
                try:
                    _lib = _build()
                except (OSError, RuntimeError) as exc:
                    _failed = str(exc)
                    logging.getLogger(__name__).warning(
                        "fused render kernels unavailable (%s); using the slower PyTorch reference renderer. "
                        "Set CTSPLAT_CACHE to a writable folder or install a C++ compiler.", _failed.splitlines()[0]
                    )
    return _lib


def available() -> bool:
    """True when the compiled kernel can be used (builds it on first call)."""
    return _get_lib() is not None


def _ptr(t: torch.Tensor) -> ctypes.c_void_p:
    return ctypes.c_void_p(t.data_ptr())


def _i64(x: int) -> ctypes.c_int64:
    return ctypes.c_int64(int(x))


def _suffix(dt: torch.dtype) -> str:
    if dt == torch.float32:
        return "f32"
    if dt == torch.float64:
        return "f64"
    raise TypeError(f"render kernel supports float32/float64, got {dt}")


class SplatAdditive(torch.autograd.Function):
    """``img = splat(means2d, conics, amps)`` with the fused kernel; bbox (N, 4) int64 is a constant."""

    @staticmethod
    def forward(ctx, means2d, conics, amps, bbox, height: int, width: int):  # noqa: ANN001
        lib = _get_lib()
        if lib is None:
            raise RuntimeError(f"render kernel unavailable: {_failed}")
        suf = _suffix(amps.dtype)
        m = means2d.detach().contiguous()
        c = conics.detach().to(amps.dtype).contiguous()
        a = amps.detach().contiguous()
        b = bbox.to(torch.int64).contiguous()
        out = torch.empty(height, width, dtype=amps.dtype)  # the kernel writes every pixel
        getattr(lib, f"splat_fwd_{suf}")(
            _i64(m.shape[0]), _ptr(m), _ptr(c), _ptr(a), _ptr(b), _i64(height), _i64(width), _ptr(out),
            ctypes.c_int(torch.get_num_threads()),
        )
        ctx.save_for_backward(m, c, a, b)
        ctx.hw = (height, width)
        return out

    @staticmethod
    def backward(ctx, grad_img):  # noqa: ANN001
        m, c, a, b = ctx.saved_tensors
        height, width = ctx.hw
        g = grad_img.to(a.dtype).contiguous()
        gm, gc, ga = torch.empty_like(m), torch.empty_like(c), torch.empty_like(a)
        getattr(_get_lib(), f"splat_bwd_{_suffix(a.dtype)}")(
            _i64(m.shape[0]), _ptr(m), _ptr(c), _ptr(a), _ptr(b), _i64(height), _i64(width), _ptr(g), _ptr(gm),
            _ptr(gc),
            _ptr(ga), ctypes.c_int(torch.get_num_threads()),
        )
        return gm, gc, ga, None, None, None


def splat_additive_kernel(proj, height: int, width: int) -> torch.Tensor:  # noqa: ANN001
    """Fused-kernel equivalent of :func:`ctsplat.render.splat_additive_reference` (CPU tensors)."""
    return SplatAdditive.apply(proj.means2d, proj.conics, proj.amps, proj.bbox, height, width)


class ProjectAdditive(torch.autograd.Function):
    """Fused :func:`ctsplat.render.project` for the additive compositors (hand-written backward).

    Inputs: means (N,3), log_scales (N,3), quats (N,4), density_raw (N,) (mode 2: opacity_raw), filter_3d_var (N,)
    or None (constant), cam: float64 parameter vector (see :func:`camera_vector`), mode 0 radiative /
    1 unrectified / 2 alpha (amplitude = sigmoid opacity, filters as unrectified), mip flag.
    Outputs: means2d (N,2), conics (N,3), amps (N,), depths (N,); without gradient: bbox (N,4) int64, radii (N,)
    int32, valid (N,) bool (in front of a cone's source), visible (N,) bool (non-empty bbox) and ``nonfinite``,
    a 0-d int32 that is 1 when an input holds NaN/Inf (or filter_3d_var < 0) -- the caller names it.
    """

    @staticmethod
    def forward(ctx, means, log_scales, quats, density_raw, fvar, cam, mode: int, mip: bool):  # noqa: ANN001
        lib = _get_lib()
        if lib is None:
            raise RuntimeError(f"render kernel unavailable: {_failed}")
        dt = means.dtype
        suf = _suffix(dt)
        ins = [t.detach().to(dt).contiguous() for t in (means, log_scales, quats, density_raw)]
        fv = None if fvar is None else fvar.detach().to(dt).contiguous()
        n = ins[0].shape[0]
        m2d = torch.empty(n, 2, dtype=dt)
        con = torch.empty(n, 3, dtype=dt)
        amp = torch.empty(n, dtype=dt)
        depth = torch.empty(n, dtype=dt)
        bb = torch.empty(n, 4, dtype=torch.int64)
        radii = torch.empty(n, dtype=torch.int32)
        valid = torch.empty(n, dtype=torch.bool)
        visible = torch.empty(n, dtype=torch.bool)
        nonfinite = torch.zeros((), dtype=torch.int32)
        getattr(lib, f"proj_fwd_{suf}")(
            _i64(n), *[_ptr(t) for t in ins], _ptr(fv) if fv is not None else None, _ptr(cam),
            ctypes.c_int(mode), ctypes.c_int(int(mip)), _ptr(m2d), _ptr(con), _ptr(amp), _ptr(depth), _ptr(bb),
            _ptr(radii), _ptr(valid), _ptr(visible), _ptr(nonfinite), ctypes.c_int(torch.get_num_threads()),
        )
        ctx.save_for_backward(*ins, *([fv] if fv is not None else []))
        ctx.has_f = fv is not None
        ctx.cam, ctx.mode, ctx.mip = cam, mode, mip
        ctx.mark_non_differentiable(depth, bb, radii, valid, visible, nonfinite)
        ctx.set_materialize_grads(False)  # no zero tensors for the outputs without gradient
        return m2d, con, amp, depth, bb, radii, valid, visible, nonfinite

    @staticmethod
    def backward(ctx, g_m2d, g_con, g_amp, *_no_grad):  # noqa: ANN001
        saved = ctx.saved_tensors
        means, ls, q, d = saved[:4]
        fv = saved[4] if ctx.has_f else None
        dt = means.dtype
        n = means.shape[0]
        gs = [g.to(dt).contiguous() if g is not None else torch.zeros((n, k) if k else (n,), dtype=dt)
              for g, k in zip((g_m2d, g_con, g_amp), (2, 3, 0), strict=True)]
        gm, gl, gq, gd = torch.empty_like(means), torch.empty_like(ls), torch.empty_like(q), torch.empty_like(d)
        getattr(_get_lib(), f"proj_bwd_{_suffix(dt)}")(
            _i64(n), _ptr(means), _ptr(ls), _ptr(q), _ptr(d), _ptr(fv) if fv is not None else None, _ptr(ctx.cam),
            ctypes.c_int(ctx.mode), ctypes.c_int(int(ctx.mip)), *[_ptr(g) for g in gs], _ptr(gm), _ptr(gl),
            _ptr(gq), _ptr(gd), ctypes.c_int(torch.get_num_threads()),
        )
        return gm, gl, gq, gd, None, None, None, None


class AlphaComposite(torch.autograd.Function):
    """Front-to-back alpha compositing of per-pixel depth-sorted lists (same definition as
    :func:`ctsplat.render.splat_alpha_reference`): ``C = Σ_i c_i α_i Π_{j<i}(1-α_j)``, ``α = min(0.99, o e^q)``.

    Backward per pixel, back to front with the suffix ``S_i = Σ_{j>i} c_j α_j T_j``:
    ``∂C/∂c_i = α_i T_i``, ``∂C/∂α_i = T_i c_i - S_i / (1 - α_i)`` (0 through the clamp), then through ``α = o e^q``
    as in :class:`SplatAdditive`. Per-thread gradient buffers are summed in a fixed order.
    """

    @staticmethod
    def forward(ctx, means2d, conics, opac, colors, bbox, depths, height: int, width: int):  # noqa: ANN001
        lib = _get_lib()
        if lib is None:
            raise RuntimeError(f"render kernel unavailable: {_failed}")
        dt = opac.dtype
        suf = _suffix(dt)
        m, c, o = (t.detach().to(dt).contiguous() for t in (means2d, conics, opac))
        col = colors.detach().to(dt).contiguous()
        if col.shape[1] > 32:
            raise ValueError(f"alpha kernel supports at most 32 colour channels, got {col.shape[1]}")
        b = bbox.to(torch.int64).contiguous()
        order = torch.argsort(depths.detach(), stable=True).to(torch.int64).contiguous()
        counts = (b[:, 1] - b[:, 0]) * (b[:, 3] - b[:, 2])
        total = int(counts.sum()) if counts.numel() else 0
        if total >= 2**31:
            raise ValueError("alpha kernel: more than 2^31 (Gaussian, pixel) pairs; render at a lower resolution")
        offsets = torch.empty(height * width + 1, dtype=torch.int64)
        ids = torch.empty(total, dtype=torch.int32)
        lib.alpha_lists_c(_i64(m.shape[0]), _ptr(order), _ptr(b), _i64(height), _i64(width), _ptr(offsets),
                          _ptr(ids))
        out = torch.empty(height, width, col.shape[1], dtype=dt)
        alphas = torch.empty(total, dtype=dt)
        getattr(lib, f"alpha_fwd_{suf}")(
            _i64(height), _i64(width), ctypes.c_int(col.shape[1]), _ptr(offsets), _ptr(ids), _ptr(m), _ptr(c),
            _ptr(o), _ptr(col), _ptr(out), _ptr(alphas), ctypes.c_int(torch.get_num_threads()),
        )
        ctx.save_for_backward(m, c, o, col, offsets, ids, alphas)
        ctx.hw = (height, width)
        return out

    @staticmethod
    def backward(ctx, grad_out):  # noqa: ANN001
        m, c, o, col, offsets, ids, alphas = ctx.saved_tensors
        height, width = ctx.hw
        g = grad_out.to(o.dtype).contiguous()
        gm, gc, go, gcol = torch.empty_like(m), torch.empty_like(c), torch.empty_like(o), torch.empty_like(col)
        getattr(_get_lib(), f"alpha_bwd_{_suffix(o.dtype)}")(
            _i64(m.shape[0]), _i64(height), _i64(width), ctypes.c_int(col.shape[1]), _ptr(offsets), _ptr(ids),
            _ptr(alphas), _ptr(m), _ptr(c), _ptr(o), _ptr(col), _ptr(g), _ptr(gm), _ptr(gc), _ptr(go), _ptr(gcol),
            ctypes.c_int(torch.get_num_threads()),
        )
        return gm, gc, go, gcol, None, None, None, None


class VoxelizeKernel(torch.autograd.Function):
    """``μ`` on a grid: each Gaussian adds ``ρ exp(-½ dᵀ P d)`` over its voxel box (rows along k vectorised);
    hand-written backward (see the C++ comments). Same inputs as :class:`ctsplat.render._Voxelize` minus chunking:
    memory is the output grid (plus one per-thread grid while it is below 2^27 voxels) and O(N)."""

    @staticmethod
    def forward(ctx, means, prec6, dens, lo, ext, affine, origin, out_shape):  # noqa: ANN001
        lib = _get_lib()
        if lib is None:
            raise RuntimeError(f"render kernel unavailable: {_failed}")
        dt = means.dtype
        m, p, d = (t.detach().to(dt).contiguous() for t in (means, prec6, dens))
        lo_, ext_ = lo.to(torch.int64).contiguous(), ext.to(torch.int64).contiguous()
        aff = torch.cat([affine[:3, :3].reshape(-1), affine[:3, 3]]).to(torch.float64).contiguous()
        org = origin.to(torch.int64).contiguous()
        shp = torch.tensor(out_shape, dtype=torch.int64)
        out = torch.zeros(int(shp.prod()), dtype=dt)
        getattr(lib, f"vox_fwd_{_suffix(dt)}")(
            _i64(m.shape[0]), _ptr(m), _ptr(p), _ptr(d), _ptr(lo_), _ptr(ext_), _ptr(aff), _ptr(org), _ptr(shp),
            _ptr(out), ctypes.c_int(torch.get_num_threads()),
        )
        ctx.save_for_backward(m, p, d, lo_, ext_, aff, org, shp)
        return out

    @staticmethod
    def backward(ctx, grad_out):  # noqa: ANN001
        m, p, d, lo_, ext_, aff, org, shp = ctx.saved_tensors
        g = grad_out.to(m.dtype).contiguous()
        gm, gp, gd = torch.empty_like(m), torch.empty_like(p), torch.empty_like(d)
        getattr(_get_lib(), f"vox_bwd_{_suffix(m.dtype)}")(
            _i64(m.shape[0]), _ptr(m), _ptr(p), _ptr(d), _ptr(lo_), _ptr(ext_), _ptr(aff), _ptr(org), _ptr(shp),
            _ptr(g), _ptr(gm), _ptr(gp), _ptr(gd), ctypes.c_int(torch.get_num_threads()),
        )
        return gm, gp, gd, None, None, None, None, None


def camera_vector(cam: dict, R: torch.Tensor, t: torch.Tensor, k2: float, near: float, cutoff: float) -> torch.Tensor:
    """Pack intrinsics (from :func:`ctsplat.render.camera_intrinsics`), pose and filter constants for the kernel."""
    cone = cam["model"] == "cone"
    if cone:
        lim_x = 1.3 * 0.5 * cam["W"] / cam["fx"] + abs(cam["cx"] - cam["W"] / 2) / cam["fx"]
        lim_y = 1.3 * 0.5 * cam["H"] / cam["fy"] + abs(cam["cy"] - cam["H"] / 2) / cam["fy"]
    else:
        lim_x = lim_y = 0.0
    vals = [1.0 if cone else 0.0, cam.get("sx", 1.0), cam.get("sy", 1.0), cam.get("fx", 1.0), cam.get("fy", 1.0),
            cam["cx"], cam["cy"], cam["W"], cam["H"], lim_x, lim_y]
    vals += [float(x) for x in R.detach().reshape(-1).tolist()] + [float(x) for x in t.detach().reshape(-1).tolist()]
    vals += [k2, near, cutoff]
    return torch.tensor(vals, dtype=torch.float64)
