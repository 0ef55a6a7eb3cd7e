"""Fused CPU kernel for the additive (radiative) rasteriser, with a hand-written backward.

Same math as :func:`ctsplat.render.splat_additive_reference` (and tested against it): for every Gaussian ``i`` and
every pixel ``p`` of its bounding box, ``img[p] += a_i exp(q_i(p))`` with
``q = -½ (A dx² + C dy²) - B dx dy``, ``dx = u_p + 0.5 - m_x``, ``dy = v_p + 0.5 - m_y``. Backward, with
``g = ∂L/∂img[p]`` and ``e = exp(q)``::

    ∂L/∂a   = Σ_p g e
    ∂L/∂m_x = Σ_p g a e (A dx + B dy),   ∂L/∂m_y = Σ_p g a e (B dx + C dy)
    ∂L/∂A   = -½ Σ_p g a e dx²,  ∂L/∂B = -Σ_p g a e dx dy,  ∂L/∂C = -½ Σ_p g a e dy²

The C source is compiled once with the system C compiler (``cc -O3 -fopenmp``) into ``$CTSPLAT_CACHE`` (default
``~/.cache/ctsplat``) keyed by a hash of the source, and loaded with ``ctypes`` -- no torch headers, so compiling
takes about a second. Forward: OpenMP over Gaussians with per-thread image buffers summed in a fixed order
(deterministic for a fixed thread count). Backward: OpenMP over Gaussians, no write conflicts. If no compiler is
available, :func:`available` returns False and the renderer uses the PyTorch reference.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

import torch

__all__ = ["available", "splat_additive_kernel", "SplatAdditive"]

_SRC = r"""
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#ifdef _OPENMP
#include <omp.h>
#endif

#define DEFINE_KERNELS(T, SUF)                                                                         \
void fwd_##SUF(int64_t n, const T* mean, const T* con, const T* amp, const int64_t* bb,             \
               int64_t H, int64_t W, T* out, int nthreads) {                                         \
    int nt = nthreads < 1 ? 1 : nthreads;                                                            \
    int64_t npx = H * W;                                                                             \
    T* bufs = nt > 1 ? (T*)calloc((size_t)(nt - 1) * (size_t)npx, sizeof(T)) : NULL;                 \
    if (nt > 1 && !bufs) nt = 1;                                                                     \
    _Pragma("omp parallel num_threads(nt)")                                                          \
    {                                                                                                \
        int tid = 0;                                                                                 \
        IF_OMP(tid = omp_get_thread_num();)                                                          \
        T* img = tid == 0 ? out : bufs + (size_t)(tid - 1) * (size_t)npx;                           \
        _Pragma("omp for schedule(static)")                                                          \
        for (int64_t i = 0; i < n; ++i) {                                                            \
            const int64_t u0 = bb[4*i], u1 = bb[4*i+1], v0 = bb[4*i+2], v1 = bb[4*i+3];              \
            if (u1 <= u0 || v1 <= v0) continue;                                                      \
            const T mx = mean[2*i], my = mean[2*i+1];                                                \
            const T A = con[3*i], B = con[3*i+1], C = con[3*i+2], a = amp[i];                        \
            for (int64_t v = v0; v < v1; ++v) {                                                      \
                const T dy = (T)v + (T)0.5 - my;                                                     \
                const T cy = (T)(-0.5) * C * dy * dy;                                                \
                const T by = -B * dy;                                                                \
                T* row = img + v * W;                                                                \
                for (int64_t u = u0; u < u1; ++u) {                                                  \
                    const T dx = (T)u + (T)0.5 - mx;                                                 \
                    const T q = (T)(-0.5) * A * dx * dx + by * dx + cy;                              \
                    row[u] += a * EXPF_##SUF(q);                                                     \
                }                                                                                    \
            }                                                                                        \
        }                                                                                            \
    }                                                                                                \
    for (int k = 1; k < nt; ++k) {                                                                   \
        const T* b = bufs + (size_t)(k - 1) * (size_t)npx;                                           \
        for (int64_t p = 0; p < npx; ++p) out[p] += b[p];                                            \
    }                                                                                                \
    free(bufs);                                                                                      \
}                                                                                                    \
void bwd_##SUF(int64_t n, const T* mean, const T* con, const T* amp, const int64_t* bb,             \
               int64_t H, int64_t W, const T* gimg, T* gmean, T* gcon, T* gamp, int nthreads) {     \
    int nt = nthreads < 1 ? 1 : nthreads;                                                            \
    (void)H;                                                                                         \
    _Pragma("omp parallel for num_threads(nt) schedule(dynamic, 256)")                               \
    for (int64_t i = 0; i < n; ++i) {                                                                \
        const int64_t u0 = bb[4*i], u1 = bb[4*i+1], v0 = bb[4*i+2], v1 = bb[4*i+3];                  \
        T s_e = 0, s_mx = 0, s_my = 0, s_xx = 0, s_xy = 0, s_yy = 0;                                 \
        if (u1 > u0 && v1 > v0) {                                                                    \
            const T mx = mean[2*i], my = mean[2*i+1];                                                \
            const T A = con[3*i], B = con[3*i+1], C = con[3*i+2];                                    \
            for (int64_t v = v0; v < v1; ++v) {                                                      \
                const T dy = (T)v + (T)0.5 - my;                                                     \
                const T cy = (T)(-0.5) * C * dy * dy;                                                \
                const T by = -B * dy;                                                                \
                const T* grow = gimg + v * W;                                                        \
                T r_e = 0, r_x = 0, r_xx = 0;                                                        \
                for (int64_t u = u0; u < u1; ++u) {                                                  \
                    const T dx = (T)u + (T)0.5 - mx;                                                 \
                    const T q = (T)(-0.5) * A * dx * dx + by * dx + cy;                              \
                    const T ge = grow[u] * EXPF_##SUF(q);                                            \
                    r_e += ge; r_x += ge * dx; r_xx += ge * dx * dx;                                 \
                }                                                                                    \
                s_e += r_e; s_mx += r_x; s_xx += r_xx;                                               \
                s_my += r_e * dy; s_xy += r_x * dy; s_yy += r_e * dy * dy;                           \
            }                                                                                        \
            const T a = amp[i];                                                                      \
            gamp[i] = s_e;                                                                           \
            gmean[2*i] = a * (A * s_mx + B * s_my);                                                  \
            gmean[2*i+1] = a * (B * s_mx + C * s_my);                                                     \
            gcon[3*i] = (T)(-0.5) * a * s_xx;                                                        \
            gcon[3*i+1] = -a * s_xy;                                                                 \
            gcon[3*i+2] = (T)(-0.5) * a * s_yy;                                                      \
        } else {                                                                                     \
            gamp[i] = 0; gmean[2*i] = 0; gmean[2*i+1] = 0;                                           \
            gcon[3*i] = 0; gcon[3*i+1] = 0; gcon[3*i+2] = 0;                                         \
        }                                                                                            \
    }                                                                                                \
}

