"""Pure-PyTorch twins of the fused kernels (:mod:`ctsplat.splat._kernel`): rasterisers and the voxelizer.

Plain autograd, any device (on CUDA the fallback when Triton is not installed). The kernels are tested against
these functions (values and gradients) and these against brute-force references;
:func:`ctsplat.splat.render.project` is the reference projection. Rasterisation enumerates every (Gaussian, pixel)
pair of the bounding boxes with ``repeat_interleave`` and scatters with ``index_add`` (alpha: pairs stably sorted by
pixel, then depth); the voxelizer does the same for (Gaussian, voxel) pairs in chunks of bounded size.

References
----------
.. [1] B. Kerbl, G. Kopanas, T. Leimkühler, G. Drettakis, "3D Gaussian Splatting for Real-Time Radiance Field
   Rendering", ACM Transactions on Graphics 42(4), 2023 (front-to-back alpha compositing).
.. [2] R. Zha, T. J. Lin, Y. Cai, J. Cao, Y. Zhang, H. Li, "R²-Gaussian: Rectifying Radiative Gaussian Splatting
   for Tomographic Reconstruction", NeurIPS 2024 (additive line integrals, voxelizer).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from ctsplat.splat.render import Projection

__all__ = ["splat_additive_reference", "splat_alpha_reference", "voxelize_reference", "Voxelize"]


def _pairs(bbox: torch.Tensor, width: int, order: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(Gaussian index, flat pixel index) for every pixel of every bounding box, Gaussians in ``order``.

    Returns int64 tensors (P,), grouped contiguously per Gaussian.
    """
    bb = bbox if order is None else bbox[order]
    bw = bb[:, 1] - bb[:, 0]
    counts = bw * (bb[:, 3] - bb[:, 2])
    ids = torch.arange(bb.shape[0], device=bb.device)
    gid_local = torch.repeat_interleave(ids, counts)
    if gid_local.numel() == 0:
        empty = torch.zeros(0, dtype=torch.int64, device=bb.device)
        return empty, empty
    starts = torch.cumsum(counts, 0) - counts
    local = torch.arange(gid_local.numel(), device=bb.device) - starts[gid_local]
    bwg = bw[gid_local]
    pu = bb[gid_local, 0] + local % bwg
    pv = bb[gid_local, 2] + local // bwg
    gid = gid_local if order is None else order[gid_local]
    return gid, pv * width + pu


def _pair_power(proj: Projection, gid: torch.Tensor, pix: torch.Tensor, width: int) -> torch.Tensor:
    """``-½ dᵀ Σ̂'⁻¹ d`` per pair (differentiable w.r.t. means2d and conics)."""
    pu = (pix % width).to(proj.means2d.dtype) + 0.5
    pv = torch.div(pix, width, rounding_mode="floor").to(proj.means2d.dtype) + 0.5
    m = proj.means2d[gid]
    con = proj.conics[gid]
    dx = pu - m[:, 0]
    dy = pv - m[:, 1]
    return -0.5 * (con[:, 0] * dx * dx + con[:, 2] * dy * dy) - con[:, 1] * dx * dy


def splat_additive_reference(proj: Projection, height: int, width: int) -> torch.Tensor:
    """Additive rasteriser: ``img[p] = Σ_i amp_i exp(-½ dᵀ Σ̂_i'⁻¹ d)`` over each Gaussian's bounding box.

    Parameters
    ----------
    proj : Projection
        From :func:`ctsplat.splat.render.project` (means2d px, conics px⁻², amps, bbox).
    height, width : int
        Image size in pixels.

    Returns
    -------
    Tensor (H, W)
        Radiative modes: line integrals in density units × mm (times ``mu_scale`` in :func:`render`).
    """
    gid, pix = _pairs(proj.bbox, width)
    val = proj.amps[gid] * torch.exp(_pair_power(proj, gid, pix, width))
    img = torch.zeros(height * width, dtype=proj.amps.dtype, device=proj.amps.device)
    img = img.index_add(0, pix, val)
    return img.reshape(height, width)


