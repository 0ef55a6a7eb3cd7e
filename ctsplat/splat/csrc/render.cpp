// C entry points of the fused CPU render kernels, loaded with ctypes by ctsplat/splat/_kernel.py (whose
// signature table lists every function below with its argument and return types: keep the two in step).
// No torch headers: plain pointers to contiguous CPU buffers; float32 (_f32) and float64 (_f64) instances.
// Each entry point flushes subnormals for its own duration only (FlushDenormals, common.h).

#include "alpha.h"
#include "project.h"
#include "splat.h"
#include "voxelize.h"

extern "C" void alpha_lists_c(int64_t n, const int64_t* order, const int64_t* bb, int64_t H, int64_t W,
                              int64_t* offsets, int32_t* ids, int nt) {
    FlushDenormals ftz;
    alpha_lists(n, order, bb, H, W, offsets, ids, nt);
}

#define EXPORT(T, SUF)                                                                                          \
extern "C" void splat_fwd_##SUF(int64_t n, const T* m, const T* c, const T* a, const int64_t* bb, int64_t H,     \
                                int64_t W, T* out, int nt) {                                                    \
    FlushDenormals ftz;                                                                                         \
    splat_fwd(n, m, c, a, bb, H, W, out, nt); }                                                                 \
extern "C" void splat_bwd_##SUF(int64_t n, const T* m, const T* c, const T* a, const int64_t* bb, int64_t H,     \
                                int64_t W,                                                                      \
                                const T* g, T* gm, T* gc, T* ga, int nt) {                                      \
    FlushDenormals ftz;                                                                                         \
    splat_bwd(n, m, c, a, bb, H, W, g, gm, gc, ga, nt); }                                                       \
extern "C" void proj_fwd_##SUF(int64_t n, const T* means, const T* ls, const T* q, const T* d, const T* fv,       \
                               const double* cam, int mode, int mip, T* m2d, T* con, T* amp, T* depth,          \
                               int64_t* bb, int32_t* radii, uint8_t* valid, uint8_t* visible, int32_t* bad,     \
                               int nt) {                                                                        \
    FlushDenormals ftz;                                                                                         \
    proj_fwd<T>(n, means, ls, q, d, fv, cam, mode, mip, m2d, con, amp, depth, bb, radii, valid, visible, bad, nt); } \
extern "C" void proj_bwd_##SUF(int64_t n, const T* means, const T* ls, const T* q, const T* d, const T* fv,       \
                               const double* cam, int mode, int mip, const T* gm2d, const T* gcon,              \
                               const T* gamp, T* gmeans, T* gls, T* gq, T* gd, int nt) {                        \
    FlushDenormals ftz;                                                                                         \
    proj_bwd<T>(n, means, ls, q, d, fv, cam, mode, mip, gm2d, gcon, gamp, gmeans, gls, gq, gd, nt); }           \
extern "C" void alpha_fwd_##SUF(int64_t H, int64_t W, int C, const int64_t* off, const int32_t* ids, const T* m, \
                                const T* con, const T* op, const T* col, T* out, T* al, int nt) {               \
    FlushDenormals ftz;                                                                                         \
    alpha_fwd<T>(H, W, C, off, ids, m, con, op, col, out, al, nt); }                                            \
extern "C" void alpha_bwd_##SUF(int64_t n, int64_t H, int64_t W, int C, const int64_t* off, const int32_t* ids,  \
                                const T* al, const T* m, const T* con, const T* op, const T* col, const T* g,   \
                                T* gm, T* gc, T* gop, T* gcol, int nt) {                                        \
    FlushDenormals ftz;                                                                                         \
    alpha_bwd<T>(n, H, W, C, off, ids, al, m, con, op, col, g, gm, gc, gop, gcol, nt); }                        \
extern "C" void vox_boxes_##SUF(int64_t n, const T* m, const T* ls, const T* q, const T* fv, const double* aff12, \
                                const int64_t* reg, double cut, int64_t* lo, int64_t* ext, int nt) {            \
    FlushDenormals ftz;                                                                                         \
    vox_boxes<T>(n, m, ls, q, fv, aff12, reg, cut, lo, ext, nt); }                                             \
extern "C" void vox_fwd_##SUF(int64_t n, const T* m, const T* p6, const T* d, const int64_t* lo, const int64_t* ext, \
                              const double* aff, const int64_t* org, const int64_t* shp, T* out, int nt) {      \
    FlushDenormals ftz;                                                                                         \
    vox_fwd<T>(n, m, p6, d, lo, ext, aff, org, shp, out, nt); }                                                 \
extern "C" void vox_bwd_##SUF(int64_t n, const T* m, const T* p6, const T* d, const int64_t* lo, const int64_t* ext, \
                              const double* aff, const int64_t* org, const int64_t* shp, const T* g, T* gm,     \
                              T* gp6, T* gd, int nt) {                                                          \
    FlushDenormals ftz;                                                                                         \
    vox_bwd<T>(n, m, p6, d, lo, ext, aff, org, shp, g, gm, gp6, gd, nt); }

EXPORT(float, f32)
EXPORT(double, f64)
