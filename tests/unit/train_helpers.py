"""The tiny training scene the training tests share: a 20³ two-ellipsoid phantom and its parallel-beam view set."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

N = 20  # voxels per side
MU = 0.02  # mu_scale_per_mm


def tiny_phantom() -> tuple[np.ndarray, np.ndarray]:
    """(data (N, N, N) float32, affine (4, 4)): an ellipsoid with a brighter ball inside, 2 mm voxels."""
    x = np.stack(np.meshgrid(*[np.arange(N)] * 3, indexing="ij"), -1).astype(float)
    c = (N - 1) / 2
    outer = np.linalg.norm((x - c) / np.array([7.0, 6.0, 5.0]), axis=-1) < 1
    inner = np.linalg.norm((x - np.array([7.0, 9.0, 10.0])) / 2.5, axis=-1) < 1
    data = (0.6 * outer + 0.4 * inner).astype(np.float32)
    aff = np.diag([2.0, 2.0, 2.0, 1.0])
    aff[:3, 3] = -19.0
    return data, aff


def write_tiny_scene(root: Path, data: np.ndarray, aff: np.ndarray, *, volume_id: str, n_views: int) -> Path:
    """``root/volume.nii.gz`` and ``root/rad`` (24² parallel-beam radiographs, ``n_views`` training angles)."""
    from ctsplat.formats.volume import Volume, save_volume
    from ctsplat.projector import render_radiographs

    save_volume(Volume(data, aff, {"volume_id": volume_id, "intensity": {"mu_scale_per_mm": MU}}),
                root / "volume.nii.gz")
    render_radiographs(root / "volume.nii.gz", root / "rad",
                       {"detector_width": 24, "detector_height": 24, "n_views": n_views, "device": "cpu"})
    return root


def tiny_train_cfg(scene: Path, **kw: Any) -> dict[str, Any]:
    """A 30-iteration training config on the tiny scene (volume init, no TV, no figures); ``kw`` overrides."""
    cfg = {
        "volume": str(scene / "volume.nii.gz"), "radiographs": str(scene / "rad"), "init": "volume",
        "n_init": 300, "iterations": 30, "eval_every": 10, "checkpoint_every": 10, "device": "cpu",
        "densify": {"interval": 10, "start": 10}, "figures": False, "fps_width": 32, "fps_height": 18,
        "progress": False, "lambda_tv": 0.0,
    }
    cfg.update(kw)
    return cfg
