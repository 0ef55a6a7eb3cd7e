"""The flash on the camera (ctsplat.photos.light): the falloff against its formula and gradcheck, the renderer's
colour factor against pre-scaled colours, and training / evaluation on a scene photographed with a flash."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from ctsplat.geometry.cameras import look_at
from ctsplat.photos.config import photo_settings
from ctsplat.photos.dataset import PhotoScene, PhotoView, PinholeCamera, scene_extent
from ctsplat.photos.evaluate import evaluate_photos
from ctsplat.photos.light import flash_falloff, nearest_point_distance, reference_distance
from ctsplat.photos.train import render_view, train_scene
from ctsplat.splat.gaussians import Gaussians
from ctsplat.splat.render import render
from ctsplat.utils import CtsplatError


def test_falloff_is_the_reference_distance_over_the_distance_to_the_power_p() -> None:
    rng = np.random.default_rng(0)
    means, centre = rng.normal(size=(50, 3)), np.array([3.0, -1.0, 2.0])
    r = np.linalg.norm(means - centre, axis=1)
    for p in (0.0, 1.3, 2.0):
        got = flash_falloff(torch.tensor(means), torch.tensor(centre), exponent=p, r_ref=3.5).numpy()
        np.testing.assert_allclose(got, (3.5 / r) ** p, rtol=1e-12)
    pts = rng.normal(size=(200, 3)) + [1.0, 2.0, 3.0]
    cams = np.array([[1.0, 2.0, 7.0], [1.0, 2.0, -1.0]]) + np.median(pts, axis=0) - [1.0, 2.0, 3.0]
    assert reference_distance(cams, pts) == pytest.approx(4.0)


def test_near_bound_lights_nothing_more_than_the_nearest_point() -> None:
    rng = np.random.default_rng(3)
    centre = np.array([0.5, -2.0, 1.0])
    means = centre + rng.normal(size=(400, 3)) * 1.5  # some within r_min of the camera, most beyond
    r = np.linalg.norm(means - centre, axis=1)
    assert (r < 1.2).sum() > 20 and (r > 1.2).sum() > 100
    got = flash_falloff(torch.tensor(means), torch.tensor(centre), exponent=1.5, r_ref=3.0, r_min=1.2).numpy()
    np.testing.assert_allclose(got, (3.0 / np.maximum(r, 1.2)) ** 1.5, rtol=1e-12)
    assert got.max() == pytest.approx((3.0 / 1.2) ** 1.5)
    cams, pts = rng.normal(size=(7, 3)) * 4, rng.normal(size=(300, 3))
    brute = min(float(np.linalg.norm(c - q)) for c in cams for q in pts)
    assert nearest_point_distance(cams, pts) == pytest.approx(brute, rel=1e-12)


def test_falloff_gradients_match_finite_differences() -> None:
    gen = torch.Generator().manual_seed(1)
    means = torch.randn(6, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    centre = torch.tensor([4.0, 0.5, 1.0], dtype=torch.float64, requires_grad=True)
    p = torch.tensor(1.4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda m, c, e: flash_falloff(m, c, exponent=e, r_ref=3.0), (means, centre, p))


@pytest.mark.parametrize("backend", ["reference", "auto"])
def test_colour_factor_equals_rendering_scaled_colours(backend: str) -> None:
    gen = torch.Generator().manual_seed(2)
    n = 30
    means = (torch.rand(n, 3, generator=gen, dtype=torch.float64) - 0.5) * 1.5
    colors = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    scale = torch.rand(n, generator=gen, dtype=torch.float64) * 1.5 + 0.2
    cam = PinholeCamera(40, 32, 45.0, 45.0, 20.0, 16.0)
    R, t = look_at(np.array([0.0, -4.0, 1.0]), np.zeros(3), (0, 0, 1))
    g = Gaussians.from_values(means, 0.15, 1.0, opacities=0.7, colors=colors)
    pre = Gaussians.from_values(means, 0.15, 1.0, opacities=0.7, colors=colors * scale[:, None])
    kw = {"compositor": "alpha", "background": [0.2, 0.3, 0.4], "backend": backend}
    got = render(g, cam, R, t, color_scale=scale, **kw).image
    want = render(pre, cam, R, t, **kw).image
    assert float(want.abs().max()) > 0.3
    torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6)  # from_values makes float32 Gaussians


def test_colour_factor_refuses_a_wrong_shape_and_the_radiative_compositor() -> None:
    g = Gaussians.from_values(torch.zeros(3, 3), 0.2, 1.0, opacities=0.5, colors=torch.full((3, 3), 0.5))
    cam = PinholeCamera(16, 16, 20.0, 20.0, 8.0, 8.0)
    R, t = look_at(np.array([0.0, -4.0, 0.0]), np.zeros(3), (0, 0, 1))
    with pytest.raises(CtsplatError, match=r"color_scale has shape \(2,\); expected \(3,\)"):
        render(g, cam, R, t, compositor="alpha", color_scale=torch.ones(2))
    with pytest.raises(CtsplatError, match="color_scale only applies to the alpha compositor"):
        render(g, cam, R, t, compositor="radiative", color_scale=torch.ones(3))


def _flash_scene(exponent: float) -> tuple[PhotoScene, Gaussians]:
    """24 coloured Gaussians photographed with a flash (``exponent``) by 16 cameras at 3-5 units (64x48)."""
    gen = torch.Generator().manual_seed(0)
    n = 24
    means = (torch.rand(n, 3, generator=gen) - 0.5) * 1.2
    colors = torch.rand(n, 3, generator=gen) * 0.5 + 0.2
    truth = Gaussians.from_values(means, 0.12, 1.0, opacities=0.8, colors=colors)
    truth.meta["flash"] = {"exponent": exponent, "r_ref": 4.0}
    cam = PinholeCamera(64, 48, 60.0, 60.0, 32.0, 24.0)
    views = []
    for k in range(16):
        a = 2 * np.pi * k / 16
        d = 4.0 + (1.0 if k % 2 else -1.0)  # near and far photos in turn: the flash makes them differ
        centre = np.array([d * np.cos(a), d * np.sin(a), 0.5])
        R, t = look_at(centre, np.zeros(3), (0, 0, 1))
        with torch.no_grad():
            img = render_view(truth, None, cam, R, t).image.clamp(0, 1)
        views.append(PhotoView(f"{k:02d}.png", img, cam, R, t, "test" if k % 8 in (0, 3) else "train"))
    rng = np.random.default_rng(1)
    xyz = means.numpy() + rng.normal(0, 0.1, (n, 3))
    scene = PhotoScene(views, xyz, np.full((n, 3), 0.5), scene_extent([v.R for v in views], [v.t for v in views]))
    return scene, truth


def test_training_learns_the_flash_and_evaluation_applies_it(tmp_path: Path) -> None:
    torch.set_num_threads(2)
    scene, truth = _flash_scene(2.0)
    base = {"iterations": 400, "log_every": 1000, "sh_degree": 0,
            "densify": {"start": 100, "interval": 100, "opacity_reset_interval": 0}}
    on = photo_settings({"train": {**base, "flash": {"enabled": True, "exponent": 0.0, "lr": 0.02}}})["train"]
    off = photo_settings({"train": {**base, "flash": {"enabled": False}}})["train"]
    model, report = train_scene(scene, on)
    _, report_off = train_scene(scene, off)
    assert model.meta["flash"] == report["flash"] and report_off["flash"] is None
    assert 1.5 < report["flash"]["exponent"] < 2.5  # from 0 towards the true 2
    train_centres = [-v.R.T @ v.t for v in scene.split("train")]
    assert report["flash"]["r_ref"] == pytest.approx(reference_distance(train_centres, scene.xyz))
    assert report["flash"]["r_min"] == pytest.approx(nearest_point_distance(train_centres, scene.xyz))
    assert report["final_test_psnr"] > report_off["final_test_psnr"] + 3
    # the saved model carries its flash into evaluation; without it the same model renders other brightnesses
    run = tmp_path / "run"
    run.mkdir()
    truth.save(run / "model.pt")
    (run / "config.json").write_text(json.dumps({"sfm_dir": str(tmp_path / "sfm"), "train": on}))
    evaluate_settings = {"turntable_frames": 2, "gallery_views": 1, "attribution": "test"}
    assert evaluate_photos(run, evaluate_settings, scene=scene)["psnr"] > 40
    truth.meta.pop("flash")
    truth.save(run / "model.pt")
    assert evaluate_photos(run, evaluate_settings, scene=scene)["psnr"] < 30
