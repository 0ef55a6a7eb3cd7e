"""The GPU path: Triton projection, rasterisers and voxelizer as autograd functions (math of the C++ kernels).

Four ``torch.autograd.Function`` s with the inputs of their twins in :mod:`ctsplat.splat._kernel`, so that
:func:`ctsplat.splat.render.render` swaps them in behind ``backend="triton"`` (and ``"auto"`` on CUDA):

* :class:`Project` -- the EWA projection (means, conics, amplitudes, depths, pixel boxes) with its hand-written
  backward, one kernel each way (as PyTorch ops it is some 570 small operations per view, forward and backward,
  each a kernel launch on a GPU);
* :class:`SplatAdditive` -- ``img[p] = Σ_i a_i exp(q_i(p))`` over each Gaussian's bounding box (radiative modes);
* :class:`AlphaComposite` -- front-to-back ``C = Σ_i c_i α_i T_i``, ``α = min(0.99, o e^q)``, in depth order;
* :class:`Voxelize` -- ``μ`` on a voxel grid from per-Gaussian voxel boxes.

Work lists are built with torch ops: each Gaussian's box covers a range of ``TILE × TILE`` pixel tiles (voxelizer:
``BRICK³`` voxel bricks); the (tile, Gaussian) pairs are stably sorted by tile (alpha: the Gaussians are put in
depth order first, so each tile's list is front to back) and a prefix sum gives each tile's slice. The kernels
(:mod:`ctsplat.splat._triton_kernels`) run one program per tile / brick; backward passes write one gradient row
per pair, summed per Gaussian here with ``index_add`` (no atomics in the kernels).

Triton is optional (the ``gpu`` extra). The kernels run on CUDA tensors, or on CPU tensors through Triton's
interpreter when ``TRITON_INTERPRET=1`` was set before the kernels were first imported (slow: tests only).
"""

from __future__ import annotations

import importlib.util
import os
from types import ModuleType
from typing import Any

import torch

__all__ = ["unavailable_reason", "kernels", "tile_lists", "Project", "SplatAdditive", "AlphaComposite", "Voxelize",
           "TILE", "BRICK"]

TILE = 16  # pixels per tile side
BRICK = 8  # voxels per brick side
# Gaussians per [G, pixels] block: on a GPU 8 x 256 px over 8 warps keeps each thread at one pixel column of 8
# values per live tensor (register-resident); the interpreter pays per operation, not per element, so it takes
# bigger blocks (the kernels are the same code for any G; the CUDA tests run G = 8)
G_GPU, G_INTERPRETER = 8, 32
WARPS = 8


def g_raster() -> int:
    """Gaussians per rasteriser block (see ``G_GPU``)."""
    return G_INTERPRETER if kernels().INTERPRETED else G_GPU


def g_voxel() -> int:
    """Gaussians per ``[G, BRICK³]`` voxelizer block."""
    return G_INTERPRETER if kernels().INTERPRETED else G_GPU


INSTALL_HINT = "install the GPU extra: pip install 'ctsplat[gpu]' (or pip install 'triton>=3.2')"

_kernels: ModuleType | None = None


def unavailable_reason(device: torch.device) -> str | None:
    """Why the Triton kernels cannot run on ``device`` (None when they can).

    Parameters
    ----------
    device : torch.device
        Device of the tensors to render.

    Returns
    -------
    str or None
        A sentence saying what is missing and how to fix it.
    """
    if importlib.util.find_spec("triton") is None:
        return f"triton is not installed; {INSTALL_HINT}"
    if device.type == "cuda":
        major, minor = torch.cuda.get_device_capability(device)
        if major < 7:  # Triton compiles for Volta (7.0) and newer
            return f"the GPU's compute capability {major}.{minor} is below Triton's minimum 7.0"
        return None
    if device.type == "cpu":
        interpreted = _kernels.INTERPRETED if _kernels is not None else os.environ.get("TRITON_INTERPRET") == "1"
        if interpreted:
            return None
        return ("the triton backend runs on CUDA tensors; on CPU tensors it needs Triton's interpreter: set "
                "TRITON_INTERPRET=1 in the environment before starting Python (slow, for tests), or use "
                "backend='kernel'/'auto' on CPU")
    return f"the triton backend does not run on {device.type} tensors; use backend='reference'"


def kernels() -> ModuleType:
    """The kernel module, imported on first use (this imports triton)."""
    global _kernels
    if _kernels is None:
        from ctsplat.splat import _triton_kernels

        _kernels = _triton_kernels
    return _kernels


def _launch_ctx(t: torch.Tensor) -> Any:
    return torch.cuda.device(t.device) if t.device.type == "cuda" else _Null()


class _Null:
    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc: object) -> None:
        return None


