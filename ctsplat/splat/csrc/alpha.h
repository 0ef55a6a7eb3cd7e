// Front-to-back alpha compositing of per-pixel depth-sorted Gaussian lists, with the hand-written backward.
#pragma once

#include "common.h"

// Per-pixel lists of Gaussians in depth order (a counting sort by pixel, filled in depth order). The counts come from
// a 2D difference array of the boxes (O(n + H W), not one increment per list entry). The fill runs on nt threads
// over bands of rows holding about 2^17 entries each (512 KiB of ids, so a band's writes stay in cache); every band
// first gets the Gaussians whose boxes reach it, in depth order, so a band walks only those, and each pixel's list
// is the same whatever the thread count.
static void alpha_lists(int64_t n, const int64_t* order, const int64_t* bb, int64_t H, int64_t W,
                        int64_t* offsets, int32_t* ids, int nt) {
    const int64_t npx = H * W, W1 = W + 1;
    std::vector<int64_t> diff((size_t)((H + 1) * W1), 0);
    for (int64_t i = 0; i < n; ++i) {
        const int64_t u0 = bb[4 * i], u1 = bb[4 * i + 1], v0 = bb[4 * i + 2], v1 = bb[4 * i + 3];
        if (u1 <= u0 || v1 <= v0) continue;
        diff[v0 * W1 + u0] += 1; diff[v0 * W1 + u1] -= 1;
        diff[v1 * W1 + u0] -= 1; diff[v1 * W1 + u1] += 1;
    }
    std::vector<int64_t> col((size_t)W, 0);  // running sums down each column
    offsets[0] = 0;
    for (int64_t v = 0; v < H; ++v) {
        int64_t row = 0;  // running sum along the row
        for (int64_t u = 0; u < W; ++u) {
            row += diff[v * W1 + u];
            col[u] += row;
            offsets[v * W + u + 1] = offsets[v * W + u] + col[u];
        }
    }
    const int64_t total = offsets[npx];
    if (total == 0) return;
    int64_t bands = std::max<int64_t>(nt < 1 ? 1 : nt, total >> 17);
    if (total < 65536) bands = 1;
    bands = std::min<int64_t>(bands, H);
    std::vector<int64_t> first((size_t)bands + 1, H);  // band b: rows first[b] .. first[b + 1] - 1
    first[0] = 0;
    for (int64_t b = 1, v = 0; b < bands; ++b) {
        while (v < H && offsets[v * W] < total * b / bands) ++v;
        first[b] = v;
    }
    std::vector<int64_t> band_of((size_t)H);  // the band of each row
    for (int64_t b = 0; b < bands; ++b)
        for (int64_t v = first[b]; v < first[b + 1]; ++v) band_of[v] = b;
    // the Gaussians of each band in depth order (a counting sort by band)
    std::vector<int64_t> start((size_t)bands + 1, 0);
    auto reach = [&](int64_t i, int64_t& b0, int64_t& b1) {
        if (bb[4 * i + 1] <= bb[4 * i] || bb[4 * i + 3] <= bb[4 * i + 2]) return false;
        b0 = band_of[bb[4 * i + 2]];
        b1 = band_of[bb[4 * i + 3] - 1];
        return true;
    };
    for (int64_t k = 0; k < n; ++k) {
        int64_t b0, b1;
        if (reach(order[k], b0, b1))
            for (int64_t b = b0; b <= b1; ++b) ++start[b + 1];
    }
    for (int64_t b = 0; b < bands; ++b) start[b + 1] += start[b];
    std::vector<int32_t> members((size_t)start[bands]);
    std::vector<int64_t> next(start.begin(), start.end() - 1);
    for (int64_t k = 0; k < n; ++k) {
        int64_t b0, b1;
        if (reach(order[k], b0, b1))
            for (int64_t b = b0; b <= b1; ++b) members[next[b]++] = (int32_t)order[k];
    }
    std::vector<int64_t> fill(offsets, offsets + npx);
    parallel_tasks(bands, nt, [&](int64_t b) {
        for (int64_t m = start[b]; m < start[b + 1]; ++m) {
            const int64_t i = members[m];
            const int64_t u0 = bb[4 * i], u1 = bb[4 * i + 1];
            const int64_t v0 = std::max(bb[4 * i + 2], first[b]), v1 = std::min(bb[4 * i + 3], first[b + 1]);
            for (int64_t v = v0; v < v1; ++v)
                for (int64_t u = u0; u < u1; ++u) ids[fill[v * W + u]++] = (int32_t)i;
        }
    });
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
            T sum[32];  // the pixel's colour, in registers rather than through out (which may alias the inputs)
            for (int c = 0; c < C; ++c) sum[c] = 0;
            for (int64_t k = offsets[p], k1 = offsets[p + 1]; k < k1; ++k) {
                const int32_t i = ids[k];
                T e, dx, dy;
                const T a = alpha_of(mean, con, op, i, px, py, e, dx, dy);
                alphas[k] = a;  // kept for the backward (no exp there)
                const T w = Tr * a;
                for (int c = 0; c < C; ++c) sum[c] += w * col[i * C + c];
                Tr *= 1 - a;
            }
            for (int c = 0; c < C; ++c) out[p * C + c] = sum[c];
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
