"""Scanner geometry: cameras and poses (:mod:`.cameras`), orbits and splits (:mod:`.orbits`)."""

from ctsplat.geometry.cameras import *  # noqa: F403
from ctsplat.geometry.cameras import __all__ as _cameras_all
from ctsplat.geometry.orbits import *  # noqa: F403
from ctsplat.geometry.orbits import __all__ as _orbits_all

__all__ = [*_cameras_all, *_orbits_all]
