"""An undistorted COLMAP scene (the output of :func:`ctsplat.photos.sfm.run_photo_sfm`) as training data.

Views are sorted by image name; every ``test_every``-th one, starting with the first, is held out for testing
(the usual 3DGS / Mip-NeRF 360 split, ``llffhold = 8``). Images and intrinsics are optionally downscaled by an
integer factor. Cameras are :class:`PinholeCamera`, the renderer's perspective (``cone``) camera with a free
principal point and separate focal lengths.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
import torch

from ctsplat.geometry.cameras import camera_center
from ctsplat.photos.config import validation_position
from ctsplat.photos.images import load_rgb
from ctsplat.training.losses import gaussian_window
from ctsplat.utils import CtsplatError, is_finite_real

__all__ = ["PinholeCamera", "PhotoView", "PhotoScene", "load_scene", "scene_extent", "split_names"]

#: The side of the SSIM window (:func:`ctsplat.training.losses.gaussian_window`, 3DGS's 11 px): photos smaller than
#: it cannot be trained or scored.
SSIM_WINDOW_PX = gaussian_window().numel()


@dataclass(frozen=True)
class PinholeCamera:
    """A COLMAP ``PINHOLE`` camera in the renderer's duck-typed camera interface (``model = "cone"``).

    Parameters
    ----------
    width, height : int
        Image size, px.
    fx, fy : float
        Focal lengths, px.
    cx, cy : float
        Principal point, px (COLMAP convention: the first pixel's centre is at 0.5).
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    model: str = field(default="cone", init=False)
    pitch_mm: float = field(default=1.0, init=False)  # unit pitch: the renderer then reads fx, fy in px directly

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if not is_finite_real(value):
                raise CtsplatError(f"pinhole camera {name} must be a finite number of pixels, got {value!r}")
        if not (self.fx > 0 and self.fy > 0):
            raise CtsplatError(f"pinhole camera focal lengths must be > 0 px, got fx {self.fx}, fy {self.fy}")

    @property
    def dsd_mm(self) -> float:
        """The focal length in units of the unit pitch (what the renderer expects of a cone camera)."""
        return self.fx

    def scaled(self, factor: int) -> PinholeCamera:
        """The camera of the image downscaled by ``factor`` (``round(W / factor)`` px wide).

        Parameters
        ----------
        factor : int

        Returns
        -------
        PinholeCamera
        """
        w, h = max(1, round(self.width / factor)), max(1, round(self.height / factor))
        sx, sy = w / self.width, h / self.height
        return PinholeCamera(w, h, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy)


@dataclass
class PhotoView:
    """One registered photograph: name, RGB image (H, W, 3) in [0, 1], camera, world->camera pose and split."""

    name: str
    image: torch.Tensor
    camera: PinholeCamera
    R: np.ndarray
    t: np.ndarray
    split: str


@dataclass
class PhotoScene:
    """Views, the SfM points (``xyz`` (P, 3), ``rgb`` (P, 3) in [0, 1]) and the scene extent (3DGS radius of the
    training cameras)."""

    views: list[PhotoView]
    xyz: np.ndarray
    rgb: np.ndarray
    extent: float
    meta: dict[str, Any] = field(default_factory=dict)

    def split(self, name: str) -> list[PhotoView]:
        """The views of split ``name`` (``train``, ``val`` or ``test``)."""
        return [v for v in self.views if v.split == name]


def split_names(names: list[str], test_every: int, *, validation: bool = False,
                validation_offset: int | None = None) -> dict[str, str]:
    """Name -> ``train`` / ``test`` (/ ``val``): every ``test_every``-th name in sorted order (from the first) is
    ``test``; with ``validation``, every ``test_every``-th name from ``validation_offset`` on is ``val``.

    Parameters
    ----------
    names : list of str
    test_every : int
        0 holds nothing out.
    validation : bool
        Also hold out validation names (between the test names, never one of them).
    validation_offset : int, optional
        Position of the first validation name, 1 .. ``test_every`` - 1; ``None`` takes ``test_every // 2`` (midway
        between two test names). Different offsets give disjoint validation folds of the same training photos.

    Returns
    -------
    dict of str to str

    Raises
    ------
    CtsplatError
        For an offset outside 1 .. ``test_every`` - 1 with ``validation``.
    """
    out = {}
    k = int(test_every)
    off = validation_position(k, validation_offset) if validation else 0
    for i, n in enumerate(sorted(names)):
        if k and i % k == 0:
            out[n] = "test"
        elif k and validation and i % k == off:
            out[n] = "val"
        else:
            out[n] = "train"
    return out


def scene_extent(Rs: list[np.ndarray], ts: list[np.ndarray]) -> float:
    """3DGS's scene radius: 1.1 × the largest distance of a camera centre from the centres' mean.

    Parameters
    ----------
    Rs, ts : lists of (3, 3) and (3,) arrays
        World->camera poses.

    Returns
    -------
    float
        At least 1e-6 (a single camera).
    """
    centres = camera_center(np.stack(Rs), np.stack(ts))
    return max(1.1 * float(np.linalg.norm(centres - centres.mean(0), axis=1).max()), 1e-6)


def _read_model(sparse: Path) -> pycolmap.Reconstruction:
    """The COLMAP model in ``sparse``; a damaged one (a file cut short or from another model) in one line."""
    try:
        return pycolmap.Reconstruction(str(sparse))
    except (RuntimeError, ValueError, IndexError, KeyError, MemoryError) as exc:
        first = next((line.strip() for line in str(exc).splitlines() if line.strip()), type(exc).__name__)
        raise CtsplatError(f"cannot read the SfM model in {sparse} ({type(exc).__name__}: {first}); it is damaged "
                           "or incomplete: run `ctsplat photos-sfm` again") from None


def load_scene(sfm_dir: str | Path, *, downscale: int = 1, test_every: int = 8, validation: bool = False,
               validation_offset: int | None = None, device: torch.device | str = "cpu") -> PhotoScene:
    """Read ``sfm_dir/sparse/0`` and ``sfm_dir/images`` into a :class:`PhotoScene`.

    Parameters
    ----------
    sfm_dir : str or Path
        Output of :func:`ctsplat.photos.sfm.run_photo_sfm`.
    downscale : int
        Images and intrinsics divided by this factor (>= 1).
    test_every : int
        Hold-out period (:func:`split_names`).
    validation : bool
        Also hold out validation views (:func:`split_names`).
    validation_offset : int, optional
        The validation fold (:func:`split_names`).
    device : torch.device or str
        Where the image tensors live.

    Returns
    -------
    PhotoScene

    Raises
    ------
    CtsplatError
        When the folder is not an SfM output, a camera is not PINHOLE, an image is missing, or no view is left for
        training.
    """
    sfm_dir = Path(sfm_dir)
    sparse = sfm_dir / "sparse" / "0"
    if not (sparse / "cameras.bin").is_file():
        raise CtsplatError(f"{sfm_dir} is not a photo SfM folder (no sparse/0/cameras.bin); run "
                           "`ctsplat photos-sfm IMAGES OUT` first")
    missing = [name for name in ("images.bin", "points3D.bin") if not (sparse / name).is_file()]
    if missing:
        raise CtsplatError(f"the SfM model in {sparse} lacks {missing[0]}; run `ctsplat photos-sfm` again")
    if int(downscale) < 1:
        raise CtsplatError(f"downscale must be an integer >= 1, got {downscale}")
    rec = _read_model(sparse)
    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    splits = split_names([im.name for im in images], test_every, validation=validation,
                         validation_offset=validation_offset)
    views: list[PhotoView] = []
    for im in images:
        cam = rec.cameras[im.camera_id]
        if cam.model.name != "PINHOLE":
            raise CtsplatError(f"camera of {im.name} is {cam.model.name}, expected PINHOLE (undistorted SfM output)")
        fx, fy, cx, cy = (float(v) for v in cam.params[:4])
        try:
            pc = PinholeCamera(int(cam.width), int(cam.height), fx, fy, cx, cy).scaled(int(downscale))
        except (CtsplatError, ValueError, OverflowError, ZeroDivisionError) as exc:  # a damaged cameras.bin
            raise CtsplatError(f"the SfM model in {sparse} gives {im.name} an impossible camera ({exc}); it is "
                               "damaged: run `ctsplat photos-sfm` again") from None
        if min(pc.width, pc.height) < SSIM_WINDOW_PX:
            raise CtsplatError(f"{im.name} is {pc.width} x {pc.height} px at downscale {int(downscale)}, smaller than "
                               f"the {SSIM_WINDOW_PX} px SSIM window of the loss and the scores; lower the downscale "
                               "(train.downscale) or use larger photos")
        path = sfm_dir / "images" / im.name
        if not path.is_file():
            raise CtsplatError(f"SfM image {path} is missing; run `ctsplat photos-sfm` again")
        try:
            rgb = load_rgb(path, int(downscale))
        except (OSError, SyntaxError, ValueError) as exc:  # PIL's errors for a corrupt or truncated file
            raise CtsplatError(f"corrupt or truncated SfM image {path}: {str(exc).splitlines()[0]}; run `ctsplat "
                               "photos-sfm` again") from None
        if rgb.shape[:2] != (pc.height, pc.width):
            raise CtsplatError(f"{path} is {rgb.shape[1]}x{rgb.shape[0]} after downscaling, its camera says "
                               f"{pc.width}x{pc.height}")
        m = im.cam_from_world().matrix()
        views.append(PhotoView(im.name, torch.from_numpy(rgb).to(device), pc, np.asarray(m[:, :3], float),
                               np.asarray(m[:, 3], float), splits[im.name]))
    if not any(v.split == "train" for v in views):
        raise CtsplatError(f"{sfm_dir} has {len(views)} registered views and none left for training; raise "
                           "test_every or register more photos")
    pts = list(rec.points3D.values())
    xyz = np.array([p.xyz for p in pts], float).reshape(-1, 3)
    rgb = np.array([p.color for p in pts], float).reshape(-1, 3) / 255.0
    # 3DGS's radius of the training cameras alone: the held-out photos' positions must not shape training (the
    # means' learning rate and the densification thresholds scale with it)
    train = [v for v in views if v.split == "train"]
    extent = scene_extent([v.R for v in train], [v.t for v in train])
    return PhotoScene(views, xyz, rgb, extent, {"sfm_dir": str(sfm_dir), "downscale": int(downscale),
                                                "test_every": int(test_every),
                                                "validation_offset": validation_offset})