def _ranges_to_pairs(
    first: list[torch.Tensor], count: list[torch.Tensor], n_cells: list[int], order: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(cell, item) pairs for items covering boxes of cells; stably sorted by cell (flat, C order over the axes).

    ``first[a]`` / ``count[a]`` are each item's first cell and cell count along axis ``a`` (count 0: no pairs).
    Items are enumerated in ``order`` (default 0..N-1), so each cell's slice keeps that order. Returns the item ids
    (int32), the cell offsets (n_cells + 1, int32) and the item index of each pair (int64).
    """
    dev = first[0].device
    counts = count[0]
    for c in count[1:]:
        counts = counts * c
    n = counts.shape[0]
    idx = torch.repeat_interleave(torch.arange(n, device=dev), counts)
    if idx.numel() >= 2**31:  # the kernels index pairs and offsets in int32 (its size is on the host already)
        from ctsplat.utils import CtsplatError

        raise CtsplatError(f"{idx.numel()} (cell, Gaussian) pairs exceed the Triton kernels' 2^31; render at a lower "
                           "resolution or with fewer or smaller Gaussians")
    starts = torch.cumsum(counts, 0) - counts
    local = torch.arange(idx.numel(), device=dev) - starts[idx]
    cell = torch.zeros_like(local)
    stride = 1
    for a in reversed(range(len(first))):
        ca = count[a][idx]
        cell = cell + (first[a][idx] + local % ca) * stride
        local = local // ca
        stride *= n_cells[a]
    cell, perm = torch.sort(cell, stable=True)
    item = idx[perm] if order is None else order[idx[perm]]
    total = 1
    for c in n_cells:
        total *= c
    offsets = torch.searchsorted(cell, torch.arange(total + 1, device=dev, dtype=cell.dtype)).to(torch.int32)
    return item.to(torch.int32).contiguous(), offsets.contiguous(), item


def tile_lists(bbox: torch.Tensor, height: int, width: int,
               depths: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, int]:
    """Per-tile Gaussian lists from pixel bounding boxes ``(u0, u1, v0, v1)`` (half-open).

    Parameters
    ----------
    bbox : Tensor (N, 4) int
    height, width : int
        Image size, px.
    depths : Tensor (N,) or None
        Alpha compositing: each tile's list in increasing depth (stable).

    Returns
    -------
    ids : Tensor (P,) int32
        Gaussian of each (tile, Gaussian) pair, grouped by tile.
    offsets : Tensor (tiles + 1,) int32
        Tile ``t``'s pairs are ``ids[offsets[t]:offsets[t + 1]]``.
    item : Tensor (P,) int64
        ``ids`` as int64 (for ``index_add``).
    tiles_x : int
        Tiles per image row.
    """
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    order = None if depths is None else torch.argsort(depths.detach(), stable=True)
    bb = bbox.to(torch.int64) if order is None else bbox.to(torch.int64)[order]
    nonempty = (bb[:, 1] > bb[:, 0]) & (bb[:, 3] > bb[:, 2])
    tx0, ty0 = bb[:, 0] // TILE, bb[:, 2] // TILE
    nx = torch.where(nonempty, (bb[:, 1] + TILE - 1) // TILE - tx0, 0)
    ny = torch.where(nonempty, (bb[:, 3] + TILE - 1) // TILE - ty0, 0)
    ids, offsets, item = _ranges_to_pairs([ty0, tx0], [ny, nx], [tiles_y, tiles_x], order)
    return ids, offsets, item, tiles_x


def _params(means2d: torch.Tensor, conics: torch.Tensor, amps: torch.Tensor, dt: torch.dtype) -> torch.Tensor:
    return torch.cat([means2d.detach().to(dt), conics.detach().to(dt), amps.detach().to(dt)[:, None]], 1).contiguous()


def _split_grads(rows: torch.Tensor, item: torch.Tensor, n: int) -> torch.Tensor:
    out = torch.zeros(n, rows.shape[1], dtype=rows.dtype, device=rows.device)
    return out.index_add_(0, item, rows)


PROJECT_BLOCK = 128  # Gaussians per projection program


class Project(torch.autograd.Function):
    """Fused projection (inputs and outputs as :class:`ctsplat.splat._kernel.Project`; ``cam`` the float64 camera
    vector on the Gaussians' device, its model read from ``cone``): one program per ``PROJECT_BLOCK`` Gaussians,
    forward and hand-written backward (the chain of ``csrc/project.h``). ``nonfinite`` is a 0-d int32 tensor on the
    device (1 when an input holds NaN/Inf or filter_3d_var < 0)."""

    @staticmethod
    def forward(ctx, means, log_scales, quats, density_raw, fvar, cam, mode: int, mip: bool, cone: bool):  # noqa: ANN001
        k = kernels()
        dt = means.dtype
        dev = means.device
        ins = [t.detach().to(dt).contiguous() for t in (means, log_scales, quats, density_raw)]
        fv = None if fvar is None else fvar.detach().to(dt).reshape(-1).contiguous()
        cam = cam.to(device=dev, dtype=torch.float64).contiguous()
        n = ins[0].shape[0]
        m2d = torch.empty(n, 2, dtype=dt, device=dev)
        con = torch.empty(n, 3, dtype=dt, device=dev)
        amp = torch.empty(n, dtype=dt, device=dev)
        depth = torch.empty(n, dtype=dt, device=dev)
        bb = torch.empty(n, 4, dtype=torch.int64, device=dev)
        radii = torch.empty(n, dtype=torch.int32, device=dev)
        flags = torch.empty(3, n, dtype=torch.int8, device=dev)  # valid, visible, bad
        grid = (max(1, -(-n // PROJECT_BLOCK)),)
        with _launch_ctx(m2d):
            k.project_fwd[grid](cam, *ins, fv if fv is not None else ins[3], m2d, con, amp, depth, bb, radii, flags[0],
                                flags[1], flags[2], n, MODE=int(mode), MIP=bool(mip), HAS_F=fv is not None,
                                CONE=bool(cone), BLOCK=PROJECT_BLOCK)
        valid, visible, bad = flags.view(torch.bool).unbind(0)
        nonfinite = bad.any().to(torch.int32)
        ctx.save_for_backward(*ins, cam, *([fv] if fv is not None else []))
        ctx.flags = (int(mode), bool(mip), fv is not None, bool(cone))
        ctx.mark_non_differentiable(depth, bb, radii, valid, visible, nonfinite)
        ctx.set_materialize_grads(False)
        return m2d, con, amp, depth, bb, radii, valid, visible, nonfinite

    @staticmethod
    def backward(ctx, g_m2d, g_con, g_amp, *_no_grad):  # noqa: ANN001
        saved = ctx.saved_tensors
        means, ls, q, d, cam = saved[:5]
        mode, mip, has_f, cone = ctx.flags
        fv = saved[5] if has_f else None
        dt, n = means.dtype, means.shape[0]
        gs = [g.to(dt).contiguous() if g is not None else torch.zeros((n, c) if c else (n,), dtype=dt,
                                                                      device=means.device)
              for g, c in zip((g_m2d, g_con, g_amp), (2, 3, 0), strict=True)]
        gm, gl, gq, gd = torch.empty_like(means), torch.empty_like(ls), torch.empty_like(q), torch.empty_like(d)
        with _launch_ctx(means):
            kernels().project_bwd[(max(1, -(-n // PROJECT_BLOCK)),)](
                cam, means, ls, q, d, fv if fv is not None else d, *gs, gm, gl, gq, gd, n, MODE=mode, MIP=mip,
                HAS_F=has_f, CONE=cone, BLOCK=PROJECT_BLOCK)
        return gm, gl, gq, gd, None, None, None, None, None


class SplatAdditive(torch.autograd.Function):
    """Additive tile rasteriser (inputs and outputs as :class:`ctsplat.splat._kernel.SplatAdditive`)."""

    @staticmethod
    def forward(ctx, means2d, conics, amps, bbox, height: int, width: int):  # noqa: ANN001
        k = kernels()
        dt = amps.dtype
        par = _params(means2d, conics, amps, dt)
        bb = bbox.to(torch.int32).contiguous()
        ids, offsets, item, tiles_x = tile_lists(bbox, height, width)
        out = torch.zeros(height, width, dtype=dt, device=amps.device)
        n_tiles = offsets.numel() - 1
        with _launch_ctx(out):
            k.additive_fwd[(n_tiles,)](par, bb, offsets, ids, out, height, width, tiles_x, TILE=TILE, G=g_raster(),
                                       num_warps=WARPS)
        ctx.save_for_backward(par, bb, ids, offsets, item)
        ctx.geom = (height, width, tiles_x)
        return out

    @staticmethod
    def backward(ctx, grad_img):  # noqa: ANN001
        par, bb, ids, offsets, item = ctx.saved_tensors
        height, width, tiles_x = ctx.geom
        g = grad_img.to(par.dtype).contiguous()
        rows = torch.empty(ids.numel(), 6, dtype=par.dtype, device=par.device)
        with _launch_ctx(par):
            kernels().additive_bwd[(offsets.numel() - 1,)](par, bb, offsets, ids, g, rows, height, width, tiles_x,
                                                           TILE=TILE, G=g_raster(), num_warps=WARPS)
        grads = _split_grads(rows, item, par.shape[0])
        return grads[:, 0:2], grads[:, 2:5], grads[:, 5], None, None, None


class AlphaComposite(torch.autograd.Function):
    """Front-to-back alpha tile compositor (inputs and outputs as :class:`ctsplat.splat._kernel.AlphaComposite`)."""

    @staticmethod
    def forward(ctx, means2d, conics, opac, colors, bbox, depths, height: int, width: int):  # noqa: ANN001
        k = kernels()
        dt = opac.dtype
        par = _params(means2d, conics, opac, dt)
        col = colors.detach().to(dt).contiguous()
        nc = col.shape[1]
        cp = 1 << max(0, (nc - 1).bit_length())
        bb = bbox.to(torch.int32).contiguous()
        ids, offsets, item, tiles_x = tile_lists(bbox, height, width, depths)
        out = torch.zeros(height, width, nc, dtype=dt, device=opac.device)
        logt = torch.zeros(height, width, dtype=dt, device=opac.device)
        with _launch_ctx(out):
            k.alpha_fwd[(offsets.numel() - 1,)](par, bb, offsets, ids, col, out, logt, height, width, tiles_x, nc,
                                                TILE=TILE, G=g_raster(), CP=cp, num_warps=WARPS)
        ctx.save_for_backward(par, bb, ids, offsets, item, col, logt)
        ctx.geom = (height, width, tiles_x, cp)
        return out

    @staticmethod
    def backward(ctx, grad_out):  # noqa: ANN001
        par, bb, ids, offsets, item, col, logt = ctx.saved_tensors
        height, width, tiles_x, cp = ctx.geom
        nc = col.shape[1]
        g = grad_out.to(par.dtype).contiguous()
        rows = torch.empty(ids.numel(), 6 + nc, dtype=par.dtype, device=par.device)
        with _launch_ctx(par):
            kernels().alpha_bwd[(offsets.numel() - 1,)](par, bb, offsets, ids, col, logt, g, rows, height, width,
                                                        tiles_x, nc, TILE=TILE, G=g_raster(), CP=cp, num_warps=WARPS)
        grads = _split_grads(rows, item, par.shape[0])
        return grads[:, 0:2], grads[:, 2:5], grads[:, 5], grads[:, 6:], None, None, None, None


class Voxelize(torch.autograd.Function):
    """Voxelizer (inputs and outputs as :class:`ctsplat.splat._kernel.Voxelize`): one program per ``BRICK³`` brick
    of the output over the brick's Gaussian list; the backward writes a gradient row per (brick, Gaussian) pair."""

    @staticmethod
    def forward(ctx, means, prec6, dens, lo, ext, affine, origin, out_shape):  # noqa: ANN001
        k = kernels()
        dt = means.dtype
        m, p, d = (t.detach().to(dt).contiguous() for t in (means, prec6, dens))
        lo_ = lo.to(torch.int64).contiguous()
        hi_ = (lo_ + ext.to(torch.int64)).contiguous()
        aff = torch.cat([affine[:3, :3].reshape(-1), affine[:3, 3]]).to(dt).contiguous()
        org = origin.to(device=m.device, dtype=torch.int64).contiguous()
        n0, n1, n2 = (int(s) for s in out_shape)
        nb = [-(-s // BRICK) for s in (n0, n1, n2)]
        rel = lo_ - org
        first = [rel[:, a] // BRICK for a in range(3)]
        count = [torch.where(ext[:, a] > 0, (rel[:, a] + ext[:, a] - 1) // BRICK + 1 - first[a], 0) for a in range(3)]
        ids, offsets, item = _ranges_to_pairs(first, count, nb, None)
        out = torch.zeros(n0 * n1 * n2, dtype=dt, device=m.device)
        geom = (n0, n1, n2, nb[1], nb[2])
        with _launch_ctx(out):
            k.voxel_fwd[(offsets.numel() - 1,)](m, p, d, lo_, hi_, aff, offsets, ids, out, org, *geom, B=BRICK,
                                                G=g_voxel(), num_warps=WARPS)
        ctx.save_for_backward(m, p, d, lo_, hi_, aff, ids, offsets, item, org)
        ctx.geom = geom
        return out

    @staticmethod
    def backward(ctx, grad_out):  # noqa: ANN001
        m, p, d, lo_, hi_, aff, ids, offsets, item, org = ctx.saved_tensors
        g = grad_out.to(m.dtype).contiguous()
        rows = torch.empty(ids.numel(), 10, dtype=m.dtype, device=m.device)
        with _launch_ctx(m):
            kernels().voxel_bwd[(offsets.numel() - 1,)](m, p, d, lo_, hi_, aff, offsets, ids, g, rows, org,
                                                        *ctx.geom, B=BRICK, G=g_voxel(), num_warps=WARPS)
        grads = _split_grads(rows, item, m.shape[0])
        return grads[:, 0:3], grads[:, 3:9], grads[:, 9], None, None, None, None, None
