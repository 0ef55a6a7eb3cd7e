"""Which Gaussians a photo's error comes from: the first-order change of a view's squared error when one Gaussian
is removed, and the error with the worst of them removed.

A Gaussian of opacity ``o = sigmoid(x)`` is removed when ``o`` drops to 0, a change of ``-o``; to first order the
view's summed squared error ``E`` changes by ``-o ∂E/∂o = -(∂E/∂x) / (1 - o)``, so its *removal gain*
``(∂E/∂x) / (1 - o)`` (one backward pass for all Gaussians) is positive when the view is better without it. A
held-out photo that fails on a floater shows one or a few Gaussians with gains far above the rest, and the error
with them removed says how much of the failure they are (docs/results.md, "Tenth round").
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import torch

from ctsplat.photos.dataset import PhotoView
from ctsplat.photos.train import image_metrics, render_view
from ctsplat.splat.gaussians import Gaussians

__all__ = ["removal_gain", "blame_view"]


def removal_gain(g: Gaussians, view: PhotoView, *, background: Any = None) -> torch.Tensor:
    """First-order decrease of ``view``'s summed squared error when each Gaussian is removed (module docstring).

    Parameters
    ----------
    g : Gaussians
        An alpha model (``opacity_raw`` set), as :func:`ctsplat.photos.train.train_photos` saves it.
    view : PhotoView
        The photo (``image`` (H, W, 3) in [0, 1]) and its camera.
    background : Tensor (3,) or sequence of 3 floats, optional
        The colour behind the Gaussians (None: black).

    Returns
    -------
    Tensor (N,)
        Per Gaussian, squared-error units (sum over pixels and channels); positive: the view is better without it.
    """
    x = g.opacity_raw.detach().clone().requires_grad_(True)
    img = render_view(replace(g.detach(), opacity_raw=x), view, background=background).image
    ((img - view.image) ** 2).sum().backward()
    return (x.grad / (1 - torch.sigmoid(x.detach())).clamp_min(1e-6)).detach()


def blame_view(g: Gaussians, view: PhotoView, *, background: Any = None, top: int = 3) -> dict[str, Any]:
    """A view's PSNR, its ``top`` Gaussians by :func:`removal_gain`, and its PSNR with the first 1..``top`` removed.

    Parameters
    ----------
    g : Gaussians
    view : PhotoView
    background : Tensor (3,) or sequence of 3 floats, optional
    top : int
        How many Gaussians to name and remove, >= 1.

    Returns
    -------
    dict
        ``psnr`` (dB), ``index`` (list of ``top`` row numbers into ``g``, largest gain first), ``gain`` (their
        gains), ``psnr_without`` (list: PSNR with the first 1, 2, .. ``top`` of them removed, dB).

    Examples
    --------
    >>> report = blame_view(model, scene.split("val")[0], background=model.meta.get("background"))  # doctest: +SKIP
    """
    gain = removal_gain(g, view, background=background)
    order = torch.argsort(gain, descending=True, stable=True)[:max(int(top), 1)]
    with torch.no_grad():
        psnr = image_metrics(render_view(g, view, background=background).image, view.image)[0]
        without = []
        for k in range(1, len(order) + 1):
            keep = torch.ones(len(g), dtype=torch.bool, device=g.means.device)
            keep[order[:k]] = False
            without.append(image_metrics(render_view(g[keep], view, background=background).image, view.image)[0])
    return {"psnr": psnr, "index": order.tolist(), "gain": gain[order].tolist(), "psnr_without": without}
