"""The scene a model is trained and evaluated on: view sets with their targets, poses and the reference volume.

Training and evaluation read radiographs from view sets (written by ``ctsplat project``) and never render them.
Two pose sources:

- ``poses: gt`` — training views are the ``train`` split of the training geometry's view set, at their true
  poses;
- ``poses: perturbed`` — as ``gt``, but the training poses carry a seeded per-view C-arm error (azimuth and
  elevation N(0, ``perturb_rot_deg``²), isocentre shift N(0, ``perturb_trans_mm``² I);
  :func:`ctsplat.training.poses.perturb_poses`) while the radiographs stay those of the true poses;
- ``poses: colmap`` — training views are views of the C-arm view set that SfM registered, with the poses SfM
  recovered (``aligned_views.json``) and the radiographs of that view set as targets (same view ids).

A ``+refine`` suffix (``perturbed+refine``, ``colmap+refine``) reads the same scene; the training loop then refines
the training poses (:mod:`ctsplat.training.poses`). Training views keep their true poses beside the ones trained
with (``true_Rs``, ``true_ts``) so pose errors can be scored.

In both cases ``views`` (> 0) picks that many training views spread evenly over the candidates in orbit order
(:func:`even_subset`; ``gt``: the train split ordered by azimuth; ``colmap``: the registered views ordered by view
id, i.e. along the C-arm orbit); ``0`` takes all. Validation and test views are always the training geometry's
``val``/``test`` splits at their true poses, so every pose source is scored on the same views.

Targets are line integrals of the *normalised* volume (radiograph line integrals divided by the volume's
``mu_scale_per_mm``), in mm.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ctsplat.formats.viewset import SPLITS, ViewSet, load_radiographs
from ctsplat.utils import CtsplatError, read_json_object

__all__ = ["ViewData", "Scene", "load_scene", "even_subset", "spread_views"]

log = logging.getLogger(__name__)


@dataclass
class ViewData:
    """Views of one split with their camera, poses and target images.

    Parameters
    ----------
    camera : ParallelCamera or ConeCamera
        The detector, ``H`` rows by ``W`` columns.
    ids : ndarray of int, shape (V,)
        View ids of the view set the images come from.
    Rs : ndarray, shape (V, 3, 3)
        World-to-camera rotations.
    ts : ndarray, shape (V, 3)
        World-to-camera translations (mm).
    azimuth_deg, elevation_deg : ndarray, shape (V,)
        View angles (degrees) as recorded in the view set.
    images : ndarray, shape (V, H, W), float32
        Line integrals of the normalised volume (mm).
    split : str
        ``"train"``, ``"val"`` or ``"test"``.
    true_Rs, true_ts : ndarray (V, 3, 3), ndarray (V, 3), optional
        The true poses of these views when ``Rs``/``ts`` are not (perturbed or SfM training poses); None otherwise.
    """

    camera: Any
    ids: np.ndarray
    Rs: np.ndarray
    ts: np.ndarray
    azimuth_deg: np.ndarray
    elevation_deg: np.ndarray
    images: np.ndarray
    split: str
    true_Rs: np.ndarray | None = None
    true_ts: np.ndarray | None = None

    def __len__(self) -> int:
        return int(len(self.ids))

    def take(self, idx: np.ndarray) -> ViewData:
        """The views at some positions.

        Parameters
        ----------
        idx : ndarray of int, shape (V',)
            Positions (not view ids) into this object's arrays.

        Returns
        -------
        ViewData
            A copy holding those ``V'`` views, same camera and split.
        """
        idx = np.asarray(idx, int)
        return ViewData(self.camera, self.ids[idx], self.Rs[idx], self.ts[idx], self.azimuth_deg[idx],
                        self.elevation_deg[idx], self.images[idx], self.split,
                        None if self.true_Rs is None else self.true_Rs[idx],
                        None if self.true_ts is None else self.true_ts[idx])

    def truth(self) -> tuple[np.ndarray, np.ndarray]:
        """The true poses of these views: ``true_Rs``/``true_ts`` when set, else ``Rs``/``ts``.

        Returns
        -------
        Rs, ts : ndarray (V, 3, 3), ndarray (V, 3)
        """
        if self.true_Rs is None:
            return self.Rs, self.ts
        return self.true_Rs, self.true_ts

    @classmethod
    def from_view_set(cls, vs: ViewSet, images: np.ndarray, rows: np.ndarray, split: str, mu_scale: float
                      ) -> ViewData:
        """Some rows of a view set with their line-integral images, converted to normalised-volume units.

        Parameters
        ----------
        vs : ViewSet
            The view set.
        images : ndarray, shape (V, H, W)
            Its line-integral stack (page order of ``vs``), dimensionless.
        rows : ndarray of int, shape (V',)
            Rows of ``vs.views`` to take (may be empty).
        split : str
            Split label stored in the result.
        mu_scale : float
            The volume's ``mu_scale_per_mm`` (1/mm): images are divided by it.

        Returns
        -------
        ViewData
            ``V'`` views, images float32 in mm.
        """
        views = [vs.views[i] for i in rows]
        return cls(
            camera=vs.camera,
            ids=np.array([v.id for v in views], int),
            Rs=np.stack([v.R for v in views]) if views else np.zeros((0, 3, 3)),
            ts=np.stack([v.t for v in views]) if views else np.zeros((0, 3)),
            azimuth_deg=np.array([v.azimuth_deg for v in views], float),
            elevation_deg=np.array([v.elevation_deg for v in views], float),
            images=(images[rows] / mu_scale).astype(np.float32) if len(rows) else
            np.zeros((0, vs.camera.height, vs.camera.width), np.float32),
            split=split,
        )


@dataclass
class Scene:
    """Everything training and evaluation read: views per split, the reference volume, scales, provenance.

    Parameters
    ----------
    train, val, test : ViewData
        Training views (true or SfM poses) and the held-out views (true poses). When the view set lacks one of
        ``val``/``test``, both hold the one it has.
    volume : ctsplat.formats.volume.Volume
        The normalised reference: its grid is where 3D metrics are measured; its voxel values are read only by
        ``init: volume`` (labelled as using the reference) and the evaluation.
    mu_scale : float
        The volume's ``mu_scale_per_mm`` (1/mm per normalised unit).
    eval_split : str
        The split training validates on: ``"val"``, or ``"test"`` when there are no val views.
    isocenter_mm : ndarray (3,)
        The designed isocentre of the training views (world mm): pose corrections turn cameras about it.
    info : dict
        Provenance: view counts, cameras, and for ``poses: colmap`` the SfM registration numbers.
    """

    train: ViewData
    val: ViewData
    test: ViewData
    volume: Any
    mu_scale: float
    eval_split: str
    info: dict[str, Any] = field(default_factory=dict)
    isocenter_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def split(self, name: str) -> ViewData:
        """The views of one split.

        Parameters
        ----------
        name : {"train", "val", "test"}
            The split.

        Returns
        -------
        ViewData
            The split's views (``train``, ``val`` or ``test`` attribute).

        Raises
        ------
        CtsplatError
            For another name.
        """
        if name not in SPLITS:
            raise CtsplatError(f"unknown split {name!r}; allowed: {', '.join(SPLITS)}")
        return getattr(self, name)


def even_subset(n_total: int, n: int) -> np.ndarray:
    """``n`` indices spread evenly over ``range(n_total)``: ``floor(k n_total / n)``, ``k < n``.

    Parameters
    ----------
    n_total : int
        Number of candidates.
    n : int
        How many to take; ``<= 0`` or ``>= n_total`` takes all.

    Returns
    -------
    ndarray of int
        Increasing indices, shape ``(n,)`` when ``0 < n < n_total``, else ``(n_total,)``.

    Examples
    --------
    >>> even_subset(10, 4)
    array([0, 2, 5, 7])
    >>> even_subset(5, 0)
    array([0, 1, 2, 3, 4])
    """
    if n <= 0 or n >= n_total:
        return np.arange(n_total)
    return np.floor(np.arange(n) * n_total / n).astype(int)


def spread_views(view_set: ViewSet, split: str, n: int) -> np.ndarray:
    """Rows of ``n`` views of ``split`` spread evenly in azimuth: the split sorted by ``azimuth mod 360`` (stable),
    then :func:`even_subset`. Training's ``views`` setting and the baselines' view counts both take this subset.

    Parameters
    ----------
    view_set : ViewSet
    split : {"train", "val", "test"}
    n : int
        How many; ``<= 0`` or ``>=`` the split's size takes all.

    Returns
    -------
    ndarray of int
        Row indices into ``view_set.views`` (and its image stack), in azimuth order.
    """
    rows = view_set.indices(split)
    order = np.argsort(np.mod([view_set.views[i].azimuth_deg for i in rows], 360.0), kind="stable")
    return rows[order][even_subset(rows.size, n)]


def _check_volume(vs: ViewSet, volume: Any, where: str) -> None:
    if vs.volume_id != volume.volume_id:
        raise CtsplatError(
            f"radiographs in {where} were rendered from volume {vs.volume_id}, but train.volume is "
            f"{volume.volume_id}; re-render the radiographs for this volume or point to the matching volume")
    recorded = vs.meta.get("volume_shape")
    if recorded is not None and tuple(recorded) != volume.shape:
        raise CtsplatError(f"radiographs in {where} were rendered from a {tuple(recorded)} volume but the "
                           f"reference volume is {volume.shape}; re-render the radiographs")


def _colmap_train(cfg: dict[str, Any], volume: Any, mu_scale: float
                  ) -> tuple[ViewData, dict[str, Any], np.ndarray]:
    """Training views of the C-arm view set at the poses SfM recovered (see the module docstring)."""
    sfm_dir = Path(cfg["sfm_dir"])
    summary_path = sfm_dir / "summary.json"
    if not summary_path.exists():
        raise CtsplatError(f"{summary_path} does not exist; run the sfm step before training with poses: colmap")
    from ctsplat.sfm.step import sfm_failure  # pycolmap loads only for poses: colmap

    summary = read_json_object(summary_path, what="SfM summary", fix="run the sfm step again")
    rate = float(summary.get("registration_rate", 0.0))
    n_total = int(summary.get("n_views", 0))
    failure = sfm_failure(summary)
    if rate < float(cfg["min_registration_rate"]) and failure is None:
        failure = f"registered only {rate:.0%} of {n_total} views (need >= {cfg['min_registration_rate']:.0%})"
    if failure is None and not (sfm_dir / "aligned_views.json").exists():
        raise CtsplatError(f"{sfm_dir / 'aligned_views.json'} is missing although {summary_path} says the SfM run is "
                           "ok (removed since?); run the sfm step again (snakemake --forcerun sfm)")
    if failure is not None:  # never train on poses the SfM step itself rejected
        raise CtsplatError(f"the SfM run failed ({summary_path}): {failure}; poses: colmap does not train on failed "
                           "poses: use poses: gt or improve the sfm step")
    aligned = ViewSet.load(sfm_dir / "aligned_views.json")
    if aligned.volume_id != volume.volume_id:
        raise CtsplatError(f"SfM poses in {sfm_dir} belong to volume {aligned.volume_id}, not {volume.volume_id}; "
                           "re-run the sfm step for this volume")
    rad_dir = Path(cfg["sfm_radiographs"] or summary.get("radiographs", ""))
    images, carm = load_radiographs(rad_dir)
    _check_volume(carm, volume, str(rad_dir))
    row_of = {v.id: i for i, v in enumerate(carm.views)}
    registered = sorted(aligned.views, key=lambda v: v.id)
    missing = [v.id for v in registered if v.id not in row_of]
    if missing:
        raise CtsplatError(f"{sfm_dir}/aligned_views.json has view id {missing[0]} that {rad_dir}/views.json lacks; "
                           "the SfM result belongs to another view set: re-run the sfm step")
    want = int(cfg["views"])
    if want > len(registered):
        raise CtsplatError(f"poses: colmap asks for {want} training views but SfM registered only "
                           f"{len(registered)} of the {len(carm)} C-arm views; lower views to <= {len(registered)} "
                           "or improve the sfm step")
    chosen = [registered[i] for i in even_subset(len(registered), want)]
    vd = ViewData(
        camera=aligned.camera,
        ids=np.array([v.id for v in chosen], int),
        Rs=np.stack([v.R for v in chosen]),
        ts=np.stack([v.t for v in chosen]),
        azimuth_deg=np.array([v.azimuth_deg for v in chosen], float),
        elevation_deg=np.array([v.elevation_deg for v in chosen], float),
        images=(images[[row_of[v.id] for v in chosen]] / mu_scale).astype(np.float32),
        split="train",
        true_Rs=np.stack([carm.views[row_of[v.id]].R for v in chosen]),
        true_ts=np.stack([carm.views[row_of[v.id]].t for v in chosen]),
    )
    info = {"sfm_registration_rate": rate, "sfm_views_total": n_total or len(carm),
            "sfm_views_registered": len(registered),
            "views_dropped_unregistered": int((n_total or len(carm)) - len(registered)),
            "sfm_ok": bool(summary.get("ok", False)), "sfm_radiographs": str(rad_dir)}
    return vd, info, carm.isocenter_mm


def load_scene(cfg: dict[str, Any]) -> Scene:
    """Read the reference volume and the view sets of a run config, check they belong together, build the splits.

    Parameters
    ----------
    cfg : dict
        A resolved ``train`` config (:func:`ctsplat.training.config.resolve_config`): ``volume``,
        ``radiographs``, ``poses``, ``views`` (``perturbed``: ``perturb_rot_deg``, ``perturb_trans_mm``, ``seed``),
        and for ``poses: colmap`` ``sfm_dir`` (+ ``sfm_radiographs``,
        ``min_registration_rate``).

    Returns
    -------
    Scene
        Views per split (images in normalised-volume units, mm), the reference volume and provenance.

    Raises
    ------
    CtsplatError
        When the radiographs belong to another volume, the volume's ``mu_scale_per_mm`` is not positive,
        ``views`` asks for more training views than there are, the train split is empty, there are no val or
        test views, or (``poses: colmap``) the SfM result is missing, registered too few views or belongs to
        another view set or volume.
    """
    from ctsplat.formats.volume import load_volume

    volume = load_volume(cfg["volume"])
    images, vs = load_radiographs(Path(cfg["radiographs"]))
    _check_volume(vs, volume, str(cfg["radiographs"]))
    mu_scale = volume.mu_scale_per_mm
    if not mu_scale > 0:
        raise CtsplatError(f"volume {cfg['volume']} has a non-positive mu_scale_per_mm ({mu_scale})")
    split_rows = {s: vs.indices(s) for s in SPLITS}
    info: dict[str, Any] = {"views_dropped_unregistered": 0}
    from ctsplat.training.poses import perturb_poses, pose_source

    source = pose_source(cfg["poses"])
    iso = vs.isocenter_mm.copy()
    if source == "colmap":
        train, extra, iso = _colmap_train(cfg, volume, mu_scale)
        info.update(extra)
    else:
        if split_rows["train"].size == 0:
            raise CtsplatError(f"radiographs in {cfg['radiographs']} have an empty train split; re-render with a "
                               "non-zero train fraction")
        want = int(cfg["views"])
        if want > split_rows["train"].size:
            raise CtsplatError(f"train.views asks for {want} training views but {cfg['radiographs']} has only "
                               f"{split_rows['train'].size}; lower views or render more")
        rows = spread_views(vs, "train", want)
        train = ViewData.from_view_set(vs, images, rows, "train", mu_scale)
        if source == "perturbed" and len(train):
            train.true_Rs, train.true_ts = train.Rs, train.ts
            train.Rs, train.ts = perturb_poses(train.Rs, train.ts, iso, float(cfg["perturb_rot_deg"]),
                                               float(cfg["perturb_trans_mm"]), int(cfg["seed"]))
    if len(train) == 0:
        raise CtsplatError("the train split is empty after selecting views; check train.views and the view set")
    if split_rows["test"].size == 0 and split_rows["val"].size == 0:
        raise CtsplatError(f"radiographs in {cfg['radiographs']} have no val or test views to evaluate on; "
                           "re-render with non-zero val/test fractions")
    test_rows = split_rows["test"] if split_rows["test"].size else split_rows["val"]
    val_rows = split_rows["val"] if split_rows["val"].size else split_rows["test"]
    eval_split = "val" if split_rows["val"].size else "test"
    test = ViewData.from_view_set(vs, images, test_rows, "test", mu_scale)
    val = ViewData.from_view_set(vs, images, val_rows, eval_split, mu_scale)
    # a view set without test views is scored on its validation views, which also chose the model: say so
    info.update(test_views_from="test" if split_rows["test"].size else "val")
    info.update(n_train_views=len(train), n_val_views=len(val), n_test_views=len(test),
                radiographs_volume_id=vs.volume_id, camera=vs.camera.to_dict(), train_camera=train.camera.to_dict())
    return Scene(train=train, val=val, test=test, volume=volume, mu_scale=mu_scale, eval_split=eval_split, info=info,
                 isocenter_mm=np.asarray(iso, float))
