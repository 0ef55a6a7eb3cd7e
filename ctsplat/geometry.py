"""Scanner geometry: parallel- and cone-beam cameras, poses, view sets ("orbits") and splits.

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

import json
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ctsplat.utils import CtsplatError, write_json_atomic

__all__ = [
    "VIEWSET_FORMAT",
    "VIEWSET_FORMAT_VERSION",
    "SPLITS",
    "ParallelCamera",
    "ConeCamera",
    "Camera",
    "View",
    "ViewSet",
    "camera_from_dict",
    "look_at",
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
    "fibonacci_directions",
    "stratified_directions",
    "sphere_orbit",
    "circular_orbit",
    "assign_splits",
    "split_counts",
    "fov_outside_fraction",
    "check_fov",
]

VIEWSET_FORMAT = "ctsplat.viewset"
VIEWSET_FORMAT_VERSION = 1
SPLITS = ("train", "val", "test")


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


# ---------------------------------------------------------------------------------------- view sets
@dataclass
class View:
    """One radiograph's pose: world-to-camera ``R (3,3)``, ``t (3,)`` (mm), angles (degrees) and split."""

    id: int
    R: np.ndarray
    t: np.ndarray
    azimuth_deg: float
    elevation_deg: float
    split: str = "train"

    def __post_init__(self) -> None:
        self.R = np.asarray(self.R, float).reshape(3, 3)
        self.t = np.asarray(self.t, float).reshape(3)
        if self.split not in SPLITS:
            raise CtsplatError(f"view {self.id}: unknown split {self.split!r}; allowed: {', '.join(SPLITS)}")

    @property
    def center_mm(self) -> np.ndarray:
        return camera_center(self.R, self.t)

    def to_dict(self) -> dict[str, Any]:
        return {"id": int(self.id), "R": self.R.tolist(), "t": self.t.tolist(),
                "azimuth_deg": float(self.azimuth_deg), "elevation_deg": float(self.elevation_deg),
                "split": self.split, "qvec": rotmat_to_qvec(self.R).tolist(), "center_mm": self.center_mm.tolist()}


@dataclass
class ViewSet:
    """A camera plus a list of views rendered from one volume (``views.json``).

    JSON layout (``format = "ctsplat.viewset"``, ``format_version = 1``)::

        {"format": ..., "format_version": 1, "volume_id": str, "isocenter_mm": [x, y, z],
         "camera": {"model": "parallel", "width", "height", "spacing_mm", "cx", "cy"}
                 | {"model": "cone", "width", "height", "pitch_mm", "dso_mm", "dsd_mm", "fx", "fy", "cx", "cy"},
         "views": [{"id", "R" (3x3 world-to-camera), "t" (mm), "qvec" (COLMAP w,x,y,z), "center_mm",
                    "azimuth_deg", "elevation_deg", "split"}, ...],
         "meta": {...}}

    The row order of ``views`` is the page order of ``line_integrals.tif``.
    """

    camera: Camera
    views: list[View]
    volume_id: str = "unknown"
    isocenter_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.isocenter_mm = np.asarray(self.isocenter_mm, float).reshape(3)
        if not self.views:
            raise CtsplatError("empty view set: need at least one view (check n_views)")

    def __len__(self) -> int:
        return len(self.views)

    def Rs(self) -> np.ndarray:
        """Stacked rotations, shape (V, 3, 3)."""
        return np.stack([v.R for v in self.views])

    def ts(self) -> np.ndarray:
        """Stacked translations (mm), shape (V, 3)."""
        return np.stack([v.t for v in self.views])

    def ids(self) -> np.ndarray:
        return np.array([v.id for v in self.views], dtype=int)

    def indices(self, split: str) -> np.ndarray:
        """Row indices (into the image stack) of the views in ``split``."""
        if split not in SPLITS:
            raise CtsplatError(f"unknown split {split!r}; allowed: {', '.join(SPLITS)}")
        return np.array([i for i, v in enumerate(self.views) if v.split == split], dtype=int)

    def subset(self, split: str) -> ViewSet:
        """The views of one split (same camera); error if that split is empty."""
        idx = self.indices(split)
        if idx.size == 0:
            raise CtsplatError(f"view set has no '{split}' views; re-render with a non-zero {split} fraction")
        return ViewSet(self.camera, [self.views[i] for i in idx], self.volume_id, self.isocenter_mm.copy(),
                       dict(self.meta))

    def to_dict(self) -> dict[str, Any]:
        return {"format": VIEWSET_FORMAT, "format_version": VIEWSET_FORMAT_VERSION, "volume_id": self.volume_id,
                "isocenter_mm": self.isocenter_mm.tolist(), "camera": self.camera.to_dict(),
                "views": [v.to_dict() for v in self.views], "meta": self.meta}

    def save(self, path: str | Path) -> None:
        write_json_atomic(path, self.to_dict())

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ViewSet:
        if d.get("format") != VIEWSET_FORMAT:
            raise CtsplatError(f"not a ctsplat view set (format {d.get('format')!r}); expected {VIEWSET_FORMAT!r}")
        version = d.get("format_version")
        if version != VIEWSET_FORMAT_VERSION:
            raise CtsplatError(f"view set format_version {version} is not supported (this ctsplat reads "
                               f"{VIEWSET_FORMAT_VERSION}); re-render the radiographs")
        views = [View(int(v["id"]), v["R"], v["t"], v["azimuth_deg"], v["elevation_deg"], v["split"])
                 for v in d["views"]]
        return cls(camera_from_dict(d["camera"]), views, str(d.get("volume_id", "unknown")),
                   np.asarray(d.get("isocenter_mm", [0, 0, 0]), float), dict(d.get("meta", {})))

    @classmethod
    def load(cls, path: str | Path) -> ViewSet:
        path = Path(path)
        if not path.exists():
            raise CtsplatError(f"view set {path} does not exist; run `ctsplat project` first")
        try:
            d = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise CtsplatError(f"view set {path} is not valid JSON ({exc}); re-render it") from exc
        return cls.from_dict(d)