#ifdef _OPENMP
#define IF_OMP(x) x
#else
#define IF_OMP(x)
#endif
#define EXPF_f32 expf
#define EXPF_f64 exp
DEFINE_KERNELS(float, f32)
DEFINE_KERNELS(double, f64)
"""

_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_failed: str | None = None


def _cache_dir() -> Path:
    return Path(os.environ.get("CTSPLAT_CACHE", Path.home() / ".cache" / "ctsplat"))


def _build() -> ctypes.CDLL:
    tag = hashlib.sha256(_SRC.encode()).hexdigest()[:16]
    out = _cache_dir() / f"splat_{tag}.so"
    if not out.exists():
        cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
        if cc is None:
            raise RuntimeError("no C compiler found")
        out.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
            src = Path(tmp) / "splat.c"
            src.write_text(_SRC)
            so = Path(tmp) / "splat.so"
            base = [cc, "-O3", "-fno-math-errno", "-fPIC", "-shared", str(src), "-o", str(so), "-lm"]
            res = subprocess.run(base[:1] + ["-fopenmp"] + base[1:], capture_output=True, text=True)
            if res.returncode != 0:  # no OpenMP: single-threaded build
                res = subprocess.run(base, capture_output=True, text=True)
            if res.returncode != 0:
                raise RuntimeError(f"C kernel compilation failed: {res.stderr.strip()[:500]}")
            os.replace(so, out)
    lib = ctypes.CDLL(str(out))
    for suf in ("f32", "f64"):
        getattr(lib, f"fwd_{suf}").restype = None
        getattr(lib, f"bwd_{suf}").restype = None
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
    return _lib


def available() -> bool:
    """True when the compiled kernel can be used (builds it on first call)."""
    return _get_lib() is not None


def _ptr(t: torch.Tensor) -> ctypes.c_void_p:
    return ctypes.c_void_p(t.data_ptr())


class SplatAdditive(torch.autograd.Function):
    """``img = splat(means2d, conics, amps)`` with the fused kernel; bbox (N, 4) int64 is a constant."""

    @staticmethod
    def forward(ctx, means2d, conics, amps, bbox, height: int, width: int):  # noqa: ANN001
        lib = _get_lib()
        if lib is None:
            raise RuntimeError(f"render kernel unavailable: {_failed}")
        dt = amps.dtype
        if dt not in (torch.float32, torch.float64):
            raise TypeError(f"render kernel supports float32/float64, got {dt}")
        m = means2d.detach().contiguous()
        c = conics.detach().contiguous()
        a = amps.detach().contiguous()
        b = bbox.to(torch.int64).contiguous()
        out = torch.zeros(height, width, dtype=dt)
        suf = "f32" if dt == torch.float32 else "f64"
        getattr(lib, f"fwd_{suf}")(
            ctypes.c_int64(m.shape[0]), _ptr(m), _ptr(c), _ptr(a), _ptr(b), ctypes.c_int64(height),
            ctypes.c_int64(width), _ptr(out), ctypes.c_int(torch.get_num_threads()),
        )
        ctx.save_for_backward(m, c, a, b)
        ctx.hw = (height, width)
        return out

    @staticmethod
    def backward(ctx, grad_img):  # noqa: ANN001
        m, c, a, b = ctx.saved_tensors
        height, width = ctx.hw
        lib = _get_lib()
        g = grad_img.to(a.dtype).contiguous()
        gm = torch.empty_like(m)
        gc = torch.empty_like(c)
        ga = torch.empty_like(a)
        suf = "f32" if a.dtype == torch.float32 else "f64"
        getattr(lib, f"bwd_{suf}")(
            ctypes.c_int64(m.shape[0]), _ptr(m), _ptr(c), _ptr(a), _ptr(b), ctypes.c_int64(height),
            ctypes.c_int64(width), _ptr(g), _ptr(gm), _ptr(gc), _ptr(ga), ctypes.c_int(torch.get_num_threads()),
        )
        return gm, gc, ga, None, None, None


def splat_additive_kernel(proj, height: int, width: int) -> torch.Tensor:  # noqa: ANN001
    """Fused-kernel equivalent of :func:`ctsplat.render.splat_additive_reference` (CPU tensors)."""
    return SplatAdditive.apply(proj.means2d, proj.conics, proj.amps, proj.bbox, height, width)
