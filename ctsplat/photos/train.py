"""Alpha-composited 3DGS with spherical-harmonic colour, trained on posed photographs.

The model is :class:`ctsplat.splat.gaussians.Gaussians` rendered by :func:`ctsplat.splat.render.render` with the
``alpha`` compositor and a :class:`ctsplat.photos.dataset.PinholeCamera`; its colour is the base colour plus the SH
terms of degrees 1..``d`` (the renderer reads ``d`` from the shape of ``sh_rest``: the full degree-3 coefficients
are trained, and the first ``(d + 1)² - 1`` of them are passed while the degree is ``d``). As in 3DGS:

- seeds: one Gaussian per SfM point, its colour, isotropic scale = ``init_scale`` × the RMS distance to the 3
  nearest points, opacity ``init_opacity``;
- the SH degree starts at 0 and rises by one every ``sh_interval`` iterations up to ``sh_degree``;
- loss ``(1 - λ) L1 + λ (1 - SSIM)``, Adam (eps 1e-15), the means' learning rate (× scene extent) decaying
  exponentially; density control by :class:`ctsplat.photos.densify.AlphaDensify` (``densify.strategy: default``)
  or by relocation, :class:`ctsplat.photos.mcmc.MCMCDensify` (``mcmc``: its regulariser joins the loss and its
  position noise follows each optimiser step);
- the composite lies over a background colour, fixed (``background: [r, g, b]``, black by default) or learned with
  the model (``background: learned``, started at the median of the training photos' border pixels); it is saved
  in the model's ``meta["background"]``;
- with ``flash.enabled``, a flash on the camera (:mod:`ctsplat.photos.light`): colours × ``(r_ref / r)^p``, the
  exponent ``p`` trained with the model (Adam) from ``flash.exponent``, ``r`` clamped below at the nearest SfM
  point's distance from a training camera with ``flash.bounded``; ``meta["flash"]`` keeps ``exponent``, ``r_ref``
  and ``r_min`` (None: unbounded), and :func:`render_view` applies it. ``model.ply`` holds the colours seen from
  ``r_ref``;
- with ``drop_rate`` > 0, DropGaussian (:func:`drop_gaussians`): each training render leaves every Gaussian out
  with probability ``drop_rate`` × iteration / iterations and divides the others' opacities by what is kept.

``holdout: validation`` leaves the test photos out entirely and monitors and evaluates on validation photos taken
from the training set (:func:`ctsplat.photos.dataset.split_names`): the split to choose settings on.
``validation_offset`` picks one of the ``test_every`` - 1 disjoint folds, so a choice can be checked on more photos
than one fold holds.

Outputs (written under a temporary name, renamed into place when training ends): ``config.json``,
``train_log.csv`` (the CT runs' columns, :data:`ctsplat.formats.runlog.LOG_COLUMNS`; ``psnr2d``/``ssim2d`` on the
held-out views, 3D metrics empty), ``model.pt``, ``model.ply`` (3DGS layout) and ``training.json``.

References
----------
Kerbl, B., Kopanas, G., Leimkühler, T., Drettakis, G. (2023). 3D Gaussian Splatting for real-time radiance field
rendering. ACM TOG 42(4).
Park, H., Ryu, G., Kim, W. (2025). DropGaussian: structural regularization for sparse-view Gaussian splatting.
CVPR.
"""

from __future__ import annotations

import logging
import math
import resource
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree

from ctsplat.formats.runlog import LOG_COLUMNS, CsvLog
from ctsplat.geometry.cameras import camera_center
from ctsplat.photos.config import check_train_settings, held_out_split, photo_settings
from ctsplat.photos.dataset import PhotoScene, PhotoView, load_scene
from ctsplat.photos.densify import AlphaDensify
from ctsplat.photos.light import flash_falloff, nearest_point_distance, reference_distance
from ctsplat.photos.mcmc import MCMCDensify
from ctsplat.splat.gaussians import Gaussians
from ctsplat.splat.render import render
from ctsplat.training.losses import ssim
from ctsplat.utils import (
    CtsplatError,
    atomic_dir,
    check_output_dir,
    code_version,
    compute_platform,
    config_hash,
    resolve_device,
    write_json_atomic,
)

