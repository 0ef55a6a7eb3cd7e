"""``ctsplat render``: render a saved Gaussian model's views to images."""

from __future__ import annotations

import argparse
import math

from ctsplat.utils import CtsplatError


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "render",
        help="render a trained Gaussian model (.pt) for the views of a views.json",
        description="Render every view of VIEWS with MODEL; writes OUT/images.tif (float32 V,H,W), "
        "OUT/png/view_XXXX.png and OUT/render.json.",
    )
    p.add_argument("model", help="model .pt written by training (Gaussians.save)")
    p.add_argument("views", help="views.json (radiograph view set)")
    p.add_argument("out", help="output folder: new, empty or an earlier render (render.json), replaced whole")
    p.add_argument("--compositor", default=None, choices=["radiative", "radiative_unrectified", "alpha"],
                   help="default: the one the model was trained with (radiative for a model that does not say)")
    p.add_argument("--split", default=None, choices=["train", "val", "test"], help="only this split's views")
    p.add_argument("--mip", action=argparse.BooleanOptionalAction, default=None,
                   help="3D (the model's own, else from the train views) + 2D mip filters; default: as the model "
                   "was trained")
    p.add_argument("--mu-scale", type=float, default=None,
                   help="multiply densities (default: model meta mu_scale_per_mm, else 1 = normalised units)")
    p.add_argument("--device", default="cpu", help="cpu, cuda or auto")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> None:
    from ctsplat.splat.render import render_to_folder

    if args.mu_scale is not None and not 0 < args.mu_scale < math.inf:
        raise CtsplatError(f"--mu-scale must be a finite number > 0 (densities are multiplied by it), got "
                           f"{args.mu_scale:g}")
    info = render_to_folder(args.model, args.views, args.out, compositor=args.compositor, split=args.split,
                            mip=args.mip, mu_scale=args.mu_scale, device=args.device)
    print(f"rendered {info['n_views']} views of {info['n_gaussians']} Gaussians in {info['seconds']:.2f} s "
          f"-> {args.out}")
