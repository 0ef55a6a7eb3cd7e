"""Test helper: a C-arm orbit (:func:`ctsplat.geometry.carm_orbit`) as stacked arrays."""

from __future__ import annotations

import numpy as np

from ctsplat.geometry import carm_orbit


def design_orbit(n_views: int, arc_deg: float, wobble_deg: float, wobble_cycles: float, dso_mm: float,
                 isocenter_mm: np.ndarray | None = None, *, jitter_deg: float = 0.0, jitter_mm: float = 0.0,
                 seed: int = 0) -> dict[str, np.ndarray]:
    """``Rs`` (V, 3, 3), ``ts`` (V, 3), ``centres`` (V, 3) mm, ``azimuth_deg``, ``elevation_deg`` (V,) of the true
    views of a C-arm orbit (the design itself when both jitters are 0)."""
    iso = np.zeros(3) if isocenter_mm is None else np.asarray(isocenter_mm, float)
    views = carm_orbit(n_views, iso, dso_mm, arc_deg=arc_deg, wobble_deg=wobble_deg, wobble_cycles=wobble_cycles,
                       jitter_deg=jitter_deg, jitter_mm=jitter_mm, seed=seed)
    return {"Rs": np.stack([v.R for v in views]), "ts": np.stack([v.t for v in views]),
            "centres": np.stack([v.center_mm for v in views]),
            "azimuth_deg": np.array([v.azimuth_deg for v in views]),
            "elevation_deg": np.array([v.elevation_deg for v in views])}
