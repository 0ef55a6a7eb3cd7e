"""Orbits: where the views of a view set are, and which split each belongs to.

Three orbit families, all about the world +z (axial) axis through an isocentre, in world mm
(``docs/conventions.md``):

- :func:`circular_orbit` — the classical CT protocol: evenly spaced training angles plus seeded held-out angles;
- :func:`sphere_orbit` — directions spread over an elevation band (Fibonacci or stratified), split by direction;
- :func:`carm_orbit` — a designed C-arm cone-beam orbit with a sinusoidal elevation wobble, whose true poses
  deviate from the design by a seeded per-view error (what SfM must recover).

One arc rule (:func:`arc_azimuths`) places evenly spaced views on an arc for every family: view ``k`` of ``n``
sits at ``start + arc · k / n`` — the start of ``n`` equal sectors, so a full circle closes without a repeated
view, and a parallel-beam half circle gives ``n`` distinct directions.

References
----------
González, Á. (2010). Measurement of areas on a sphere using Fibonacci and latitude-longitude lattices.
Mathematical Geosciences 42(1), 49-64. (The equal-area Fibonacci lattice of :func:`fibonacci_directions`.)
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ctsplat.formats.viewset import SPLITS, View
from ctsplat.geometry.cameras import Camera, look_at, pose_from_angles, project_points
from ctsplat.utils import CtsplatError

__all__ = [
    "check_orbit_settings",
    "check_held_out_views",
    "classical_methods",
    "has_held_out_views",
    "arc_azimuths",
    "unwrap_arc",
    "fibonacci_directions",
    "stratified_directions",
    "split_counts",
    "assign_splits",
    "sphere_orbit",
    "circular_orbit",
    "carm_orbit",
    "support_radius_mm",
    "fov_outside_fraction",
    "check_fov",
    "object_points_mm",
    "covering_spacing_mm",
]


def check_orbit_settings(cfg: Mapping[str, Any], where: str = "radiographs") -> None:
    """Check the settings of one radiographs geometry that do not depend on the volume.

    Run by the projector before it builds a view set, and by the workflow on every geometry before any job runs.

    Parameters
    ----------
    cfg : mapping
        One geometry's settings with the defaults filled (``orbit``, ``camera``, ``n_val``, ``n_test``,
        ``pixel_spacing_mm``, ``detector_size_factor``).
    where : str
        Key path shown in the error (``radiographs.circular``).

    Raises
    ------
    CtsplatError
        For an unknown orbit or camera, a C-arm orbit on a parallel camera, held-out counts on an orbit that
        splits by fractions, or both detector-size settings.

    Examples
    --------
    >>> check_orbit_settings({"orbit": "carm", "camera": "parallel"}, "radiographs.carm")
    Traceback (most recent call last):
    ...
    ctsplat.utils.CtsplatError: radiographs.carm: orbit carm needs camera: cone (a C-arm is a cone-beam scanner)
    """
    orbit, camera = cfg.get("orbit"), cfg.get("camera")
    if orbit not in ("circular", "sphere", "carm"):
        raise CtsplatError(f"{where}: unknown orbit {orbit!r}; allowed: circular, sphere, carm")
    if camera not in ("parallel", "cone"):
        raise CtsplatError(f"{where}: unknown camera {camera!r}; allowed: parallel, cone")
    if orbit == "carm" and camera != "cone":
        raise CtsplatError(f"{where}: orbit carm needs camera: cone (a C-arm is a cone-beam scanner)")
    if orbit != "circular" and (cfg.get("n_val") is not None or cfg.get("n_test") is not None):
        raise CtsplatError(f"{where}: n_val / n_test set the held-out views of orbit: circular; orbit {orbit} "
                           "splits by the split fractions (set n_val and n_test to null)")
    if cfg.get("pixel_spacing_mm") is not None and cfg.get("detector_size_factor") is not None:
        raise CtsplatError(f"{where}: set pixel_spacing_mm or detector_size_factor, not both")
    if camera == "cone":  # the distances that do not depend on the volume's size (the projector checks the rest)
        dso, dsd = cfg.get("dso_mm"), cfg.get("dsd_mm")
        if dso is None and dsd is None:
            dso, dsd, unit = cfg.get("dso_factor"), cfg.get("dsd_factor"), "_factor"
        else:
            unit = "_mm"
        if isinstance(dso, int | float) and isinstance(dsd, int | float) and 0 < dsd <= dso:
            raise CtsplatError(f"{where}: dsd{unit} ({dsd:g}) must be larger than dso{unit} ({dso:g}): the detector "
                               "lies beyond the isocentre")


def check_held_out_views(cfg: Mapping[str, Any], where: str = "radiographs") -> None:
    """The split of a circular or sphere orbit's views, made as the projector makes it (it does not depend on the
    volume), so that the workflow reports a split left empty before any step runs; the projector, which builds the
    orbit anyway, needs no separate check.

    Parameters
    ----------
    cfg : mapping
        One geometry's settings with the defaults filled.
    where : str
        Key path shown in the error.

    Raises
    ------
    CtsplatError
        For a held-out split with a positive fraction that would receive no view.
    """
    orbit = cfg.get("orbit")
    if orbit not in ("circular", "sphere") or not isinstance(cfg.get("n_views"), int) or cfg["n_views"] <= 0:
        return
    kwargs: dict[str, Any] = {"split_fractions": cfg.get("split") or {"train": 1.0}, "seed": 0}
    try:
        if orbit == "circular":
            circular_orbit(int(cfg["n_views"]), np.zeros(3), 1000.0, **kwargs,
                           heldout_counts={"val": cfg.get("n_val"), "test": cfg.get("n_test")})
        else:
            sphere_orbit(int(cfg["n_views"]), np.zeros(3), 1000.0, **kwargs,
                         elevation_range_deg=cfg.get("elevation_range_deg", (-60.0, 60.0)),
                         sampling=cfg.get("sphere_sampling", "fibonacci"))
    except CtsplatError as exc:
        raise CtsplatError(f"{where}: {exc}") from None


def classical_methods(cfg: Mapping[str, Any]) -> tuple[str, ...]:
    """The classical reconstructions a geometry's settings admit, before any view is rendered.

    The settings' side of :func:`ctsplat.recon.suite.applicable_methods`, which decides on the rendered view set:
    a circular orbit without wobble (``wobble_deg`` or ``wobble_cycles`` 0) is planar, so parallel beams take the
    slice-wise methods and MBIR, cone beams FDK (which the suite still drops on a short scan under 180° plus the fan
    angle); every other orbit takes the 3D iterative methods only.

    Parameters
    ----------
    cfg : mapping
        One geometry's settings with the defaults filled (``orbit``, ``camera``, ``wobble_deg``,
        ``wobble_cycles``).

    Returns
    -------
    tuple of str
        Names of :data:`ctsplat.recon.suite.METHODS`.

    Examples
    --------
    >>> classical_methods({"orbit": "circular", "camera": "parallel", "wobble_deg": 0.0})
    ('fbp', 'sart', 'asd_pocs', 'mbir')
    >>> classical_methods({"orbit": "sphere", "camera": "cone", "wobble_deg": 0.0})
    ('sart', 'asd_pocs')
    """
    wobble = float(cfg.get("wobble_deg") or 0.0) * float(cfg.get("wobble_cycles", 2.0) or 0.0)
    planar = cfg.get("orbit") == "circular" and wobble == 0.0
    if planar and cfg.get("camera") == "parallel":
        return ("fbp", "sart", "asd_pocs", "mbir")
    if planar and cfg.get("camera") == "cone":
        return ("fdk", "sart", "asd_pocs")
    return ("sart", "asd_pocs")


def has_held_out_views(cfg: Mapping[str, Any], split: str) -> bool:
    """Whether a geometry's settings render ``val`` or ``test`` views.

    A circular orbit's ``n_val`` / ``n_test`` win over its split fractions; other orbits split by the fractions
    (a C-arm orbit renders training views only).

    Parameters
    ----------
    cfg : mapping
        One geometry's settings with the defaults filled (``orbit``, ``split``, ``n_val``, ``n_test``).
    split : {"val", "test"}

    Returns
    -------
    bool

    Examples
    --------
    >>> has_held_out_views({"orbit": "circular", "n_test": 0, "split": {"test": 0.15}}, "test")
    False
    """
    if cfg.get("orbit") == "carm":
        return False
    count = cfg.get(f"n_{split}")
    return int(count) > 0 if count is not None else float(cfg["split"].get(split, 0.0)) > 0


def arc_azimuths(n: int, arc_deg: float, start_deg: float = 0.0, offsets: np.ndarray | None = None, *,
                 wrap: bool = True) -> np.ndarray:
    """Azimuths (degrees, in [0, 360)) of ``n`` views evenly spaced over an arc: ``start + arc (k + o_k) / n``.

    Parameters
    ----------
    n : int
        Number of views (> 0).
    arc_deg : float
        Angular range in (0, 360].
    start_deg : float
        Azimuth of the first sector's start.
    offsets : ndarray, shape (n,), optional
        Position of each view inside its sector, in [0, 1) (0: the sector start; random offsets stratify).
    wrap : bool, keyword-only
        Wrap into [0, 360) (False: the angle along the arc, continuous where the arc crosses 0°).

    Returns
    -------
    ndarray, shape (n,)
        Azimuths (degrees), wrapped into [0, 360) unless ``wrap`` is False.

    Raises
    ------
    CtsplatError
        When ``arc_deg`` is outside (0, 360].

    Examples
    --------
    >>> arc_azimuths(4, 360.0)
    array([  0.,  90., 180., 270.])
    >>> arc_azimuths(4, 180.0, start_deg=10.0)
    array([ 10.,  55., 100., 145.])
    """
    if not 0 < arc_deg <= 360:
        raise CtsplatError(f"arc_deg {arc_deg} must be in (0, 360]")
    k = np.arange(int(n), dtype=float) + (0.0 if offsets is None else np.asarray(offsets, float))
    along = start_deg + arc_deg * k / int(n)
    return np.mod(along, 360.0) if wrap else along


def unwrap_arc(azimuth_deg: np.ndarray) -> np.ndarray:
    """Azimuths of views on an arc as angles from its first view: the arc starts after the largest gap between
    neighbouring views on the circle, so an arc that crosses 0° stays in one piece.

    Parameters
    ----------
    azimuth_deg : ndarray, shape (V,)
        Azimuths, degrees (any order, any turn).

    Returns
    -------
    ndarray, shape (V,)
        Degrees in [0, 360), 0 at the arc's first view.

    Examples
    --------
    >>> unwrap_arc(np.array([300.0, 350.0, 40.0, 90.0]))
    array([  0.,  50., 100., 150.])
    """
    a = np.mod(np.asarray(azimuth_deg, float), 360.0)
    s = np.sort(a)
    gaps = np.diff(np.concatenate([s, s[:1] + 360.0]))  # the gap after each sorted view, round the circle
    return np.mod(a - s[(int(np.argmax(gaps)) + 1) % len(s)], 360.0)


def fibonacci_directions(n: int, elevation_range_deg: Sequence[float] = (-60.0, 60.0),
                         azimuth_offset_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` (azimuth, elevation) pairs of a Fibonacci lattice on a spherical band.

    Equal-area: ``sin(e_k)`` uniform on ``[sin e_min, sin e_max]`` at midpoints, azimuth by the golden angle
    ``a_k = offset + k * 180 (3 - sqrt 5)``. Ordered by elevation (index ``k``).

    Parameters
    ----------
    n : int
        Number of directions.
    elevation_range_deg : sequence of float, shape (2,)
        ``(e_min, e_max)`` of the band (degrees).
    azimuth_offset_deg : float
        Azimuth of the first direction (degrees).

    Returns
    -------
    azimuth_deg : ndarray, shape (n,)
        Azimuths (degrees) in [0, 360).
    elevation_deg : ndarray, shape (n,)
        Elevations (degrees), increasing.
    """
    lo, hi = (math.sin(math.radians(x)) for x in elevation_range_deg)
    k = np.arange(n)
    z = lo + (hi - lo) * (k + 0.5) / n
    el = np.degrees(np.arcsin(z))
    az = np.mod(azimuth_offset_deg + k * 180.0 * (3.0 - math.sqrt(5.0)), 360.0)
    return az, el


