"""Training losses for radiative Gaussian splatting: L1, differentiable SSIM, TV and regularisers.

The total objective is

.. math::

    \\mathcal{L} = \\lambda_1 \\lVert \\hat I - I \\rVert_1 + \\lambda_s (1 - \\mathrm{SSIM}(\\hat I, I))
        + \\lambda_\\rho \\overline{\\rho} + \\lambda_{scale} \\overline{\\lVert s \\rVert}
        + \\lambda_{tv} \\mathrm{TV}(V_{sub})

with the image terms averaged over pixels and the regularisers averaged over Gaussians (so that a weight
does not silently change its meaning when densification changes the number of Gaussians). All functions
work on the device of their inputs (CPU or CUDA) and are differentiable with torch autograd.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = [
    "gaussian_window",
    "band_matrix",
    "ssim",
    "l1",
    "tv3d",
    "density_reg",
    "scale_reg",
    "total_loss",
]


def gaussian_window(sigma: float = 1.5, truncate: float = 3.5, *, dtype=torch.float32, device=None) -> torch.Tensor:
    """Normalised 1D Gaussian taps as :func:`scipy.ndimage.gaussian_filter` uses them.

    ``radius = int(truncate * sigma + 0.5)`` so the default window has 11 taps (the classic SSIM window).

    Parameters
    ----------
    sigma : float
        Standard deviation in pixels.
    truncate : float
        Half-width in standard deviations.
    dtype : torch.dtype
    device : torch.device or str, optional

    Returns
    -------
    Tensor, shape (2 * radius + 1,)
    """
    radius = int(truncate * sigma + 0.5)
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    w = torch.exp(-0.5 * (x / sigma) ** 2)
    return (w / w.sum()).to(dtype=dtype, device=device)


# Longest image side (pixels) that a CPU blurs as a product with banded matrices; longer sides use conv2d, whose
# cost grows with the taps instead of the side (the two meet near 2048 px on a 2-core CPU). The dense band is
# (n - 2r) x n, 16 MiB in float32 at this limit. GPUs always use conv2d (cuDNN).
BAND_MAX_PX = 2048


def band_matrix(n: int, w: torch.Tensor) -> torch.Tensor:
    """The 'valid' correlation with taps ``w`` along an axis of length ``n``, as a matrix.

    Parameters
    ----------
    n : int
        Length of the axis (at least ``w.numel()``).
    w : Tensor, shape (k,)
        Taps.

    Returns
    -------
    Tensor, shape (n - k + 1, n)
        Row ``i`` holds ``w`` at columns ``i .. i + k - 1``, so ``band_matrix(n, w) @ x`` is
        ``[Σ_j w[j] x[i + j]]_i``.

    Examples
    --------
    >>> band_matrix(4, torch.tensor([1.0, 2.0]))
    tensor([[1., 2., 0., 0.],
            [0., 1., 2., 0.],
            [0., 0., 1., 2.]])
    """
    k = w.numel()
    m = w.new_zeros(n - k + 1, n)
    for j in range(k):
        m.diagonal(j).fill_(w[j])
    return m


def _blur(x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Separable 'valid' Gaussian blur of ``x`` (B, H, W) -> (B, H - 2r, W - 2r).

    On a CPU, two products with banded matrices: several times faster than ``conv2d`` with one-channel 11-tap
    kernels, forward and backward, for images up to :data:`BAND_MAX_PX` a side; otherwise two ``conv2d`` passes.
    """
    h, wd = x.shape[-2:]
    if x.device.type == "cpu" and max(h, wd) <= BAND_MAX_PX:
        return band_matrix(h, w) @ x @ band_matrix(wd, w).T
    k = w.numel()
    y = F.conv2d(x.unsqueeze(1), w.view(1, 1, k, 1))
    return F.conv2d(y, w.view(1, 1, 1, k)).squeeze(1)


def ssim(
    img: torch.Tensor,
    ref: torch.Tensor,
    data_range: float | torch.Tensor = 1.0,
    *,
    sigma: float = 1.5,
    k1: float = 0.01,
    k2: float = 0.03,
) -> torch.Tensor:
    """Mean structural similarity with a Gaussian window (differentiable).

    Matches ``skimage.metrics.structural_similarity(img, ref, gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=R)``: local statistics are Gaussian-weighted means,

    .. math::

        \\mathrm{SSIM} = \\frac{(2\\mu_x\\mu_y + C_1)(2\\sigma_{xy} + C_2)}
                              {(\\mu_x^2 + \\mu_y^2 + C_1)(\\sigma_x^2 + \\sigma_y^2 + C_2)},
        \\quad C_1 = (k_1 R)^2,\\ C_2 = (k_2 R)^2,

    averaged over the pixels whose whole window lies inside the image (skimage crops the same border).

    Parameters
    ----------
    img, ref : Tensor, shape (H, W) or (B, H, W)
        Images (any units; ``data_range`` R in the same units). H and W must be at least the window size.
    data_range : float or 0-d Tensor
        Dynamic range R of the images.
    sigma : float
        Window standard deviation (pixels).
    k1, k2 : float
        Stabilising constants.

    Returns
    -------
    Tensor, 0-d
        Mean SSIM over the batch.
    """
    if img.shape != ref.shape:
        raise ValueError(f"shape mismatch: {tuple(img.shape)} vs {tuple(ref.shape)}")
    x = img.reshape(-1, *img.shape[-2:])
    y = ref.reshape(-1, *ref.shape[-2:]).to(x.dtype)
    w = gaussian_window(sigma, dtype=x.dtype, device=x.device)
    if min(x.shape[-2:]) < w.numel():
        raise ValueError(f"images of size {tuple(x.shape[-2:])} are smaller than the {w.numel()}-pixel SSIM window")
    c1 = (k1 * data_range) ** 2
    c2 = (k2 * data_range) ** 2
    # the local moments blurred in two batches: those of the reference alone need no gradient
    mx, xx, xy = _blur(torch.cat([x, x * x, x * y]), w).chunk(3)
    my, yy = _blur(torch.cat([y, y * y]), w).chunk(2)
    sxx = xx - mx * mx
    syy = yy - my * my
    sxy = xy - mx * my
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return s.mean()


