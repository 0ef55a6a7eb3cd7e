"""Triton kernels of the GPU path: tile rasterisers (additive and alpha, forward and backward) and the voxelizer.

Imported only by :mod:`ctsplat.splat._triton` (lazily: importing this module imports ``triton`` and decorates the
kernels; with ``TRITON_INTERPRET=1`` in the environment at that moment they run on CPU tensors through Triton's
interpreter, which is how CI tests them). The math is that of :mod:`ctsplat.splat._reference`; the wrappers and the
per-tile lists are in :mod:`ctsplat.splat._triton`.

Rasterisers: one program per ``TILE × TILE`` pixel tile, looping over the tile's list of Gaussians ``G`` at a time as
a ``[G, TILE²]`` block (pixels outside a Gaussian's bounding box get nothing, exactly like the reference's box
cut-off). Backward passes write one row of gradients per (tile, Gaussian) pair; the wrapper sums the rows per
Gaussian, so there are no atomics. Alpha compositing keeps the transmittance in log space (``log T = Σ log(1 - α)``)
so it never underflows, and its backward walks each tile's depth-sorted list back to front with the suffix sums
``S_i = Σ_{j>i} c_j α_j T_j`` of the 3DGS backward.

Voxelizer: one program per ``8³`` brick of the output, gathering over the brick's Gaussian list (forward), or
writing one gradient row per (brick, Gaussian) pair (backward), as the rasterisers do with tiles.
"""

from __future__ import annotations

import triton
import triton.language as tl

ALPHA_MAX = tl.constexpr(0.99)  # opacity cap (3DGS); a constexpr so that compiled kernels may read it


@triton.jit
def _log1m(al):
    """``log(1 - α)``, accurate for small α (a series below 1e-3, where ``1 - α`` loses digits in float32)."""
    small = al < 1e-3
    series = -al * (1.0 + al * (0.5 + al * (1.0 / 3.0)))
    return tl.where(small, series, tl.log(tl.where(small, 0.5, 1.0 - al)))