def splat_alpha_reference(proj: Projection, colors: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Front-to-back alpha compositing (pure PyTorch autograd), vectorised over (Gaussian, pixel) pairs.

    ``C(p) = Σ_i c_i α_i Π_{j<i} (1 - α_j)`` with ``α_i = min(0.99, amp_i exp(-½ dᵀ Σ̂_i'⁻¹ d))``, Gaussians in
    increasing depth. Pairs are generated in increasing depth, then stably sorted by pixel, so each pixel's run lists
    its Gaussians front to back; ``T = exp(exclusive segment cumsum of log(1 - α))`` (float64 cumsum for accuracy).

    Parameters
    ----------
    proj : Projection
        From :func:`ctsplat.splat.render.project` with the alpha compositor (amps = opacities).
    colors : Tensor (N, C)
        Colour per Gaussian for this view.
    height, width : int
        Image size in pixels.

    Returns
    -------
    Tensor (H, W, C)
    """
    order = torch.argsort(proj.depths.detach(), stable=True)
    gid, pix = _pairs(proj.bbox, width, order)
    c = colors.shape[1]
    out = torch.zeros(height * width, c, dtype=colors.dtype, device=colors.device)
    if gid.numel() == 0:
        # no Gaussian touches a pixel: zero image, still connected to the parameters (zero gradients, as the
        # fused kernels give), so that a training step's backward does not fail
        keep = proj.valid  # culled Gaussians' projections need not be finite
        linked = proj.amps.sum() + colors.sum() + proj.means2d[keep].sum() + proj.conics[keep].sum()
        return (out + 0.0 * linked).reshape(height, width, c)
    srt = torch.sort(pix, stable=True)
    pix = srt.values
    gid = gid[srt.indices]
    alpha = torch.clamp(proj.amps[gid] * torch.exp(_pair_power(proj, gid, pix, width)), max=0.99)
    log1m = torch.log1p(-alpha).double()
    csum = torch.cumsum(log1m, 0)
    excl = csum - log1m
    # subtract the cumulative sum before each pixel's run
    new_seg = torch.ones_like(pix, dtype=torch.bool)
    new_seg[1:] = pix[1:] != pix[:-1]
    seg_id = torch.cumsum(new_seg.to(torch.int64), 0) - 1
    seg_base = excl[new_seg]
    trans = torch.exp(excl - seg_base[seg_id]).to(alpha.dtype)
    w = trans * alpha
    out = out.index_add(0, pix, w[:, None] * colors[gid])
    return out.reshape(height, width, c)


def _voxel_pairs(
    lo: torch.Tensor, ext: torch.Tensor, affine: torch.Tensor, origin: torch.Tensor, out_shape: tuple[int, int, int],
    dtype: torch.dtype,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(local Gaussian index, voxel centre in mm, flat output index) for every voxel of every box in a chunk."""
    counts = ext.prod(-1)
    ids = torch.arange(lo.shape[0], device=lo.device)
    g = torch.repeat_interleave(ids, counts)
    starts = torch.cumsum(counts, 0) - counts
    local = torch.arange(g.numel(), device=lo.device) - starts[g]
    e = ext[g]
    k = local % e[:, 2]
    rest = local // e[:, 2]
    idx = lo[g] + torch.stack([rest // e[:, 1], rest % e[:, 1], k], -1)  # absolute voxel indices
    pos = idx.to(dtype) @ affine[:3, :3].T + affine[:3, 3]
    rel = idx - origin
    flat = (rel[:, 0] * out_shape[1] + rel[:, 1]) * out_shape[2] + rel[:, 2]
    return g, pos, flat


def _voxel_values(means: torch.Tensor, prec6: torch.Tensor, dens: torch.Tensor, g: torch.Tensor,
                  pos: torch.Tensor) -> torch.Tensor:
    """``ρ exp(-½ dᵀ P d)`` per pair; ``prec6`` = (P00, P11, P22, P01, P02, P12) per Gaussian."""
    d = pos - means[g]
    p = prec6[g]
    q = (p[:, 0] * d[:, 0] ** 2 + p[:, 1] * d[:, 1] ** 2 + p[:, 2] * d[:, 2] ** 2
         + 2 * (p[:, 3] * d[:, 0] * d[:, 1] + p[:, 4] * d[:, 0] * d[:, 2] + p[:, 5] * d[:, 1] * d[:, 2]))
    return dens[g] * torch.exp(-0.5 * q)


class Voxelize(torch.autograd.Function):
    """Chunked scatter of Gaussian values into a grid; the backward recomputes each chunk (memory-bounded)."""

    @staticmethod
    def forward(ctx, means, prec6, dens, lo, ext, bounds, affine, origin, out_shape):  # noqa: ANN001
        out = torch.zeros(out_shape[0] * out_shape[1] * out_shape[2], dtype=means.dtype, device=means.device)
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            g, pos, flat = _voxel_pairs(lo[a:b], ext[a:b], affine, origin, out_shape, means.dtype)
            out.index_add_(0, flat, _voxel_values(means[a:b], prec6[a:b], dens[a:b], g, pos))
        ctx.save_for_backward(means, prec6, dens, lo, ext, affine, origin)
        ctx.bounds, ctx.out_shape = bounds, out_shape
        return out

    @staticmethod
    def backward(ctx, grad_out):  # noqa: ANN001
        means, prec6, dens, lo, ext, affine, origin = ctx.saved_tensors
        grads = [torch.zeros_like(means), torch.zeros_like(prec6), torch.zeros_like(dens)]
        for a, b in zip(ctx.bounds[:-1], ctx.bounds[1:], strict=True):
            g, pos, flat = _voxel_pairs(lo[a:b], ext[a:b], affine, origin, ctx.out_shape, means.dtype)
            with torch.enable_grad():
                chunk = [t[a:b].detach().requires_grad_(True) for t in (means, prec6, dens)]
                vals = _voxel_values(*chunk, g, pos)
                gc = torch.autograd.grad(vals, chunk, grad_out[flat])
            for acc, part in zip(grads, gc, strict=True):
                acc[a:b] = part
        return (*grads, None, None, None, None, None, None)


def chunk_bounds(counts: torch.Tensor, chunk: int) -> list[int]:
    """Greedy split of consecutive Gaussians into chunks of at most ``chunk`` (Gaussian, voxel) pairs.

    Parameters
    ----------
    counts : Tensor (N,) int64
        Pairs per Gaussian (> 0).
    chunk : int
        Pair budget; a Gaussian with more pairs forms its own chunk.

    Returns
    -------
    list of int
        Boundaries ``[0, b_1, ..., N]``: chunk ``k`` is Gaussians ``b_k .. b_{k+1} - 1``.
    """
    cum_cpu = torch.cumsum(counts, 0).cpu()
    n = int(counts.numel())
    bounds = [0]
    base = 0
    while bounds[-1] < n:
        nxt = int(torch.searchsorted(cum_cpu, torch.tensor(base + chunk), right=True))
        nxt = max(nxt, bounds[-1] + 1)
        bounds.append(min(nxt, n))
        base = int(cum_cpu[bounds[-1] - 1])
    return bounds


def voxelize_reference(
    means: torch.Tensor, prec6: torch.Tensor, dens: torch.Tensor, lo: torch.Tensor, ext: torch.Tensor,
    affine: torch.Tensor, origin: torch.Tensor, out_shape: tuple[int, int, int], chunk: int,
) -> torch.Tensor:
    """``μ`` on a grid from per-Gaussian voxel boxes, chunked (peak memory: output grid + one chunk of pairs).

    Parameters
    ----------
    means : Tensor (N, 3)
        Centres, world mm.
    prec6 : Tensor (N, 6)
        Precision matrix ``Σ⁻¹`` entries ``(P00, P11, P22, P01, P02, P12)``, mm⁻².
    dens : Tensor (N,)
        Peak densities ρ (after any 3D-filter factor).
    lo, ext : Tensor (N, 3) int64
        First voxel index and extent of each Gaussian's box (non-empty).
    affine : Tensor (4, 4)
        Voxel index -> world mm.
    origin : Tensor (3,) int64
        Voxel index of the output's first voxel.
    out_shape : (I, J, K)
        Output size in voxels.
    chunk : int
        Pair budget per chunk (see :func:`chunk_bounds`).

    Returns
    -------
    Tensor (I·J·K,)
        Flat values in density units, C order.
    """
    bounds = chunk_bounds(ext.prod(-1), chunk)
    return Voxelize.apply(means, prec6, dens, lo, ext, bounds, affine, origin, out_shape)
