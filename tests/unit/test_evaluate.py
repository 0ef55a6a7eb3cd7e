"""Evaluation pieces: per-view metrics, voxelised model vs analytic Gaussian, turntable poses,
figures and GIF, speed/memory, and bad run folders."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from ctsplat.evaluation import metrics
from ctsplat.evaluation import run as ev
from ctsplat.utils import CtsplatError


def test_view_metrics_match_scikit_image_per_view() -> None:
    """Per view: PSNR and SSIM of scikit-image with each reference view's own range (line integrals have no fixed
    range); LPIPS a number only where the package exists, else null with a reason."""
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    rng = np.random.default_rng(0)
    refs = rng.random((3, 16, 16)).astype(np.float32) * np.array([5.0, 1.0, 20.0], np.float32)[:, None, None]
    preds = refs + rng.normal(0, 0.1, refs.shape).astype(np.float32)
    vm = ev.view_metrics(preds, refs, with_lpips=True)
    for i in range(3):
        r, p = refs[i].astype(np.float64), preds[i].astype(np.float64)
        span = r.max() - r.min()
        assert vm["psnr2d"][i] == pytest.approx(peak_signal_noise_ratio(r, p, data_range=span), rel=1e-9)
        assert vm["ssim2d"][i] == pytest.approx(structural_similarity(p, r, data_range=span), rel=1e-9)
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


def test_turntable_gif_and_figures(tmp_path, monkeypatch) -> None:
    import imageio.v3 as iio

    from ctsplat.evaluation import figures

    units = {}
    save_fig = figures._save_fig

    def record_units(fig, path):  # the colour bars' labels, read from the figure before it is written
        units[path.name] = {ax.get_ylabel() for ax in fig.axes if ax.get_label() == "<colorbar>"}
        save_fig(fig, path)

    monkeypatch.setattr(figures, "_save_fig", record_units)

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
    # every colour bar says its unit: line integrals in the gallery, the normalised volume in the slices
    assert units == {"g.png": {"line integral (normalised μ × mm)"}, "s.png": {"normalised μ"}}
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


# ------------------------------------------------------------------------------- R²-Gaussian's 3D metrics
def _r2_ssim_slice_torch(a: np.ndarray, b: np.ndarray) -> float:
    """R²-Gaussian's ``ssim`` for one slice, written out with torch's conv2d (11x11 Gaussian, σ 1.5, zero pad)."""
    x = torch.arange(11, dtype=torch.float64) - 5
    g = torch.exp(-(x**2) / (2 * 1.5**2))
    g = g / g.sum()
    win = (g[:, None] @ g[None, :])[None, None]
    i1 = torch.as_tensor(a, dtype=torch.float64)[None, None]
    i2 = torch.as_tensor(b, dtype=torch.float64)[None, None]
    conv = lambda v: torch.nn.functional.conv2d(v, win, padding=5)  # noqa: E731
    m1, m2 = conv(i1), conv(i2)
    s11, s22, s12 = conv(i1 * i1) - m1**2, conv(i2 * i2) - m2**2, conv(i1 * i2) - m1 * m2
    c1, c2 = 0.01**2, 0.03**2
    smap = ((2 * m1 * m2 + c1) * (2 * s12 + c2)) / ((m1**2 + m2**2 + c1) * (s11 + s22 + c2))
    return float(smap.mean())


def _r2_metric_vol_ssim(test: np.ndarray, ref: np.ndarray) -> float:
    """R²-Gaussian's ``metric_vol(ref, test, "ssim")`` as a slice loop: skip slices whose reference max <= 0."""
    per_axis = []
    for axis in range(3):
        vals = [_r2_ssim_slice_torch(np.take(test, i, axis), np.take(ref, i, axis))
                for i in range(ref.shape[axis]) if np.take(ref, i, axis).max() > 0]
        per_axis.append(sum(vals) / len(vals))
    return float(np.mean(per_axis))


