"""Every classical reconstruction that applies to a view set, each with its parameters chosen on validation views.

Which methods apply depends on the geometry:

- circular parallel beam at elevation 0: slice-wise FBP (:func:`ctsplat.baselines.fbp_volume`), slice-wise SART
  (:func:`ctsplat.baselines.sart_volumes`), ASD-POCS (3D, :mod:`ctsplat.recon.iterative`) and MBIR (svmbir,
  :mod:`ctsplat.recon.mbir`);
- circular cone beam without wobble: FDK (:mod:`ctsplat.recon.fdk`), 3D SART (ordered subsets) and ASD-POCS;
- any other orbit (sphere, wobbling, C-arm): 3D SART and ASD-POCS.

The 3D iterative methods may reconstruct from a binned detector (``detector_binning``: ``b × b`` pixels averaged,
pitch ``b`` times larger), which divides their cost by about ``b²`` when the detector samples the volume finer
than its voxels (the cone-beam protocol's 2 pixels per voxel edge). Every method's validation score uses the
validation views binned the same way; the test metrics use the full radiographs. The ``best`` choice is the one
with the highest validation score.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ctsplat.formats.viewset import ViewSet
from ctsplat.recon.fdk import is_circular_cone, short_scan_shortfall
from ctsplat.recon.select import Choice, Validator, choose, choose_iterative, rank
from ctsplat.utils import CtsplatError, scratch_dir

__all__ = ["METHODS", "applicable_methods", "bin_detector", "auto_binning", "classical_reconstructions", "sharpened",
           "best_choice"]

log = logging.getLogger(__name__)

#: Every classical method ``baselines.methods`` may name.
METHODS = ("fbp", "fdk", "sart", "asd_pocs", "mbir")


def applicable_methods(view_set: ViewSet) -> tuple[str, ...]:
    """The methods of :data:`METHODS` that can reconstruct ``view_set``'s geometry (see the module docstring); FDK
    not on a short scan under 180° plus the fan angle (:func:`ctsplat.recon.fdk.short_scan_shortfall`)."""
    from ctsplat.baselines import is_circular_parallel

    if is_circular_parallel(view_set):
        return ("fbp", "sart", "asd_pocs", "mbir")
    if is_circular_cone(view_set):
        shortfall = short_scan_shortfall(view_set)
        if shortfall is not None:
            log.warning("baselines: FDK skipped: %s", shortfall)
            return ("sart", "asd_pocs")
        return ("fdk", "sart", "asd_pocs")
    return ("sart", "asd_pocs")


def auto_binning(view_set: ViewSet, reference: Any) -> int:
    """Largest ``b`` dividing both detector sides whose binned pixel at the isocentre is at most 1.5 voxel edges.

    One detector pixel per voxel at the isocentre samples the volume about as finely as it can be reconstructed;
    the 1.5 lets the cone-beam protocol's 2 pixels per voxel edge (0.71 voxels at the isocentre) bin by 2.
    """
    cam = view_set.camera
    iso_pixel = cam.spacing_mm if cam.model == "parallel" else cam.pitch_mm * cam.dso_mm / cam.dsd_mm
    voxel = float(np.max(np.linalg.norm(np.asarray(reference.affine, float)[:3, :3], axis=0)))
    b = max(1, int(np.floor(1.5 * voxel / iso_pixel + 1e-6)))
    while b > 1 and (cam.width % b or cam.height % b):
        b -= 1
    return b


def bin_detector(line_integrals: np.ndarray, view_set: ViewSet, factor: int) -> tuple[np.ndarray, ViewSet]:
    """Average ``factor × factor`` detector pixels: the line integrals and the view set of the coarser detector.

    Parameters
    ----------
    line_integrals : ndarray, shape (V, H, W)
        Line integrals of the views of ``view_set``.
    view_set : ViewSet
        The views; its camera gets ``factor`` times the pixel size and ``1 / factor`` the pixels.
    factor : int
        >= 1, dividing both detector sides.

    Returns
    -------
    p : ndarray, shape (V, H / factor, W / factor), float32
    view_set : ViewSet
        Same poses; the principal point stays at the detector centre.

    Raises
    ------
    CtsplatError
        For a factor < 1 or one that does not divide the detector.
    """
    from ctsplat.geometry import ConeCamera, ParallelCamera

    f = int(factor)
    cam = view_set.camera
    if f < 1 or cam.width % f or cam.height % f:
        raise CtsplatError(f"baselines.detector_binning {factor} must be >= 1 and divide the detector "
                           f"({cam.width} x {cam.height} pixels)")
    p = np.asarray(line_integrals, np.float32)
    if f == 1:
        return p, view_set
    V, H, W = p.shape
    p = p.reshape(V, H // f, f, W // f, f).mean(axis=(2, 4))
    if cam.model == "parallel":
        new = ParallelCamera(W // f, H // f, cam.spacing_mm * f)
    else:
        new = ConeCamera(W // f, H // f, cam.pitch_mm * f, cam.dso_mm, cam.dsd_mm)
    return np.ascontiguousarray(p), replace(view_set, camera=new)


def _as_list(value: Any) -> list[Any]:
    return list(value) if isinstance(value, list | tuple) else [value]


def classical_reconstructions(train_p: np.ndarray, train_vs: ViewSet, val_p: np.ndarray, val_vs: ViewSet,
                              reference: Any, config: dict[str, Any] | None = None, *,
                              work_dir: str | Path | None = None) -> list[Choice]:
    """Run every applicable classical method, each with its parameters chosen on the validation views.

    Parameters
    ----------
    train_p : ndarray, shape (V, H, W)
        Line integrals of the views to reconstruct from (the training views), page order of ``train_vs``.
    train_vs : ViewSet
        Those views.
    val_p : ndarray, shape (Vv, H, W)
        Line integrals of the validation views (noise-free in the protocol), page order of ``val_vs``.
    val_vs : ViewSet
        The validation views (same camera). Test views and the reference values are never read.
    reference : Volume-like
        The reconstruction grid: ``affine``, ``shape``, ``mu_scale_per_mm`` (values not read).
    config : dict, optional
        The ``baselines`` section (:data:`ctsplat.baselines.BASELINE_DEFAULTS`), already checked.
    work_dir : path-like, optional
        Where svmbir caches its system matrices (default a temporary folder, removed afterwards).

    Returns
    -------
    list of Choice
        One per method that ran (in :data:`METHODS` order): chosen parameters (``filter``, ``iterations``,
        ``relaxation``, ``alpha``, ``sharpness``, ``snr_db``, ...), validation PSNR, volume, seconds, trials.

    Raises
    ------
    CtsplatError
        For an empty validation set, a ``methods`` entry that does not apply to the geometry when named alone,
        or a detector binning that does not divide the detector.
    """
    from ctsplat.baselines import BASELINE_DEFAULTS, fbp_volume, sart_volumes
    from ctsplat.recon.fdk import fdk_volume
    from ctsplat.recon.iterative import asd_pocs_iterates, sart_iterates
    from ctsplat.recon.mbir import mbir_volume, svmbir_available
    from ctsplat.utils import merge_config, resolve_device

    cfg = merge_config("baselines", config, BASELINE_DEFAULTS)
    device = resolve_device(cfg["device"])
    binning = cfg["detector_binning"] or auto_binning(train_vs, reference)
    # the validation views are binned like the iterative methods' detector: every method is scored the same way,
    # at a cost per score below one data sweep
    validator = Validator(*bin_detector(val_p, val_vs, binning), reference, device=device)
    usable = applicable_methods(train_vs)
    wanted = [m for m in METHODS if m in cfg["methods"]]
    run = [m for m in wanted if m in usable]
    if wanted and not run:
        raise CtsplatError(f"baselines methods {wanted} (baselines.settings.methods in a workflow config) cannot "
                           f"reconstruct this geometry ({train_vs.camera.model} beam, orbit "
                           f"{train_vs.meta.get('orbit', '?')}); it allows {', '.join(usable)}")
    for m in wanted:
        if m not in usable:
            log.info("baselines: %s does not apply to this geometry; skipped", m)
    clip = bool(cfg["clip"])
    amounts = [float(a) for a in cfg["sharpen"]["amounts"]]
    radius = float(cfg["sharpen"]["radius_voxels"])
    filters = _as_list(cfg["fbp_filters"])
    patience = int(cfg["patience"]) if cfg["patience"] else None
    it_p, it_vs = bin_detector(train_p, train_vs, binning)
    common = {"device": device, "step_voxels": float(cfg["step_voxels"])}
    out: list[Choice] = []
    for method in run:
        if method == "fbp":
            c = choose("fbp", ({"filter": f} for f in filters),
                       lambda filter: fbp_volume(train_p, train_vs, reference, filter_name=filter, clip=clip),
                       validator, clip=clip)
        elif method == "fdk":
            c = choose("fdk", ({"filter": f} for f in filters),
                       lambda filter: fdk_volume(train_p, train_vs, reference, filter_name=filter, clip=clip,
                                                 device=device), validator, clip=clip)
        elif method == "sart" and "fbp" in usable:
            def slice_sart(relaxation: float) -> Any:
                return sart_volumes(train_p, train_vs, reference, iterations=cfg["sart_max_iterations"],
                                    relaxation=relaxation, clip=False)

            c = choose_iterative("sart", ({"relaxation": float(r)} for r in _as_list(cfg["sart_relaxation"])),
                                 slice_sart, validator, clip=clip, patience=patience)
        elif method == "sart":
            def sart3d(relaxation: float, subsets: int) -> Any:
                return sart_iterates(it_p, it_vs, reference, iterations=cfg["sart_max_iterations"],
                                     relaxation=relaxation, subsets=subsets, **common)

            c = choose_iterative("sart", ({"relaxation": float(r), "subsets": int(cfg["sart_subsets"])}
                                          for r in _as_list(cfg["sart_relaxation"])),
                                 sart3d, validator, clip=clip, patience=patience)
            c.params["detector_binning"] = binning
        elif method == "asd_pocs":
            def asd(alpha: float, tv_steps: int, subsets: int) -> Any:
                return asd_pocs_iterates(it_p, it_vs, reference, iterations=cfg["asd_pocs_iterations"], alpha=alpha,
                                         tv_steps=tv_steps, subsets=subsets, **common)

            c = choose_iterative("asd_pocs", ({"alpha": float(a), "tv_steps": int(cfg["asd_pocs_tv_steps"]),
                                               "subsets": int(cfg["asd_pocs_subsets"])}
                                              for a in _as_list(cfg["asd_pocs_alpha"])),
                                 asd, validator, clip=clip, patience=patience)
            c.params["detector_binning"] = binning
        else:  # mbir
            why = svmbir_available()
            if why:
                log.warning("baselines: MBIR skipped: %s", why)
                continue
            if work_dir is not None:
                Path(work_dir).mkdir(parents=True, exist_ok=True)
            with scratch_dir(work_dir, prefix="svmbir-") as tmp:
                grid = [{"sharpness": float(s), "snr_db": float(q)} for s in _as_list(cfg["mbir_sharpness"])
                        for q in _as_list(cfg["mbir_snr_db"])]
                c = choose("mbir", grid, lambda sharpness, snr_db, cache=tmp: mbir_volume(
                    train_p, train_vs, reference, sharpness=sharpness, snr_db=snr_db, clip=clip, lib_path=cache,
                    max_iterations=int(cfg["mbir_max_iterations"]), num_threads=int(cfg["mbir_threads"])),
                    validator, clip=clip)
        if any(amounts):
            c = sharpened(c, validator, amounts=amounts, radius_voxels=radius, clip=clip)
        log.info("baselines: %s chose %s (validation PSNR %.2f dB, %.1f s)", c.method, c.params, c.val_psnr,
                 c.seconds)
        out.append(c)
    return out


def sharpened(choice: Choice, validator: Validator, *, amounts: list[float], radius_voxels: float,
              clip: bool = True) -> Choice:
    """A method's chosen reconstruction sharpened by the amount its validation views prefer.

    The rule of the Gaussians' read-out (:func:`ctsplat.evaluation.readout.choose_sharpening`): unsharp masking
    with each of ``amounts`` (0 keeps the reconstruction), the best re-projection PSNR on the validation views wins.

    Parameters
    ----------
    choice : Choice
        The method's choice (its volume on the reference grid).
    validator : Validator
        The validation views the parameters were chosen on.
    amounts : list of float
        Candidate amounts.
    radius_voxels : float
        Blur radius (voxels).
    clip : bool
        Clip the candidates to [0, 1] (the baselines' ``clip``).

    Returns
    -------
    Choice
        The same method with the chosen volume, its validation PSNR, ``params["sharpen_amount"]``, the chosen
        amount's filtering time added to ``seconds`` and every amount's to ``selection_seconds`` (validation scoring
        excluded, as for the method's own candidates), and one trial per amount.
    """
    from ctsplat.evaluation.readout import choose_sharpening

    volume, info = choose_sharpening(choice.volume, validator, amounts=amounts, radius_voxels=radius_voxels, clip=clip)
    scores, filtering = info["sharpen_val_psnr"], info["sharpen_filter_seconds"]
    k = amounts.index(info["sharpen_amount"])
    trials = [*choice.trials, *({"method": choice.method, **choice.params, "sharpen_amount": a, "val_psnr": v,
                                 "seconds": sec} for a, v, sec in zip(amounts, scores, filtering, strict=True))]
    return replace(choice, params={**choice.params, "sharpen_amount": amounts[k]}, val_psnr=scores[k],
                   volume=volume, seconds=choice.seconds + filtering[k],
                   selection_seconds=choice.selection_seconds + sum(filtering), trials=trials)


def best_choice(choices: list[Choice]) -> Choice | None:
    """The choice with the highest validation PSNR (the "best classical" reconstruction), or None."""
    return max(choices, key=lambda c: rank(c.val_psnr)) if choices else None
