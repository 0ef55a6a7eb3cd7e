"""Cameras and poses: parallel- and cone-beam detectors, world-to-camera transforms, COLMAP conversions.

Everything is in millimetres in the volume's world frame (NIfTI RAS+: +x = patient's right,
+y = anterior, +z = superior; see ``docs/conventions.md``).

Camera frame (OpenCV / COLMAP)
------------------------------
World-to-camera ``x_cam = R x_world + t``; camera +x = image right (column ``u``), +y = image down
(row ``v``), +z = forward along the rays. The camera centre is ``C = -R^T t``. Image arrays are indexed
``[v, u]`` (shape ``(H, W)``); pixel ``(u, v)`` covers ``[u, u+1) x [v, v+1)`` with its centre at
``(u + 0.5, v + 0.5)``.

- ``parallel``: ``u = x_cam / spacing + cx``, ``v = y_cam / spacing + cy``, ``cx = W/2``, ``cy = H/2``;
  every ray has direction ``+z_cam`` and starts on the plane ``z_cam = 0``.
- ``cone``: pinhole at the source (camera centre), detector plane at ``z_cam = DSD``, isocentre at
  ``z_cam = DSO``; ``u = fx x_cam / z_cam + cx`` with ``fx = fy = DSD / pitch``.

Azimuth, elevation and the up-vector
------------------------------------
A view at azimuth ``a`` and elevation ``e`` (degrees) puts the camera centre (the source, for cone beam) at

    C = iso + D s,   s = (cos e cos a, cos e sin a, sin e)

looking at the isocentre (``z_cam = -s``). Azimuth turns about the world +z (axial, superior) axis from
+x towards +y; elevation is positive above the axial plane. The image "up" (``-y_cam``) is the projection
of world +z onto the image plane, so radiographs show the head upright (superior at the top of the image):

    y_cam = normalise(-z_w + (z_w . z_cam) z_cam),   x_cam = y_cam x z_cam.

For ``e = 0``: ``z_cam = (-cos a, -sin a, 0)``, ``x_cam = (-sin a, cos a, 0)``, ``y_cam = (0, 0, -1)``.
With RAS+ world axes, ``a = 0`` is a lateral view from the patient's right, ``a = 90`` a frontal
(antero-posterior) view in which the patient's right appears on the image left (radiological display).
The parallel circular orbit at elevation 0 is exactly ``skimage.transform.radon`` of each axial slice
``mu[:, :, k]`` with ``theta = azimuth`` when the volume's axes are (+x, +y, +z) (tested).

|e| must stay below 90 degrees (the up-vector is undefined when looking along the z axis).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ctsplat.utils import CtsplatError

__all__ = [
    "ParallelCamera",
    "ConeCamera",
    "Camera",
    "camera_from_dict",
    "look_at",
    "direction_from_angles",
    "pose_from_angles",
    "camera_center",
    "world_to_camera",
    "camera_to_world",
    "project_points",
    "camera_rays",
    "rotmat_to_qvec",
    "qvec_to_rotmat",
    "c2w_from_Rt",
    "Rt_from_c2w",
    "opencv_to_opengl_c2w",
]

# --------------------------------------------------------------------------------------------- cameras
#: The most pixels a detector or image may have on a side.
MAX_PIXELS = 65536


def _check_size(width: int, height: int) -> None:
    for name, n in (("width", width), ("height", height)):
        try:  # a bool is an int to Python, not a pixel count
            whole = not isinstance(n, bool) and int(n) == n and 0 < int(n) <= MAX_PIXELS
        except (TypeError, ValueError, OverflowError):  # text, None, infinity, NaN
            whole = False
        if not whole:
            raise CtsplatError(f"detector {name} must be a whole number of pixels from 1 to {MAX_PIXELS}, got {n!r}")


def _check_positive(name: str, value: float) -> None:
    if not (np.isfinite(value) and value > 0):
        raise CtsplatError(f"{name} must be a positive finite number of millimetres, got {value!r}")


@dataclass(frozen=True)
class ParallelCamera:
    """Parallel-beam (orthographic) detector.

    Every ray runs along ``+z_cam`` from the plane ``z_cam = 0``; pixel ``(u, v)`` sees the ray through
    ``x_cam = (u + 0.5 - W/2) spacing_mm``, ``y_cam = (v + 0.5 - H/2) spacing_mm``.

    Parameters
    ----------
    width, height : int
        Detector size in pixels (W columns ``u``, H rows ``v``), positive.
    spacing_mm : float
        Detector pixel spacing (mm), positive; ``u = x_cam / spacing_mm + W/2``.

    Attributes
    ----------
    model : str
        ``"parallel"`` (set by the class, not an argument).

    Raises
    ------
    CtsplatError
        For a non-positive or non-integer size, or a non-positive spacing.

    Examples
    --------
    >>> cam = ParallelCamera(128, 128, 1.5)
    >>> cam.cx, cam.to_dict()["model"]
    (64.0, 'parallel')
    """

    width: int
    height: int
    spacing_mm: float
    model: str = field(default="parallel", init=False)

    def __post_init__(self) -> None:
        _check_size(self.width, self.height)
        _check_positive("detector pixel spacing_mm", self.spacing_mm)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "spacing_mm", float(self.spacing_mm))

    @property
    def cx(self) -> float:
        """Column of the optical axis (px): ``W / 2``, the detector's centre line."""
        return self.width / 2.0

    @property
    def cy(self) -> float:
        """Row of the optical axis (px): ``H / 2``."""
        return self.height / 2.0

    def to_dict(self) -> dict[str, Any]:
        """The camera as the JSON object stored in ``views.json``.

        Returns
        -------
        dict
            ``model``, ``width``, ``height``, ``spacing_mm`` and the derived ``cx``, ``cy`` (px), which
            :func:`camera_from_dict` ignores.
        """
        return {"model": self.model, "width": self.width, "height": self.height, "spacing_mm": self.spacing_mm,
                "cx": self.cx, "cy": self.cy}