def _volumes_with_empty_margins() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(3)
    ref = np.zeros((14, 17, 12))
    ref[3:11, 2:15, 4:9] = rng.random((8, 13, 5))  # empty slices on every axis
    test = np.clip(ref + rng.normal(0, 0.05, ref.shape), 0, None)  # noise in the empty margins too
    return test, ref


def test_ssim3d_r2_matches_a_slice_loop_of_r2_gaussians_ssim() -> None:
    test, ref = _volumes_with_empty_margins()
    assert metrics.ssim3d_r2(test, ref) == pytest.approx(_r2_metric_vol_ssim(test, ref), abs=1e-10)
    # the empty slices are skipped: counting them would change the value
    assert metrics.ssim3d_r2(test, ref) != pytest.approx(metrics.ssim3d(test, ref), abs=1e-3)


def test_ssim3d_treats_the_three_axes_alike() -> None:
    """The project's 3D SSIM averages over all three axes, so it cannot depend on how the volume is transposed;
    an error confined to slices of one axis still lowers the slices of the other two."""
    import itertools

    test, ref = _volumes_with_empty_margins()
    value = metrics.ssim3d(test, ref)
    for perm in itertools.permutations(range(3)):
        assert metrics.ssim3d(test.transpose(perm), ref.transpose(perm)) == pytest.approx(value, abs=1e-12), perm
    one_slice = ref.copy()
    one_slice[7] = 0.0  # one slice along axis 0 lost
    lost = metrics.ssim3d(one_slice, ref)
    assert 0.9 < lost < 1.0
    assert metrics.ssim3d(one_slice.transpose(1, 2, 0), ref.transpose(1, 2, 0)) == pytest.approx(lost, abs=1e-12)


def test_ssim_map_r2_interior_matches_skimage_gaussian_ssim() -> None:
    """Away from the zero-padded border R²'s SSIM is skimage's Gaussian-window SSIM with population variances."""
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(1)
    ref = rng.random((3, 30, 28))
    test = np.clip(ref + rng.normal(0, 0.1, ref.shape), 0, 1)
    smap = metrics.ssim_map_r2(test, ref, axis=0)
    for k in range(3):
        _, sk = structural_similarity(test[k], ref[k], data_range=1.0, gaussian_weights=True, sigma=1.5,
                                      use_sample_covariance=False, full=True)
        np.testing.assert_allclose(smap[k, 5:-5, 5:-5], sk[5:-5, 5:-5], atol=1e-10)


def test_psnr3d_r2_is_whole_volume_psnr_with_range_one() -> None:
    test, ref = _volumes_with_empty_margins()
    mse = np.mean((test - ref) ** 2)
    assert metrics.psnr3d_r2(test, ref) == pytest.approx(10 * np.log10(1 / mse))
    assert metrics.psnr3d_r2(test, ref) == pytest.approx(metrics.psnr3d(test, ref))  # same on [0, 1] volumes
    assert metrics.psnr3d_r2(ref, ref) == math.inf
    assert metrics.ssim3d_r2(ref, ref) == pytest.approx(1.0)


def test_r2_metrics_normalise_a_reference_outside_unit_range() -> None:
    test, ref = _volumes_with_empty_margins()
    test, ref = test / ref.max(), ref / ref.max()  # min-max of a reference with min 0: scale by its max
    assert metrics.psnr3d_r2(test * 40.0, ref * 40.0) == pytest.approx(metrics.psnr3d_r2(test, ref))
    assert metrics.ssim3d_r2(test * 40.0, ref * 40.0) == pytest.approx(metrics.ssim3d_r2(test, ref))


