"""Initial Gaussian sets (``init``): ``volume``, ``uniform``, ``fbp`` and ``sfm`` seeding.

Every strategy returns a :class:`Seed` of plain NumPy arrays in world millimetres (``docs/conventions.md``):
isotropic scales, identity rotations, densities ρ in normalised-volume units. Only ``volume`` reads the
reference volume's voxel values; its seed is flagged ``uses_reference_volume=True`` so every output of such a
run can say so. ``fbp`` seeds from a reconstruction of the training views (FBP, FDK or SIRT), optionally refined
by ASD-POCS iterations on the same views (``init_asd_pocs``).

Mass bookkeeping used by the grid-based seeds: a Gaussian ``ρ exp(-|x - m|² / 2σ²)`` carries
``ρ (2π)^{3/2} σ³`` (normalised units × mm³). Drawing ``n`` Gaussians uniformly among ``M`` candidate voxels
of volume ``v_vox`` puts on average ``n / M`` Gaussians in each voxel, so choosing

.. math:: ρ_i = \\frac{M\\, v_{vox}}{n\\, (2π)^{3/2} σ^3}\\, V(p_i)

makes the expected seeded field equal to the voxel values ``V`` ("density proportional to the value").
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ctsplat.formats.ply import read_ply_points
from ctsplat.utils import CtsplatError

if TYPE_CHECKING:
    from ctsplat.formats.viewset import ViewSet
    from ctsplat.scene import Scene


__all__ = [
    "make_seed",
    "fbp_reconstruction",
    "asd_pocs_refinement",
    "Seed",
    "seed_from_grid",
    "seed_uniform",
    "seed_from_points",
    "grid_bounds_mm",
]

_GAUSS_NORM = (2.0 * np.pi) ** 1.5


@dataclass
class Seed:
    """An initial Gaussian set.

    Attributes
    ----------
    means : ndarray, shape (N, 3), float32 — centres in world mm.
    scales : ndarray, shape (N, 3), float32 — standard deviations in mm.
    densities : ndarray, shape (N,), float32 — peak densities ρ (normalised volume units), > 0.
    uses_reference_volume : bool — True when the reference volume's voxel values were read.
    strategy : str — the ``init`` value that produced it.
    """

    means: np.ndarray
    scales: np.ndarray
    densities: np.ndarray
    uses_reference_volume: bool
    strategy: str

    def __len__(self) -> int:
        return int(self.means.shape[0])


def grid_bounds_mm(shape: tuple[int, int, int], affine: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned world box (mm) covered by the voxels of a grid (voxel edges, not centres).

    Parameters
    ----------
    shape : (I, J, K)
        Grid size in voxels.
    affine : ndarray, shape (4, 4)
        Voxel index -> world mm.

    Returns
    -------
    lo, hi : ndarray, shape (3,)
    """
    corners = np.array([[a, b, c] for a in (-0.5, shape[0] - 0.5) for b in (-0.5, shape[1] - 0.5)
                        for c in (-0.5, shape[2] - 0.5)], float)
    world = corners @ np.asarray(affine, float)[:3, :3].T + np.asarray(affine, float)[:3, 3]
    return world.min(0), world.max(0)


def seed_from_grid(
    data: np.ndarray,
    affine: np.ndarray,
    n: int,
    rng: np.random.Generator,
    *,
    top_fraction: float = 0.3,
    scale_voxels: float = 0.75,
    uses_reference_volume: bool,
    strategy: str,
) -> Seed:
    """Sample Gaussians at the brightest voxels of a volume (reference volume or a reconstruction).

    Candidates are voxels whose value is in the top ``top_fraction`` of all voxels and positive; ``n`` of them
    are drawn (without replacement when possible), each centre is jittered uniformly within its voxel, the
    scale is ``scale_voxels`` × the mean voxel edge, and ρ is proportional to the voxel value with the
    mass-preserving factor of the module docstring.

    Parameters
    ----------
    data : ndarray, shape (I, J, K)
        Voxel values (normalised units; negative values, e.g. FBP ringing, are clipped to 0).
    affine : ndarray, shape (4, 4)
        Voxel index -> world mm.
    n : int
        Number of Gaussians (> 0).
    rng : numpy.random.Generator
    top_fraction : float in (0, 1]
        Fraction of voxels eligible (0.3 = top 30 %).
    scale_voxels : float
        Isotropic scale in voxels (× mean voxel edge -> mm).
    uses_reference_volume, strategy : bool, str
        Provenance recorded in the seed.

    Returns
    -------
    Seed
        ``n`` Gaussians: means (n, 3) mm, scales (n, 3) mm, densities (n,).
    """
    data = np.clip(np.asarray(data, np.float64), 0.0, None)
    if n <= 0:
        raise CtsplatError(f"init needs a positive number of Gaussians, got n_init={n}")
    if not 0.0 < top_fraction <= 1.0:
        raise CtsplatError(f"init_top_fraction must be in (0, 1], got {top_fraction}")
    thr = np.quantile(data, 1.0 - top_fraction)
    mask = (data >= thr) & (data > 0)
    cand = np.flatnonzero(mask)
    if cand.size == 0:
        raise CtsplatError(f"cannot seed init={strategy}: the volume has no positive voxels (all values <= 0)")
    pick = rng.choice(cand, size=n, replace=n > cand.size)
    idx = np.stack(np.unravel_index(pick, data.shape), axis=1).astype(np.float64)
    idx += rng.uniform(-0.5, 0.5, size=idx.shape)
    affine = np.asarray(affine, float)
    means = idx @ affine[:3, :3].T + affine[:3, 3]
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    sigma = scale_voxels * float(spacing.mean())
    v_vox = float(abs(np.linalg.det(affine[:3, :3])))
    k = cand.size * v_vox / (n * _GAUSS_NORM * sigma**3)
    dens = np.maximum(k * data.ravel()[pick], 1e-6)
    return Seed(
        means=means.astype(np.float32),
        scales=np.full((n, 3), sigma, np.float32),
        densities=dens.astype(np.float32),
        uses_reference_volume=uses_reference_volume,
        strategy=strategy,
    )


