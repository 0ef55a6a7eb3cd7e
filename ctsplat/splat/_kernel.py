"""Fused CPU kernels with hand-written backward passes: projection, additive rasteriser, alpha compositing, voxelizer.

Four ``torch.autograd.Function`` s, chained exactly like the reference path (:mod:`ctsplat.splat._reference`) so that
``means2d`` stays a real graph node (its ``.grad`` feeds densification):

* :class:`Project` -- :func:`ctsplat.splat.render.project` for every compositor (same formulas, same 3D filter /
  2D mip / ``EPS_2D`` handling, same bounding boxes) in one pass over the Gaussians; its backward re-computes the
  forward per Gaussian and applies the chain rule by hand (quaternion normalisation, ``R S² Rᵀ``, the cone Jacobian
  with the 3DGS clamp, ``log|J|``, conic inversion, softplus / sigmoid).
* :class:`SplatAdditive` -- for every Gaussian ``i`` and every pixel ``p`` of its bounding box,
  ``img[p] += a_i exp(q_i(p))``, ``q = -½ (A dx² + C dy²) - B dx dy``, ``dx = u_p + 0.5 - m_x``,
  ``dy = v_p + 0.5 - m_y``. Backward, with ``g = ∂L/∂img[p]`` and ``e = exp(q)``::

      ∂L/∂a   = Σ_p g e
      ∂L/∂m_x = a Σ_p g e (A dx + B dy),   ∂L/∂m_y = a Σ_p g e (B dx + C dy)
      ∂L/∂A   = -½ a Σ_p g e dx²,  ∂L/∂B = -a Σ_p g e dx dy,  ∂L/∂C = -½ a Σ_p g e dy²

* :class:`AlphaComposite` -- front-to-back compositing of per-pixel depth-sorted lists.
* :class:`Voxelize` -- ``μ`` on a voxel grid (each Gaussian over its box, rows along k vectorised).

All are tested against the autograd reference (values and gradients, float32 and float64) and by gradcheck.
The float32 rasteriser cuts each footprint row into 8-lane chunks (GCC/Clang vector extensions, the last chunk
masked) with an inline vector ``exp`` (Cody-Waite reduction + Cephes polynomial, about 1 ulp): footprint rows are
~8 px long, too short for auto-vectorised loops. The projection runs in blocks of separate short passes
(activations through libmvec, finiteness, per-Gaussian algebra, boxes); in float32 its algebra, forward and
backward, runs on 8 Gaussians side by side (``proj8``: one Gaussian's chain of dependent operations is
latency-bound). float64 keeps the scalar code (gradcheck, the exactness tests), the float32 path is tested
against it.

Build: the C++ sources in ``csrc/`` (package data, no torch headers) are compiled on first use with the system
compiler (``c++ -O3 -ffast-math -march=native``, without ``-march=native`` if the compiler rejects it; other loops
vectorise with glibc's libmvec ``exp``) into ``$CTSPLAT_CACHE`` (default ``~/.cache/ctsplat``), keyed by the
sources, the CPU and the flags, and loaded with ``ctypes``; compiling takes a few seconds. Every C function is
declared once in :data:`SIGNATURES` (argument and return types) and called through a wrapper that also checks the
argument count. Threads: ``torch.get_num_threads()`` threads of a pool kept between calls (``WorkerPool`` in
``csrc/common.h``: workers sleep between kernels; no OpenMP runtime that would spin against torch's). Gradients:
static blocks of Gaussians, each Gaussian's sums by one thread. Image forward: each thread scatters its block into
its own image, and the images are summed in thread order (over pixel blocks in parallel beyond 4 threads), so
results are deterministic for a fixed thread count. Voxelizer forward: the grid is cut into slabs of its first
axis, handed out to the threads, and each slab sums its Gaussians in index order (``banded_scatter`` in
``csrc/common.h``): no per-thread grids, and the same bits for any thread count. Without a compiler (or with
``CTSPLAT_NO_KERNEL=1``) :func:`available` is False and the renderer uses the reference.

References
----------
.. [1] M. Zwicker, H. Pfister, J. van Baar, M. Gross, "EWA Volume Splatting", IEEE Visualization 2001.
.. [2] B. Kerbl, G. Kopanas, T. Leimkühler, G. Drettakis, "3D Gaussian Splatting for Real-Time Radiance Field
   Rendering", ACM Transactions on Graphics 42(4), 2023.
.. [3] R. Zha, T. J. Lin, Y. Cai, J. Cao, Y. Zhang, H. Li, "R²-Gaussian: Rectifying Radiative Gaussian Splatting
   for Tomographic Reconstruction", NeurIPS 2024.
.. [4] Z. Yu, A. Chen, B. Huang, T. Sattler, A. Geiger, "Mip-Splatting: Alias-free 3D Gaussian Splatting",
   CVPR 2024.
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
from collections.abc import Callable
from pathlib import Path

import torch

__all__ = ["available", "SIGNATURES", "CSRC", "Project", "SplatAdditive", "AlphaComposite", "Voxelize",
           "voxel_boxes", "camera_vector"]

#: folder of the C++ sources (``render.cpp`` includes the headers next to it)
CSRC = Path(__file__).resolve().parent / "csrc"

_P, _I64, _INT, _F64 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int, ctypes.c_double
# (argument types, return type) of each per-dtype entry point; exported as NAME_f32 and NAME_f64 (buffers are
# passed as untyped pointers, so both instances share one signature). Order and meaning: csrc/render.cpp.
_PER_DTYPE: dict[str, tuple[tuple[type, ...], type | None]] = {
    # n, means2d, conics, amps, bbox, H, W, out, threads
    "splat_fwd": ((_I64, _P, _P, _P, _P, _I64, _I64, _P, _INT), None),
    # n, means2d, conics, amps, bbox, H, W, grad_img, g_means2d, g_conics, g_amps, threads
    "splat_bwd": ((_I64, _P, _P, _P, _P, _I64, _I64, _P, _P, _P, _P, _INT), None),
    # n, means, log_scales, quats, raw, fvar|NULL, cam, mode, mip, means2d, conics, amps, depths, bbox, radii,
    # valid, visible, nonfinite, threads
    "proj_fwd": ((_I64, _P, _P, _P, _P, _P, _P, _INT, _INT, _P, _P, _P, _P, _P, _P, _P, _P, _P, _INT), None),
    # n, means, log_scales, quats, raw, fvar|NULL, cam, mode, mip, g_means2d, g_conics, g_amps, g_means,
    # g_log_scales, g_quats, g_raw, threads
    "proj_bwd": ((_I64, _P, _P, _P, _P, _P, _P, _INT, _INT, _P, _P, _P, _P, _P, _P, _P, _INT), None),
    # H, W, C, offsets, ids, means2d, conics, opacities, colours, out, alphas, threads
    "alpha_fwd": ((_I64, _I64, _INT, _P, _P, _P, _P, _P, _P, _P, _P, _INT), None),
    # n, H, W, C, offsets, ids, alphas, means2d, conics, opacities, colours, grad_out, g_means2d, g_conics,
    # g_opacities, g_colours, threads
    "alpha_bwd": ((_I64, _I64, _I64, _INT, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _INT), None),
    # n, means, log_scales, quats, fvar|NULL, inverse affine + translation (12 doubles), region (6), cutoff, lo, ext,
    # threads
    "vox_boxes": ((_I64, _P, _P, _P, _P, _P, _P, _F64, _P, _P, _INT), None),
    # n, means, prec6, dens, lo, ext, affine, origin, shape, out, threads
    "vox_fwd": ((_I64, _P, _P, _P, _P, _P, _P, _P, _P, _P, _INT), None),
    # n, means, prec6, dens, lo, ext, affine, origin, shape, grad_out, g_means, g_prec6, g_dens, threads
    "vox_bwd": ((_I64, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _INT), None),
}
#: every C function the Python side calls: name -> (argtypes, restype)
SIGNATURES: dict[str, tuple[tuple[type, ...], type | None]] = {
    # n, depth order, bbox, H, W, offsets (H W + 1), ids, threads
    "alpha_lists_c": ((_I64, _P, _P, _I64, _I64, _P, _P, _INT), None),
    **{f"{name}_{suf}": sig for name, sig in _PER_DTYPE.items() for suf in ("f32", "f64")},
}

# tried in order; the first set the compiler accepts is used (some compilers lack -march=native)
_FLAG_SETS = (["-march=native"], [])
#: How the library is built (part of the cache key): compiled and linked in two steps (see _build).
_BUILD = "compile -ffast-math, link without"

_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_funcs: dict[str, Callable[..., None]] = {}
_failed: str | None = None


def _cache_dir() -> Path:
    return Path(os.environ.get("CTSPLAT_CACHE", Path.home() / ".cache" / "ctsplat"))


def _sources() -> dict[str, str]:
    """The C++ sources by file name (``render.cpp`` and the headers it includes)."""
    if not (CSRC / "render.cpp").is_file():
        raise OSError(f"render kernel source {CSRC / 'render.cpp'} is missing; reinstall ctsplat")
    files = sorted(p for p in CSRC.iterdir() if p.suffix in (".cpp", ".h"))
    return {p.name: p.read_text() for p in files}


def _build() -> ctypes.CDLL:
    srcs = _sources()
    # -march=native: the build is specific to this CPU, so the cache key includes the machine and CPU model
    cpu = platform.machine() + platform.processor()
    with contextlib.suppress(OSError):
        cpu += next((ln for ln in Path("/proc/cpuinfo").read_text().splitlines() if ln.startswith("flags")), "")
    text = "".join(f"// {name}\n{body}" for name, body in srcs.items())
    tag = hashlib.sha256((text + cpu + repr(_FLAG_SETS) + _BUILD).encode()).hexdigest()[:16]
    out = _cache_dir() / f"render_{tag}.so"
    if not out.exists():
        cxx = os.environ.get("CXX") or shutil.which("c++") or shutil.which("g++") or shutil.which("clang++")
        if cxx is None:
            raise RuntimeError("no C++ compiler found (c++, g++ or clang++)")
        out.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
            for name, body in srcs.items():  # compile exactly the hashed text
                (Path(tmp) / name).write_text(body)
            src = Path(tmp) / "render.cpp"
            obj = Path(tmp) / "render.o"
            so = Path(tmp) / "render.so"
            # compiled with -ffast-math but linked without it: GCC links crtfastmath.o into a -ffast-math link,
            # whose constructor turns on flush-to-zero for the whole process (numpy and torch included) on load
            base = [cxx, "-O3", "-std=c++17", "-ffast-math", "-fPIC", "-c", str(src), "-o", str(obj)]
            for extra in _FLAG_SETS:  # the first set the compiler accepts
                res = subprocess.run(base[:1] + extra + base[1:], capture_output=True, text=True)
                if res.returncode == 0:
                    res = subprocess.run([cxx, "-shared", str(obj), "-o", str(so), "-pthread"], capture_output=True,
                                         text=True)
                    break
            if res.returncode != 0:
                raise RuntimeError(f"render kernel compilation failed: {res.stderr.strip()[:500]}")
            os.replace(so, out)
    return ctypes.CDLL(str(out))


def _checked(name: str, fn: Callable[..., None], nargs: int) -> Callable[..., None]:
    # ctypes rejects too few arguments once argtypes is set but passes extra ones on (C varargs rules)
    def call(*args: object) -> None:
        if len(args) != nargs:
            raise TypeError(f"render kernel function {name} takes {nargs} arguments ({len(args)} given)")
        return fn(*args)

    return call


def _bind(lib: ctypes.CDLL) -> dict[str, Callable[..., None]]:
    """Declare every function of :data:`SIGNATURES` on ``lib`` (argtypes and restype); checked callables by name."""
    funcs = {}
    for name, (argtypes, restype) in SIGNATURES.items():
        fn = getattr(lib, name)
        fn.argtypes = list(argtypes)
        fn.restype = restype
        funcs[name] = _checked(name, fn, len(argtypes))
    return funcs


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
                    lib = _build()
                    _funcs.update(_bind(lib))
                    _lib = lib
                except (OSError, RuntimeError) as exc:
                    _failed = str(exc)
                    logging.getLogger(__name__).warning(
                        "fused render kernels unavailable (%s); using the slower PyTorch reference renderer. "
                        "Set CTSPLAT_CACHE to a writable folder or install a C++ compiler.", _failed.splitlines()[0]
                    )
    return _lib


def available() -> bool:
    """Whether the compiled kernels can be used (builds them on the first call).

    Returns
    -------
    bool
        False without a C++ compiler, with ``CTSPLAT_NO_KERNEL`` set, or when the build failed (reason in the log).
    """
    return _get_lib() is not None


def _fn(name: str, dtype: torch.dtype | None = None) -> Callable[..., None]:
    """The checked C function ``name`` (``name_f32`` / ``name_f64`` for a ``dtype``); raises if the kernels are off."""
    if _get_lib() is None:
        raise RuntimeError(f"render kernel unavailable: {_failed}")
    return _funcs[name if dtype is None else f"{name}_{_suffix(dtype)}"]


def _ptr(t: torch.Tensor) -> int:
    return t.data_ptr()


def _suffix(dt: torch.dtype) -> str:
    if dt == torch.float32:
        return "f32"
    if dt == torch.float64:
        return "f64"
    raise TypeError(f"render kernel supports float32/float64, got {dt}")


class SplatAdditive(torch.autograd.Function):
    """``img = splat(means2d, conics, amps)`` (:func:`ctsplat.splat._reference.splat_additive_reference`).

    Inputs: means2d (N, 2) px, conics (N, 3) px⁻², amps (N,), bbox (N, 4) int64 (a constant), height, width.
    Output: image (H, W).
    """

    @staticmethod
    def forward(ctx, means2d, conics, amps, bbox, height: int, width: int):  # noqa: ANN001
        dt = amps.dtype
        fwd = _fn("splat_fwd", dt)
        m = means2d.detach().contiguous()
        c = conics.detach().to(dt).contiguous()
        a = amps.detach().contiguous()
        b = bbox.to(torch.int64).contiguous()
        out = torch.empty(height, width, dtype=dt)  # the kernel writes every pixel
        fwd(m.shape[0], _ptr(m), _ptr(c), _ptr(a), _ptr(b), height, width, _ptr(out), torch.get_num_threads())
        ctx.save_for_backward(m, c, a, b)
        ctx.hw = (height, width)
        return out

    @staticmethod
    def backward(ctx, grad_img):  # noqa: ANN001
        m, c, a, b = ctx.saved_tensors
        height, width = ctx.hw
        g = grad_img.to(a.dtype).contiguous()
        gm, gc, ga = torch.empty_like(m), torch.empty_like(c), torch.empty_like(a)
        _fn("splat_bwd", a.dtype)(
            m.shape[0], _ptr(m), _ptr(c), _ptr(a), _ptr(b), height, width, _ptr(g), _ptr(gm), _ptr(gc), _ptr(ga),
            torch.get_num_threads(),
        )
        return gm, gc, ga, None, None, None


class Project(torch.autograd.Function):
    """Fused :func:`ctsplat.splat.render.project` (hand-written backward).

    Inputs: means (N,3), log_scales (N,3), quats (N,4), density_raw (N,) (mode 2: opacity_raw), filter_3d_var (N,)
    or None (constant), cam: float64 parameter vector (see :func:`camera_vector`), mode 0 radiative /
    1 unrectified / 2 alpha (amplitude = sigmoid opacity, filters as unrectified), mip flag.
    Outputs: means2d (N,2), conics (N,3), amps (N,), depths (N,); without gradient: bbox (N,4) int64, radii (N,)
    int32, valid (N,) bool (in front of a cone's source), visible (N,) bool (non-empty bbox) and ``nonfinite``,
    a 0-d int32 that is 1 when an input holds NaN/Inf (or filter_3d_var < 0) -- the caller names it.
    """

    @staticmethod
    def forward(ctx, means, log_scales, quats, density_raw, fvar, cam, mode: int, mip: bool):  # noqa: ANN001
        dt = means.dtype
        fwd = _fn("proj_fwd", dt)
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
        fwd(
            n, *[_ptr(t) for t in ins], _ptr(fv) if fv is not None else None, _ptr(cam), mode, int(mip), _ptr(m2d),
            _ptr(con), _ptr(amp), _ptr(depth), _ptr(bb), _ptr(radii), _ptr(valid), _ptr(visible), _ptr(nonfinite),
            torch.get_num_threads(),
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
        _fn("proj_bwd", dt)(
            n, _ptr(means), _ptr(ls), _ptr(q), _ptr(d), _ptr(fv) if fv is not None else None, _ptr(ctx.cam),
            ctx.mode, int(ctx.mip), *[_ptr(g) for g in gs], _ptr(gm), _ptr(gl), _ptr(gq), _ptr(gd),
            torch.get_num_threads(),
        )
        return gm, gl, gq, gd, None, None, None, None


class AlphaComposite(torch.autograd.Function):
    """Front-to-back alpha compositing of per-pixel depth-sorted lists (same definition as
    :func:`ctsplat.splat._reference.splat_alpha_reference`): ``C = Σ_i c_i α_i Π_{j<i}(1-α_j)``,
    ``α = min(0.99, o e^q)``.

    Backward per pixel, back to front with the suffix ``S_i = Σ_{j>i} c_j α_j T_j``:
    ``∂C/∂c_i = α_i T_i``, ``∂C/∂α_i = T_i c_i - S_i / (1 - α_i)`` (0 through the clamp), then through ``α = o e^q``
    as in :class:`SplatAdditive`. Per-thread gradient buffers are summed in a fixed order.
    """

    @staticmethod
    def forward(ctx, means2d, conics, opac, colors, bbox, depths, height: int, width: int):  # noqa: ANN001
        dt = opac.dtype
        fwd = _fn("alpha_fwd", dt)
        m, c, o = (t.detach().to(dt).contiguous() for t in (means2d, conics, opac))
        col = colors.detach().to(dt).contiguous()
        if col.shape[1] > 32:  # render() appends one channel (the coverage) when a background is given
            from ctsplat.utils import CtsplatError

            raise CtsplatError(f"the C++ alpha kernel composites at most 32 channels (31 colours with a background), "
                               f"got {col.shape[1]}; render with backend='reference'")
        b = bbox.to(torch.int64).contiguous()
        order = torch.argsort(depths.detach(), stable=True).to(torch.int64).contiguous()
        counts = (b[:, 1] - b[:, 0]) * (b[:, 3] - b[:, 2])
        total = int(counts.sum()) if counts.numel() else 0
        if total >= 2**31:
            from ctsplat.utils import CtsplatError

            raise CtsplatError(f"{total} (Gaussian, pixel) pairs exceed the C++ alpha kernel's 2^31; render at a "
                               "lower resolution or with fewer or smaller Gaussians")
        offsets = torch.empty(height * width + 1, dtype=torch.int64)
        ids = torch.empty(total, dtype=torch.int32)
        _fn("alpha_lists_c")(m.shape[0], _ptr(order), _ptr(b), height, width, _ptr(offsets), _ptr(ids),
                             torch.get_num_threads())
        out = torch.empty(height, width, col.shape[1], dtype=dt)
        alphas = torch.empty(total, dtype=dt)
        fwd(
            height, width, col.shape[1], _ptr(offsets), _ptr(ids), _ptr(m), _ptr(c), _ptr(o), _ptr(col), _ptr(out),
            _ptr(alphas), torch.get_num_threads(),
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
        _fn("alpha_bwd", o.dtype)(
            m.shape[0], height, width, col.shape[1], _ptr(offsets), _ptr(ids), _ptr(alphas), _ptr(m), _ptr(c),
            _ptr(o), _ptr(col), _ptr(g), _ptr(gm), _ptr(gc), _ptr(go), _ptr(gcol), torch.get_num_threads(),
        )
        return gm, gc, go, gcol, None, None, None, None


def voxel_boxes(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor, fvar: torch.Tensor | None,
                ainv: torch.Tensor, shift: torch.Tensor, region: torch.Tensor, cutoff: float
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """Index-space boxes of the Gaussians for :func:`ctsplat.splat.render.voxelize` (no gradients; csrc/voxelize.h).

    Parameters
    ----------
    means, log_scales : Tensor (N, 3)
    quats : Tensor (N, 4)
    fvar : Tensor (N,) or None
        3D filter variance, mm².
    ainv : Tensor (3, 3)
        Inverse of the grid's index-to-world linear part.
    shift : Tensor (3,)
        The grid's index-to-world translation, mm.
    region : Tensor (3, 2) int64
        ``[start, stop)`` per index axis.
    cutoff : float
        Half width in standard deviations.

    Returns
    -------
    lo, ext : Tensor (N, 3) int64
        First index and extent (0 when the Gaussian misses the region) per axis.
    """
    dt = means.dtype
    m, ls, q = (t.detach().to(dt).contiguous() for t in (means, log_scales, quats))
    fv = None if fvar is None else fvar.detach().to(dt).reshape(-1).contiguous()
    aff = torch.cat([ainv.reshape(-1), shift.reshape(-1)]).to(torch.float64).contiguous()
    reg = region.to(torch.int64).reshape(-1).contiguous()
    lo = torch.empty(m.shape[0], 3, dtype=torch.int64)
    ext = torch.empty_like(lo)
    _fn("vox_boxes", dt)(m.shape[0], _ptr(m), _ptr(ls), _ptr(q), None if fv is None else _ptr(fv), _ptr(aff),
                         _ptr(reg), float(cutoff), _ptr(lo), _ptr(ext), torch.get_num_threads())
    return lo, ext


class Voxelize(torch.autograd.Function):
    """``μ`` on a grid: each Gaussian adds ``ρ exp(-½ dᵀ P d)`` over its voxel box (rows along k vectorised);
    hand-written backward (see csrc/voxelize.h). Same inputs as :class:`ctsplat.splat._reference.Voxelize` minus
    chunking: memory is the output grid and O(N) (threads scatter into disjoint slabs of the first index axis,
    no per-thread grids)."""

    @staticmethod
    def forward(ctx, means, prec6, dens, lo, ext, affine, origin, out_shape):  # noqa: ANN001
        dt = means.dtype
        fwd = _fn("vox_fwd", dt)
        m, p, d = (t.detach().to(dt).contiguous() for t in (means, prec6, dens))
        lo_, ext_ = lo.to(torch.int64).contiguous(), ext.to(torch.int64).contiguous()
        aff = torch.cat([affine[:3, :3].reshape(-1), affine[:3, 3]]).to(torch.float64).contiguous()
        org = origin.to(torch.int64).contiguous()
        shp = torch.tensor(out_shape, dtype=torch.int64)
        out = torch.zeros(int(shp.prod()), dtype=dt)
        fwd(
            m.shape[0], _ptr(m), _ptr(p), _ptr(d), _ptr(lo_), _ptr(ext_), _ptr(aff), _ptr(org), _ptr(shp), _ptr(out),
            torch.get_num_threads(),
        )
        ctx.save_for_backward(m, p, d, lo_, ext_, aff, org, shp)
        return out

    @staticmethod
    def backward(ctx, grad_out):  # noqa: ANN001
        m, p, d, lo_, ext_, aff, org, shp = ctx.saved_tensors
        g = grad_out.to(m.dtype).contiguous()
        gm, gp, gd = torch.empty_like(m), torch.empty_like(p), torch.empty_like(d)
        _fn("vox_bwd", m.dtype)(
            m.shape[0], _ptr(m), _ptr(p), _ptr(d), _ptr(lo_), _ptr(ext_), _ptr(aff), _ptr(org), _ptr(shp), _ptr(g),
            _ptr(gm), _ptr(gp), _ptr(gd), torch.get_num_threads(),
        )
        return gm, gp, gd, None, None, None, None, None


def camera_vector(cam: dict, R: torch.Tensor, t: torch.Tensor, k2: float, near: float, cutoff: float) -> torch.Tensor:
    """Pack intrinsics, pose and filter constants into the kernel's camera vector (layout: csrc/project.h ``Cam``).

    Parameters
    ----------
    cam : dict
        From :func:`ctsplat.splat.render.camera_intrinsics`.
    R : Tensor (3, 3)
    t : Tensor (3,)
        World-to-camera pose (mm).
    k2 : float
        2D filter variance added to the footprint, px².
    near : float
        Cone beam: cull Gaussians with ``z_cam`` below this, mm.
    cutoff : float
        Bounding-box half-width in standard deviations.

    Returns
    -------
    Tensor (26,) float64
        On the device of ``R`` (built there: the pose is not read back to the host).
    """
    cone = cam["model"] == "cone"
    if cone:
        lim_x = 1.3 * 0.5 * cam["W"] / cam["fx"] + abs(cam["cx"] - cam["W"] / 2) / cam["fx"]
        lim_y = 1.3 * 0.5 * cam["H"] / cam["fy"] + abs(cam["cy"] - cam["H"] / 2) / cam["fy"]
    else:
        lim_x = lim_y = 0.0
    vals = [1.0 if cone else 0.0, cam.get("sx", 1.0), cam.get("sy", 1.0), cam.get("fx", 1.0), cam.get("fy", 1.0),
            cam["cx"], cam["cy"], cam["W"], cam["H"], lim_x, lim_y]
    dev = R.device
    consts = torch.tensor([*vals, k2, near, cutoff], dtype=torch.float64).to(dev)  # one copy to the device
    pose = [R.detach().reshape(-1).to(torch.float64), t.detach().reshape(-1).to(device=dev, dtype=torch.float64)]
    return torch.cat([consts[: len(vals)], *pose, consts[len(vals) :]])