@triton.jit
def _tile_pixels(tile, tiles_x, TILE: tl.constexpr):
    p = tl.arange(0, TILE * TILE)
    px = (tile % tiles_x) * TILE + p % TILE
    py = (tile // tiles_x) * TILE + p // TILE
    return px, py


@triton.jit
def _gauss_block(params_ptr, bbox_ptr, ids_ptr, kk, km, px, py, fx, fy):
    """Load ``G`` Gaussians (ids at list positions ``kk``) and evaluate ``q`` and the box mask on the pixel block."""
    gid = tl.load(ids_ptr + kk, mask=km, other=0).to(tl.int64)
    mx = tl.load(params_ptr + gid * 6 + 0, mask=km, other=0.0)
    my = tl.load(params_ptr + gid * 6 + 1, mask=km, other=0.0)
    ca = tl.load(params_ptr + gid * 6 + 2, mask=km, other=0.0)
    cb = tl.load(params_ptr + gid * 6 + 3, mask=km, other=0.0)
    cc = tl.load(params_ptr + gid * 6 + 4, mask=km, other=0.0)
    amp = tl.load(params_ptr + gid * 6 + 5, mask=km, other=0.0)
    u0 = tl.load(bbox_ptr + gid * 4 + 0, mask=km, other=0)
    u1 = tl.load(bbox_ptr + gid * 4 + 1, mask=km, other=0)
    v0 = tl.load(bbox_ptr + gid * 4 + 2, mask=km, other=0)
    v1 = tl.load(bbox_ptr + gid * 4 + 3, mask=km, other=0)
    dx = fx[None, :] - mx[:, None]
    dy = fy[None, :] - my[:, None]
    q = -0.5 * (ca[:, None] * dx * dx + cc[:, None] * dy * dy) - cb[:, None] * dx * dy
    inb = (px[None, :] >= u0[:, None]) & (px[None, :] < u1[:, None]) & (py[None, :] >= v0[:, None]) & (
        py[None, :] < v1[:, None])
    return gid, ca, cb, cc, amp, dx, dy, q, inb


@triton.jit
def additive_fwd(params_ptr, bbox_ptr, offsets_ptr, ids_ptr, out_ptr, H, W, tiles_x,
                 TILE: tl.constexpr, G: tl.constexpr):
    """``img[p] = Σ_i a_i exp(q_i(p))`` over the tile's Gaussians whose box holds ``p``."""
    tile = tl.program_id(0)
    px, py = _tile_pixels(tile, tiles_x, TILE)
    dt = out_ptr.dtype.element_ty
    fx = px.to(dt) + 0.5
    fy = py.to(dt) + 0.5
    start = tl.load(offsets_ptr + tile)
    end = tl.load(offsets_ptr + tile + 1)
    acc = tl.zeros([TILE * TILE], dtype=dt)
    for k0 in range(start, end, G):
        kk = k0 + tl.arange(0, G)
        km = kk < end
        gid, ca, cb, cc, amp, dx, dy, q, inb = _gauss_block(params_ptr, bbox_ptr, ids_ptr, kk, km, px, py, fx, fy)
        acc += tl.sum(tl.where(inb, amp[:, None] * tl.exp(q), 0.0), axis=0)
    tl.store(out_ptr + py * W + px, acc, mask=(px < W) & (py < H))


@triton.jit
def additive_bwd(params_ptr, bbox_ptr, offsets_ptr, ids_ptr, grad_ptr, pair_ptr, H, W, tiles_x,
                 TILE: tl.constexpr, G: tl.constexpr):
    """Per (tile, Gaussian) pair: ``∂L/∂(m_x, m_y, A, B, C, a)`` summed over the tile's pixels."""
    tile = tl.program_id(0)
    px, py = _tile_pixels(tile, tiles_x, TILE)
    dt = grad_ptr.dtype.element_ty
    fx = px.to(dt) + 0.5
    fy = py.to(dt) + 0.5
    g = tl.load(grad_ptr + py * W + px, mask=(px < W) & (py < H), other=0.0)
    start = tl.load(offsets_ptr + tile)
    end = tl.load(offsets_ptr + tile + 1)
    for k0 in range(start, end, G):
        kk = k0 + tl.arange(0, G)
        km = kk < end
        gid, ca, cb, cc, amp, dx, dy, q, inb = _gauss_block(params_ptr, bbox_ptr, ids_ptr, kk, km, px, py, fx, fy)
        ge = tl.where(inb, g[None, :] * tl.exp(q), 0.0)
        row = pair_ptr + kk.to(tl.int64) * 6
        tl.store(row + 0, amp * tl.sum(ge * (ca[:, None] * dx + cb[:, None] * dy), axis=1), mask=km)
        tl.store(row + 1, amp * tl.sum(ge * (cb[:, None] * dx + cc[:, None] * dy), axis=1), mask=km)
        tl.store(row + 2, -0.5 * amp * tl.sum(ge * dx * dx, axis=1), mask=km)
        tl.store(row + 3, -amp * tl.sum(ge * dx * dy, axis=1), mask=km)
        tl.store(row + 4, -0.5 * amp * tl.sum(ge * dy * dy, axis=1), mask=km)
        tl.store(row + 5, tl.sum(ge, axis=1), mask=km)


@triton.jit
def alpha_fwd(params_ptr, bbox_ptr, offsets_ptr, ids_ptr, col_ptr, out_ptr, logt_ptr, H, W, tiles_x, NC,
              TILE: tl.constexpr, G: tl.constexpr, CP: tl.constexpr):
    """Front-to-back ``C = Σ_i c_i α_i T_i`` over the tile's depth-sorted list; also stores ``log T`` after the last."""
    tile = tl.program_id(0)
    px, py = _tile_pixels(tile, tiles_x, TILE)
    dt = out_ptr.dtype.element_ty
    fx = px.to(dt) + 0.5
    fy = py.to(dt) + 0.5
    ch = tl.arange(0, CP)
    start = tl.load(offsets_ptr + tile)
    end = tl.load(offsets_ptr + tile + 1)
    acc = tl.zeros([TILE * TILE, CP], dtype=dt)
    logt = tl.zeros([TILE * TILE], dtype=dt)
    for k0 in range(start, end, G):
        kk = k0 + tl.arange(0, G)
        km = kk < end
        gid, ca, cb, cc, opac, dx, dy, q, inb = _gauss_block(params_ptr, bbox_ptr, ids_ptr, kk, km, px, py, fx, fy)
        al = tl.where(inb, tl.minimum(opac[:, None] * tl.exp(q), ALPHA_MAX), 0.0)
        la = _log1m(al)
        trans = tl.exp(logt[None, :] + tl.cumsum(la, axis=0) - la)
        w = al * trans
        col = tl.load(col_ptr + gid[:, None] * NC + ch[None, :], mask=km[:, None] & (ch[None, :] < NC), other=0.0)
        acc += tl.sum(w[:, :, None] * col[:, None, :], axis=0)
        logt += tl.sum(la, axis=0)
    inside = (px < W) & (py < H)
    pix = (py * W + px).to(tl.int64)
    tl.store(out_ptr + pix[:, None] * NC + ch[None, :], acc, mask=inside[:, None] & (ch[None, :] < NC))
    tl.store(logt_ptr + pix, logt, mask=inside)


@triton.jit
def alpha_bwd(params_ptr, bbox_ptr, offsets_ptr, ids_ptr, col_ptr, logt_ptr, grad_ptr, pair_ptr, H, W, tiles_x, NC,
              TILE: tl.constexpr, G: tl.constexpr, CP: tl.constexpr):
    """Back to front over each tile's list: per pair ``∂L/∂(m_x, m_y, A, B, C, o)`` and ``∂L/∂c`` (row ``6 + NC``).

    ``∂C/∂α_i = T_i c_i - S_i / (1 - α_i)`` with the suffix ``S_i = Σ_{j>i} c_j α_j T_j``; zero through the 0.99 clamp
    where ``o e^q > 0.99`` (as torch.clamp's gradient); ``T_i`` from the stored final ``log T`` minus the log terms.
    """
    tile = tl.program_id(0)
    px, py = _tile_pixels(tile, tiles_x, TILE)
    dt = grad_ptr.dtype.element_ty
    fx = px.to(dt) + 0.5
    fy = py.to(dt) + 0.5
    ch = tl.arange(0, CP)
    inside = (px < W) & (py < H)
    pix = (py * W + px).to(tl.int64)
    gmask = inside[:, None] & (ch[None, :] < NC)
    g = tl.load(grad_ptr + pix[:, None] * NC + ch[None, :], mask=gmask, other=0.0)
    logt_end = tl.load(logt_ptr + pix, mask=inside, other=0.0)
    suffix = tl.zeros([TILE * TILE, CP], dtype=dt)
    start = tl.load(offsets_ptr + tile)
    end = tl.load(offsets_ptr + tile + 1)
    n_chunks = tl.cdiv(end - start, G)
    for it in range(0, n_chunks):
        k0 = start + (n_chunks - 1 - it) * G
        kk = k0 + tl.arange(0, G)
        km = kk < end
        gid, ca, cb, cc, opac, dx, dy, q, inb = _gauss_block(params_ptr, bbox_ptr, ids_ptr, kk, km, px, py, fx, fy)
        e = tl.exp(q)
        ar = opac[:, None] * e
        al = tl.where(inb, tl.minimum(ar, ALPHA_MAX), 0.0)
        la = _log1m(al)
        logt_start = logt_end - tl.sum(la, axis=0)
        trans = tl.exp(logt_start[None, :] + tl.cumsum(la, axis=0) - la)
        w = al * trans
        col = tl.load(col_ptr + gid[:, None] * NC + ch[None, :], mask=km[:, None] & (ch[None, :] < NC), other=0.0)
        wc = w[:, :, None] * col[:, None, :]
        after = tl.cumsum(wc, axis=0, reverse=True) - wc + suffix[None, :, :]
        dal = tl.sum(g[None, :, :] * (trans[:, :, None] * col[:, None, :] - after / (1.0 - al)[:, :, None]), axis=2)
        gq = tl.where(inb & (ar <= ALPHA_MAX), dal, 0.0)
        ge = gq * e
        row = pair_ptr + kk.to(tl.int64) * (6 + NC)
        tl.store(row + 0, opac * tl.sum(ge * (ca[:, None] * dx + cb[:, None] * dy), axis=1), mask=km)
        tl.store(row + 1, opac * tl.sum(ge * (cb[:, None] * dx + cc[:, None] * dy), axis=1), mask=km)
        tl.store(row + 2, -0.5 * opac * tl.sum(ge * dx * dx, axis=1), mask=km)
        tl.store(row + 3, -opac * tl.sum(ge * dx * dy, axis=1), mask=km)
        tl.store(row + 4, -0.5 * opac * tl.sum(ge * dy * dy, axis=1), mask=km)
        tl.store(row + 5, tl.sum(ge, axis=1), mask=km)
        gcol = tl.sum(w[:, :, None] * g[None, :, :], axis=1)
        tl.store(row[:, None] + 6 + ch[None, :], gcol, mask=km[:, None] & (ch[None, :] < NC))
        suffix += tl.sum(wc, axis=0)
        logt_end = logt_start


@triton.jit
def _brick_voxels(aff_ptr, org_ptr, brick, n0, n1, n2, nb1, nb2, B: tl.constexpr):
    """The brick's voxels: absolute indices, centres in mm, flat output index and the inside-the-output mask.

    ``org_ptr``: the output's first voxel index (3 int64), read from memory rather than passed as scalars: the 3D
    TV term's region moves every iteration, and scalar arguments would be specialised (a compiled variant per
    divisibility pattern) and read back from the GPU by the caller."""
    v = tl.arange(0, B * B * B)
    r0 = (brick // (nb1 * nb2)) * B + v // (B * B)
    r1 = ((brick // nb2) % nb1) * B + (v // B) % B
    r2 = (brick % nb2) * B + v % B
    i0 = r0 + tl.load(org_ptr + 0)
    i1 = r1 + tl.load(org_ptr + 1)
    i2 = r2 + tl.load(org_ptr + 2)
    dt = aff_ptr.dtype.element_ty
    f0, f1, f2 = i0.to(dt), i1.to(dt), i2.to(dt)
    x = tl.load(aff_ptr + 0) * f0 + tl.load(aff_ptr + 1) * f1 + tl.load(aff_ptr + 2) * f2 + tl.load(aff_ptr + 9)
    y = tl.load(aff_ptr + 3) * f0 + tl.load(aff_ptr + 4) * f1 + tl.load(aff_ptr + 5) * f2 + tl.load(aff_ptr + 10)
    z = tl.load(aff_ptr + 6) * f0 + tl.load(aff_ptr + 7) * f1 + tl.load(aff_ptr + 8) * f2 + tl.load(aff_ptr + 11)
    flat = (r0.to(tl.int64) * n1 + r1) * n2 + r2
    inside = (r0 < n0) & (r1 < n1) & (r2 < n2)
    return i0, i1, i2, x, y, z, flat, inside


@triton.jit
def _voxel_block(means_ptr, prec_ptr, dens_ptr, lo_ptr, hi_ptr, ids_ptr, kk, km, i0, i1, i2, x, y, z):
    """``G`` Gaussians on the brick: offsets ``d`` [G, V], precision entries, densities, ``q = dᵀ P d`` and the
    box mask."""
    gid = tl.load(ids_ptr + kk, mask=km, other=0).to(tl.int64)
    d0 = x[None, :] - tl.load(means_ptr + gid * 3 + 0, mask=km, other=0.0)[:, None]
    d1 = y[None, :] - tl.load(means_ptr + gid * 3 + 1, mask=km, other=0.0)[:, None]
    d2 = z[None, :] - tl.load(means_ptr + gid * 3 + 2, mask=km, other=0.0)[:, None]
    p00 = tl.load(prec_ptr + gid * 6 + 0, mask=km, other=0.0)[:, None]
    p11 = tl.load(prec_ptr + gid * 6 + 1, mask=km, other=0.0)[:, None]
    p22 = tl.load(prec_ptr + gid * 6 + 2, mask=km, other=0.0)[:, None]
    p01 = tl.load(prec_ptr + gid * 6 + 3, mask=km, other=0.0)[:, None]
    p02 = tl.load(prec_ptr + gid * 6 + 4, mask=km, other=0.0)[:, None]
    p12 = tl.load(prec_ptr + gid * 6 + 5, mask=km, other=0.0)[:, None]
    q = (p00 * d0 * d0 + p11 * d1 * d1 + p22 * d2 * d2 + 2.0 * (p01 * d0 * d1 + p02 * d0 * d2 + p12 * d1 * d2))
    rho = tl.load(dens_ptr + gid, mask=km, other=0.0)
    inb = ((i0[None, :] >= tl.load(lo_ptr + gid * 3 + 0, mask=km, other=0)[:, None])
           & (i0[None, :] < tl.load(hi_ptr + gid * 3 + 0, mask=km, other=0)[:, None])
           & (i1[None, :] >= tl.load(lo_ptr + gid * 3 + 1, mask=km, other=0)[:, None])
           & (i1[None, :] < tl.load(hi_ptr + gid * 3 + 1, mask=km, other=0)[:, None])
           & (i2[None, :] >= tl.load(lo_ptr + gid * 3 + 2, mask=km, other=0)[:, None])
           & (i2[None, :] < tl.load(hi_ptr + gid * 3 + 2, mask=km, other=0)[:, None]))
    return d0, d1, d2, p00, p11, p22, p01, p02, p12, q, rho, inb


@triton.jit
def voxel_fwd(means_ptr, prec_ptr, dens_ptr, lo_ptr, hi_ptr, aff_ptr, offsets_ptr, ids_ptr, out_ptr,
              org_ptr, n0, n1, n2, nb1, nb2, B: tl.constexpr, G: tl.constexpr):
    """One ``B³`` brick of the output: ``μ(x) = Σ ρ_i exp(-½ dᵀ P_i d)`` over its Gaussians whose box holds x."""
    brick = tl.program_id(0)
    i0, i1, i2, x, y, z, flat, inside = _brick_voxels(aff_ptr, org_ptr, brick, n0, n1, n2, nb1, nb2, B)
    start = tl.load(offsets_ptr + brick)
    end = tl.load(offsets_ptr + brick + 1)
    acc = tl.zeros([B * B * B], dtype=out_ptr.dtype.element_ty)
    for k0 in range(start, end, G):
        kk = k0 + tl.arange(0, G)
        km = kk < end
        d0, d1, d2, p00, p11, p22, p01, p02, p12, q, rho, inb = _voxel_block(
            means_ptr, prec_ptr, dens_ptr, lo_ptr, hi_ptr, ids_ptr, kk, km, i0, i1, i2, x, y, z)
        acc += tl.sum(tl.where(inb, rho[:, None] * tl.exp(-0.5 * q), 0.0), axis=0)
    tl.store(out_ptr + flat, acc, mask=inside)


@triton.jit
def voxel_bwd(means_ptr, prec_ptr, dens_ptr, lo_ptr, hi_ptr, aff_ptr, offsets_ptr, ids_ptr, grad_ptr, pair_ptr,
              org_ptr, n0, n1, n2, nb1, nb2, B: tl.constexpr, G: tl.constexpr):
    """Per (brick, Gaussian) pair, ``∂L/∂(m, P, ρ)`` summed over the brick's voxels (row of 10: means 3, P 6 as
    (P00, P11, P22, P01, P02, P12), ρ): ``∂μ/∂m = ρ e P d``, ``∂μ/∂P_aa = -½ ρ e d_a²``, ``∂μ/∂P_ab = -ρ e d_a d_b``,
    ``∂μ/∂ρ = e``."""
    brick = tl.program_id(0)
    i0, i1, i2, x, y, z, flat, inside = _brick_voxels(aff_ptr, org_ptr, brick, n0, n1, n2, nb1, nb2, B)
    g = tl.load(grad_ptr + flat, mask=inside, other=0.0)
    start = tl.load(offsets_ptr + brick)
    end = tl.load(offsets_ptr + brick + 1)
    for k0 in range(start, end, G):
        kk = k0 + tl.arange(0, G)
        km = kk < end
        d0, d1, d2, p00, p11, p22, p01, p02, p12, q, rho, inb = _voxel_block(
            means_ptr, prec_ptr, dens_ptr, lo_ptr, hi_ptr, ids_ptr, kk, km, i0, i1, i2, x, y, z)
        ge = tl.where(inb, g[None, :] * tl.exp(-0.5 * q), 0.0)
        row = pair_ptr + kk.to(tl.int64) * 10
        tl.store(row + 0, rho * tl.sum(ge * (p00 * d0 + p01 * d1 + p02 * d2), axis=1), mask=km)
        tl.store(row + 1, rho * tl.sum(ge * (p01 * d0 + p11 * d1 + p12 * d2), axis=1), mask=km)
        tl.store(row + 2, rho * tl.sum(ge * (p02 * d0 + p12 * d1 + p22 * d2), axis=1), mask=km)
        tl.store(row + 3, -0.5 * rho * tl.sum(ge * d0 * d0, axis=1), mask=km)
        tl.store(row + 4, -0.5 * rho * tl.sum(ge * d1 * d1, axis=1), mask=km)
        tl.store(row + 5, -0.5 * rho * tl.sum(ge * d2 * d2, axis=1), mask=km)
        tl.store(row + 6, -rho * tl.sum(ge * d0 * d1, axis=1), mask=km)
        tl.store(row + 7, -rho * tl.sum(ge * d0 * d2, axis=1), mask=km)
        tl.store(row + 8, -rho * tl.sum(ge * d1 * d2, axis=1), mask=km)
        tl.store(row + 9, tl.sum(ge, axis=1), mask=km)


#: whether the kernels were built for Triton's CPU interpreter (TRITON_INTERPRET=1 when this module was imported)
INTERPRETED = type(additive_fwd).__name__ == "InterpretedFunction"