def seed_uniform(
    lo: np.ndarray, hi: np.ndarray, n: int, rng: np.random.Generator, *, density: float = 0.05
) -> Seed:
    """Gaussians uniformly distributed in the box ``[lo, hi]`` (the scanner field of view).

    The isotropic scale is half the mean spacing ``((∏(hi - lo)) / n)^{1/3}`` so neighbours overlap
    without blurring the box; all densities equal ``density`` (small: the SfM-free baseline).

    Parameters
    ----------
    lo, hi : ndarray, shape (3,)
        Box corners (mm).
    n : int
        Number of Gaussians (> 0).
    rng : numpy.random.Generator
    density : float
        ρ of every Gaussian (normalised units).

    Returns
    -------
    Seed
        Means (n, 3) mm, scales (n, 3) mm, densities (n,).
    """
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    if n <= 0:
        raise CtsplatError(f"init needs a positive number of Gaussians, got n_init={n}")
    if np.any(hi <= lo):
        raise CtsplatError(f"empty field of view box lo={lo.tolist()} hi={hi.tolist()}")
    means = rng.uniform(lo, hi, size=(n, 3))
    d = (float(np.prod(hi - lo)) / n) ** (1.0 / 3.0)
    return Seed(
        means=means.astype(np.float32),
        scales=np.full((n, 3), 0.5 * d, np.float32),
        densities=np.full(n, density, np.float32),
        uses_reference_volume=False,
        strategy="uniform",
    )


def seed_from_points(
    points: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    n: int,
    rng: np.random.Generator,
    *,
    fill_fraction: float = 0.5,
    density: float = 0.05,
) -> Seed:
    """SfM sparse points plus a uniform fill of the field of view.

    Points outside ``[lo, hi]`` are dropped; at most ``n - round(fill_fraction n)`` points are kept (random
    subset) and the rest of the ``n`` Gaussians are uniform in the box. A point's scale is the mean distance to
    its 3 nearest neighbours among the kept points (as 3DGS), clipped to [0.25, 1] × the fill spacing.

    Parameters
    ----------
    points : ndarray, shape (P, 3)
        SfM points (mm, volume frame).
    lo, hi : ndarray, shape (3,)
        Field-of-view box (mm).
    n : int
        Number of Gaussians.
    rng : numpy.random.Generator
    fill_fraction : float in [0, 1]
        Least fraction of ``n`` given to the uniform fill.
    density : float
        ρ of every Gaussian (normalised units).

    Returns
    -------
    Seed
        Means (n, 3) mm, scales (n, 3) mm, densities (n,).
    """
    from scipy.spatial import cKDTree

    points = np.asarray(points, float).reshape(-1, 3)
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    inside = np.all((points >= lo) & (points <= hi), axis=1)
    points = points[inside]
    n_fill_min = int(round(fill_fraction * n))
    keep = max(0, min(points.shape[0], n - n_fill_min))
    if keep < points.shape[0]:
        points = points[np.sort(rng.choice(points.shape[0], size=keep, replace=False))]
    fill = seed_uniform(lo, hi, n - keep, rng, density=density) if n - keep > 0 else None
    d_fill = (float(np.prod(hi - lo)) / n) ** (1.0 / 3.0)
    if keep >= 4:
        dist, _ = cKDTree(points).query(points, k=4)
        s = np.clip(dist[:, 1:].mean(1), 0.25 * d_fill, d_fill)
    else:
        s = np.full(keep, 0.5 * d_fill)
    means = [points]
    scales = [np.repeat(s[:, None], 3, axis=1)]
    dens = [np.full(keep, density)]
    if fill is not None:
        means.append(fill.means)
        scales.append(fill.scales)
        dens.append(fill.densities)
    return Seed(
        means=np.concatenate(means).astype(np.float32),
        scales=np.concatenate(scales).astype(np.float32),
        densities=np.concatenate(dens).astype(np.float32),
        uses_reference_volume=False,
        strategy="sfm",
    )



