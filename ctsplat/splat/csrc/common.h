// Shared by every kernel: thread partition, scalar exp / finiteness helpers, the row loops of one Gaussian's
// footprint and the 8-lane float vector type (GCC/Clang vector extensions: AVX2 on x86-64, SSE or NEON pairs
// elsewhere).
#pragma once

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
static inline float log1p_(float x) { return log1pf(x); }
static inline double log1p_(double x) { return log1p(x); }

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

// 8 floats / 8 int32 masks (a true comparison is -1 in every bit)
typedef float v8f __attribute__((vector_size(32)));
typedef int32_t v8i __attribute__((vector_size(32)));
static inline v8f bc8(float s) { return (v8f){s, s, s, s, s, s, s, s}; }
static inline v8f ld8(const float* p) { v8f v; std::memcpy(&v, p, sizeof v); return v; }
static inline void st8(float* p, v8f v) { std::memcpy(p, &v, sizeof v); }
static inline v8f keep8(v8f a, v8i m) { return (v8f)((v8i)a & m); }
static inline float hsum8(v8f a) { return ((a[0] + a[1]) + (a[2] + a[3])) + ((a[4] + a[5]) + (a[6] + a[7])); }
static const v8f IOTA8 = {0.f, 1.f, 2.f, 3.f, 4.f, 5.f, 6.f, 7.f};