# ------------------------------------------------------------------------------------------ orbits
def fibonacci_directions(n: int, elevation_range_deg: Sequence[float] = (-60.0, 60.0),
                         azimuth_offset_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` (azimuth, elevation) pairs (degrees) of a Fibonacci lattice on the spherical band.

    Equal-area: ``sin(e_k)`` uniform on ``[sin e_min, sin e_max]`` at midpoints, azimuth by the golden angle
    ``a_k = offset + k * 180 (3 - sqrt 5)``. Ordered by elevation (index ``k``).
    """
    lo, hi = (math.sin(math.radians(x)) for x in elevation_range_deg)
    k = np.arange(n)
    z = lo + (hi - lo) * (k + 0.5) / n
    el = np.degrees(np.arcsin(z))
    az = np.mod(azimuth_offset_deg + k * 180.0 * (3.0 - math.sqrt(5.0)), 360.0)
    return az, el


def stratified_directions(n: int, elevation_range_deg: Sequence[float] = (-60.0, 60.0),
                          rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``n`` (azimuth, elevation) pairs (degrees), one random direction per equal-area cell of the band.

    The band is cut into ``b = round(sqrt(n / 2))`` rings of equal area (uniform in ``sin e``); ring ``r``
    gets ``n_r`` cells (largest remainder of ``n / b``), each an azimuth sector; one uniform point per cell.
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


def split_counts(n: int, fractions: dict[str, float]) -> dict[str, int]:
    """Largest-remainder allocation of ``n`` views to ``train/val/test`` by ``fractions``.

    A split with a positive fraction that would receive no view is an error (use more views or set its
    fraction to 0).
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
                               f"{dict(zip(SPLITS, f.round(3).tolist(), strict=True))}; use more views or set {s}: 0")
    return out


def assign_splits(azimuth_deg: np.ndarray, elevation_deg: np.ndarray, fractions: dict[str, float],
                  seed: int = 0) -> list[str]:
    """Seeded train/val/test labels, stratified over view direction.

    Views are ordered along the sphere (elevation rings of ``~sqrt(2n)`` views, azimuth inside each ring,
    serpentine). The test views are drawn one at random from each of ``n_test`` consecutive equal strata of
    that order, then the val views likewise from the remaining views, so held-out directions are spread
    over the orbit rather than clumped. Same inputs and seed -> same labels.
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
                   start_deg: float = 0.0, seed: int = 0, arc_deg: float = 360.0) -> list[View]:
    """Classical CT protocol: ``n_views`` training angles evenly over 360 deg plus random held-out angles.

    Training view ``k`` has azimuth ``start + 360 k / n_views`` about the world +z (axial) axis, so the
    training set is exactly what FBP/SART expect. Held-out (val/test) views are added at seeded random
    angles, one uniform angle per equal azimuth sector (stratified), with counts chosen so that the
    whole set follows ``split_fractions`` (train fraction = ``n_views`` / total; default 70/15/15, e.g.
    50 train + 11 val + 10 test). ``wobble_deg > 0`` adds an elevation ``wobble * sin(2 azimuth)`` to all
    views (a non-planar orbit; not usable for slice-wise FBP).

    ``arc_deg`` (default 360) is the angular range of the training angles (``start + arc k / n_views``)
    and of the held-out sectors. For *parallel* beams the views at ``a`` and ``a + 180`` are mirror images,
    so over 360 deg an even ``n_views`` gives only ``n_views / 2`` distinct directions while an odd one
    gives ``n_views`` interleaved ones; ``arc_deg=180`` gives ``n_views`` distinct directions for any count.
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
    for s in ("val", "test"):
        if fr[s] > 0 and held[s] == 0:
            raise CtsplatError(f"split leaves '{s}' empty: {n} training views with fractions {fr}; "
                               f"use more views or set {s}: 0")
    rng = np.random.default_rng(seed)
    az = [np.mod(start_deg + arc_deg * np.arange(n) / n, 360.0)]
    splits = ["train"] * n
    for s in ("val", "test"):
        m = held[s]
        if m:
            az.append(np.mod(start_deg + arc_deg * (np.arange(m) + rng.uniform(0, 1, m)) / m, 360.0))
            splits += [s] * m
    azimuth = np.concatenate(az)
    elevation = wobble_deg * np.sin(np.radians(2.0 * azimuth)) if wobble_deg else np.zeros_like(azimuth)
    return _views_from_angles(azimuth, elevation, splits, isocenter_mm, distance_mm)


# ------------------------------------------------------------------------------------ field of view
def fov_outside_fraction(camera: Camera, Rs: np.ndarray, ts: np.ndarray, points_mm: np.ndarray) -> np.ndarray:
    """Per view, the fraction of ``points_mm`` (N, 3) that project outside the detector (or behind a cone source).

    Returns an array (V,) in [0, 1].
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

    The object is the voxels with ``data > threshold * max(data)`` (all voxels if none), subsampled to
    ``max_points`` voxel centres. The warning names the fraction of the object outside the field of view.
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
        warnings.warn(
            f"detector does not cover the volume: {100 * worst:.1f}% of the object lies outside the field of view "
            f"in the worst view ({int(np.sum(frac > 0))}/{len(frac)} views affected); enlarge the detector or "
            "its pixel spacing",
            stacklevel=2,
        )
    return worst