def _sfm_seed(cfg: dict[str, Any], lo: np.ndarray, hi: np.ndarray, n: int, rng: np.random.Generator) -> Seed:
    """``init: sfm``: the points of an SfM run that passed its verdict, inside the volume's box; a failed run, or
    points of which none lies in the box, are refused (the seed would be uniform under the name sfm)."""
    from ctsplat.sfm.step import sfm_failure  # pycolmap loads only for init: sfm

    sfm_dir = Path(cfg["sfm_dir"])
    failure = sfm_failure(sfm_dir / "summary.json")
    if failure is not None:
        raise CtsplatError(f"init: sfm seeds from the SfM run in {sfm_dir}, which may not be trained on: {failure}; "
                           "use another init or improve the sfm step")
    points = read_ply_points(sfm_dir / "points3d.ply")
    inside = int(np.all((points >= lo) & (points <= hi), axis=1).sum())
    if inside == 0:
        raise CtsplatError(f"none of the {len(points)} SfM points in {sfm_dir / 'points3d.ply'} lies inside the "
                           "volume's box, so init: sfm would seed uniformly; run the sfm step again for this volume")
    seed = seed_from_points(points, lo, hi, n, rng, fill_fraction=cfg["sfm_fill_fraction"],
                            density=cfg["init_density"])
    used = min(inside, n - int(round(float(cfg["sfm_fill_fraction"]) * n)))
    seed.strategy = f"sfm ({used} of {len(points)} points, {n - used} uniform)"
    return seed


# ------------------------------------------------------------------------------------------ the init setting
def make_seed(cfg: dict[str, Any], scene: Scene, rng: np.random.Generator) -> Seed:
    """The initial Gaussians for ``cfg['init']`` (only ``volume`` reads the reference voxel values).

    Parameters
    ----------
    cfg : dict
        Resolved ``train`` config (``init``, ``n_init``, ``init_*``, ``sfm_*``, ``fbp_filter``).
    scene : Scene
        Training views and the reference grid.
    rng : numpy.random.Generator

    Returns
    -------
    Seed
        ``n_init`` Gaussians: means (N, 3) mm, scales (N, 3) mm, densities (N,).
    """
    vol = scene.volume
    n = int(cfg["n_init"])
    lo, hi = grid_bounds_mm(vol.shape, vol.affine)
    scale = cfg["init_scale_voxels"]
    if cfg["init"] == "volume":
        return seed_from_grid(vol.data, vol.affine, n, rng, top_fraction=cfg["init_top_fraction"],
                              scale_voxels=0.75 if scale is None else float(scale), uses_reference_volume=True,
                              strategy="volume")
    if cfg["init"] == "uniform":
        return seed_uniform(lo, hi, n, rng, density=cfg["init_density"])
    if cfg["init"] == "sfm":
        return _sfm_seed(cfg, lo, hi, n, rng)
    recon, method = fbp_reconstruction(scene, cfg.get("fbp_filter", "ramp"), device=cfg["device"])
    strategy = "fbp" if method == "fbp" else f"fbp ({method})"
    refine_iterations = int(cfg["init_asd_pocs"]["iterations"])
    if refine_iterations > 0:
        recon = asd_pocs_refinement(scene, recon, iterations=refine_iterations,
                                    alpha=float(cfg["init_asd_pocs"]["alpha"]), device=cfg["device"])
        strategy += f" + asd_pocs x{refine_iterations}"
    return seed_from_grid(recon, vol.affine, n, rng, top_fraction=cfg["init_top_fraction"],
                          scale_voxels=1.5 if scale is None else float(scale), uses_reference_volume=False,
                          strategy=strategy)


SIRT_SEED_ITERATIONS = 10


def _train_view_set(scene: Scene) -> ViewSet:
    """The scene's training views as a :class:`~ctsplat.formats.viewset.ViewSet` (page order of its images)."""
    from ctsplat.formats.viewset import View, ViewSet

    tr = scene.train
    views = [View(int(i), R, t, float(a), float(e), "train")
             for i, R, t, a, e in zip(tr.ids, tr.Rs, tr.ts, tr.azimuth_deg, tr.elevation_deg, strict=True)]
    return ViewSet(tr.camera, views, scene.volume.volume_id, scene.volume.center_mm(), {})


