"""ctsplat.evaluation.readout: unsharp masking of the voxel read-out, its amount chosen on validation views."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter
from train_helpers import tiny_phantom, tiny_train_cfg, write_tiny_scene

from ctsplat.evaluation import evaluate
from ctsplat.evaluation.readout import choose_sharpening, sharpen
from ctsplat.formats.viewset import ViewSet
from ctsplat.formats.volume import Volume
from ctsplat.geometry import ConeCamera, circular_orbit
from ctsplat.projector import line_integrals
from ctsplat.recon.select import Validator
from ctsplat.training import train
from ctsplat.training.config import resolve_config
from ctsplat.utils import CtsplatError

MU = 0.02
AMOUNTS = [0.0, 0.2, 0.4, 0.6, 0.8, 1.0, 1.5]


def _balls(n: int = 24, h: float = 2.0) -> Volume:
    """Two balls and a thin slab (sharp edges): the object, normalised units, on an n³ grid of h mm voxels."""
    A = np.diag([h, h, h, 1.0])
    A[:3, 3] = -(n - 1) / 2 * h
    g = (np.arange(n) - (n - 1) / 2) * h
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    vol = 0.6 * ((X - 6) ** 2 + (Y + 4) ** 2 + Z**2 <= 64) + 0.3 * ((X + 8) ** 2 + (Y - 6) ** 2 + Z**2 <= 36)
    vol = vol + 0.4 * ((np.abs(Z - 8) <= 1) & (np.abs(X) <= 12) & (np.abs(Y) <= 12))
    return Volume(vol.astype(np.float32), A, {"volume_id": "balls", "intensity": {"mu_scale_per_mm": MU}})


def _views(vol: Volume, n_views: int, start_deg: float) -> ViewSet:
    n, h = vol.data.shape[0], 2.0
    L = n * h
    cam = ConeCamera(2 * n, 2 * n, 2 * L / (2 * n), 2.5 * L, 3.5 * L)
    views = circular_orbit(n_views, np.zeros(3), 2.5 * L, split_fractions={"train": 1.0}, arc_deg=360.0,
                           start_deg=start_deg)
    return ViewSet(cam, views, "balls", np.zeros(3))


@pytest.fixture(scope="module")
def validation() -> tuple[Volume, Validator]:
    vol = _balls()
    vs = _views(vol, 8, 11.0)
    p = line_integrals(vol.data * MU, vol.affine, vs.camera, vs.Rs(), vs.ts()).numpy()
    return vol, Validator(p, vs, vol)


def _mse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean((np.asarray(a, float) - b) ** 2))


def test_sharpen_is_unsharp_masking_clipped_at_zero() -> None:
    rng = np.random.default_rng(0)
    x = rng.random((10, 11, 12)).astype(np.float32)
    expected = np.clip(x + 0.7 * (x - gaussian_filter(x.astype(float), 1.3, mode="reflect")), 0, None)
    out = sharpen(x, amount=0.7, radius_voxels=1.3)
    assert out.dtype == np.float32 and out.shape == x.shape
    np.testing.assert_allclose(out, expected, atol=1e-5)
    assert out.min() >= 0 and (expected == 0).any()  # the clip acted
    np.testing.assert_array_equal(sharpen(x - 0.5, amount=0.0), np.clip(x - 0.5, 0, None))
    # a constant volume has no edges to sharpen
    np.testing.assert_allclose(sharpen(np.full((6, 6, 6), 0.3), amount=2.0), 0.3, atol=1e-6)


def test_from_views_scores_like_the_view_set_validator(validation) -> None:
    vol, v = validation
    vs = _views(vol, 8, 11.0)
    w = Validator.from_views(v.target, vs.camera, vs.Rs(), vs.ts(), vol.affine)
    blurred = gaussian_filter(vol.data, 1.0)
    assert w.score(blurred) == pytest.approx(v.score(blurred), abs=1e-9)
    with pytest.raises(CtsplatError, match=r"do not match 7 views"):
        Validator.from_views(v.target, vs.camera, vs.Rs()[:7], vs.ts()[:7], vol.affine)


def test_a_blurred_read_out_is_sharpened_towards_the_object(validation) -> None:
    vol, v = validation
    blurred = gaussian_filter(vol.data, 1.0)
    out, info = choose_sharpening(blurred, v, amounts=AMOUNTS, radius_voxels=1.0)
    assert info["sharpen_amount"] > 0
    assert len(info["sharpen_val_psnr"]) == len(AMOUNTS)
    assert info["sharpen_val_psnr"][AMOUNTS.index(info["sharpen_amount"])] == max(info["sharpen_val_psnr"])
    # chosen on the validation projections only, and closer to the object in 3D than the blurred read-out
    assert _mse(out, vol.data) < 0.8 * _mse(blurred, vol.data)
    np.testing.assert_allclose(out, sharpen(blurred, amount=info["sharpen_amount"], radius_voxels=1.0))


def test_a_sharp_read_out_is_left_as_it_is(validation) -> None:
    vol, v = validation
    out, info = choose_sharpening(vol.data, v, amounts=AMOUNTS, radius_voxels=1.0)
    assert info["sharpen_amount"] == 0.0
    np.testing.assert_array_equal(out, vol.data)


def test_amount_zero_is_the_volume_as_given_negative_values_included(validation) -> None:
    """An unclipped reconstruction (FBP/FDK with clip off) keeps its negative values when 0 wins, and is scored
    with them."""
    vol, v = validation
    ringing = (vol.data - 0.05 * (vol.data == 0)).astype(np.float32)  # undershoot in the air, as a ramp filter leaves
    out, info = choose_sharpening(ringing, v, amounts=[0.0], radius_voxels=1.0)
    np.testing.assert_array_equal(out, ringing)
    assert info["sharpen_val_psnr"] == [pytest.approx(v.score(ringing), abs=1e-12)]
    assert len(info["sharpen_filter_seconds"]) == 1


@pytest.mark.parametrize(("section", "message"), [
    ({"amounts": []}, r"train\.sharpen\.amounts must be a non-empty list of numbers in \[0, 4\]"),
    ({"amounts": [0, -0.1]}, r"train\.sharpen\.amounts must be .*got \[0, -0\.1\]"),
    ({"amounts": 0.4}, r"train\.sharpen\.amounts must be .*got 0\.4"),
    ({"amounts": [0, 5]}, r"train\.sharpen\.amounts must be"),
    ({"radius_voxels": 0}, r"train\.sharpen\.radius_voxels must be a number in \(0, 10\], got 0"),
    ({"radius_voxels": "1"}, r"train\.sharpen\.radius_voxels must be"),
])
def test_bad_sharpen_settings_fail_in_one_line(section, message) -> None:
    with pytest.raises(CtsplatError, match=message):
        resolve_config({"volume": "v.nii.gz", "radiographs": "rad", "sharpen": section})


def test_evaluate_sharpens_on_validation_and_keeps_the_raw_read_out(tmp_path: Path) -> None:
    data, aff = tiny_phantom()
    scene = write_tiny_scene(tmp_path / "scene", data, aff, volume_id="tiny_sharp", n_views=12)
    run = tmp_path / "run"
    train(tiny_train_cfg(scene, sharpen={"amounts": [0.0, 0.3, 0.6]}), run)
    m = evaluate(run, device="cpu")
    assert m["sharpen_amount"] in (0.0, 0.3, 0.6) and len(m["sharpen_val_psnr"]) == 3
    assert m["sharpen_seconds"] > 0
    for key in ("psnr3d", "ssim3d", "psnr3d_r2", "ssim3d_r2"):
        assert f"{key}_unsharpened" in m
    assert (run / "model_volume_unsharpened.nii.gz").exists()
    assert json.loads((run / "metrics.json").read_text())["sharpen_amount"] == m["sharpen_amount"]
    if m["sharpen_amount"] == 0.0:
        assert m["psnr3d"] == pytest.approx(m["psnr3d_unsharpened"])
    # switched off: no sharpening keys, and the earlier raw read-out is not left beside the new one
    m_off = evaluate(run, device="cpu", settings={"sharpen": {"amounts": [0.0], "radius_voxels": 1.0}})
    assert "sharpen_amount" not in m_off and "psnr3d_unsharpened" not in m_off
    assert m_off["psnr3d"] == pytest.approx(m["psnr3d_unsharpened"])
    assert not (run / "model_volume_unsharpened.nii.gz").exists()


def test_sharpening_without_validation_views_fails_before_training(tmp_path: Path) -> None:
    from ctsplat.formats.volume import save_volume
    from ctsplat.projector import render_radiographs

    data, aff = tiny_phantom()
    save_volume(Volume(data, aff, {"volume_id": "tiny_noval", "intensity": {"mu_scale_per_mm": MU}}),
                tmp_path / "volume.nii.gz")
    render_radiographs(tmp_path / "volume.nii.gz", tmp_path / "rad",
                       {"detector_width": 24, "detector_height": 24, "n_views": 10, "device": "cpu",
                        "split": {"train": 0.8, "val": 0.0, "test": 0.2}})
    with pytest.raises(CtsplatError, match=r"train\.sharpen\.amounts \[0\.0, 0\.5\] is chosen on validation views, "
                                           r"but the radiographs in .* have none"):
        train(tiny_train_cfg(tmp_path, sharpen={"amounts": [0.0, 0.5]}), tmp_path / "run")
    assert not (tmp_path / "run" / "model.pt").exists()


def test_gauge_aligned_metrics_score_the_sharpened_read_out(monkeypatch) -> None:
    """With the gauge motion the identity, the gauge-aligned pair equals the run's own ``psnr3d`` / ``ssim3d``: the
    moved read-out gets the amount chosen for the run's read-out, so the pair differs by the motion alone."""
    from types import SimpleNamespace

    import ctsplat.training.poses as poses
    from ctsplat.evaluation import run as ev

    ref = _balls().data
    read_out = gaussian_filter(ref, 1.2).astype(np.float32)
    monkeypatch.setattr(ev, "voxelize_model", lambda g, shape, affine, f=None: read_out)
    monkeypatch.setattr(ev, "gauge_aligned_model", lambda g, G, b: g)
    monkeypatch.setattr(poses, "gauge_motion", lambda Rs, ts, Rt, tt, model, **kw: (np.eye(3), np.zeros(3)))
    R = np.stack([np.eye(3)] * 4)
    train_views = SimpleNamespace(truth=lambda: (R, np.zeros((4, 3))), Rs=R, ts=np.full((4, 3), 1e-3),
                                  ids=np.arange(4), camera=SimpleNamespace(model="cone"))
    scene = SimpleNamespace(train=train_views, volume=SimpleNamespace(data=ref, shape=ref.shape, affine=np.eye(4),
                                                                      metric_range=1.0), isocenter_mm=np.zeros(3))
    for amount in (0.6, 0.0):
        info = {"sharpen_amount": amount, "sharpen_radius_voxels": 1.0}
        own = ev.volume_metrics(read_out if amount == 0 else sharpen(read_out, amount=amount), ref, data_range=1.0)
        got = ev._gauge_aligned_metrics(Path("no_run/refined_views.json"), None, scene, {}, info)
        assert got["psnr3d_gauge_aligned"] == pytest.approx(own["psnr3d"], abs=1e-9)
        assert got["ssim3d_gauge_aligned"] == pytest.approx(own["ssim3d"], abs=1e-9)
    unsharpened = ev._gauge_aligned_metrics(Path("no_run/refined_views.json"), None, scene, {}, {})
    assert unsharpened["psnr3d_gauge_aligned"] == pytest.approx(ev.volume_metrics(read_out, ref)["psnr3d"], abs=1e-9)
    assert unsharpened["psnr3d_gauge_aligned"] != pytest.approx(
        ev.volume_metrics(sharpen(read_out, amount=0.6), ref)["psnr3d"], abs=1e-3)