@dataclass(frozen=True)
class ConeCamera:
    """Cone-beam (perspective) detector with the source at the camera centre.

    Pinhole intrinsics (COLMAP ``PINHOLE``): ``fx = fy = dsd_mm / pitch_mm`` (pixels), ``cx = W/2``, ``cy = H/2``.
    A voxel at the isocentre is magnified by ``dsd_mm / dso_mm`` on the detector.

    Parameters
    ----------
    width, height : int
        Detector size in pixels, positive.
    pitch_mm : float
        Detector pixel pitch (mm) on the detector plane, positive.
    dso_mm : float
        Source-to-object (isocentre) distance (mm), positive.
    dsd_mm : float
        Source-to-detector distance (mm), ``> dso_mm``.

    Attributes
    ----------
    model : str
        ``"cone"`` (set by the class, not an argument).

    Raises
    ------
    CtsplatError
        For a non-positive size or distance, or ``dsd_mm <= dso_mm``.

    Examples
    --------
    >>> cam = ConeCamera(256, 256, pitch_mm=1.0, dso_mm=1000.0, dsd_mm=1500.0)
    >>> cam.fx, cam.magnification
    (1500.0, 1.5)
    """

    width: int
    height: int
    pitch_mm: float
    dso_mm: float
    dsd_mm: float
    model: str = field(default="cone", init=False)

    def __post_init__(self) -> None:
        _check_size(self.width, self.height)
        _check_positive("detector pitch_mm", self.pitch_mm)
        _check_positive("dso_mm (source-to-object distance)", self.dso_mm)
        _check_positive("dsd_mm (source-to-detector distance)", self.dsd_mm)
        if self.dsd_mm <= self.dso_mm:
            raise CtsplatError(
                f"dsd_mm ({self.dsd_mm}) must be larger than dso_mm ({self.dso_mm}): "
                "the detector must lie behind the object"
            )
        for name in ("width", "height"):
            object.__setattr__(self, name, int(getattr(self, name)))
        for name in ("pitch_mm", "dso_mm", "dsd_mm"):
            object.__setattr__(self, name, float(getattr(self, name)))

    @property
    def fx(self) -> float:
        """Horizontal focal length (px): ``dsd_mm / pitch_mm``."""
        return self.dsd_mm / self.pitch_mm

    @property
    def fy(self) -> float:
        """Vertical focal length (px): ``dsd_mm / pitch_mm`` (square pixels)."""
        return self.dsd_mm / self.pitch_mm

    @property
    def cx(self) -> float:
        """Principal point column (px): ``W / 2``."""
        return self.width / 2.0

    @property
    def cy(self) -> float:
        """Principal point row (px): ``H / 2``."""
        return self.height / 2.0

    @property
    def K(self) -> np.ndarray:
        """Pinhole intrinsic matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``, shape (3, 3), pixels."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def magnification(self) -> float:
        """Geometric magnification at the isocentre, ``dsd_mm / dso_mm`` (dimensionless)."""
        return self.dsd_mm / self.dso_mm

    def to_dict(self) -> dict[str, Any]:
        """The camera as the JSON object stored in ``views.json``.

        Returns
        -------
        dict
            ``model``, ``width``, ``height``, ``pitch_mm``, ``dso_mm``, ``dsd_mm`` and the derived ``fx``, ``fy``,
            ``cx``, ``cy`` (px), which :func:`camera_from_dict` ignores.
        """
        return {"model": self.model, "width": self.width, "height": self.height, "pitch_mm": self.pitch_mm,
                "dso_mm": self.dso_mm, "dsd_mm": self.dsd_mm, "fx": self.fx, "fy": self.fy, "cx": self.cx,
                "cy": self.cy}


#: Either detector model; dispatch on ``camera.model`` (``"parallel"`` or ``"cone"``).
Camera = ParallelCamera | ConeCamera


def camera_from_dict(d: dict[str, Any]) -> Camera:
    """The camera described by a ``to_dict()`` object (derived intrinsics are ignored and recomputed).

    Parameters
    ----------
    d : dict
        ``model`` (``"parallel"`` or ``"cone"``) and that model's constructor fields (mm, px).

    Returns
    -------
    ParallelCamera or ConeCamera
        The camera, with its derived intrinsics recomputed.

    Raises
    ------
    CtsplatError
        For an unknown ``model`` or invalid field values.

    Examples
    --------
    >>> camera_from_dict({"model": "parallel", "width": 4, "height": 4, "spacing_mm": 1})
    ParallelCamera(width=4, height=4, spacing_mm=1.0, model='parallel')
    """
    model = d.get("model")
    if model == "parallel":
        return ParallelCamera(d["width"], d["height"], d["spacing_mm"])
    if model == "cone":
        return ConeCamera(d["width"], d["height"], d["pitch_mm"], d["dso_mm"], d["dsd_mm"])
    raise CtsplatError(f"unknown camera model {model!r}; allowed: parallel, cone")


# ----------------------------------------------------------------------------------------------- poses
def look_at(
    center: np.ndarray, target: np.ndarray, up: Sequence[float] = (0.0, 0.0, 1.0)
) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera ``(R, t)`` of a camera at ``center`` looking at ``target`` with world ``up`` at image top.

    ``z_cam = normalise(target - center)``, ``y_cam = normalise(-up + (up . z) z)``, ``x_cam = y_cam x z_cam``;
    rows of ``R`` are the camera axes in world coordinates, ``t = -R center``.

    Parameters
    ----------
    center : ndarray, shape (3,)
        Camera centre (the source, for cone beam), world mm.
    target : ndarray, shape (3,)
        Point on the optical axis, world mm.
    up : sequence of float, shape (3,)
        World direction shown towards the image top; default world +z (superior).

    Returns
    -------
    R : ndarray, shape (3, 3)
        World-to-camera rotation (OpenCV axes).
    t : ndarray, shape (3,)
        World-to-camera translation (mm).

    Raises
    ------
    CtsplatError
        When ``center == target`` or the view direction is parallel to ``up``.
    """
    center = np.asarray(center, float)
    z = np.asarray(target, float) - center
    nz = np.linalg.norm(z)
    if not np.isfinite(nz):
        raise CtsplatError(f"camera centre {center} or target {target} is not finite")
    if nz == 0:
        raise CtsplatError("camera centre coincides with its target; use a positive distance")
    z = z / nz
    up = np.asarray(up, float)
    y = -up + np.dot(up, z) * z
    ny = np.linalg.norm(y)
    if not ny >= 1e-9:  # (a NaN up-vector fails here too)
        raise CtsplatError("view direction is parallel to the up-vector; keep |elevation| below 90 degrees")
    y = y / ny
    x = np.cross(y, z)
    R = np.stack([x, y, z])
    return R, -R @ center


