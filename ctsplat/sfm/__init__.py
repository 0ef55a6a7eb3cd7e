"""Structure from motion on radiographs: features (:mod:`.features`), COLMAP (:mod:`.colmap`), alignment and pose
errors (:mod:`.align`), isocentric bundle adjustment (:mod:`.bundle`) and the ``sfm`` step (:mod:`.step`)."""

from ctsplat.sfm.step import SFM_DEFAULTS, run_sfm

__all__ = ["SFM_DEFAULTS", "run_sfm"]