def fbp_reconstruction(scene: Scene, filter_name: str = "ramp", *, device: str = "cpu") -> tuple[np.ndarray, str]:
    """Reconstruction of the *training* projections only onto the reference grid (geometry only, no voxel values).

    Circular parallel-beam orbits at elevation 0 use slice-wise FBP (``ctsplat.baselines.fbp_volume``); planar
    circular cone-beam orbits use FDK (``ctsplat.recon.fdk.fdk_volume``, where
    ``ctsplat.recon.fdk.is_circular_cone`` holds); any other geometry (wobbling or spherical orbits, C-arm or
    SfM poses) uses ``SIRT_SEED_ITERATIONS`` iterations of ``ctsplat.baselines.sirt_volume``, which works with the
    projector's own geometry. The training targets are already normalised line integrals, so the result is in
    normalised units.

    Parameters
    ----------
    scene : Scene
        Its training views and reference grid (geometry only).
    filter_name : str
        FBP / FDK filter (``ctsplat.baselines.FBP_FILTERS``).
    device : str
        Where FDK and SIRT run (``cpu``, ``cuda``, ``auto``: the training's device); the slice-wise FBP runs on
        the CPU (scikit-image).

    Returns
    -------
    recon : ndarray (I, J, K) float32
    method : "fbp", "fdk" or "sirt"
    """
    from ctsplat.baselines import fbp_volume, is_circular_parallel, sirt_volume
    from ctsplat.formats.volume import Volume
    from ctsplat.recon import fdk
    from ctsplat.utils import resolve_device

    dev = resolve_device(device)
    tr = scene.train
    vs = _train_view_set(scene)
    grid = Volume(np.zeros(scene.volume.shape, np.float32), np.asarray(scene.volume.affine, float), {})
    if is_circular_parallel(vs):
        return np.asarray(fbp_volume(tr.images, vs, grid, filter_name=filter_name, mu_scale_per_mm=1.0),
                          np.float32), "fbp"
    if fdk.is_circular_cone(vs):
        # the grid carries no intensity scale (1.0): the targets are normalised line integrals already
        return np.asarray(fdk.fdk_volume(tr.images, vs, grid, filter_name=filter_name, device=dev), np.float32), "fdk"
    recon = sirt_volume(tr.images, vs, grid, iterations=SIRT_SEED_ITERATIONS, mu_scale_per_mm=1.0, device=str(dev))
    return np.asarray(recon, np.float32), "sirt"


def asd_pocs_refinement(scene: Scene, recon: np.ndarray, *, iterations: int, alpha: float,
                        device: str = "cpu") -> np.ndarray:
    """ASD-POCS iterations on the *training* projections, started from a reconstruction (the ``fbp`` seed's).

    TV-regularised SART with non-negativity (:func:`ctsplat.recon.iterative.asd_pocs_iterates`) with the
    classical baseline's settings (``ctsplat.baselines.BASELINE_DEFAULTS``: TV steps, ordered subsets, projector
    step, and the detector binned as :func:`ctsplat.recon.suite.auto_binning` says). From the FDK volume of noisy
    sparse views a few iterations remove most streaks and noise, so the seeds land on the object rather than on
    its artefacts.

    Parameters
    ----------
    scene : Scene
        Its training views and reference grid (geometry only, no voxel values).
    recon : ndarray, shape (I, J, K)
        The starting volume on the reference grid (normalised units).
    iterations : int
        ASD-POCS outer iterations, >= 1.
    alpha : float
        TV weight (:func:`~ctsplat.recon.iterative.asd_pocs_iterates`), > 0.
    device : str
        ``auto``, ``cpu`` or ``cuda``.

    Returns
    -------
    ndarray, shape (I, J, K), float32
        Normalised units, clipped to [0, 1].

    References
    ----------
    .. [1] E. Y. Sidky and X. Pan, "Image reconstruction in circular cone-beam computed tomography by constrained,
       total-variation minimization", Phys. Med. Biol. 53 (2008) 4777-4807.
    """
    from ctsplat.baselines import BASELINE_DEFAULTS
    from ctsplat.recon.iterative import asd_pocs_volume
    from ctsplat.recon.suite import auto_binning, bin_detector
    from ctsplat.utils import resolve_device

    vs = _train_view_set(scene)
    p, binned = bin_detector(scene.train.images, vs, auto_binning(vs, scene.volume))
    return asd_pocs_volume(p, binned, scene.volume, iterations=iterations, alpha=alpha,
                           tv_steps=int(BASELINE_DEFAULTS["asd_pocs_tv_steps"]),
                           subsets=int(BASELINE_DEFAULTS["asd_pocs_subsets"]),
                           step_voxels=float(BASELINE_DEFAULTS["step_voxels"]), mu_scale_per_mm=1.0,
                           device=resolve_device(device), x0=recon)
