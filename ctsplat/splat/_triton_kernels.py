"""Triton kernels of the GPU path: projection, tile rasterisers (additive and alpha) and the voxelizer, each both ways.

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


# ------------------------------------------------------------------------------------------- projection
# The EWA projection of csrc/project.h (proj8 / proj8_bwd), one Gaussian per lane of a BLOCK: forward writes
# means2d, conics, amplitudes, depths and the pixel boxes; backward recomputes the state and writes the gradients
# of means, log-scales, quaternions and the raw density (opacity). cam_ptr: the float64 vector of
# ``ctsplat.splat._kernel.camera_vector`` (on the device: no read-back), its model a constexpr (CONE).


@triton.jit
def _finite(x):
    # |x| < inf is false for NaN and ±inf. (x - x) == 0 is not safe here: with floating-point contraction (on by
    # default when compiling for a GPU) a product's x * y - x * y becomes fma(x, y, -(x * y)), the product's rounding
    # error, which is not 0, so finite values would read as non-finite (the interpreter never contracts)
    return tl.abs(x) < float("inf")


@triton.jit
def _log1p(y):
    """``log(1 + y)`` to full precision for small ``y`` (Goldberg's correction of the rounded ``1 + y``)."""
    u = 1.0 + y
    return tl.where(u == 1.0, y, tl.log(u) * (y / tl.where(u == 1.0, 1.0, u - 1.0)))


@triton.jit
def _cam_rotation(cam_ptr, dt: tl.constexpr):
    """The camera's world-to-camera rotation (row-major, entries 11..19 of the camera vector) in ``dt``."""
    return (tl.load(cam_ptr + 11).to(dt), tl.load(cam_ptr + 12).to(dt), tl.load(cam_ptr + 13).to(dt),
            tl.load(cam_ptr + 14).to(dt), tl.load(cam_ptr + 15).to(dt), tl.load(cam_ptr + 16).to(dt),
            tl.load(cam_ptr + 17).to(dt), tl.load(cam_ptr + 18).to(dt), tl.load(cam_ptr + 19).to(dt))


@triton.jit
def _det_cb(t0, t1, t2, t3, t4, t5, s0, s1, s2):
    """``|T diag(s) Tᵀ|`` for the 2×3 ``T = [[t0, t1, t2], [t3, t4, t5]]``: Σ_{j<k} s_j s_k m_jk², m_jk its minors."""
    m01 = t0 * t4 - t1 * t3
    m02 = t0 * t5 - t2 * t3
    m12 = t1 * t5 - t2 * t4
    return s0 * s1 * m01 * m01 + s0 * s2 * m02 * m02 + s1 * s2 * m12 * m12


@triton.jit
def _det_cb_bwd(t0, t1, t2, t3, t4, t5, s0, s1, s2, g):
    """``g`` times the gradient of :func:`_det_cb` with respect to ``t0 .. t5`` and ``s0 .. s2``."""
    m01 = t0 * t4 - t1 * t3
    m02 = t0 * t5 - t2 * t3
    m12 = t1 * t5 - t2 * t4
    a01 = g * s0 * s1 * m01
    a02 = g * s0 * s2 * m02
    a12 = g * s1 * s2 * m12
    return (2.0 * (a01 * t4 + a02 * t5), 2.0 * (a12 * t5 - a01 * t3), -2.0 * (a02 * t3 + a12 * t4),
            -2.0 * (a01 * t1 + a02 * t2), 2.0 * (a01 * t0 - a12 * t2), 2.0 * (a02 * t0 + a12 * t1),
            g * (s1 * m01 * m01 + s2 * m02 * m02), g * (s0 * m01 * m01 + s2 * m12 * m12),
            g * (s0 * m02 * m02 + s1 * m12 * m12))


@triton.jit
def _proj_state(cam_ptr, means_ptr, ls_ptr, q_ptr, draw_ptr, fv_ptr, i, msk, MODE: tl.constexpr, MIP: tl.constexpr,
                HAS_F: tl.constexpr, CONE: tl.constexpr):
    dt = means_ptr.dtype.element_ty
    # camera: [model, sx, sy, fx, fy, cx, cy, W, H, lim_x, lim_y, R (9), t (3), k2, near, cutoff]
    sx = tl.load(cam_ptr + 1).to(dt)
    sy = tl.load(cam_ptr + 2).to(dt)
    fx = tl.load(cam_ptr + 3).to(dt)
    fy = tl.load(cam_ptr + 4).to(dt)
    limx = tl.load(cam_ptr + 9).to(dt)
    limy = tl.load(cam_ptr + 10).to(dt)
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = _cam_rotation(cam_ptr, dt)
    k2 = tl.load(cam_ptr + 23).to(dt)
    near = tl.load(cam_ptr + 24).to(dt)
    # activations
    s2_0 = tl.exp(2.0 * tl.load(ls_ptr + i * 3 + 0, mask=msk, other=0.0))
    s2_1 = tl.exp(2.0 * tl.load(ls_ptr + i * 3 + 1, mask=msk, other=0.0))
    s2_2 = tl.exp(2.0 * tl.load(ls_ptr + i * 3 + 2, mask=msk, other=0.0))
    raw = tl.load(draw_ptr + i, mask=msk, other=0.0)
    if MODE == 2:
        xr = tl.minimum(tl.maximum(raw, -80.0), 80.0)
        rho = 1.0 / (1.0 + tl.exp(-xr))
        drho = rho * (1.0 - rho)
    else:
        rho = tl.where(raw > 20.0, raw, _log1p(tl.exp(tl.minimum(raw, 20.0))))
        drho = 1.0 / (1.0 + tl.exp(tl.minimum(-raw, 80.0)))
    if HAS_F:
        fv = tl.load(fv_ptr + i, mask=msk, other=0.0)
    else:
        fv = tl.zeros_like(raw)
    s2f_0 = s2_0 + fv
    s2f_1 = s2_1 + fv
    s2f_2 = s2_2 + fv
    # unit quaternion, rotation, M = R Rq
    q0 = tl.load(q_ptr + i * 4 + 0, mask=msk, other=1.0)
    q1 = tl.load(q_ptr + i * 4 + 1, mask=msk, other=0.0)
    q2 = tl.load(q_ptr + i * 4 + 2, mask=msk, other=0.0)
    q3 = tl.load(q_ptr + i * 4 + 3, mask=msk, other=0.0)
    nq = tl.maximum(tl.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3), 1e-12)
    w = q0 / nq
    x = q1 / nq
    y = q2 / nq
    z = q3 / nq
    a00 = 1.0 - 2.0 * (y * y + z * z)
    a01 = 2.0 * (x * y - w * z)
    a02 = 2.0 * (x * z + w * y)
    a10 = 2.0 * (x * y + w * z)
    a11 = 1.0 - 2.0 * (x * x + z * z)
    a12 = 2.0 * (y * z - w * x)
    a20 = 2.0 * (x * z - w * y)
    a21 = 2.0 * (y * z + w * x)
    a22 = 1.0 - 2.0 * (x * x + y * y)
    m00 = r00 * a00 + r01 * a10 + r02 * a20
    m01 = r00 * a01 + r01 * a11 + r02 * a21
    m02 = r00 * a02 + r01 * a12 + r02 * a22
    m10 = r10 * a00 + r11 * a10 + r12 * a20
    m11 = r10 * a01 + r11 * a11 + r12 * a21
    m12 = r10 * a02 + r11 * a12 + r12 * a22
    m20 = r20 * a00 + r21 * a10 + r22 * a20
    m21 = r20 * a01 + r21 * a11 + r22 * a21
    m22 = r20 * a02 + r21 * a12 + r22 * a22
    mx = tl.load(means_ptr + i * 3 + 0, mask=msk, other=0.0)
    my = tl.load(means_ptr + i * 3 + 1, mask=msk, other=0.0)
    mz = tl.load(means_ptr + i * 3 + 2, mask=msk, other=0.0)
    xc0 = r00 * mx + r01 * my + r02 * mz + tl.load(cam_ptr + 20).to(dt)
    xc1 = r10 * mx + r11 * my + r12 * mz + tl.load(cam_ptr + 21).to(dt)
    xc2 = r20 * mx + r21 * my + r22 * mz + tl.load(cam_ptr + 22).to(dt)
    zero = tl.zeros_like(xc2)
    if CONE:
        valid = xc2 > near
        zs = tl.where(valid, xc2, 1.0)
        rx = xc0 / zs
        ry = xc1 / zs
        unclx = (rx >= -limx) & (rx <= limx)
        uncly = (ry >= -limy) & (ry <= limy)
        clx = tl.minimum(tl.maximum(rx, -limx), limx)
        cly = tl.minimum(tl.maximum(ry, -limy), limy)
        tx = zs * clx
        ty = zs * cly
        r = tl.sqrt(tx * tx + ty * ty + zs * zs)
        j0 = fx / zs
        j2 = -fx * tx / (zs * zs)
        j4 = fy / zs
        j5 = -fy * ty / (zs * zs)
        detj = fx * fy * r / (zs * zs * zs)
    else:
        valid = xc2 == xc2
        zs = xc2
        unclx = valid
        uncly = valid
        clx = zero
        cly = zero
        tx = zero
        ty = zero
        r = zero + 1.0
        j0 = zero + 1.0 / sx
        j2 = zero
        j4 = zero + 1.0 / sy
        j5 = zero
        detj = zero + 1.0 / (sx * sy)
    # T = J2 M (J2 = [[j0, 0, j2], [0, j4, j5]])
    t0 = j0 * m00 + j2 * m20
    t1 = j0 * m01 + j2 * m21
    t2 = j0 * m02 + j2 * m22
    t3 = j4 * m10 + j5 * m20
    t4 = j4 * m11 + j5 * m21
    t5 = j4 * m12 + j5 * m22
    c00 = t0 * t0 * s2f_0 + t1 * t1 * s2f_1 + t2 * t2 * s2f_2
    c01 = t0 * t3 * s2f_0 + t1 * t4 * s2f_1 + t2 * t5 * s2f_2
    c11 = t3 * t3 * s2f_0 + t4 * t4 * s2f_1 + t5 * t5 * s2f_2
    f00 = c00 + k2
    f11 = c11 + k2
    # |Σ̂| by Cauchy–Binet (csrc/project.h det_cb): c00 c11 − c01² cancels for needle-like Gaussians in float32
    dh_raw = _det_cb(t0, t1, t2, t3, t4, t5, s2f_0, s2f_1, s2f_2)
    dd = dh_raw + k2 * (c00 + c11) + k2 * k2
    dh = tl.maximum(dh_raw, 1e-20)
    if MODE == 0:
        ampn = tl.sqrt(6.283185307179586 / dd * (s2_0 * s2_1 * s2_2)) * detj
    else:
        ampn = zero + 1.0
        if HAS_F:
            ampn = ampn * tl.sqrt((s2_0 / s2f_0) * (s2_1 / s2f_1) * (s2_2 / s2f_2))
        if MIP:
            ampn = ampn * tl.sqrt(dh / dd)
    return (rho, drho, s2_0, s2_1, s2_2, s2f_0, s2f_1, s2f_2, nq, w, x, y, z,
            m00, m01, m02, m10, m11, m12, m20, m21, m22, xc0, xc1, xc2, valid, zs, unclx, uncly, clx, cly, tx, ty, r,
            j0, j2, j4, j5, t0, t1, t2, t3, t4, t5, c00, c01, c11, f00, f11, dd, dh_raw, dh, ampn)