def direction_from_angles(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit vector ``s = (cos e cos a, cos e sin a, sin e)`` from the isocentre towards the camera.

    Parameters
    ----------
    azimuth_deg : float
        Azimuth ``a`` about world +z, from +x towards +y (degrees).
    elevation_deg : float
        Elevation ``e`` above the axial plane (degrees).

    Returns
    -------
    ndarray, shape (3,)
        World direction (unit length).

    Examples
    --------
    >>> direction_from_angles(90.0, 0.0).round(6)
    array([0., 1., 0.])
    """
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


def pose_from_angles(azimuth_deg: float, elevation_deg: float, isocenter_mm: Sequence[float],
                     distance_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Pose of the camera at ``iso + distance · s(azimuth, elevation)`` looking at the isocentre, world +z up.

    Parameters
    ----------
    azimuth_deg, elevation_deg : float
        View direction (degrees), see :func:`direction_from_angles`; ``|elevation_deg| < 90``.
    isocenter_mm : sequence of float, shape (3,)
        Isocentre, world mm.
    distance_mm : float
        Camera-centre distance from the isocentre (mm), positive (DSO for cone beam).

    Returns
    -------
    R : ndarray, shape (3, 3)
        World-to-camera rotation.
    t : ndarray, shape (3,)
        World-to-camera translation (mm).

    Raises
    ------
    CtsplatError
        For ``|elevation_deg| >= 90`` or a non-positive distance.

    Examples
    --------
    >>> R, t = pose_from_angles(0.0, 0.0, [0.0, 0.0, 0.0], 500.0)
    >>> camera_center(R, t).round(6) + 0.0  # + 0.0 turns -0.0 into 0.0
    array([500.,   0.,   0.])
    """
    if not abs(elevation_deg) < 90.0:  # (NaN included)
        raise CtsplatError(f"elevation {elevation_deg} deg is out of range; keep |elevation| < 90")
    _check_positive("camera distance", distance_mm)
    iso = np.asarray(isocenter_mm, float)
    return look_at(iso + distance_mm * direction_from_angles(azimuth_deg, elevation_deg), iso)


def camera_center(R: Any, t: Any) -> Any:
    """Camera centre ``C = -R^T t`` (world mm) of world-to-camera poses.

    Parameters
    ----------
    R : array_like or Tensor, shape (..., 3, 3)
        World-to-camera rotations.
    t : array_like or Tensor, shape (..., 3)
        World-to-camera translations (mm).

    Returns
    -------
    ndarray or Tensor, shape (..., 3)
        Camera centres (the source, for cone beam), world mm: a tensor (differentiable in ``R`` and ``t``, on
        their device) when ``R`` is one, else an ndarray.
    """
    if not isinstance(R, np.ndarray) and hasattr(R, "mT"):  # a torch tensor (this module does not import torch)
        return -(R.mT @ t) if R.ndim == 2 else -(R.mT @ t.unsqueeze(-1)).squeeze(-1)
    return -np.einsum("...ji,...j->...i", R, t)


def world_to_camera(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Map world points to the camera frame: ``x_cam = R x + t``.

    Parameters
    ----------
    points : ndarray, shape (..., 3)
        World points (mm).
    R : ndarray, shape (3, 3)
        World-to-camera rotation.
    t : ndarray, shape (3,)
        World-to-camera translation (mm).

    Returns
    -------
    ndarray, shape (..., 3)
        Camera-frame points (mm).
    """
    return np.asarray(points, float) @ np.asarray(R, float).T + np.asarray(t, float)


def camera_to_world(points_cam: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Map camera-frame points to the world: ``x = R^T (x_cam - t)``.

    Parameters
    ----------
    points_cam : ndarray, shape (..., 3)
        Camera-frame points (mm).
    R : ndarray, shape (3, 3)
        World-to-camera rotation.
    t : ndarray, shape (3,)
        World-to-camera translation (mm).

    Returns
    -------
    ndarray, shape (..., 3)
        World points (mm).
    """
    return (np.asarray(points_cam, float) - np.asarray(t, float)) @ np.asarray(R, float)


def project_points(camera: Camera, R: np.ndarray, t: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project world points to continuous pixel coordinates.

    Parameters
    ----------
    camera : ParallelCamera or ConeCamera
        The detector.
    R : ndarray, shape (3, 3)
        World-to-camera rotation.
    t : ndarray, shape (3,)
        World-to-camera translation (mm).
    points : ndarray, shape (N, 3)
        World points (mm).

    Returns
    -------
    uv : ndarray, shape (N, 2)
        ``(u, v)`` in px; pixel ``(i, j)`` covers ``[i, i+1) x [j, j+1)``, its centre at ``(i + 0.5, j + 0.5)``.
        ``nan`` for cone-beam points with ``z_cam <= 0`` (behind the source).
    depth : ndarray, shape (N,)
        ``z_cam`` (mm).
    """
    pc = world_to_camera(points, R, t)
    z = pc[..., 2]
    if camera.model == "parallel":
        u = pc[..., 0] / camera.spacing_mm + camera.cx
        v = pc[..., 1] / camera.spacing_mm + camera.cy
    else:
        with np.errstate(divide="ignore", invalid="ignore"):
            zz = np.where(z > 0, z, np.nan)
            u = camera.fx * pc[..., 0] / zz + camera.cx
            v = camera.fy * pc[..., 1] / zz + camera.cy
    return np.stack([u, v], axis=-1), z


def camera_rays(camera: Camera, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Detector rays through every pixel centre, in world mm.

    Parameters
    ----------
    camera : ParallelCamera or ConeCamera
        The detector, ``H`` rows by ``W`` columns.
    R : ndarray, shape (3, 3)
        World-to-camera rotation.
    t : ndarray, shape (3,)
        World-to-camera translation (mm).

    Returns
    -------
    origins : ndarray, shape (H, W, 3)
        Parallel: the pixel centre on the plane ``z_cam = 0``; cone: the source (camera centre). World mm.
    dirs : ndarray, shape (H, W, 3)
        Unit direction of each ray (towards the detector), world frame.
    """
    H, W = camera.height, camera.width
    v, u = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
    R = np.asarray(R, float)
    t = np.asarray(t, float)
    if camera.model == "parallel":
        pc = np.stack([(u - camera.cx) * camera.spacing_mm, (v - camera.cy) * camera.spacing_mm, np.zeros_like(u)], -1)
        origins = camera_to_world(pc, R, t)
        dirs = np.broadcast_to(R[2], origins.shape).copy()
    else:
        dc = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], -1)
        dc /= np.linalg.norm(dc, axis=-1, keepdims=True)
        dirs = dc @ R
        origins = np.broadcast_to(camera_center(R, t), dirs.shape).copy()
    return origins, dirs


# ---------------------------------------------------------------------------- OpenCV / COLMAP helpers
def rotmat_to_qvec(R: np.ndarray) -> np.ndarray:
    """Convert a rotation matrix to a unit quaternion ``(w, x, y, z)`` with ``w >= 0`` (COLMAP ``qvec``).

    Parameters
    ----------
    R : ndarray, shape (3, 3)
        Rotation matrix.

    Returns
    -------
    ndarray, shape (4,)
        ``(w, x, y, z)``, unit norm, sign chosen so that ``w >= 0``.

    Examples
    --------
    >>> rotmat_to_qvec(np.eye(3))
    array([1., 0., 0., 0.])
    """
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(np.asarray(R, float)).as_quat()
    q = np.array([w, x, y, z])
    return q if q[0] >= 0 else -q


def qvec_to_rotmat(qvec: Sequence[float]) -> np.ndarray:
    """Convert a COLMAP ``qvec (w, x, y, z)`` to a rotation matrix (the quaternion is normalised first).

    Parameters
    ----------
    qvec : sequence of float, shape (4,)
        Quaternion ``(w, x, y, z)``, any non-zero norm.

    Returns
    -------
    ndarray, shape (3, 3)
        Rotation matrix.
    """
    w, x, y, z = np.asarray(qvec, float) / np.linalg.norm(qvec)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def c2w_from_Rt(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Convert an OpenCV world-to-camera ``(R, t)`` to the camera-to-world matrix ``[[R^T, C], [0, 1]]``.

    Parameters
    ----------
    R : ndarray, shape (3, 3)
        World-to-camera rotation.
    t : ndarray, shape (3,)
        World-to-camera translation (mm).

    Returns
    -------
    ndarray, shape (4, 4)
        Camera-to-world matrix (OpenCV camera axes), with the camera centre ``C`` (world mm) in the last column.
    """
    M = np.eye(4)
    M[:3, :3] = np.asarray(R, float).T
    M[:3, 3] = camera_center(np.asarray(R, float), np.asarray(t, float))
    return M


def Rt_from_c2w(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Convert a camera-to-world matrix (OpenCV camera axes) to the world-to-camera ``(R, t)``.

    Parameters
    ----------
    c2w : ndarray, shape (4, 4)
        Camera-to-world matrix, translation in mm.

    Returns
    -------
    R : ndarray, shape (3, 3)
        World-to-camera rotation.
    t : ndarray, shape (3,)
        World-to-camera translation (mm).
    """
    c2w = np.asarray(c2w, float)
    R = c2w[:3, :3].T
    return R, -R @ c2w[:3, 3]


def opencv_to_opengl_c2w(c2w: np.ndarray) -> np.ndarray:
    """Convert a camera-to-world matrix from OpenCV axes (x right, y down, z forward) to OpenGL/NeRF axes.

    OpenGL/NeRF camera axes are x right, y up, z backward: the camera's y and z columns change sign.

    Parameters
    ----------
    c2w : ndarray, shape (4, 4)
        Camera-to-world matrix, OpenCV camera axes.

    Returns
    -------
    ndarray, shape (4, 4)
        Camera-to-world matrix, OpenGL camera axes (same centre).
    """
    return np.asarray(c2w, float) @ np.diag([1.0, -1.0, -1.0, 1.0])
