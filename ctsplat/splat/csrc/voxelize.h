// Voxelizer: mu(x) = sum_i rho_i exp(-1/2 (x - m_i)^T P_i (x - m_i)) at voxel centres, with the backward.
#pragma once

#include "common.h"
#include "project.h"  // unit_rotmat

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

// rows a0 <= a < a1 of the box along the first index axis (the backward walks them all, the forward one band's)
template <typename T, typename F>
static inline void vox_rows(int64_t i, const T* means, const T* P, const VoxAxis<T>& ax, const int64_t* lo,
                            const int64_t* ext, const double* aff, const int64_t* origin, const int64_t* shape,
                            int64_t a0, int64_t a1, F&& row) {
    for (int64_t a = a0; a < a1; ++a)
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

// Threads for a voxelizer pass: by the voxels it touches, not the Gaussians' count (a small region's few
// hundred Gaussians can cover a million voxels; many tiny boxes can be too little work to share out)
static inline int vox_threads(int64_t n, const int64_t* ext, int nt) {
    if (nt <= 1) return 1;
    int64_t work = 0;
    for (int64_t i = 0; i < n && work < ((int64_t)1 << 15); ++i) work += ext[3 * i] * ext[3 * i + 1] * ext[3 * i + 2];
    return work < ((int64_t)1 << 15) ? 1 : nt;
}

// Index-space boxes of the Gaussians (no gradients): centre c = A⁻¹ (m - t_A), half widths cutoff sqrt(var_a) with
// var_a = Σ_k (A⁻¹ R)_ak² (s_k² + fvar), lo = ceil(c - half), hi = floor(c + half) + 1, both clamped to the region
// [reg_lo, reg_hi), ext = max(hi - lo, 0). The same arithmetic, in T, as the PyTorch path of voxelize() (render.py);
// aff12 = A⁻¹ (row-major 3x3) then t_A; reg = lo0, hi0, lo1, hi1, lo2, hi2; fv may be NULL.
template <typename T>
static void vox_boxes(int64_t n, const T* means, const T* ls, const T* q, const T* fv, const double* aff12,
                      const int64_t* reg, double cutoff, int64_t* lo, int64_t* ext, int nt) {
    parallel_for(n, nt, [&](int64_t i0, int64_t i1, int) {
        T Ai[9], tA[3];
        for (int k = 0; k < 9; ++k) Ai[k] = (T)aff12[k];
        for (int k = 0; k < 3; ++k) tA[k] = (T)aff12[9 + k];
        for (int64_t i = i0; i < i1; ++i) {
            T qn[4], Rq[9];
            unit_rotmat(q + 4 * i, qn, Rq);
            T s2[3];
            for (int k = 0; k < 3; ++k) s2[k] = std::exp(2 * ls[3 * i + k]) + (fv ? fv[i] : (T)0);
            T d[3];
            for (int k = 0; k < 3; ++k) d[k] = means[3 * i + k] - tA[k];
            for (int a = 0; a < 3; ++a) {
                T var = 0, c = 0;
                for (int k = 0; k < 3; ++k) {
                    const T ar = Ai[3 * a] * Rq[k] + Ai[3 * a + 1] * Rq[3 + k] + Ai[3 * a + 2] * Rq[6 + k];
                    var += ar * ar * s2[k];
                    c += Ai[3 * a + k] * d[k];
                }
                const T half = (T)cutoff * std::sqrt(var > 0 ? var : (T)0);
                const T rl = (T)reg[2 * a], rh = (T)reg[2 * a + 1];
                const T l = std::min(std::max(std::ceil(c - half), rl), rh);
                const T h = std::min(std::max(std::floor(c + half) + 1, rl), rh);
                lo[3 * i + a] = (int64_t)l;
                ext[3 * i + a] = std::max<int64_t>((int64_t)h - (int64_t)l, 0);
            }
        }
    });
}

// out (zeroed by the caller) += every Gaussian's values, cut into slabs of the first index axis (banded_scatter):
// each voxel summed in Gaussian order whatever the thread count
template <typename T>
static void vox_fwd(int64_t n, const T* means, const T* p6, const T* dens, const int64_t* lo, const int64_t* ext,
                    const double* aff, const int64_t* origin, const int64_t* shape, T* out, int nthreads) {
    banded_scatter(n, shape[0], vox_threads(n, ext, nthreads),
                   [=](int64_t i, int64_t& first, int64_t& last) {
                       first = lo[3 * i] - origin[0];
                       last = first + ext[3 * i] - 1;
                       return ext[3 * i + 1] > 0 && ext[3 * i + 2] > 0;
                   },
                   [=](int64_t i, int64_t r0, int64_t r1) {
        const int64_t first = lo[3 * i] - origin[0];
        const T* P = p6 + 6 * i;
        const VoxAxis<T> ax(P, aff);
        vox_rows(i, means, P, ax, lo, ext, aff, origin, shape, std::max<int64_t>(0, r0 - first),
                 std::min<int64_t>(ext[3 * i], r1 - first), [&](int64_t flat, const T*, T q0, T q1) {
            // value = rho exp(-q/2)
            row_fwd<T>(out + flat, (int)ext[3 * i + 2], (T)0, ax.wPw, (T)(-0.5) * q1, (T)(-0.5) * q0, dens[i]);
        });
    });
}

template <typename T>
static void vox_bwd(int64_t n, const T* means, const T* p6, const T* dens, const int64_t* lo, const int64_t* ext,
                    const double* aff, const int64_t* origin, const int64_t* shape, const T* gout, T* gmeans, T* gp6,
                    T* gdens, int nt) {
    parallel_for(n, vox_threads(n, ext, nt), [&](int64_t i0, int64_t i1, int) {
        for (int64_t i = i0; i < i1; ++i) {
            const T* P = p6 + 6 * i;
            const VoxAxis<T> ax(P, aff);
            const T* w = ax.w;
            double S = 0, Sd[3] = {0, 0, 0}, Sdd[6] = {0, 0, 0, 0, 0, 0};  // sums of g e, g e d, g e d d^T
            vox_rows(i, means, P, ax, lo, ext, aff, origin, shape, 0, ext[3 * i], [&](int64_t flat, const T* d, T q0,
                                                                                   T q1) {
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
    }, 1);
}
