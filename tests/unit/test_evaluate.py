"""Evaluation pieces: per-view metrics, voxelised model vs analytic Gaussian, turntable poses,
figures and GIF, speed/memory, and bad run folders."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from ctsplat.evaluation import metrics
from ctsplat.evaluation import run as ev
from ctsplat.utils import CtsplatError


def test_view_metrics_match_metrics_module() -> None:
    rng = np.random.default_rng(0)
    refs = rng.random((3, 16, 16)).astype(np.float32) * 5
    preds = refs + rng.normal(0, 0.1, refs.shape).astype(np.float32)
    vm = ev.view_metrics(preds, refs, with_lpips=True)
    for i in range(3):
        assert vm["psnr2d"][i] == pytest.approx(metrics.psnr(preds[i], refs[i]))
        assert vm["ssim2d"][i] == pytest.approx(metrics.ssim2d(preds[i], refs[i]))
    value, reason = metrics.lpips_distance(preds[0], refs[0])
    if value is None:  # never a made-up number
        assert vm["lpips"] == [None] * 3 and vm["lpips_reason"] == reason and reason
    else:
        assert vm["lpips"][0] == pytest.approx(value)
    with pytest.raises(ValueError):
        ev.view_metrics(preds[:2], refs)


def test_voxelize_model_matches_analytic_gaussian() -> None:
    from ctsplat.splat.gaussians import Gaussians

    m = np.array([[1.0, -2.0, 0.5]])
    s = np.array([[2.0, 3.0, 1.5]])
    g = Gaussians.from_values(m, s, np.array([0.7]), dtype=torch.float64)
    aff = np.diag([1.5, 1.5, 1.5, 1.0])
    aff[:3, 3] = -9.0
    vol = ev.voxelize_model(g, (13, 13, 13), aff)
    idx = np.stack(np.meshgrid(*[np.arange(13)] * 3, indexing="ij"), -1).astype(float)
    x = idx @ aff[:3, :3].T + aff[:3, 3]
    ref = 0.7 * np.exp(-0.5 * (((x - m[0]) / s[0]) ** 2).sum(-1))
    inside = (np.abs((x - m[0]) / s[0]) <= 3.0).all(-1)  # the renderer's 3-sigma footprint
    assert np.allclose(vol[inside], ref[inside], atol=1e-6)
    m3 = ev.volume_metrics(vol, ref.astype(np.float32))
    assert m3["psnr3d"] > 40 and m3["ssim3d"] > 0.99


def _rodrigues(axis: np.ndarray, angle: float) -> np.ndarray:
    k = axis / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def test_orbit_poses_rotate_scene_about_up_axis() -> None:
    from ctsplat.geometry import look_at

    c = np.array([3.0, -1.0, 2.0])
    R0, t0 = look_at(c + np.array([100.0, 0, 0]), c)
    Rs, ts = ev.orbit_poses(R0, t0, c, 8)
    assert np.allclose(Rs[0], R0) and np.allclose(ts[0], t0)
    x = np.random.default_rng(0).normal(size=(5, 3)) * 10
    axis = -R0[1]
    for k in (1, 3):
        Q = _rodrigues(axis, 2 * math.pi * k / 8)
        expect = (Q @ (x - c).T).T + c
        assert np.allclose(x @ Rs[k].T + ts[k], expect @ R0.T + t0, atol=1e-9)
        assert np.allclose(Rs[k] @ Rs[k].T, np.eye(3), atol=1e-12)
    # the camera centre stays at the same distance from the centre (a turntable)
    centres = [-R.T @ t for R, t in zip(Rs, ts, strict=True)]
    assert np.allclose([np.linalg.norm(p - c) for p in centres], 100.0)


def test_scaled_camera_keeps_field_of_view() -> None:
    from ctsplat.geometry import ConeCamera, ParallelCamera

    cam = ParallelCamera(128, 96, 2.0)
    big = ev.scaled_camera(cam, 1920, 1080)
    assert (big.width, big.height) == (1920, 1080)
    assert big.width * big.spacing_mm >= 128 * 2.0 - 1e-9 and big.height * big.spacing_mm >= 96 * 2.0 - 1e-9
    assert min(big.width * big.spacing_mm / 256, big.height * big.spacing_mm / 192) == pytest.approx(1.0)
    cone = ConeCamera(64, 64, 1.0, 500.0, 800.0)
    bc = ev.scaled_camera(cone, 1920, 1080)
    assert bc.pitch_mm == pytest.approx(64 / 1080) and bc.dso_mm == 500.0


def test_turntable_gif_and_figures(tmp_path) -> None:
    import imageio.v3 as iio

    from ctsplat.evaluation import figures

    frames = np.stack([np.full((10, 12), v, np.float32) for v in (0.0, 1.0, 3.0)])
    frames[:, 0, 0] = 2.0
    figures.save_turntable(tmp_path / "t.gif", frames)
    back = iio.imread(tmp_path / "t.gif", index=None)
    assert back.shape[:3] == (3, 10, 12)
    grey = back[..., 0] if back.ndim == 4 else back
    assert grey[0, 5, 5] == 0 and grey[2, 5, 5] == 255 and grey[1, 5, 5] == 85
    rng = np.random.default_rng(0)
    refs = rng.random((4, 16, 16))
    figures.save_gallery(tmp_path / "g.png", refs, refs + 0.1, [3, 4, 5, 6], np.array([20.0, 21, 22, 23]))
    figures.save_slices(tmp_path / "s.png", rng.random((8, 9, 10)), rng.random((8, 9, 10)))
    g = iio.imread(tmp_path / "g.png")
    s = iio.imread(tmp_path / "s.png")
    assert g.shape[0] > g.shape[1] / 2 and s.ndim == 3
    assert not list(tmp_path.glob(".*tmp*"))  # atomic writes left no temp files


def test_speed_and_memory() -> None:
    from ctsplat.geometry import ParallelCamera, look_at
    from ctsplat.splat.gaussians import Gaussians

    g = Gaussians.from_values(np.zeros((5, 3)), 1.0, 0.5)
    R, t = look_at(np.array([50.0, 0, 0]), np.zeros(3))
    fps = ev.forward_fps(g, ParallelCamera(16, 16, 1.0), R, t, {}, width=64, height=36, repeats=1)
    assert fps > 0 and math.isfinite(fps)
    mem, kind = ev.peak_memory_mb(torch.device("cpu"))
    assert kind == "process_peak_rss" and mem > 10


def test_evaluate_rejects_unfinished_run(tmp_path) -> None:
    with pytest.raises(CtsplatError, match="not a finished training run"):
        ev.evaluate(tmp_path)
