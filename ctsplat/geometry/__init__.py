"""Scanner geometry: cameras and poses (:mod:`.cameras`), orbits and splits (:mod:`.orbits`).

Orbit names are resolved on first use: orbits build :class:`ctsplat.formats.viewset.View` objects, and the view-set
format itself needs the cameras, so importing both eagerly here would be circular.
"""

from typing import Any

from ctsplat.geometry.cameras import *  # noqa: F403
from ctsplat.geometry.cameras import __all__ as _cameras_all

_ORBIT_NAMES = ("arc_azimuths", "fibonacci_directions", "stratified_directions", "split_counts", "assign_splits",
                "sphere_orbit", "circular_orbit", "carm_orbit", "support_radius_mm", "fov_outside_fraction",
                "check_fov", "object_points_mm", "covering_spacing_mm", "check_orbit_settings")

__all__ = [*_cameras_all, *_ORBIT_NAMES]


def __getattr__(name: str) -> Any:
    if name in _ORBIT_NAMES:
        from ctsplat.geometry import orbits

        return getattr(orbits, name)
    raise AttributeError(f"module 'ctsplat.geometry' has no attribute {name!r}")
