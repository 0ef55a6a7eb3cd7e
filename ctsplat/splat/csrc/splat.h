// Additive rasteriser: for every Gaussian i and every pixel p of its bounding box, img[p] += a_i exp(q_i(p)).
#pragma once

#include "common.h"

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
    // the per-thread images, summed in thread order; over pixel blocks in parallel once there are many of them (a
    // serial sum of nt images would grow with nt; for a few, a thread start costs more than it saves)
    parallel_for(npx, nt > 4 ? nt : 1, [&](int64_t p0, int64_t p1, int) {
        for (int k = 1; k < nt; ++k) {
            const T* b = bufs.data() + (size_t)(k - 1) * (size_t)npx;
            for (int64_t p = p0; p < p1; ++p) out[p] += b[p];
        }
    });
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

// ---------------------------------------------------------------- float32: 8 lanes
// A footprint row is ~8 px wide, too short for the compiler's auto-vectorised libmvec loop (mostly scalar
// remainder), so each row is cut into 8-lane chunks, the last one masked; buffers carry 8 floats of padding so a
// chunk never leaves them.

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
    // the per-thread images, summed in thread order; over pixel blocks in parallel once there are many of them (a
    // serial sum of nt images would grow with nt; for a few, a thread start costs more than it saves)
    parallel_for(npx, nt > 4 ? nt : 1, [&](int64_t p0, int64_t p1, int) {
        for (int64_t p = p0; p < p1; ++p) {
            float s = bufs[(size_t)p];
            for (int k = 1; k < nt; ++k) s += bufs[(size_t)k * (size_t)stride + (size_t)p];
            out[p] = s;
        }
    });
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