def stratified_directions(n: int, elevation_range_deg: Sequence[float] = (-60.0, 60.0),
                          rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``n`` (azimuth, elevation) pairs, one random direction per equal-area cell of a spherical band.

    The band is cut into ``b = round(sqrt(n / 2))`` rings of equal area (uniform in ``sin e``); ring ``r``
    gets ``n_r`` cells (the ``n mod b`` first rings one more than ``n // b``), each an azimuth sector (rotated by a
    random offset per ring); one uniform point (in azimuth and ``sin e``) per cell.

    Parameters
    ----------
    n : int
        Number of directions.
    elevation_range_deg : sequence of float, shape (2,)
        ``(e_min, e_max)`` of the band (degrees).
    rng : numpy.random.Generator, optional
        Source of randomness; default ``default_rng(0)``.

    Returns
    -------
    azimuth_deg : ndarray, shape (n,)
        Azimuths (degrees) in [0, 360).
    elevation_deg : ndarray, shape (n,)
        Elevations (degrees), ordered by ring.
    """
    rng = rng or np.random.default_rng(0)
    lo, hi = (math.sin(math.radians(x)) for x in elevation_range_deg)
    b = max(1, round(math.sqrt(n / 2)))
    per = np.full(b, n // b)
    per[: n - per.sum()] += 1
    az, z = [], []
    for r, m in enumerate(per):
        if m == 0:
            continue
        z0 = lo + (hi - lo) * r / b
        z1 = lo + (hi - lo) * (r + 1) / b
        off = rng.uniform(0, 360.0 / m)
        az.append(np.mod(off + 360.0 * (np.arange(m) + rng.uniform(0, 1, m)) / m, 360.0))
        z.append(rng.uniform(z0, z1, m))
    return np.concatenate(az), np.degrees(np.arcsin(np.concatenate(z)))


def _check_elevation_range(elevation_range_deg: Sequence[float]) -> tuple[float, float]:
    if len(elevation_range_deg) != 2:
        raise CtsplatError(f"elevation_range_deg must be [min, max], got {elevation_range_deg!r}")
    lo, hi = float(elevation_range_deg[0]), float(elevation_range_deg[1])
    if not (-90.0 < lo <= hi < 90.0):
        raise CtsplatError(f"elevation_range_deg {[lo, hi]} must satisfy -90 < min <= max < 90")
    return lo, hi


def _more_views(split: str) -> str:
    """The advice for a split left empty: test views are needed (a run is scored on them), validation views not."""
    more = f"use more views (n_views) or a larger {split} fraction"
    return more + (", or set val: 0 (no validation views)" if split == "val" else "")


def split_counts(n: int, fractions: dict[str, float]) -> dict[str, int]:
    """Largest-remainder allocation of ``n`` views to ``train/val/test`` by ``fractions``.

    Parameters
    ----------
    n : int
        Number of views.
    fractions : dict of str to float
        Split name -> non-negative weight (normalised to sum 1); missing splits get 0.

    Returns
    -------
    dict of str to int
        ``{"train": ..., "val": ..., "test": ...}``, summing to ``n``.

    Raises
    ------
    CtsplatError
        For an unknown split name, negative or all-zero fractions, or a split with a positive fraction that would
        receive no view (use more views or set its fraction to 0).

    Examples
    --------
    >>> split_counts(10, {"train": 0.7, "val": 0.15, "test": 0.15})
    {'train': 7, 'val': 2, 'test': 1}
    """
    unknown = set(fractions) - set(SPLITS)
    if unknown:
        raise CtsplatError(f"unknown split name {sorted(unknown)[0]!r}; allowed: {', '.join(SPLITS)}")
    f = np.array([float(fractions.get(s, 0.0)) for s in SPLITS])
    if np.any(f < 0) or f.sum() <= 0:
        raise CtsplatError(f"split fractions {fractions} must be non-negative and not all zero")
    f = f / f.sum()
    raw = f * n
    counts = np.floor(raw).astype(int)
    order = np.argsort(-(raw - counts), kind="stable")
    counts[order[: n - counts.sum()]] += 1
    out = dict(zip(SPLITS, (int(c) for c in counts), strict=True))
    for s, frac in zip(SPLITS, f, strict=True):
        if frac > 0 and out[s] == 0:
            raise CtsplatError(f"split leaves '{s}' empty: {n} views with fractions "
                               f"{dict(zip(SPLITS, f.round(3).tolist(), strict=True))}; {_more_views(s)}")
    return out


def assign_splits(azimuth_deg: np.ndarray, elevation_deg: np.ndarray, fractions: dict[str, float],
                  seed: int = 0) -> list[str]:
    """Seeded train/val/test labels, stratified over view direction.

    Views are ordered along the sphere (elevation rings of ``~sqrt(2n)`` views, azimuth inside each ring,
    serpentine). The test views are drawn one at random from each of ``n_test`` consecutive equal strata of
    that order, then the val views likewise from the remaining views, so held-out directions are spread
    over the orbit rather than clumped. Same inputs and seed -> same labels.

    Parameters
    ----------
    azimuth_deg, elevation_deg : ndarray, shape (V,)
        View directions (degrees).
    fractions : dict of str to float
        Split weights, see :func:`split_counts`.
    seed : int
        Seeds the draw within each stratum.

    Returns
    -------
    list of str, length V
        ``"train"``, ``"val"`` or ``"test"`` per view, in input order.

    Raises
    ------
    CtsplatError
        For an empty view set or invalid fractions (:func:`split_counts`).
    """
    az = np.asarray(azimuth_deg, float)
    el = np.asarray(elevation_deg, float)
    n = az.size
    if n == 0:
        raise CtsplatError("empty view set: need at least one view (check n_views)")
    counts = split_counts(n, fractions)
    rng = np.random.default_rng(seed)
    n_rings = max(1, round(math.sqrt(n / 2)))
    if np.ptp(el) < 1e-6:
        order = np.argsort(np.mod(az, 360.0), kind="stable")
    else:
        zr = np.sin(np.radians(el))
        ring = np.minimum(((zr - zr.min()) / (np.ptp(zr) + 1e-12) * n_rings).astype(int), n_rings - 1)
        key_az = np.where(ring % 2 == 0, np.mod(az, 360.0), -np.mod(az, 360.0))
        order = np.lexsort((key_az, ring))
    labels = np.array(["train"] * n, dtype=object)
    remaining = list(order)
    for split in ("test", "val"):
        m = counts[split]
        if m == 0:
            continue
        bounds = np.floor(np.linspace(0, len(remaining), m + 1)).astype(int)
        picks = [remaining[b0 + int(rng.integers(0, max(1, b1 - b0)))]
                 for b0, b1 in zip(bounds[:-1], bounds[1:], strict=True)]
        for p in picks:
            labels[p] = split
        chosen = set(picks)
        remaining = [r for r in remaining if r not in chosen]
    return [str(s) for s in labels]


def _views_from_angles(az: np.ndarray, el: np.ndarray, splits: list[str], isocenter_mm: Sequence[float],
                       distance_mm: float) -> list[View]:
    views = []
    for i, (a, e, s) in enumerate(zip(az, el, splits, strict=True)):
        R, t = pose_from_angles(float(a), float(e), isocenter_mm, distance_mm)
        views.append(View(i, R, t, float(a), float(e), s))
    return views


def sphere_orbit(n_views: int, isocenter_mm: Sequence[float], distance_mm: float, *,
                 elevation_range_deg: Sequence[float] = (-60.0, 60.0), sampling: str = "fibonacci",
                 split_fractions: dict[str, float] | None = None, seed: int = 0) -> list[View]:
    """``n_views`` directions spread evenly over azimuth and elevation within the elevation limits.

    ``sampling="fibonacci"`` (equal-area golden-angle lattice, its azimuth rotated by a seeded offset) or
    ``"stratified"`` (one random direction per equal-area cell). Splits by :func:`assign_splits`.
    Cameras sit at ``distance_mm`` from the isocentre (DSO for cone beam).

    Parameters
    ----------
    n_views : int
        Number of views (train + val + test), positive.
    isocenter_mm : sequence of float, shape (3,)
        Isocentre, world mm.
    distance_mm : float
        Camera-centre distance from the isocentre (mm).
    elevation_range_deg : sequence of float, shape (2,)
        ``(min, max)`` elevation (degrees), ``-90 < min <= max < 90``.
    sampling : {"fibonacci", "stratified"}
        How directions are placed, see above.
    split_fractions : dict of str to float, optional
        Split weights; default 70/15/15 train/val/test.
    seed : int
        Seeds the lattice offset or the stratified draw, and the split assignment.

    Returns
    -------
    list of View, length ``n_views``
        View ``i`` has id ``i``, ordered as the sampler returns them (by elevation ring).

    Raises
    ------
    CtsplatError
        For a non-positive ``n_views``, a bad elevation range, an unknown sampling or invalid split fractions.
    """
    if int(n_views) <= 0:
        raise CtsplatError(f"n_views must be a positive integer, got {n_views!r} (empty view set)")
    lo, hi = _check_elevation_range(elevation_range_deg)
    rng = np.random.default_rng(seed)
    if sampling == "fibonacci":
        az, el = fibonacci_directions(int(n_views), (lo, hi), azimuth_offset_deg=float(rng.uniform(0, 360)))
    elif sampling == "stratified":
        az, el = stratified_directions(int(n_views), (lo, hi), rng)
    else:
        raise CtsplatError(f"unknown sphere sampling {sampling!r}; allowed: fibonacci, stratified")
    splits = assign_splits(az, el, split_fractions or {"train": 0.7, "val": 0.15, "test": 0.15}, seed)
    return _views_from_angles(az, el, splits, isocenter_mm, distance_mm)


def circular_orbit(n_views: int, isocenter_mm: Sequence[float], distance_mm: float, *,
                   split_fractions: dict[str, float] | None = None, wobble_deg: float = 0.0,
                   start_deg: float = 0.0, seed: int = 0, arc_deg: float = 360.0,
                   wobble_cycles: float = 2.0, heldout_counts: dict[str, int | None] | None = None) -> list[View]:
    """Classical CT protocol: ``n_views`` training angles evenly over 360 deg plus random held-out angles.

    Training view ``k`` has azimuth ``start + 360 k / n_views`` about the world +z (axial) axis, so the
    training set is exactly what FBP/SART expect. Held-out (val/test) views are added at seeded random
    angles, one uniform angle per equal azimuth sector (stratified), with counts chosen so that the
    whole set follows ``split_fractions`` (train fraction = ``n_views`` / total; default 70/15/15, e.g.
    50 train + 11 val + 11 test). ``wobble_deg > 0`` adds an elevation ``wobble * sin(wobble_cycles * azimuth)``
    to all views (a non-planar orbit; not usable for slice-wise FBP).

    ``arc_deg`` (default 360) is the angular range of the training angles (``start + arc k / n_views``)
    and of the held-out sectors. For *parallel* beams the views at ``a`` and ``a + 180`` are mirror images,
    so over 360 deg an even ``n_views`` gives only ``n_views / 2`` distinct directions while an odd one
    gives ``n_views`` interleaved ones; ``arc_deg=180`` gives ``n_views`` distinct directions for any count.

    Parameters
    ----------
    n_views : int
        Number of training views, positive.
    isocenter_mm : sequence of float, shape (3,)
        Isocentre, world mm.
    distance_mm : float
        Camera-centre distance from the isocentre (mm).
    split_fractions : dict of str to float, optional
        Split weights with a positive ``train``; default 70/15/15.
    wobble_deg : float
        Elevation amplitude (degrees), ``|wobble_deg| < 90``; 0 keeps the orbit planar.
    start_deg : float
        Azimuth of training view 0 (degrees).
    seed : int
        Seeds the held-out angles.
    arc_deg : float
        Angular range (degrees) in (0, 360].
    wobble_cycles : float
        Wobble periods per 360 degrees of azimuth.
    heldout_counts : dict, optional
        ``{"val": n, "test": m}``: explicit held-out counts (>= 0) that replace the ones the fractions give; a
        missing or ``None`` entry keeps the fraction's count. The held-out angles stay stratified: one uniform
        random angle per equal sector, so each is uniformly distributed over the arc.

    Returns
    -------
    list of View
        The ``n_views`` training views (id ``k`` at azimuth ``start + arc k / n_views``), then the val views, then
        the test views.

    Raises
    ------
    CtsplatError
        For an arc outside (0, 360], a non-positive ``n_views``, ``|wobble_deg| >= 90``, invalid fractions or a
        held-out split that would be empty.

    Examples
    --------
    >>> views = circular_orbit(4, [0.0, 0.0, 0.0], 500.0, split_fractions={"train": 0.5, "val": 0.25, "test": 0.25})
    >>> [v.split for v in views]
    ['train', 'train', 'train', 'train', 'val', 'val', 'test', 'test']
    """
    if not 0 < arc_deg <= 360:
        raise CtsplatError(f"arc_deg {arc_deg} must be in (0, 360]")
    if int(n_views) <= 0:
        raise CtsplatError(f"n_views must be a positive integer, got {n_views!r} (empty view set)")
    if abs(wobble_deg) >= 90:
        raise CtsplatError(f"wobble_deg {wobble_deg} must be below 90 degrees")
    fr = {s: float((split_fractions or {"train": 0.7, "val": 0.15, "test": 0.15}).get(s, 0.0)) for s in SPLITS}
    unknown = set(split_fractions or {}) - set(SPLITS)
    if unknown:
        raise CtsplatError(f"unknown split name {sorted(unknown)[0]!r}; allowed: {', '.join(SPLITS)}")
    if fr["train"] <= 0 or min(fr.values()) < 0:
        raise CtsplatError(f"circular orbit needs a positive train fraction and non-negative others, got {fr}")
    n = int(n_views)
    held = {s: (round(n * fr[s] / fr["train"]) if fr[s] > 0 else 0) for s in ("val", "test")}
    explicit = {s: c for s, c in (heldout_counts or {}).items() if c is not None}
    for s, c in explicit.items():
        if s not in ("val", "test") or isinstance(c, bool) or not isinstance(c, int | np.integer) or c < 0:
            raise CtsplatError(f"n_{s} must be an integer >= 0 (held-out views of a circular orbit), got {c!r}")
        held[s] = int(c)
    for s in ("val", "test"):
        if s not in explicit and fr[s] > 0 and held[s] == 0:
            raise CtsplatError(f"split leaves '{s}' empty: {n} training views with fractions {fr}; "
                               f"{_more_views(s)}, or give n_{s}")
    rng = np.random.default_rng(seed)
    az = [arc_azimuths(n, arc_deg, start_deg, wrap=False)]
    splits = ["train"] * n
    for s in ("val", "test"):
        m = held[s]
        if m:
            az.append(arc_azimuths(m, arc_deg, start_deg, rng.uniform(0, 1, m), wrap=False))
            splits += [s] * m
    along = np.concatenate(az)
    azimuth = np.mod(along, 360.0)
    # the wobble follows the angle along the orbit: on the wrapped azimuth an arc crossing 0° would jump there
    elevation = (wobble_deg * np.sin(np.radians(wobble_cycles * along)) if wobble_deg
                 else np.zeros_like(azimuth))
    return _views_from_angles(azimuth, elevation, splits, isocenter_mm, distance_mm)


def carm_orbit(n_views: int, isocenter_mm: Sequence[float], dso_mm: float, *, arc_deg: float = 360.0,
               start_deg: float = 0.0, wobble_deg: float = 15.0, wobble_cycles: float = 2.0,
               jitter_deg: float = 0.0, jitter_mm: float = 0.0, seed: int = 0) -> list[View]:
    """A designed C-arm cone-beam orbit and the true poses of its views, which deviate from the design.

    Designed view ``i``: azimuth φ_i from :func:`arc_azimuths`, elevation θ_i = wobble · sin(cycles · a_i) with
    ``a_i`` the angle along the arc from ``start_deg`` (φ_i unwrapped, so that the elevation stays continuous where
    the arc crosses 0°; equal to φ_i on an arc that does not, or with whole cycles), source at ``c_i = iso + DSO (cos
    θ cos φ, cos θ sin φ, sin θ)`` looking at the isocentre. The true view adds
    independent N(0, jitter_deg²) errors to φ_i and θ_i and, with ``jitter_mm > 0``, shifts the whole
    source-detector assembly by δ_i ~ N(0, jitter_mm² I) (a gantry whose isocentre wobbles): the true source is
    at ``c_i + δ_i`` looking at ``iso + δ_i``.

    Parameters
    ----------
    n_views : int
        Number of views (>= 2).
    isocenter_mm : sequence of float, shape (3,)
        Designed isocentre, world mm.
    dso_mm : float
        Source-to-isocentre distance (mm).
    arc_deg, start_deg : float
        Angular range in (0, 360] and its start (degrees).
    wobble_deg, wobble_cycles : float
        Elevation amplitude (|wobble| < 80 degrees) and its cycles per turn.
    jitter_deg, jitter_mm : float
        Per-view pose error of the true orbit: angles (degrees) and isocentre shift (mm), standard deviations.
    seed : int
        Seeds the pose error.

    Returns
    -------
    list of View, length ``n_views``
        True poses (``R``, ``t``, angles), every view in the ``train`` split, each with its designed pose in
        ``View.design``.

    Raises
    ------
    CtsplatError
        For ``n_views < 2``, ``|wobble_deg| >= 80`` or a negative jitter.
    """
    if n_views < 2:
        raise CtsplatError(f"a C-arm orbit needs n_views >= 2, got {n_views}")
    if abs(wobble_deg) >= 80:
        raise CtsplatError(f"wobble_deg must be < 80 degrees, got {wobble_deg}")
    for name, val in (("jitter_deg", jitter_deg), ("jitter_mm", jitter_mm)):
        if not val >= 0:
            raise CtsplatError(f"orbit_{name} must be >= 0, got {val}")
    iso = np.asarray(isocenter_mm, float)
    along = arc_azimuths(int(n_views), arc_deg, start_deg, wrap=False)
    az0 = np.mod(along, 360.0)
    el0 = wobble_deg * np.sin(np.deg2rad(wobble_cycles * along))  # continuous where the arc crosses 0°
    az, el = az0.copy(), el0.copy()
    if jitter_deg > 0:
        rng = np.random.default_rng(seed)
        az = az + rng.normal(0.0, jitter_deg, n_views)
        el = el + rng.normal(0.0, jitter_deg, n_views)
    shift = np.zeros((n_views, 3))
    if jitter_mm > 0:
        shift = np.random.default_rng([seed, 1]).normal(0.0, jitter_mm, (n_views, 3))
    views = []
    for i in range(int(n_views)):
        Rd, td = pose_from_angles(float(az0[i]), float(el0[i]), iso, dso_mm)
        a, e = np.deg2rad(az[i]), np.deg2rad(el[i])
        c = iso + shift[i] + dso_mm * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        R, t = look_at(c, iso + shift[i])
        design = View(i, Rd, td, float(az0[i]), float(el0[i]), "train")
        views.append(View(i, R, t, float(az[i]), float(el[i]), "train", design))
    return views


def support_radius_mm(data: np.ndarray, affine: np.ndarray, centre_mm: np.ndarray, rel_threshold: float = 0.2
                      ) -> float:
    """Radius (mm) around ``centre_mm`` of the sphere holding every voxel above ``rel_threshold · max``.

    Sizes a detector to the object rather than to the (mostly empty) volume box; the half-diagonal of the box for
    an empty volume.

    Parameters
    ----------
    data : ndarray, shape (I, J, K)
        Voxel values (any non-negative unit).
    affine : ndarray, shape (4, 4)
        Voxel index to world mm.
    centre_mm : ndarray, shape (3,)
        Centre of the sphere, world mm.
    rel_threshold : float
        Fraction of the maximum above which a voxel belongs to the object.

    Returns
    -------
    float
        Radius (mm): the farthest object voxel centre plus one voxel diagonal.
    """
    data = np.asarray(data)
    vmax = float(data.max()) if data.size else 0.0
    ijk = np.argwhere(data > rel_threshold * vmax) if vmax > 0 else np.empty((0, 3))
    if len(ijk) == 0:
        ext = np.asarray(data.shape, float) * np.linalg.norm(np.asarray(affine)[:3, :3], axis=0)
        return 0.5 * float(np.linalg.norm(ext))
    xyz = ijk @ np.asarray(affine)[:3, :3].T + np.asarray(affine)[:3, 3]
    vox = float(np.linalg.norm(np.linalg.norm(np.asarray(affine)[:3, :3], axis=0)))  # voxel diagonal
    return float(np.linalg.norm(xyz - np.asarray(centre_mm), axis=1).max()) + vox


# ------------------------------------------------------------------------------------ field of view
def object_points_mm(data: np.ndarray, affine: np.ndarray, threshold: float = 0.01) -> np.ndarray:
    """Corners of the voxels on the convex hull of the object: points whose convex hull holds every object voxel.

    The object is the voxels above ``threshold * max(data)`` (all voxels when the maximum is not positive), as
    :func:`check_fov` defines it. Taking the hull vertices first keeps the point count small for any volume.

    Parameters
    ----------
    data : ndarray, shape (I, J, K)
        Volume values.
    affine : ndarray, shape (4, 4)
        Voxel index to world mm.
    threshold : float
        Fraction of the maximum above which a voxel belongs to the object.

    Returns
    -------
    ndarray, shape (N, 3)
        World points (mm): each hull voxel's 8 corners (index ± 0.5).
    """
    from scipy.spatial import ConvexHull, QhullError

    data = np.asarray(data)
    vmax = float(data.max()) if data.size else 0.0
    idx = np.argwhere(data > threshold * vmax) if vmax > 0 else np.argwhere(np.ones(data.shape, bool))
    idx = idx.astype(float)
    if len(idx) > 8:
        try:
            idx = idx[ConvexHull(idx).vertices]
        except QhullError:  # a flat object (one slice or one line): every voxel is on its "hull"
            pass
    offsets = np.array([[a, b, c] for a in (-0.5, 0.5) for b in (-0.5, 0.5) for c in (-0.5, 0.5)])
    corners = (idx[:, None, :] + offsets[None]).reshape(-1, 3)
    A = np.asarray(affine, float)
    return corners @ A[:3, :3].T + A[:3, 3]


def covering_spacing_mm(camera: Camera, Rs: np.ndarray, ts: np.ndarray, points_mm: np.ndarray,
                        margin_px: float = 1.0) -> float:
    """Smallest detector pixel spacing (parallel) or pitch (cone) at which every point falls on the detector.

    Points project linearly in ``1 / spacing`` about the detector centre (``u - W/2 = x_cam / spacing`` for a
    parallel beam, ``(dsd / pitch) x_cam / z_cam`` for a cone beam), so the spacing that puts the farthest point
    ``margin_px`` pixels inside the detector's edge is ``max |offset at spacing 1| / (W/2 - margin_px)`` (and
    likewise for the rows).

    Parameters
    ----------
    camera : ParallelCamera or ConeCamera
        The detector (its size and, for cone beams, its distances; its spacing is not used).
    Rs : ndarray, shape (V, 3, 3)
        World-to-camera rotations.
    ts : ndarray, shape (V, 3)
        World-to-camera translations (mm).
    points_mm : ndarray, shape (N, 3)
        World points to cover, e.g. :func:`object_points_mm`.
    margin_px : float
        Pixels left free at each edge (0 to half the shorter side).

    Returns
    -------
    float
        Spacing or pitch (mm); 0 when every point projects onto the detector centre.

    Raises
    ------
    CtsplatError
        When a point lies behind a cone-beam source (no pitch can cover it).
    """
    from ctsplat.geometry.cameras import world_to_camera

    half_w = camera.width / 2.0 - margin_px
    half_h = camera.height / 2.0 - margin_px
    if half_w <= 0 or half_h <= 0:
        half_w, half_h = camera.width / 2.0, camera.height / 2.0
    need = 0.0
    for R, t in zip(np.asarray(Rs, float), np.asarray(ts, float), strict=True):
        pc = world_to_camera(np.asarray(points_mm, float), R, t)
        if camera.model == "cone":
            if np.any(pc[:, 2] <= 0):
                raise CtsplatError("part of the object lies behind the cone-beam source: raise dso_mm")
            x, y = camera.dsd_mm * pc[:, 0] / pc[:, 2], camera.dsd_mm * pc[:, 1] / pc[:, 2]
        else:
            x, y = pc[:, 0], pc[:, 1]
        need = max(need, float(np.abs(x).max()) / half_w, float(np.abs(y).max()) / half_h)
    return need


def fov_outside_fraction(camera: Camera, Rs: np.ndarray, ts: np.ndarray, points_mm: np.ndarray) -> np.ndarray:
    """Per view, the fraction of points that project outside the detector (or behind a cone-beam source).

    Parameters
    ----------
    camera : ParallelCamera or ConeCamera
        The detector.
    Rs : ndarray, shape (V, 3, 3)
        World-to-camera rotations.
    ts : ndarray, shape (V, 3)
        World-to-camera translations (mm).
    points_mm : ndarray, shape (N, 3)
        World points (mm).

    Returns
    -------
    ndarray, shape (V,)
        Fractions in [0, 1].
    """
    out = np.empty(len(Rs))
    for i, (R, t) in enumerate(zip(Rs, ts, strict=True)):
        uv, z = project_points(camera, R, t, points_mm)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= camera.height)
        if camera.model == "cone":
            inside &= z > 0
        out[i] = 1.0 - float(np.mean(inside))
    return out


def check_fov(camera: Camera, Rs: np.ndarray, ts: np.ndarray, data: np.ndarray, affine: np.ndarray, *,
              threshold: float = 0.01, max_points: int = 20000, seed: int = 0) -> float:
    """Warn when the detector does not cover the object; return the worst view's outside fraction.

    The object is the voxels with ``data > threshold * max(data)`` (all voxels if the maximum is not positive),
    subsampled to ``max_points`` voxel centres.

    Parameters
    ----------
    camera : ParallelCamera or ConeCamera
        The detector.
    Rs : ndarray, shape (V, 3, 3)
        World-to-camera rotations.
    ts : ndarray, shape (V, 3)
        World-to-camera translations (mm).
    data : ndarray, shape (I, J, K)
        Volume values.
    affine : ndarray, shape (4, 4)
        Voxel index to world mm.
    threshold : float
        Fraction of the maximum above which a voxel belongs to the object.
    max_points : int
        Most voxel centres tested (a seeded random subset beyond that).
    seed : int
        Seeds the subset.

    Returns
    -------
    float
        The largest per-view fraction of object points outside the field of view, in [0, 1].

    Warns
    -----
    UserWarning
        When that fraction is positive, naming it and the number of views affected.
    """
    data = np.asarray(data)
    mask = data > threshold * float(data.max()) if data.max() > 0 else np.ones(data.shape, bool)
    idx = np.argwhere(mask)
    if len(idx) > max_points:
        idx = idx[np.random.default_rng(seed).choice(len(idx), max_points, replace=False)]
    pts = idx @ np.asarray(affine, float)[:3, :3].T + np.asarray(affine, float)[:3, 3]
    frac = fov_outside_fraction(camera, np.asarray(Rs), np.asarray(ts), pts)
    worst = float(frac.max())
    if worst > 0:
        pct = 100 * worst
        # a few points of a faint rim must not read as "0.0%"
        shown = f"{pct:.1f}" if pct >= 0.1 else f"{pct:.2g}"
        warnings.warn(
            f"detector does not cover the volume: {shown}% of the object lies outside the field of view "
            f"in the worst view ({int(np.sum(frac > 0))}/{len(frac)} views affected); enlarge the detector or "
            "its pixel spacing",
            stacklevel=2,
        )
    return worst
