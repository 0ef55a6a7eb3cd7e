"""Which Gaussians a photo's error comes from: the first-order change of a view's squared error when one Gaussian
is removed, and the error with the worst of them removed.

A Gaussian of opacity ``o = sigmoid(x)`` is removed when ``o`` drops to 0, a change of ``-o``; to first order the
view's summed squared error ``E`` changes by ``-o ∂E/∂o = -(∂E/∂x) / (1 - o)``, so its *removal gain*
``(∂E/∂x) / (1 - o)`` (one backward pass for all Gaussians) is positive when the view is better without it. The
render is affine in each opacity, so ``E`` is quadratic in it and the first-order gain overstates the true one by
``o² ‖∂img/∂o‖²``; :func:`blame_view` therefore renders the view without each Gaussian of a shortlist (the largest
first-order gains) and ranks them by the exact decrease. A held-out photo that fails on a floater shows one or a
few Gaussians with gains far above the rest, and the error with them removed says how much of the failure they are
(docs/results.md, "Tenth round").
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


def blame_view(g: Gaussians, view: PhotoView, *, background: Any = None, top: int = 3,
               shortlist: int = 50) -> dict[str, Any]:
    """A view's PSNR, its ``top`` Gaussians by the exact decrease of its squared error when each alone is removed
    (among the ``shortlist`` largest :func:`removal_gain`), and its PSNR with the first 1..``top`` removed.

    Parameters
    ----------
    g : Gaussians
    view : PhotoView
    background : Tensor (3,) or sequence of 3 floats, optional
    top : int
        How many Gaussians to name and remove, >= 1.
    shortlist : int
        How many Gaussians, by first-order gain, are removed one at a time and ranked exactly (at least ``top``).

    Returns
    -------
    dict
        ``psnr`` (dB), ``index`` (list of ``top`` row numbers into ``g``, largest exact gain first), ``gain``
        (their exact decrease of the summed squared error, the units of :func:`removal_gain`), ``first_order``
        (their :func:`removal_gain`), ``psnr_without`` (list: PSNR with the first 1, 2, .. ``top`` of them removed,
        dB).

    Examples
    --------
    >>> report = blame_view(model, scene.split("val")[0], background=model.meta.get("background"))  # doctest: +SKIP
    """
    top = max(int(top), 1)
    first = removal_gain(g, view, background=background)
    short = torch.argsort(first, descending=True, stable=True)[:max(int(shortlist), top)]

    def render_without(drop: Any) -> torch.Tensor:
        keep = torch.ones(len(g), dtype=torch.bool, device=g.means.device)
        keep[drop] = False
        return render_view(g[keep], view, background=background).image

    with torch.no_grad():
        img = render_view(g, view, background=background).image
        psnr = image_metrics(img, view.image)[0]
        err = float(((img - view.image) ** 2).sum())
        exact_t = torch.tensor([err - float(((render_without(i) - view.image) ** 2).sum()) for i in short.tolist()],
                               dtype=torch.float64)
        rank = torch.argsort(exact_t, descending=True, stable=True)[:top]
        order = short[rank]
        without = [image_metrics(render_without(order[:k]), view.image)[0] for k in range(1, len(order) + 1)]
    return {"psnr": psnr, "index": order.tolist(), "gain": exact_t[rank].tolist(), "first_order": first[order].tolist(),
            "psnr_without": without}