__all__ = ["PHOTO_LOG_EXTRAS", "check_run", "train_photos", "train_scene", "init_params", "border_colour",
           "to_gaussians", "render_view", "peak_memory", "reset_gpu_peak", "image_metrics", "drop_gaussians"]

log = logging.getLogger(__name__)

#: Columns of ``train_log.csv`` after :data:`LOG_COLUMNS` (a subset of the CT runs' extras, same names).
PHOTO_LOG_EXTRAS: tuple[str, ...] = ("loss", "l1", "dssim", "n_gaussians", "lr_means", "iters_per_s", "cloned",
                                     "split", "pruned", "sh_degree")
_PARAMS = ("means", "log_scales", "quats", "opacity_raw", "colors", "sh_rest")


def init_params(xyz: np.ndarray, rgb: np.ndarray, settings: dict[str, Any], gen: np.random.Generator,
                device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
    """Trainable tensors seeded from SfM points (module docstring).

    Parameters
    ----------
    xyz : ndarray (P, 3)
    rgb : ndarray (P, 3) in [0, 1]
    settings : dict
        The ``photos.train`` section (``max_points``, ``init_opacity``, ``init_scale``).
    gen : numpy.random.Generator
        Picks the subset when there are more than ``max_points`` points.
    device : torch.device or str

    Returns
    -------
    dict of str to Tensor
        ``means`` (N, 3), ``log_scales`` (N, 3), ``quats`` (N, 4), ``opacity_raw`` (N,), ``colors`` (N, 3),
        ``sh_rest`` (N, 15, 3), leaves that require grad.
    """
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    rgb = np.asarray(rgb, float).reshape(-1, 3)
    if len(xyz) < 4:
        raise CtsplatError(f"{len(xyz)} SfM points cannot seed a model (need >= 4); register more photos")
    if len(xyz) > int(settings["max_points"]):
        idx = np.sort(gen.choice(len(xyz), int(settings["max_points"]), replace=False))
        xyz, rgb = xyz[idx], rgb[idx]
    d, _ = cKDTree(xyz).query(xyz, k=4)
    scale = float(settings["init_scale"]) * np.sqrt(np.maximum(np.mean(d[:, 1:] ** 2, axis=1), 1e-14))
    n = len(xyz)
    kw = {"dtype": torch.float32, "device": device}
    quats = torch.zeros(n, 4, **kw)
    quats[:, 0] = 1.0
    op = float(settings["init_opacity"])
    params = {
        "means": torch.as_tensor(xyz, **kw),
        "log_scales": torch.as_tensor(np.log(scale), **kw)[:, None].repeat(1, 3),
        "quats": quats,
        "opacity_raw": torch.full((n,), math.log(op / (1 - op)), **kw),
        "colors": torch.as_tensor(rgb, **kw),
        "sh_rest": torch.zeros(n, 15, 3, **kw),
    }
    return {k: v.clone().requires_grad_(True) for k, v in params.items()}


def border_colour(views: list[PhotoView], *, width_px: int = 4) -> np.ndarray:
    """The median colour of the photos' border pixels (the start of a learned background colour).

    Parameters
    ----------
    views : list of PhotoView
    width_px : int
        Border width, px.

    Returns
    -------
    ndarray (3,) in [0, 1]
    """
    rims = []
    for v in views:
        img = v.image.detach().cpu()
        k = max(1, min(width_px, img.shape[0] // 2, img.shape[1] // 2))
        rims += [img[:k].reshape(-1, 3), img[-k:].reshape(-1, 3), img[:, :k].reshape(-1, 3),
                 img[:, -k:].reshape(-1, 3)]
    return torch.cat(rims).median(dim=0).values.double().numpy()


def to_gaussians(params: dict[str, torch.Tensor], degree: int) -> Gaussians:
    """The :class:`Gaussians` the renderer sees at SH degree ``degree`` (0..3).

    Parameters
    ----------
    params : dict of str to Tensor
        From :func:`init_params`.
    degree : int

    Returns
    -------
    Gaussians
        Sharing (not copying) the parameter tensors; ``density_raw`` is an unused constant.
    """
    k = (degree + 1) ** 2 - 1
    m = params["means"]
    return Gaussians(means=m, log_scales=params["log_scales"], quats=params["quats"],
                     density_raw=torch.zeros(m.shape[0], dtype=m.dtype, device=m.device),
                     opacity_raw=params["opacity_raw"], colors=params["colors"],
                     sh_rest=params["sh_rest"][:, :k] if k else None)


def drop_gaussians(opacity_raw: torch.Tensor, rate: float, gen: torch.Generator) -> torch.Tensor:
    """DropGaussian's opacities for one training render: each Gaussian left out with probability ``rate``, the
    others' opacities divided by ``1 - rate`` (so the expected opacity is unchanged), as logits.

    The renderer takes opacities as logits, so a kept opacity ``σ(x) / (1 - rate)`` is capped at 0.999 (the
    compositor caps α at 0.99 anyway); its gradient passes the cap as if uncapped, as in DropGaussian, where the
    scaled opacity may exceed 1 and only α is capped, so an opaque Gaussian's opacity keeps training.

    Parameters
    ----------
    opacity_raw : Tensor (N,)
        Opacity logits.
    rate : float
        Probability in [0, 1) that a Gaussian is left out.
    gen : torch.Generator
        A CPU generator: the draws do not depend on the device.

    Returns
    -------
    Tensor (N,)
        Logits of the opacities to render: -30 (an opacity of 1e-13) for a dropped Gaussian; ``opacity_raw``
        itself when ``rate`` is 0.

    References
    ----------
    Park, H., Ryu, G., Kim, W. (2025). DropGaussian: structural regularization for sparse-view Gaussian
    splatting. CVPR.

    Examples
    --------
    >>> x = torch.zeros(4)
    >>> drop_gaussians(x, 0.0, torch.Generator().manual_seed(0)) is x
    True
    """
    if rate <= 0.0:
        return opacity_raw
    if rate >= 1.0:
        raise CtsplatError(f"drop rate {rate} leaves no Gaussian; keep photos.train.drop_rate below 1")
    keep = (torch.rand(opacity_raw.shape, generator=gen) >= rate).to(opacity_raw.device)
    scaled = torch.sigmoid(opacity_raw) / (1.0 - rate)
    capped = scaled - (scaled - torch.clamp(scaled, max=0.999)).detach()  # straight through the cap
    return torch.where(keep, torch.logit(capped), torch.full_like(opacity_raw, -30.0))


def render_view(g: Gaussians, view: PhotoView | Any, camera: Any = None, R: Any = None, t: Any = None, *,
                background: Any = None, flash: dict[str, Any] | None = None) -> Any:
    """Render ``g`` from a view (or from ``camera``, ``R``, ``t``) with the alpha compositor.

    Parameters
    ----------
    g : Gaussians
    view : PhotoView or None
    camera, R, t : optional
        Used instead of the view's.
    background : Tensor (3,) or sequence of 3 floats, optional
        The colour behind the Gaussians (None: black).
    flash : dict, optional
        ``{"exponent": p, "r_ref": r, "r_min": r_min or None}`` (p a float or a tensor being trained): the
        flash falloff of :func:`ctsplat.photos.light.flash_falloff` on the colours. None: ``g.meta.get("flash")``
        (none: no falloff).

    Returns
    -------
    ctsplat.splat.render.RenderOutput
        ``image`` (H, W, 3).
    """
    cam = camera if camera is not None else view.camera
    R = R if R is not None else view.R
    t = t if t is not None else view.t
    flash = flash if flash is not None else g.meta.get("flash")
    scale = None
    if flash is not None:
        centre = torch.as_tensor(camera_center(np.asarray(R, float), np.asarray(t, float)), dtype=g.means.dtype,
                                 device=g.means.device)
        scale = flash_falloff(g.means, centre, exponent=flash["exponent"], r_ref=float(flash["r_ref"]),
                              r_min=flash.get("r_min"))
    return render(g, cam, R, t, compositor="alpha", background=background, color_scale=scale)


def image_metrics(img: torch.Tensor, ref: torch.Tensor) -> tuple[float, float]:
    """PSNR (dB, data range 1) and SSIM (Gaussian window σ 1.5, mean over RGB) of one image in [0, 1].

    Parameters
    ----------
    img, ref : Tensor (H, W, 3)
        ``img`` is clipped to [0, 1] first.

    Returns
    -------
    (float, float)
    """
    x = img.detach().clamp(0, 1).float()
    y = ref.float()
    mse = float(torch.mean((x - y) ** 2))
    p = float("inf") if mse == 0 else 10 * math.log10(1.0 / mse)
    s = float(ssim(x.permute(2, 0, 1), y.permute(2, 0, 1), 1.0))
    return p, s


def _optimizer(params: dict[str, torch.Tensor], lr: dict[str, float], extent: float) -> torch.optim.Adam:
    key = {"opacity_raw": "opacity"}
    groups = [{"params": [params[k]], "lr": float(lr[key.get(k, k)]) * (extent if k == "means" else 1.0),
               "name": k} for k in _PARAMS]
    return torch.optim.Adam(groups, lr=0.0, eps=1e-15)


def _eval_views(params: dict[str, torch.Tensor], degree: int, views: list[PhotoView], background: torch.Tensor,
                flash: dict[str, Any] | None) -> tuple[float, float]:
    if not views:
        return float("nan"), float("nan")
    with torch.no_grad():
        g = to_gaussians(params, degree)
        vals = [image_metrics(render_view(g, v, background=background.detach(), flash=flash).image, v.image)
                for v in views]
    return float(np.mean([a for a, _ in vals])), float(np.mean([b for _, b in vals]))


def train_scene(scene: PhotoScene, settings: dict[str, Any], log_path: Path | None = None,
                device: torch.device | str = "cpu") -> tuple[Gaussians, dict[str, Any]]:
    """Train on the ``train`` views of a scene (module docstring); held-out PSNR/SSIM every ``log_every`` (on the
    :func:`held_out_split` views).

    Parameters
    ----------
    scene : PhotoScene
    settings : dict
        The filled ``photos.train`` section.
    log_path : Path, optional
        ``train_log.csv`` to write (started over).
    device : torch.device or str

    Returns
    -------
    model : Gaussians
        Detached, at the final SH degree; ``meta["background"]`` is its background colour (list of 3 floats),
        ``meta["flash"]`` its flash (``exponent``, ``r_ref``, ``r_min``; only with ``flash.enabled``).
    report : dict
        ``iterations``, ``seconds``, ``n_gaussians``, ``initial_test_psnr``, ``final_test_psnr``,
        ``final_test_ssim`` (on the held-out split, named by ``held_out``), ``sh_degree``, ``background``,
        ``flash`` (None without).
    """
    s = settings
    iters = int(s["iterations"])
    seed = int(s["seed"])
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    rng = np.random.default_rng(seed)
    held = held_out_split(s)
    train, test = scene.split("train"), scene.split(held)
    if not train:
        raise CtsplatError("no training photo left after the held-out split; raise photos.train.test_every")
    if not test:
        what = ("no validation photo (fewer registered photos than validation_offset + 1)" if held == "val" else
                f"no test photo (test_every {s['test_every']})")
        raise CtsplatError(f"the held-out split has {what}, and the run is evaluated on held-out photos; set "
                           "photos.train.test_every to 2 or more, or hold out the test photos only")
    params = init_params(scene.xyz, scene.rgb, s, rng, device)
    opt = _optimizer(params, s["lr"], scene.extent)
    learned = s["background"] == "learned"
    bg0 = border_colour(train) if learned else np.asarray(s["background"], float)
    background = torch.tensor(bg0, dtype=torch.float32, device=device, requires_grad=learned)
    bg_opt = torch.optim.Adam([background], lr=float(s["lr"]["background"]), eps=1e-15) if learned else None
    centres = camera_center(np.stack([v.R for v in train]), np.stack([v.t for v in train]))  # (C, 3)
    flash, flash_opt = None, None
    if s["flash"]["enabled"]:
        exponent = torch.tensor(float(s["flash"]["exponent"]), dtype=torch.float32, device=device,
                                requires_grad=True)
        flash = {"exponent": exponent, "r_ref": reference_distance(centres, scene.xyz),
                 "r_min": nearest_point_distance(centres, scene.xyz) if s["flash"]["bounded"] else None}
        flash_opt = torch.optim.Adam([exponent], lr=float(s["flash"]["lr"]), eps=1e-15)
    dens: AlphaDensify | MCMCDensify = (
        MCMCDensify(s["densify"], s["mcmc"], iterations=iters) if s["densify"]["strategy"] == "mcmc"
        else AlphaDensify(s["densify"], iterations=iters, extent=scene.extent, means=params["means"],
                          camera_centers=torch.as_tensor(centres, dtype=torch.float32, device=device)))
    lam = float(s["lambda_dssim"])
    drop = float(s["drop_rate"])
    lr0 = float(s["lr"]["means"]) * scene.extent
    lr1 = float(s["lr"]["means_final"]) * scene.extent
    csv = CsvLog(log_path, [*LOG_COLUMNS, *PHOTO_LOG_EXTRAS]) if log_path is not None else None
    if csv is not None:
        csv.reset()
    p0, s0 = _eval_views(params, 0, test, background, flash)
    if csv is not None:
        csv.append([{"iteration": 0, "timestamp": 0.0, "psnr2d": p0, "ssim2d": s0,
                     "n_gaussians": int(params["means"].shape[0]), "sh_degree": 0}])
    order: list[int] = []
    counts = {"cloned": 0, "split": 0, "pruned": 0}
    t_start = time.perf_counter()
    t_last, it_last = t_start, 0
    degree = 0
    for it in range(1, iters + 1):
        degree = min(int(s["sh_degree"]), (it - 1) // max(int(s["sh_interval"]), 1))
        if not order:
            order = rng.permutation(len(train)).tolist()
        view = train[order.pop()]
        lr_means = lr0 * (lr1 / lr0) ** ((it - 1) / max(iters - 1, 1)) if lr0 > 0 else 0.0
        opt.param_groups[0]["lr"] = lr_means
        shown = {**params, "opacity_raw": drop_gaussians(params["opacity_raw"], drop * it / iters, gen)}
        out = render_view(to_gaussians(shown, degree), view, background=background, flash=flash)
        img = out.image
        l1 = torch.mean(torch.abs(img - view.image))
        dssim = 1.0 - ssim(img.permute(2, 0, 1), view.image.permute(2, 0, 1), 1.0)
        loss = (1 - lam) * l1 + lam * dssim
        if isinstance(dens, MCMCDensify):
            loss = loss + dens.regularisation(params)
        loss.backward()
        if not torch.isfinite(loss):
            raise CtsplatError(f"training diverged at iteration {it} (loss {float(loss)}); lower photos.train.lr")
        with torch.no_grad():
            ndc = torch.tensor([view.camera.width / 2, view.camera.height / 2], device=img.device)
            dens.accumulate(out.means2d.grad, out.visible, ndc, footprints=out.footprints, depths=out.depths)
        opt.step()
        opt.zero_grad(set_to_none=True)
        if isinstance(dens, MCMCDensify):
            dens.perturb(params, gen, lr_means)
        if flash_opt is not None:
            flash_opt.step()
            flash_opt.zero_grad(set_to_none=True)
        if bg_opt is not None:
            bg_opt.step()
            bg_opt.zero_grad(set_to_none=True)
            with torch.no_grad():
                background.clamp_(0.0, 1.0)
        if dens.due(it):
            params, st = dens.step(params, opt, gen, iteration=it)
            for k in counts:
                counts[k] += st[k]
        if dens.reset_due(it):
            dens.reset_opacity(params, opt)
        if csv is not None and (it % int(s["log_every"]) == 0 or it == iters):
            now = time.perf_counter()
            ps, ss = _eval_views(params, degree, test, background, flash)
            csv.append([{"iteration": it, "timestamp": now - t_start, "psnr2d": ps, "ssim2d": ss,
                         "loss": float(loss.detach()), "l1": float(l1.detach()), "dssim": float(dssim.detach()),
                         "n_gaussians": int(params["means"].shape[0]), "lr_means": lr_means,
                         "iters_per_s": (it - it_last) / max(now - t_last, 1e-9), **counts, "sh_degree": degree}])
            log.info("photos train %d/%d: held-out PSNR %.2f dB SSIM %.3f, %d Gaussians%s", it, iters, ps, ss,
                     params["means"].shape[0], f", flash p {float(flash['exponent'].detach()):.3f}" if flash else "")
            counts = dict.fromkeys(counts, 0)
            t_last, it_last = time.perf_counter(), it
    seconds = time.perf_counter() - t_start
    model = to_gaussians({k: v.detach() for k, v in params.items()}, degree)
    bg = [float(c) for c in background.detach().cpu()]
    model.meta["background"] = bg
    if flash is not None:
        flash = {**flash, "exponent": float(flash["exponent"].detach())}
        model.meta["flash"] = flash
    pf, sf = _eval_views(params, degree, test, background, flash)
    report = {"iterations": iters, "seconds": seconds, "n_gaussians": len(model), "sh_degree": degree,
              "held_out": held, "initial_test_psnr": p0, "initial_test_ssim": s0,
              "final_test_psnr": pf, "final_test_ssim": sf, "n_train": len(train), "n_test": len(test),
              "background": bg, "flash": flash}
    return model, report


def peak_memory(device: torch.device) -> dict[str, float | None]:
    """Peak memory: ``peak_rss_mb`` (the process's resident set so far, MiB: whatever ran before in the same
    process counts too) and ``peak_gpu_mb`` (CUDA max allocated since the last ``reset_gpu_peak``, MiB; ``None``
    off the GPU)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    rss_mb = rss / (1024 * 1024) if sys.platform == "darwin" else rss / 1024  # bytes on macOS, KiB on Linux
    gpu = torch.cuda.max_memory_allocated() / 2**20 if device.type == "cuda" else None
    return {"peak_rss_mb": rss_mb, "peak_gpu_mb": gpu}


def reset_gpu_peak(device: torch.device) -> None:
    """Start :func:`peak_memory`'s GPU peak afresh (training and evaluation each report their own)."""
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)


#: Files that mark a folder as an earlier photo run, which a new run may replace (the evaluation's metrics.json
#: stays when the workflow reruns training, which removes the training's own files first).
RUN_MARKERS = ("config.json", "model.pt", "metrics.json")

#: The other files of a photo run folder: training's and the evaluation's (:mod:`ctsplat.photos.evaluate`). A
#: folder holding anything else is not replaced.
RUN_FILES = ("model.ply", "training.json", "train_log.csv", "per_view_test.csv", "figures/gallery.png",
             "figures/turntable.gif", "blame.csv")  # blame.csv: benchmarks/photo_blame.py's table of this model


def check_run(out_dir: str | Path, settings: dict[str, Any], *, inputs: tuple[str | Path, ...] = ()) -> None:
    """Refuse, before any work, what :func:`train_photos` would refuse at its start.

    Callers that run SfM first call this before it, so that bad settings or a run folder that must not be
    replaced fail in a second instead of after the SfM step.

    Parameters
    ----------
    out_dir : str or Path
        The run folder: it must be new, empty or an earlier photo run (:data:`RUN_MARKERS`, nothing but
        :data:`RUN_MARKERS` and :data:`RUN_FILES` in it).
    settings : dict
        The filled ``photos.train`` section.
    inputs : tuple of str or Path, optional
        Folders the run reads (the SfM folder), which the run folder must neither be nor hold.

    Raises
    ------
    CtsplatError
        One line, from :func:`ctsplat.photos.config.check_train_settings` or
        :func:`ctsplat.utils.check_output_dir`.
    """
    check_train_settings(settings)
    check_output_dir(Path(out_dir), marker=RUN_MARKERS, contents=RUN_FILES, inputs=inputs)


def train_photos(sfm_dir: str | Path, out_dir: str | Path, settings: dict[str, Any] | None = None, *,
                 evaluate: dict[str, Any] | None = None) -> dict[str, Any]:
    """Train alpha 3DGS on an SfM folder and write the run folder (module docstring).

    Parameters
    ----------
    sfm_dir : str or Path
        Output of :func:`ctsplat.photos.sfm.run_photo_sfm`.
    out_dir : str or Path
        The run folder (replaced when training succeeds, and only when it is new, empty or an earlier photo run;
        nothing is written on failure).
    settings : dict, optional
        The ``photos.train`` section; missing keys take :data:`ctsplat.photos.config.PHOTOS_DEFAULTS`.
    evaluate : dict, optional
        The ``photos.evaluate`` section: the run is then also evaluated
        (:func:`ctsplat.photos.evaluate.evaluate_photos`) before it replaces ``out_dir``, so a failed or interrupted
        evaluation leaves an earlier run as it was instead of a new model without its metrics.

    Returns
    -------
    dict
        The contents of ``training.json``.
    """
    s = photo_settings({"train": dict(settings or {})})["train"]
    out_dir = Path(out_dir)
    check_run(out_dir, s, inputs=(sfm_dir,))  # before training, not after it
    sfm_dir = Path(sfm_dir).resolve()  # config.json and the model must find it from any working folder
    device = resolve_device(s["device"])
    reset_gpu_peak(device)
    torch.set_num_threads(int(s["num_threads"]))
    scene = load_scene(sfm_dir, downscale=int(s["downscale"]), test_every=int(s["test_every"]),
                       validation=held_out_split(s) == "val",
                       validation_offset=s.get("validation_offset"), device=device)
    with atomic_dir(out_dir, marker=RUN_MARKERS, contents=RUN_FILES, inputs=(sfm_dir,)) as tmp:
        config = {"sfm_dir": str(sfm_dir), "train": s}
        write_json_atomic(tmp / "config.json", {**config, "config_hash": config_hash(config),
                                                "code_version": code_version()})
        model, report = train_scene(scene, s, tmp / "train_log.csv", device)
        model.meta.update({"compositor": "alpha", "source": "photos", "sfm_dir": str(sfm_dir)})
        model.save(tmp / "model.pt")
        model.to_ply(tmp / "model.ply")
        w, h = scene.views[0].camera.width, scene.views[0].camera.height
        report.update({"resolution": [w, h], "downscale": int(s["downscale"]), "extent": scene.extent,
                       "device": str(device), "platform": compute_platform(device), **peak_memory(device)})
        write_json_atomic(tmp / "training.json", report)
        if evaluate is not None:
            from ctsplat.photos.evaluate import evaluate_photos  # it reads run folders with this module's helpers

            evaluate_photos(tmp, evaluate, scene=scene)
    return report