def l1(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Mean absolute error over all pixels.

    Parameters
    ----------
    img, ref : Tensor, same shape
        Images (any units).

    Returns
    -------
    Tensor, 0-d
        In the images' units.
    """
    return (img - ref).abs().mean()


def tv3d(vol: torch.Tensor) -> torch.Tensor:
    """Anisotropic total variation of a (sub-)volume, mean absolute forward difference per axis.

    .. math:: \\mathrm{TV}(V) = \\sum_{a \\in \\{i,j,k\\}} \\operatorname{mean} |V_{p + e_a} - V_p|

    Parameters
    ----------
    vol : Tensor, shape (I, J, K), each at least 2

    Returns
    -------
    Tensor, 0-d
        In the volume's units per voxel.
    """
    if vol.ndim != 3 or min(vol.shape) < 2:
        raise ValueError(f"tv3d needs a 3D volume with every side >= 2, got shape {tuple(vol.shape)}")
    return (
        (vol[1:] - vol[:-1]).abs().mean()
        + (vol[:, 1:] - vol[:, :-1]).abs().mean()
        + (vol[:, :, 1:] - vol[:, :, :-1]).abs().mean()
    )


def density_reg(density: torch.Tensor) -> torch.Tensor:
    """Mean Gaussian density ρ (normalised volume units); 0 for an empty model.

    Parameters
    ----------
    density : Tensor, shape (N,)

    Returns
    -------
    Tensor, 0-d
    """
    return density.mean() if density.numel() else density.sum()


def scale_reg(scales: torch.Tensor) -> torch.Tensor:
    """Mean Euclidean norm of the Gaussian scale vectors ``(N, 3)`` in mm; 0 for an empty model.

    Parameters
    ----------
    scales : Tensor, shape (N, 3)
        Activated scales (mm).

    Returns
    -------
    Tensor, 0-d
        mm.
    """
    return scales.norm(dim=-1).mean() if scales.numel() else scales.sum()


def total_loss(
    img: torch.Tensor,
    ref: torch.Tensor,
    *,
    density: torch.Tensor,
    scales: torch.Tensor,
    data_range: float = 1.0,
    lambda_l1: float = 1.0,
    lambda_ssim: float = 0.2,
    lambda_density: float = 5e-5,
    lambda_scale: float = 1e-4,
    lambda_tv: float = 0.0,
    tv_volume: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Weighted training objective and its terms (for logging).

    Parameters
    ----------
    img, ref : Tensor, shape (H, W) or (B, H, W)
        Rendered and target images, already scaled so that ``data_range`` is their dynamic range.
    density : Tensor, shape (N,)
        Activated Gaussian densities ρ.
    scales : Tensor, shape (N, 3)
        Activated Gaussian scales (mm).
    data_range : float
        Dynamic range of the images (SSIM).
    lambda_l1, lambda_ssim, lambda_density, lambda_scale, lambda_tv : float
        Weights of the terms (>= 0; a term with weight 0 is not computed, except the L1 term, which is always logged).
    tv_volume : Tensor, shape (i, j, k), optional
        Voxelised random sub-volume for the TV term; required when ``lambda_tv > 0``.

    Returns
    -------
    loss : Tensor, 0-d
    terms : dict of str to Tensor
        ``l1``, ``dssim`` (= 1 - SSIM), ``density``, ``scale``, ``tv``: unweighted values, 0-d and detached (``float``
        them to log; a term with weight 0 is 0, except ``l1``, the image error, which is always measured).
    """
    zero = img.new_zeros(())
    t_l1 = l1(img, ref)
    t_dssim = 1.0 - ssim(img, ref, data_range) if lambda_ssim > 0 else zero
    t_rho = density_reg(density) if lambda_density > 0 else zero
    t_scale = scale_reg(scales) if lambda_scale > 0 else zero
    if lambda_tv > 0:
        if tv_volume is None:
            raise ValueError("lambda_tv > 0 needs tv_volume")
        t_tv = tv3d(tv_volume)
    else:
        t_tv = zero
    loss = (
        lambda_l1 * t_l1 + lambda_ssim * t_dssim + lambda_density * t_rho + lambda_scale * t_scale + lambda_tv * t_tv
    )
    # tensors, not floats: on a GPU each float() waits for the queued work; the caller reads them when it logs
    terms = {"l1": t_l1.detach(), "dssim": t_dssim.detach(), "density": t_rho.detach(), "scale": t_scale.detach(),
             "tv": t_tv.detach()}
    return loss, terms
