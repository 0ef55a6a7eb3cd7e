"""``ctsplat phantom`` and ``ctsplat ingest``: the built-in phantom as DICOM, and CT ingestion."""

from __future__ import annotations

import argparse
import math
import sys

from ctsplat.cli._common import load_section, seed_value
from ctsplat.utils import CtsplatError


def _numbers(text: str, kind: type, form: str, *, shown: str | None = None) -> list:
    """The comma-separated numbers of an option value; anything else is argparse's one-line error naming ``form``
    and the value as typed (``shown``, default ``text``)."""
    try:
        return [kind(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be {form}, got {text if shown is None else shown!r}") from None


def _grid(text: str) -> int | list[int]:
    parts = _numbers(",".join(x for x in text.replace("x", ",").split(",") if x), int,
                     "N or I,J,K (whole numbers, e.g. 128 or 128,128,96)", shown=text)
    if len(parts) == 1:
        return parts[0]
    if len(parts) == 3:
        return parts
    raise argparse.ArgumentTypeError(f"must be N or I,J,K (e.g. 128 or 128,128,96), got {text!r}")


def _window(text: str) -> str | list[float]:
    if "," in text:
        parts = _numbers(text, float, "a preset name or LEVEL,WIDTH in HU (e.g. 40,80)")
        if len(parts) != 2:
            raise argparse.ArgumentTypeError(f"must be a preset name or LEVEL,WIDTH in HU (e.g. 40,80), got {text!r}")
        return parts
    return text


def _rescale(text: str) -> list[float]:
    parts = _numbers(text, float, "SLOPE,INTERCEPT (e.g. 1,-1024)")
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"must be SLOPE,INTERCEPT (e.g. 1,-1024), got {text!r}")
    if not all(math.isfinite(x) for x in parts):
        raise argparse.ArgumentTypeError(f"rescale SLOPE,INTERCEPT must be finite numbers (e.g. 1,-1024), got {text}")
    if not parts[0] > 0:
        raise argparse.ArgumentTypeError(f"rescale SLOPE must be > 0, got {parts[0]:g}")
    return parts


def _voxel(text: str) -> float | list[float]:
    parts = _numbers(text, float, "S or X,Y,Z in mm (e.g. 0.5,0.5,1.25)")
    if len(parts) not in (1, 3) or not all(math.isfinite(x) and x > 0 for x in parts):
        raise argparse.ArgumentTypeError(f"voxel size must be S or X,Y,Z in mm, each a finite number > 0 (e.g. "
                                         f"0.5,0.5,1.25), got {text}")
    return parts[0] if len(parts) == 1 else parts


# bead options of `ctsplat phantom` and their defaults (None on the parser, so that a given one is recognised)
BEAD_DEFAULTS = {"n_beads": 12, "bead_radius_mm": 3.0}


def run_phantom(args: argparse.Namespace) -> None:
    from ctsplat.config import check_values, load_schema
    from ctsplat.phantom import write_phantom_dicom

    given = [k for k in BEAD_DEFAULTS if getattr(args, k) is not None]
    if args.no_beads and given:
        raise CtsplatError(f"--{given[0].replace('_', '-')} has no effect with --no-beads; drop one of them")
    beads = {k: BEAD_DEFAULTS[k] if getattr(args, k) is None else getattr(args, k) for k in BEAD_DEFAULTS}
    settings = {"size": args.size, "seed": args.seed, "fov_mm": args.fov_mm, **beads}
    # the ranges of the workflow's volumes.<name>.phantom section
    check_values(settings, load_schema()["properties"]["volumes"]["additionalProperties"]["properties"]["phantom"],
                 "phantom")
    out = write_phantom_dicom(args.out_dir, beads=not args.no_beads, variant=args.variant, force=args.force,
                              **settings)
    print(out)


def _check_ingest_options(args: argparse.Namespace, cfg: dict) -> None:
    """Refuse options that would have no effect (combinations, or options of another input kind)."""
    from ctsplat.config import schema_defaults

    if args.native and (args.voxel_size_mm is not None or args.grid is not None):
        raise CtsplatError("--native keeps the scan's spacing: drop --voxel-size / --grid, or drop --native")
    if args.voxel_size_mm is not None and args.grid is not None:
        raise CtsplatError("give either --voxel-size (isotropic voxels of that size) or --grid (that many voxels), "
                           "not both")
    intensity = cfg.get("intensity", schema_defaults("preprocessing")["intensity"])
    for option, key, used_by in (("--window", "window", ("window",)), ("--hu-max", "hu_max", ("attenuation", "mu")),
                                 ("--mu-water", "mu_water_per_mm", ("attenuation", "mu", "window"))):
        if getattr(args, key) is not None and intensity not in used_by:
            raise CtsplatError(f"{option} only applies to intensity {' / '.join(used_by)}, not {intensity}; add "
                               f"--intensity {used_by[0]} or drop {option}")
    from ctsplat.formats.sources import SOURCE_KIND_KEYS, source_kind

    kind = source_kind(args.source)
    options = {"series_uid": ("--series-uid", args.series_uid), "rescale": ("--rescale", args.rescale),
               "allow_modalities": ("--allow-modality", args.allow_modality),
               "skip_corrupt": ("--skip-corrupt", args.skip_corrupt or None),
               "tiff_voxel_size_mm": ("--tiff-voxel-size", args.tiff_voxel_size)}
    for key, wants in SOURCE_KIND_KEYS.items():
        option, value = options[key]
        if value is not None and kind != wants:
            raise CtsplatError(f"{option} applies to {wants.upper()} input only, not {args.source}; drop it")


def run_ingest(args: argparse.Namespace) -> None:
    from ctsplat.config import check_section
    from ctsplat.formats.sources import find_dicom_series
    from ctsplat.volume import ingest

    if args.list_series:
        # Series are listed by id (the salted hash of the SeriesInstanceUID, as in volume.json), never by UID.
        series = find_dicom_series(args.source, skip_corrupt=args.skip_corrupt)
        for s in series:
            print(s.label())
        if len(series) > 1:
            print("choose one with --series-uid ID (workflow config: series_uid: ID)", file=sys.stderr)
        return
    cfg = load_section(args.config, "preprocessing")
    for key in ("voxel_size_mm", "grid", "intensity", "window", "denoise", "mask", "hu_max", "mu_water_per_mm"):
        value = getattr(args, key)
        if value is not None:
            cfg[key] = value
    if args.native:
        cfg["voxel_size_mm"], cfg["grid"] = None, None
    # an option on the command line replaces the file's choice of output grid, whichever key the file used
    if args.voxel_size_mm is not None:
        cfg["grid"] = None
    if args.grid is not None:
        cfg["voxel_size_mm"] = None
    _check_ingest_options(args, cfg)
    check_section("preprocessing", cfg)
    if args.out is None:
        raise CtsplatError("give the output path OUT (e.g. results/head/volume.nii.gz)")
    vol = ingest(
        args.source, args.out, cfg, series_uid=args.series_uid,
        allow_modalities=tuple(["CT", *(args.allow_modality or [])]),
        skip_corrupt=args.skip_corrupt, tiff_voxel_size_mm=args.tiff_voxel_size, rescale=args.rescale,
        nonfinite=args.nonfinite,
    )
    sp = ", ".join(f"{x:.3f}" for x in vol.spacing_mm)
    print(f"{args.out}: shape {vol.shape}, voxel ({sp}) mm, volume_id {vol.volume_id}")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "phantom",
        help="write the built-in 3D Shepp-Logan head phantom as a DICOM CT series",
        description="Write the analytic 3D Shepp-Logan head (Kak-Slaney; ~200 mm) with optional dense bead "
        "markers as a real DICOM CT series (one file per slice) plus phantom.json (ellipsoids in world mm).",
    )
    p.add_argument("out_dir", help="output folder: new, empty, or a previous phantom output (its files are replaced)")
    p.add_argument("--size", type=int, default=128, help="voxels per axis (slices and rows/columns; default 128)")
    p.add_argument("--fov-mm", type=float, default=240.0, help="field of view edge in mm (default 240)")
    p.add_argument("--no-beads", action="store_true", help="leave out the bead markers")
    p.add_argument("--n-beads", type=int, help=f"number of beads (default {BEAD_DEFAULTS['n_beads']})")
    p.add_argument("--bead-radius-mm", type=float,
                   help=f"bead radius in mm (default {BEAD_DEFAULTS['bead_radius_mm']:g})")
    p.add_argument("--seed", type=seed_value, default=0, help="seed of the bead positions (default 0)")
    p.add_argument("--variant", choices=["kak_slaney", "high_contrast"], default="kak_slaney",
                   help="ellipsoid values: physical Kak-Slaney (default) or high-contrast")
    p.add_argument("--force", action="store_true",
                   help="write into a non-empty folder that is not a previous phantom output (other files are "
                   "kept, phantom.json and slice_NNNN.dcm replaced)")
    p.set_defaults(func=run_phantom)

    q = subparsers.add_parser(
        "ingest",
        help="CT scan (DICOM folder, NIfTI, TIFF stack) -> preprocessed NIfTI volume + volume.json",
        description="Read a CT scan, resample it in world coordinates to an isotropic grid, map HU to "
        "attenuation (or a window), normalise to [0, 1] and write NIfTI-1 + provenance JSON atomically. "
        "Identifying DICOM fields never reach the outputs.",
    )
    q.add_argument("source", help="DICOM folder (searched recursively), .nii/.nii.gz file, .tif stack or TIFF folder")
    q.add_argument("out", nargs="?", help="output NAME.nii.gz (its sidecar NAME.json, read by later steps, beside it)")
    q.add_argument("--config", help="YAML/JSON file with preprocessing options (the section or {preprocessing: ...})")
    q.add_argument("--voxel-size", dest="voxel_size_mm", type=float, help="isotropic voxel size in mm")
    q.add_argument("--grid", type=_grid, help="target grid N (N^3) or I,J,K with isotropic voxels (default 128)")
    q.add_argument("--native", action="store_true", help="keep the scan's spacing (median slice gap)")
    q.add_argument("--intensity", choices=["attenuation", "window", "mu", "hu"],
                   help="value mapping (default attenuation: mu/mu_max in [0, 1])")
    q.add_argument("--window", type=_window, help="window preset (brain, soft_tissue, bone, lung) or LEVEL,WIDTH "
                   "(a negative level with '=': --window=-600,1500)")
    q.add_argument("--hu-max", dest="hu_max", type=float,
                   help="HU mapped to 1.0 by attenuation, and where mu clips (default 3000)")
    q.add_argument("--mu-water", dest="mu_water_per_mm", type=float,
                   help="mu of water in 1/mm (default 0.019); with --intensity window it sets the window top's mu, "
                        "the radiographs' scale")
    q.add_argument("--denoise", choices=["tv", "bilateral"], help="optional denoising")
    q.add_argument("--mask", choices=["otsu", "convex_hull"], help="optional body mask; air outside")
    q.add_argument("--series-uid", metavar="ID",
                   help="the series to read when the folder holds several: its id as --list-series shows it, its "
                   "SeriesInstanceUID or its SeriesNumber")
    q.add_argument("--list-series", action="store_true",
                   help="list the DICOM series found (id, number, description, modality, files) and exit; ids are "
                   "salted hashes of the SeriesInstanceUIDs, as in volume.json")
    q.add_argument("--allow-modality", action="append", metavar="MOD", help="accept a non-CT modality (e.g. MR)")
    q.add_argument("--skip-corrupt", action="store_true", help="skip unreadable DICOM files with a warning")
    q.add_argument("--tiff-voxel-size", type=_voxel, help="TIFF stack voxel size in mm: S or X,Y,Z")
    q.add_argument("--rescale", type=_rescale, metavar="SLOPE,INTERCEPT",
                   help="DICOM slices without RescaleSlope/RescaleIntercept: HU = stored * SLOPE + INTERCEPT "
                   "(1,0 if the stored values are HU); without it such CT slices must look like HU")
    q.add_argument("--nonfinite", choices=["error", "fill_min"], default="error",
                   help="NaN/Inf source voxels: error (default, names how many and where) or fill_min (replace "
                   "them by the smallest finite value; recorded in volume.json)")
    q.set_defaults(func=run_ingest)
