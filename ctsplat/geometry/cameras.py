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
def _check_size(width: int, height: int) -> None:
    for name, n in (("width", width), ("height", height)):
        if int(n) != n or int(n) <= 0:
            raise CtsplatError(f"detector {name} must be a positive integer number of pixels, got {n!r}")


def _check_positive(name: str, value: float) -> None:
    if not (np.isfinite(value) and value > 0):
        raise CtsplatError(f"{name} must be a positive finite number of millimetres, got {value!r}")


@dataclass(frozen=True)
class ParallelCamera:
    """Parallel-beam (orthographic) detector.

    Parameters
    ----------
    width, height : int
        Detector size in pixels (W columns ``u``, H rows ``v``).
    spacing_mm : float
        Detector pixel spacing (mm); ``u = x_cam / spacing_mm + W/2``.
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
        return self.width / 2.0

    @property
    def cy(self) -> float:
        return self.height / 2.0

    def to_dict(self) -> dict[str, Any]:
        return {"model": self.model, "width": self.width, "height": self.height, "spacing_mm": self.spacing_mm,
                "cx": self.cx, "cy": self.cy}


@dataclass(frozen=True)
class ConeCamera:
    """Cone-beam (perspective) detector with the source at the camera centre.

    Parameters
    ----------
    width, height : int
        Detector size in pixels.
    pitch_mm : float
        Detector pixel pitch (mm) on the detector plane.
    dso_mm : float
        Source-to-object (isocentre) distance (mm).
    dsd_mm : float
        Source-to-detector distance (mm), ``> dso_mm``.

    Pinhole intrinsics (COLMAP ``PINHOLE``): ``fx = fy = dsd_mm / pitch_mm`` (pixels), ``cx = W/2``, ``cy = H/2``.
    A voxel at the isocentre is magnified by ``dsd_mm / dso_mm`` on the detector.
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
        return self.dsd_mm / self.pitch_mm

    @property
    def fy(self) -> float:
        return self.dsd_mm / self.pitch_mm

    @property
    def cx(self) -> float:
        return self.width / 2.0

    @property
    def cy(self) -> float:
        return self.height / 2.0

    @property
    def K(self) -> np.ndarray:
        """3x3 pinhole intrinsic matrix (pixels)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def magnification(self) -> float:
        return self.dsd_mm / self.dso_mm

    def to_dict(self) -> dict[str, Any]:
        return {"model": self.model, "width": self.width, "height": self.height, "pitch_mm": self.pitch_mm,
                "dso_mm": self.dso_mm, "dsd_mm": self.dsd_mm, "fx": self.fx, "fy": self.fy, "cx": self.cx,
                "cy": self.cy}


Camera = ParallelCamera | ConeCamera


def camera_from_dict(d: dict[str, Any]) -> Camera:
    """Inverse of ``camera.to_dict()`` (derived intrinsics are ignored and recomputed)."""
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
    """
    center = np.asarray(center, float)
    z = np.asarray(target, float) - center
    nz = np.linalg.norm(z)
    if nz == 0:
        raise CtsplatError("camera centre coincides with its target; use a positive distance")
    z = z / nz
    up = np.asarray(up, float)
    y = -up + np.dot(up, z) * z
    ny = np.linalg.norm(y)
    if ny < 1e-9:
        raise CtsplatError("view direction is parallel to the up-vector; keep |elevation| below 90 degrees")
    y = y / ny
    x = np.cross(y, z)
    R = np.stack([x, y, z])
    return R, -R @ center


def direction_from_angles(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit vector ``s`` from the isocentre towards the camera, shape (3,)."""
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


def pose_from_angles(azimuth_deg: float, elevation_deg: float, isocenter_mm: Sequence[float],
                     distance_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """``(R (3,3), t (3,))`` of the camera at ``iso + distance * s(azimuth, elevation)`` looking at the isocentre."""
    if abs(elevation_deg) >= 90.0:
        raise CtsplatError(f"elevation {elevation_deg} deg is out of range; keep |elevation| < 90")
    _check_positive("camera distance", distance_mm)
    iso = np.asarray(isocenter_mm, float)
    return look_at(iso + distance_mm * direction_from_angles(azimuth_deg, elevation_deg), iso)


def camera_center(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Camera centre in world mm: ``C = -R^T t``; works batched (``R (..., 3, 3)``, ``t (..., 3)``)."""
    return -np.einsum("...ji,...j->...i", R, t)


def world_to_camera(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``x_cam = R x + t`` for points (..., 3)."""
    return np.asarray(points, float) @ np.asarray(R, float).T + np.asarray(t, float)


def camera_to_world(points_cam: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``x = R^T (x_cam - t)`` for points (..., 3)."""
    return (np.asarray(points_cam, float) - np.asarray(t, float)) @ np.asarray(R, float)


def project_points(camera: Camera, R: np.ndarray, t: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project world points (N, 3) mm to continuous pixel coordinates.

    Returns
    -------
    uv : ndarray (N, 2)
        ``(u, v)``; a pixel's centre is at ``(u + 0.5, v + 0.5)``. ``nan`` for cone points with ``z_cam <= 0``.
    depth : ndarray (N,)
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

    Returns
    -------
    origins : ndarray (H, W, 3)
        Parallel: the pixel centre on the plane ``z_cam = 0``; cone: the source (camera centre).
    dirs : ndarray (H, W, 3)
        Unit direction of each ray (towards the detector).
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
    """Rotation matrix -> unit quaternion ``(w, x, y, z)`` with ``w >= 0`` (COLMAP ``qvec``)."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(np.asarray(R, float)).as_quat()
    q = np.array([w, x, y, z])
    return q if q[0] >= 0 else -q


def qvec_to_rotmat(qvec: Sequence[float]) -> np.ndarray:
    """COLMAP ``qvec (w, x, y, z)`` -> 3x3 rotation matrix (normalises the quaternion)."""
    w, x, y, z = np.asarray(qvec, float) / np.linalg.norm(qvec)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def c2w_from_Rt(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """OpenCV world-to-camera ``(R, t)`` -> 4x4 camera-to-world matrix ``[[R^T, C], [0, 1]]``."""
    M = np.eye(4)
    M[:3, :3] = np.asarray(R, float).T
    M[:3, 3] = camera_center(np.asarray(R, float), np.asarray(t, float))
    return M


def Rt_from_c2w(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """4x4 camera-to-world (OpenCV axes) -> world-to-camera ``(R, t)``."""
    c2w = np.asarray(c2w, float)
    R = c2w[:3, :3].T
    return R, -R @ c2w[:3, 3]


def opencv_to_opengl_c2w(c2w: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world (x right, y down, z forward) -> OpenGL/NeRF (x right, y up, z backward)."""
    return np.asarray(c2w, float) @ np.diag([1.0, -1.0, -1.0, 1.0])