@triton.jit
def project_fwd(cam_ptr, means_ptr, ls_ptr, q_ptr, draw_ptr, fv_ptr, m2d_ptr, con_ptr, amp_ptr, depth_ptr, bb_ptr,
                radii_ptr, valid_ptr, visible_ptr, bad_ptr, n, MODE: tl.constexpr, MIP: tl.constexpr,
                HAS_F: tl.constexpr, CONE: tl.constexpr, BLOCK: tl.constexpr):
    """Project ``BLOCK`` Gaussians: ``means2d``, conic ``(f11, -f01, f00) / D``, amplitude, depth, valid, pixel box
    (centres ``i + 0.5`` inside ``[m - h, m + h]``, ``h = cutoff sqrt(f_aa)``, clipped), radii, visible, and a flag
    per Gaussian for NaN/Inf inputs (or a negative filter variance)."""
    i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    msk = i < n
    (rho, drho, s2_0, s2_1, s2_2, s2f_0, s2f_1, s2f_2, nq, w, x, y, z,
     m00, m01, m02, m10, m11, m12, m20, m21, m22, xc0, xc1, xc2, valid, zs, unclx, uncly, clx, cly, tx, ty, r,
     j0, j2, j4, j5, t0, t1, t2, t3, t4, t5, c00, c01, c11, f00, f11, dd, dh_raw, dh, ampn) = _proj_state(
        cam_ptr, means_ptr, ls_ptr, q_ptr, draw_ptr, fv_ptr, i, msk, MODE, MIP, HAS_F, CONE)
    dt = means_ptr.dtype.element_ty
    cx = tl.load(cam_ptr + 5).to(dt)
    cy = tl.load(cam_ptr + 6).to(dt)
    wf = tl.load(cam_ptr + 7).to(dt)
    hf = tl.load(cam_ptr + 8).to(dt)
    cut = tl.load(cam_ptr + 25).to(dt)
    if CONE:
        u = tl.load(cam_ptr + 3).to(dt) * xc0 / zs + cx
        v = tl.load(cam_ptr + 4).to(dt) * xc1 / zs + cy
    else:
        u = xc0 / tl.load(cam_ptr + 1).to(dt) + cx
        v = xc1 / tl.load(cam_ptr + 2).to(dt) + cy
    tl.store(m2d_ptr + i * 2 + 0, u, mask=msk)
    tl.store(m2d_ptr + i * 2 + 1, v, mask=msk)
    tl.store(con_ptr + i * 3 + 0, f11 / dd, mask=msk)
    tl.store(con_ptr + i * 3 + 1, -c01 / dd, mask=msk)
    tl.store(con_ptr + i * 3 + 2, f00 / dd, mask=msk)
    tl.store(amp_ptr + i, rho * ampn, mask=msk)
    tl.store(depth_ptr + i, xc2, mask=msk)
    tl.store(valid_ptr + i, valid.to(tl.int8), mask=msk)
    hx = cut * tl.sqrt(tl.maximum(f00, 0.0))
    hy = cut * tl.sqrt(tl.maximum(f11, 0.0))
    ok = valid & _finite(u) & _finite(v) & _finite(hx) & _finite(hy)
    us = tl.where(ok, u, 0.0)
    vs = tl.where(ok, v, 0.0)
    hxs = tl.where(ok, hx, 0.0)
    hys = tl.where(ok, hy, 0.0)
    u0 = tl.minimum(tl.maximum(tl.ceil(tl.minimum(tl.maximum(us - hxs - 0.5, -2.0), wf + 2.0)), 0.0), wf)
    u1 = tl.minimum(tl.maximum(tl.floor(tl.minimum(tl.maximum(us + hxs - 0.5, -2.0), wf + 2.0)) + 1.0, 0.0), wf)
    v0 = tl.minimum(tl.maximum(tl.ceil(tl.minimum(tl.maximum(vs - hys - 0.5, -2.0), hf + 2.0)), 0.0), hf)
    v1 = tl.minimum(tl.maximum(tl.floor(tl.minimum(tl.maximum(vs + hys - 0.5, -2.0), hf + 2.0)) + 1.0, 0.0), hf)
    u0i = tl.where(ok, u0.to(tl.int64), 0)
    u1i = tl.maximum(tl.where(ok, u1.to(tl.int64), 0), u0i)
    v0i = tl.where(ok, v0.to(tl.int64), 0)
    v1i = tl.maximum(tl.where(ok, v1.to(tl.int64), 0), v0i)
    tl.store(bb_ptr + i * 4 + 0, u0i, mask=msk)
    tl.store(bb_ptr + i * 4 + 1, u1i, mask=msk)
    tl.store(bb_ptr + i * 4 + 2, v0i, mask=msk)
    tl.store(bb_ptr + i * 4 + 3, v1i, mask=msk)
    vis = (u1i > u0i) & (v1i > v0i)
    tl.store(visible_ptr + i, vis.to(tl.int8), mask=msk)
    tl.store(radii_ptr + i, tl.where(vis, tl.maximum(u1i - u0i, v1i - v0i) // 2 + 1, 0).to(tl.int32), mask=msk)
    mx = tl.load(means_ptr + i * 3 + 0, mask=msk, other=0.0)
    my = tl.load(means_ptr + i * 3 + 1, mask=msk, other=0.0)
    mz = tl.load(means_ptr + i * 3 + 2, mask=msk, other=0.0)
    good = _finite(mx) & _finite(my) & _finite(mz) & _finite(tl.load(draw_ptr + i, mask=msk, other=0.0))
    for k in tl.static_range(3):
        good = good & _finite(tl.load(ls_ptr + i * 3 + k, mask=msk, other=0.0))
    for k in tl.static_range(4):
        good = good & _finite(tl.load(q_ptr + i * 4 + k, mask=msk, other=0.0))
    if HAS_F:
        fvv = tl.load(fv_ptr + i, mask=msk, other=0.0)
        good = good & _finite(fvv) & (fvv >= 0)
    tl.store(bad_ptr + i, (~good).to(tl.int8), mask=msk)


@triton.jit
def project_bwd(cam_ptr, means_ptr, ls_ptr, q_ptr, draw_ptr, fv_ptr, gm2d_ptr, gcon_ptr, gamp_ptr, gmeans_ptr,
                gls_ptr, gq_ptr, gdraw_ptr, n, MODE: tl.constexpr, MIP: tl.constexpr, HAS_F: tl.constexpr,
                CONE: tl.constexpr, BLOCK: tl.constexpr):
    """Gradients of ``project_fwd``'s means2d, conics and amplitudes with respect to means, log-scales,
    quaternions and the raw density (the chain of csrc/project.h ``proj_bwd``)."""
    i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    msk = i < n
    (rho, drho, s2_0, s2_1, s2_2, s2f_0, s2f_1, s2f_2, nq, w, x, y, z,
     m00, m01, m02, m10, m11, m12, m20, m21, m22, xc0, xc1, xc2, valid, zs, unclx, uncly, clx, cly, tx, ty, r,
     j0, j2, j4, j5, t0, t1, t2, t3, t4, t5, c00, c01, c11, f00, f11, dd, dh_raw, dh, ampn) = _proj_state(
        cam_ptr, means_ptr, ls_ptr, q_ptr, draw_ptr, fv_ptr, i, msk, MODE, MIP, HAS_F, CONE)
    dt = means_ptr.dtype.element_ty
    zero = tl.zeros_like(xc2)
    amp = rho * ampn
    ga = tl.load(gamp_ptr + i, mask=msk, other=0.0)
    gaa = ga * amp
    g_ls0 = zero
    g_ls1 = zero
    g_ls2 = zero
    g_s2f0 = zero
    g_s2f1 = zero
    g_s2f2 = zero
    g_logdetj = zero
    gd = zero
    gdh = zero
    if MODE == 0:
        g_ls0 += gaa
        g_ls1 += gaa
        g_ls2 += gaa
        g_logdetj += gaa
        gd += -0.5 * gaa / dd
    else:
        if HAS_F:
            g_ls0 += gaa
            g_ls1 += gaa
            g_ls2 += gaa
            g_s2f0 += -0.5 * gaa / s2f_0
            g_s2f1 += -0.5 * gaa / s2f_1
            g_s2f2 += -0.5 * gaa / s2f_2
        if MIP:
            gd += -0.5 * gaa / dd
            gdh += tl.where(dh_raw >= 1e-20, 0.5 * gaa / dh, 0.0)
    tl.store(gdraw_ptr + i, ga * ampn * drho, mask=msk)
    g_a = tl.load(gcon_ptr + i * 3 + 0, mask=msk, other=0.0)
    g_b = tl.load(gcon_ptr + i * 3 + 1, mask=msk, other=0.0)
    g_c = tl.load(gcon_ptr + i * 3 + 2, mask=msk, other=0.0)
    gd += -(g_a * f11 - g_b * c01 + g_c * f00) / (dd * dd)
    # D = |Σ̂| + k2 (c00 + c11) + k2², |Σ̂| by Cauchy–Binet; the conic's numerators are f11, -c01, f00
    k2 = tl.load(cam_ptr + 23).to(dt)
    g_c00 = g_c / dd + gd * k2
    g_c11 = g_a / dd + gd * k2
    g_c01 = -g_b / dd
    gt0 = (2.0 * g_c00 * t0 + g_c01 * t3) * s2f_0
    gt1 = (2.0 * g_c00 * t1 + g_c01 * t4) * s2f_1
    gt2 = (2.0 * g_c00 * t2 + g_c01 * t5) * s2f_2
    gt3 = (2.0 * g_c11 * t3 + g_c01 * t0) * s2f_0
    gt4 = (2.0 * g_c11 * t4 + g_c01 * t1) * s2f_1
    gt5 = (2.0 * g_c11 * t5 + g_c01 * t2) * s2f_2
    g_s2f0 += g_c00 * t0 * t0 + g_c01 * t0 * t3 + g_c11 * t3 * t3
    g_s2f1 += g_c00 * t1 * t1 + g_c01 * t1 * t4 + g_c11 * t4 * t4
    g_s2f2 += g_c00 * t2 * t2 + g_c01 * t2 * t5 + g_c11 * t5 * t5
    (d0, d1, d2, d3, d4, d5, ds0, ds1, ds2) = _det_cb_bwd(t0, t1, t2, t3, t4, t5, s2f_0, s2f_1, s2f_2, gd + gdh)
    gt0 += d0
    gt1 += d1
    gt2 += d2
    gt3 += d3
    gt4 += d4
    gt5 += d5
    g_s2f0 += ds0
    g_s2f1 += ds1
    g_s2f2 += ds2
    g_ls0 += 2.0 * s2_0 * g_s2f0
    g_ls1 += 2.0 * s2_1 * g_s2f1
    g_ls2 += 2.0 * s2_2 * g_s2f2
    # T = J2 M: gJ2 = gT Mᵀ (the entries J2 has), gM = J2ᵀ gT
    gj0 = gt0 * m00 + gt1 * m01 + gt2 * m02
    gj2 = gt0 * m20 + gt1 * m21 + gt2 * m22
    gj4 = gt3 * m10 + gt4 * m11 + gt5 * m12
    gj5 = gt3 * m20 + gt4 * m21 + gt5 * m22
    gm00 = j0 * gt0
    gm01 = j0 * gt1
    gm02 = j0 * gt2
    gm10 = j4 * gt3
    gm11 = j4 * gt4
    gm12 = j4 * gt5
    gm20 = j2 * gt0 + j5 * gt3
    gm21 = j2 * gt1 + j5 * gt4
    gm22 = j2 * gt2 + j5 * gt5
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = _cam_rotation(cam_ptr, dt)
    # M = R Rq: gRq = Rᵀ gM
    ga00 = r00 * gm00 + r10 * gm10 + r20 * gm20
    ga01 = r00 * gm01 + r10 * gm11 + r20 * gm21
    ga02 = r00 * gm02 + r10 * gm12 + r20 * gm22
    ga10 = r01 * gm00 + r11 * gm10 + r21 * gm20
    ga11 = r01 * gm01 + r11 * gm11 + r21 * gm21
    ga12 = r01 * gm02 + r11 * gm12 + r21 * gm22
    ga20 = r02 * gm00 + r12 * gm10 + r22 * gm20
    ga21 = r02 * gm01 + r12 * gm11 + r22 * gm21
    ga22 = r02 * gm02 + r12 * gm12 + r22 * gm22
    gw = 2.0 * (-z * ga01 + y * ga02 + z * ga10 - x * ga12 - y * ga20 + x * ga21)
    gx = 2.0 * (y * ga01 + z * ga02 + y * ga10 - 2.0 * x * ga11 - w * ga12 + z * ga20 + w * ga21 - 2.0 * x * ga22)
    gy = 2.0 * (-2.0 * y * ga00 + x * ga01 + w * ga02 + x * ga10 + z * ga12 - w * ga20 + z * ga21 - 2.0 * y * ga22)
    gz_q = 2.0 * (-2.0 * z * ga00 - w * ga01 + x * ga02 + w * ga10 - 2.0 * z * ga11 + y * ga12 + x * ga20 + y * ga21)
    dotq = gw * w + gx * x + gy * y + gz_q * z
    tl.store(gq_ptr + i * 4 + 0, (gw - w * dotq) / nq, mask=msk)
    tl.store(gq_ptr + i * 4 + 1, (gx - x * dotq) / nq, mask=msk)
    tl.store(gq_ptr + i * 4 + 2, (gy - y * dotq) / nq, mask=msk)
    tl.store(gq_ptr + i * 4 + 3, (gz_q - z * dotq) / nq, mask=msk)
    gu = tl.load(gm2d_ptr + i * 2 + 0, mask=msk, other=0.0)
    gv = tl.load(gm2d_ptr + i * 2 + 1, mask=msk, other=0.0)
    if CONE:
        fx = tl.load(cam_ptr + 3).to(dt)
        fy = tl.load(cam_ptr + 4).to(dt)
        z2 = zs * zs
        z3 = z2 * zs
        d0 = gu * fx / zs
        d1 = gv * fy / zs
        d2 = -gu * fx * xc0 / z2 - gv * fy * xc1 / z2
        gzz = -gj0 * fx / z2 + 2.0 * gj2 * fx * tx / z3 - gj4 * fy / z2 + 2.0 * gj5 * fy * ty / z3
        gtx = -gj2 * fx / z2
        gty = -gj5 * fy / z2
        r2 = r * r
        gtx += g_logdetj * tx / r2
        gty += g_logdetj * ty / r2
        gzz += g_logdetj * (zs / r2 - 3.0 / zs)
        d0 += tl.where(unclx, gtx, 0.0)
        gzz += tl.where(unclx, 0.0, gtx * clx)
        d1 += tl.where(uncly, gty, 0.0)
        gzz += tl.where(uncly, 0.0, gty * cly)
        d2 += gzz
        g_xc0 = tl.where(valid, d0, 0.0)
        g_xc1 = tl.where(valid, d1, 0.0)
        g_xc2 = tl.where(valid, d2, 0.0)
    else:
        g_xc0 = gu / tl.load(cam_ptr + 1).to(dt)
        g_xc1 = gv / tl.load(cam_ptr + 2).to(dt)
        g_xc2 = zero
    tl.store(gls_ptr + i * 3 + 0, g_ls0, mask=msk)
    tl.store(gls_ptr + i * 3 + 1, g_ls1, mask=msk)
    tl.store(gls_ptr + i * 3 + 2, g_ls2, mask=msk)
    tl.store(gmeans_ptr + i * 3 + 0, r00 * g_xc0 + r10 * g_xc1 + r20 * g_xc2, mask=msk)
    tl.store(gmeans_ptr + i * 3 + 1, r01 * g_xc0 + r11 * g_xc1 + r21 * g_xc2, mask=msk)
    tl.store(gmeans_ptr + i * 3 + 2, r02 * g_xc0 + r12 * g_xc1 + r22 * g_xc2, mask=msk)


#: whether the kernels were built for Triton's CPU interpreter (TRITON_INTERPRET=1 when this module was imported)
INTERPRETED = type(additive_fwd).__name__ == "InterpretedFunction"
