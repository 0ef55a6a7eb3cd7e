"""Gaussian splatting of CT attenuation: the model container, the renderer (compositors, filters) and the voxelizer.

Public API, re-exported here: :class:`Gaussians` (``gaussians``), :func:`render`, :func:`project`,
:func:`voxelize`, :func:`compute_3d_filter`, :func:`random_region`, :func:`camera_intrinsics`,
:data:`COMPOSITORS` (``render``). ``render`` and ``voxelize`` dispatch between the fused C++ CPU kernels
(``_kernel``, sources in ``csrc/``) and their pure-PyTorch twins (``_reference``) with ``backend=``.
"""

from ctsplat.splat.gaussians import SH_C0, Gaussians, covariance, eval_sh, inverse_softplus, quat_to_rotmat
from ctsplat.splat.render import (
    BACKENDS,
    COMPOSITORS,
    Projection,
    RenderOutput,
    camera_intrinsics,
    compute_3d_filter,
    project,
    random_region,
    render,
    render_to_folder,
    resolved_backend,
    voxelize,
)

__all__ = [
    "SH_C0",
    "Gaussians",
    "covariance",
    "eval_sh",
    "inverse_softplus",
    "quat_to_rotmat",
    "BACKENDS",
    "COMPOSITORS",
    "Projection",
    "RenderOutput",
    "camera_intrinsics",
    "compute_3d_filter",
    "project",
    "random_region",
    "render",
    "resolved_backend",
    "render_to_folder",
    "voxelize",
]