def test_r2_metrics_min_max_a_shifted_reference() -> None:
    """A reference with a non-zero minimum (HU-like, below 0) is min-max normalised with the test volume under the
    same map, min-max written out here; SSIM is not shift-invariant, so the shift must be removed."""
    test, ref = _volumes_with_empty_margins()
    test, ref = test / ref.max(), ref / ref.max()
    lo, hi = -1000.0, 2000.0
    shifted_test, shifted_ref = lo + (hi - lo) * test, lo + (hi - lo) * ref  # ref spans exactly [lo, hi]
    t, r = metrics.normalise_r2(shifted_test, shifted_ref)
    np.testing.assert_allclose(r, (shifted_ref - lo) / (hi - lo), atol=1e-12)
    np.testing.assert_allclose(t, (shifted_test - lo) / (hi - lo), atol=1e-12)
    assert metrics.ssim3d_r2(shifted_test, shifted_ref) == pytest.approx(metrics.ssim3d_r2(test, ref), abs=1e-9)
    assert metrics.psnr3d_r2(shifted_test, shifted_ref) == pytest.approx(metrics.psnr3d_r2(test, ref), abs=1e-9)


def test_r2_metrics_edge_cases() -> None:
    assert math.isnan(metrics.ssim3d_r2(np.ones((8, 8, 8)), np.zeros((8, 8, 8))))  # no slice counts
    with pytest.raises(ValueError, match="shape mismatch"):
        metrics.psnr3d_r2(np.zeros((4, 4, 4)), np.zeros((4, 4, 5)))
    with pytest.raises(ValueError, match="finite"):
        metrics.ssim3d_r2(np.full((4, 4, 4), np.nan), np.zeros((4, 4, 4)))
    with pytest.raises(ValueError, match="3D"):
        metrics.ssim3d_r2(np.zeros((4, 4)), np.zeros((4, 4)))
    tiny_ref = np.zeros((3, 3, 3))
    tiny_ref[1, 1, 1] = 1.0  # one non-empty slice per axis, smaller than the window: still defined
    assert metrics.ssim3d_r2(tiny_ref, tiny_ref) == pytest.approx(1.0)


def test_slice_figure_of_a_volume_in_per_mm_is_drawn_normalised(tmp_path, monkeypatch) -> None:
    """A volume ingested with ``intensity: mu`` holds 1/mm (here up to 0.06); the slice figure's fixed [0, 1] grey
    range gets it divided by the volume's metric range, as the 3D metrics do, not the raw values (near black)."""
    from train_helpers import tiny_phantom, tiny_train_cfg

    from ctsplat.evaluation import figures
    from ctsplat.formats.volume import Volume, save_volume
    from ctsplat.projector import render_radiographs
    from ctsplat.training import train

    data, aff = tiny_phantom()
    intensity = {"kind": "attenuation_per_mm", "mu_water_per_mm": 0.019, "hu_max": 3000.0, "mu_scale_per_mm": 1.0}
    vol = Volume(data * 0.06, aff, {"volume_id": "tiny_mu", "intensity": intensity})
    save_volume(vol, tmp_path / "volume.nii.gz")
    render_radiographs(tmp_path / "volume.nii.gz", tmp_path / "rad",
                       {"detector_width": 24, "detector_height": 24, "n_views": 12, "device": "cpu"})
    train(tiny_train_cfg(tmp_path, iterations=10, eval_every=10, checkpoint_every=10), tmp_path / "run")
    drawn = {}
    monkeypatch.setattr(figures, "save_slices", lambda path, model, ref: drawn.update(model=model, ref=ref))
    monkeypatch.setattr(figures, "save_gallery", lambda *a, **k: None)
    monkeypatch.setattr(figures, "save_turntable", lambda *a, **k: None)
    cfg = json.loads((tmp_path / "run" / "config.json").read_text())
    cfg["config"]["figures"] = True
    (tmp_path / "run" / "config.json").write_text(json.dumps(cfg))
    ev.evaluate(tmp_path / "run", device="cpu")
    scale = 0.019 * 4.0
    np.testing.assert_allclose(drawn["ref"], data * 0.06 / scale, atol=1e-6)
    assert 0.5 < float(drawn["ref"].max()) <= 1.0
    assert float(np.max(drawn["model"])) > 0.2  # the model's read-out, on the same scale
