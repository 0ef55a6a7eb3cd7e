"""The flash on the camera (ctsplat.photos.light): the falloff against its formula and gradcheck, the renderer's
colour factor against pre-scaled colours, and training / evaluation on a scene photographed with a flash."""

from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from ctsplat.geometry.cameras import look_at
from ctsplat.photos.config import photo_settings
from ctsplat.photos.dataset import PhotoScene, PhotoView, PinholeCamera, scene_extent
from ctsplat.photos.evaluate import evaluate_photos, turntable_poses
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


# ------------------------------------------------------------------------------------------------ photo path rules
# Tests of the photo path beyond the flash, added here by a mutation review (each pins a rule a surviving mutation
# broke). By topic they belong in test_photos.py (training log, evaluation, dataset, AlphaDensify), test_photos_mcmc.py
# (MCMCDensify) and test_photos_sfm.py (summary, matching mode).
sys.path.insert(0, str(Path(__file__).parent))
from test_photos import _jpeg, _synthetic_scene, _three_gaussians  # noqa: E402


@pytest.fixture(scope="module")
def short_run_log(tmp_path_factory: pytest.TempPathFactory) -> tuple[PhotoScene, dict[str, Any], list[dict[str, str]]]:
    """Eight iterations on the synthetic scene logged at every iteration (SH interval 3, no densification)."""
    torch.set_num_threads(2)
    scene, _ = _synthetic_scene()
    s = photo_settings({"train": {"iterations": 8, "log_every": 1, "sh_interval": 3, "sh_degree": 3,
                                  "densify": {"start": 100, "interval": 100, "opacity_reset_interval": 0}}})["train"]
    path = tmp_path_factory.mktemp("short_run") / "train_log.csv"
    train_scene(scene, s, path)
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    return scene, s, rows


def test_logged_loss_is_the_3dgs_blend_of_l1_and_dssim(
        short_run_log: tuple[PhotoScene, dict[str, Any], list[dict[str, str]]]) -> None:
    """Each logged loss is (1 - λ) L1 + λ (1 - SSIM) of the logged L1 and D-SSIM (Kerbl et al. 2023, eq. 7)."""
    _, s, rows = short_run_log
    lam = s["lambda_dssim"]
    assert lam == pytest.approx(0.2)
    trained = [r for r in rows if int(r["iteration"]) > 0]
    assert len(trained) == 8
    for r in trained:
        l1, dssim, loss = float(r["l1"]), float(r["dssim"]), float(r["loss"])
        assert l1 > 0.01 and dssim > 0.05  # both terms matter, so a wrong weight shows
        assert loss == pytest.approx((1 - lam) * l1 + lam * dssim, rel=1e-5)


def test_sh_degree_rises_by_one_after_every_interval(
        short_run_log: tuple[PhotoScene, dict[str, Any], list[dict[str, str]]]) -> None:
    """Degree 0 for iterations 1..k, 1 for k+1..2k, 2 for 2k+1..3k (k = sh_interval = 3)."""
    _, _, rows = short_run_log
    got = {int(r["iteration"]): int(r["sh_degree"]) for r in rows}
    assert got == {0: 0, 1: 0, 2: 0, 3: 0, 4: 1, 5: 1, 6: 1, 7: 2, 8: 2}


def test_means_learning_rate_decays_log_linearly_from_lr0_to_lr_final(
        short_run_log: tuple[PhotoScene, dict[str, Any], list[dict[str, str]]]) -> None:
    """lr_means is lr0·extent at the first iteration, lr_final·extent at the last, log-linear between (3DGS's
    exponential decay, get_expon_lr_func)."""
    scene, s, rows = short_run_log
    lr0, lr1 = s["lr"]["means"] * scene.extent, s["lr"]["means_final"] * scene.extent
    got = {int(r["iteration"]): float(r["lr_means"]) for r in rows if int(r["iteration"]) > 0}
    assert got[1] == pytest.approx(lr0, rel=1e-12) and got[8] == pytest.approx(lr1, rel=1e-12)
    for it, lr in got.items():
        t = (it - 1) / 7
        assert lr == pytest.approx(math.exp((1 - t) * math.log(lr0) + t * math.log(lr1)), rel=1e-12)


def test_seed_scale_is_the_rms_distance_to_the_three_nearest_other_points() -> None:
    """init_scale × sqrt(mean of the 3 smallest squared distances to other points), as 3DGS's distCUDA2 (brute
    force over all pairs, self excluded)."""
    from ctsplat.photos.train import init_params

    rng = np.random.default_rng(5)
    xyz = rng.uniform(-1, 1, (9, 3))
    s = {**photo_settings()["train"], "init_scale": 0.7}
    params = init_params(xyz, np.full((9, 3), 0.5), s, rng)
    d2 = ((xyz[:, None] - xyz[None]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    want = 0.7 * np.sqrt(np.sort(d2, axis=1)[:, :3].mean(1))
    got = torch.exp(params["log_scales"]).detach().double().numpy()
    np.testing.assert_allclose(got, np.repeat(want[:, None], 3, axis=1), rtol=1e-6)


def test_scene_extent_is_1_1_times_the_camera_ring_radius() -> None:
    """Cameras on a circle of radius r about their mean centre give 1.1·r (3DGS getNerfppNorm)."""
    centre = np.array([2.0, -1.0, 0.5])
    r = 3.0
    Rs, ts = [], []
    for k in range(7):
        a = 2 * np.pi * k / 7
        c = centre + r * np.array([np.cos(a), np.sin(a), 0.0])
        R, t = look_at(c, centre + [0.0, 0.0, -1.0], (0, 0, 1))
        Rs.append(R)
        ts.append(t)
    assert scene_extent(Rs, ts) == pytest.approx(1.1 * r, rel=1e-9)


def test_downscaled_size_rounds_to_nearest_like_the_loaded_image(tmp_path: Path) -> None:
    """1063x709 / 4 is 266x177 (round(265.75), round(177.25)) for the camera and for the loaded image alike."""
    from PIL import Image

    from ctsplat.photos.images import load_rgb

    path = tmp_path / "odd.png"
    Image.fromarray(np.zeros((709, 1063, 3), np.uint8)).save(path)
    q = PinholeCamera(1063, 709, 900.0, 900.0, 531.5, 354.5).scaled(4)
    assert (q.width, q.height) == (266, 177)
    assert load_rgb(path, 4).shape == (q.height, q.width, 3)
    assert q.fx == pytest.approx(900.0 * 266 / 1063) and q.fy == pytest.approx(900.0 * 177 / 709)


def test_turntable_ring_sits_at_the_photographs_mean_height() -> None:
    """The turntable cameras circle at the cameras' mean height above the point they look at (here 1.5)."""
    cam = PinholeCamera(32, 24, 30.0, 30.0, 16.0, 12.0)
    views = []
    for k in range(8):
        a = 2 * np.pi * k / 8
        c = np.array([3 * np.cos(a), 3 * np.sin(a), 1.5 + (0.5 if k % 2 else -0.5)])  # heights 1 and 2
        R, t = look_at(c, np.zeros(3), (0, 0, 1))
        views.append(PhotoView(f"{k}.png", torch.zeros(24, 32, 3), cam, R, t, "train"))
    poses = turntable_poses(views, 6)
    centres = np.stack([-R.T @ t for R, t in poses])
    np.testing.assert_allclose(centres[:, 2], 1.5, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(centres[:, :2], axis=1), 3.0, atol=1e-6)


def _skimage_ssim(img: np.ndarray, ref: np.ndarray) -> float:
    from skimage.metrics import structural_similarity

    return float(structural_similarity(img, ref, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                       data_range=1.0, channel_axis=2))


def test_evaluation_ssim_is_the_mean_of_per_view_ssim_and_the_gallery_spans_the_views(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """metrics ssim = mean of per_view_test.csv's SSIM (each skimage's Gaussian SSIM), psnr likewise; the gallery
    shows held-out views evenly spaced over the test set (two of six: the first and the last)."""
    import ctsplat.photos.evaluate as photo_eval

    torch.set_num_threads(2)
    scene, truth = _synthetic_scene()
    for k, v in enumerate(scene.views):
        v.split = "test" if k % 3 == 0 else "train"  # six held-out views: 00, 03, ..., 15
    model = Gaussians.from_values(truth.means, 0.14, 1.0, opacities=0.7, colors=truth.colors * 0.8)  # not the truth
    run = tmp_path / "run"
    run.mkdir()
    model.save(run / "model.pt")
    (run / "config.json").write_text(json.dumps({"sfm_dir": str(tmp_path / "sfm"),
                                                 "train": photo_settings()["train"]}))
    shown: list[list[str]] = []
    monkeypatch.setattr(photo_eval, "save_photo_gallery", lambda path, photos, renders, names, *a: shown.append(names))
    m = evaluate_photos(run, {"turntable_frames": 0, "gallery_views": 2}, scene=scene)
    assert shown == [["00.png", "15.png"]]
    with (run / "per_view_test.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["view_id"] for r in rows] == [f"{k:02d}.png" for k in range(0, 16, 3)]
    ssims = [float(r["ssim2d"]) for r in rows]
    assert 0.3 < min(ssims) and max(ssims) < 0.99  # a model that is not the truth: SSIM well inside (0, 1)
    assert m["ssim"] == pytest.approx(float(np.mean(ssims)), rel=1e-12) and m["ssim"] <= 1
    assert m["psnr"] == pytest.approx(float(np.mean([float(r["psnr2d"]) for r in rows])), rel=1e-12)
    v = scene.split("test")[1]
    with torch.no_grad():
        img = render_view(model, v, background=model.meta.get("background")).image.clamp(0, 1)
    assert ssims[1] == pytest.approx(_skimage_ssim(img.double().numpy(), v.image.double().numpy()), abs=1e-6)


def _densify_params(scales: list[float], opacity: float = 0.9) -> dict[str, torch.Tensor]:
    """Opaque isotropic Gaussians on the x axis (one per scale), seeded like training seeds them."""
    from ctsplat.photos.train import init_params

    n = len(scales)
    xyz = np.stack([np.arange(n, dtype=float), np.zeros(n), np.zeros(n)], 1)
    params = init_params(xyz, np.full((n, 3), 0.5), photo_settings()["train"], np.random.default_rng(0))
    with torch.no_grad():
        params["log_scales"][:] = torch.log(torch.tensor(scales))[:, None]
        params["opacity_raw"][:] = math.log(opacity / (1 - opacity))
    return params


def test_densify_budget_keeps_the_largest_gradients() -> None:
    """With room for two more Gaussians, the two with the largest mean gradients are the ones cloned."""
    from ctsplat.photos.densify import AlphaDensify
    from ctsplat.photos.train import _optimizer

    params = _densify_params([0.001] * 6)  # all small (clone) for an extent of 1
    opt = _optimizer(params, photo_settings()["train"]["lr"], 1.0)
    settings = {**photo_settings()["train"]["densify"], "start": 100, "max_gaussians": 8}
    dens = AlphaDensify(settings, iterations=1000, extent=1.0, means=params["means"])
    dens.grad_accum[:] = torch.tensor([5.0, 1.0, 4.0, 2.0, 3.0, 6.0]) * 1e-3  # all above grad_threshold
    dens.grad_count[:] = 1.0
    params, st = dens.step(params, opt, torch.Generator().manual_seed(0), iteration=100)
    assert (st["cloned"], st["split"], st["pruned"], st["n"]) == (2, 0, 0, 8)
    assert sorted(params["means"][6:, 0].tolist()) == [0.0, 5.0]  # copies of Gaussians 0 and 5


@pytest.mark.parametrize(("extent", "cloned", "split"), [(10.0, 1, 1), (1.0, 0, 2)])
def test_clone_split_boundary_is_percent_dense_times_the_extent(extent: float, cloned: int, split: int) -> None:
    """A Gaussian of σ 0.05 is cloned when percent_dense × extent (0.01 × 10) exceeds it and split when not (× 1);
    one of σ 0.5 is split either way."""
    from ctsplat.photos.densify import AlphaDensify
    from ctsplat.photos.train import _optimizer

    params = _densify_params([0.05, 0.5, 0.001, 0.001])
    opt = _optimizer(params, photo_settings()["train"]["lr"], extent)
    settings = {**photo_settings()["train"]["densify"], "start": 100}
    dens = AlphaDensify(settings, iterations=1000, extent=extent, means=params["means"])
    dens.grad_accum[:] = torch.tensor([1e-2, 1e-2, 0.0, 0.0])
    dens.grad_count[:] = 1.0
    params, st = dens.step(params, opt, torch.Generator().manual_seed(0), iteration=100)
    assert (st["cloned"], st["split"], st["pruned"]) == (cloned, split, 0)
    assert st["n"] == 4 + cloned + split


@pytest.mark.parametrize(("iteration", "wide_pruned"), [(200, False), (300, True)])
def test_size_prune_starts_after_the_first_reset_not_at_it(iteration: int, wide_pruned: bool) -> None:
    """3DGS prunes by size only when iteration > opacity_reset_interval: a step at the reset itself keeps wide
    Gaussians, the next one prunes them."""
    from ctsplat.photos.densify import AlphaDensify
    from ctsplat.photos.train import _optimizer

    params = _three_gaussians()  # wide (0.5 x the extent of 1), small, transparent
    opt = _optimizer(params, photo_settings()["train"]["lr"], 1.0)
    settings = {**photo_settings()["train"]["densify"], "start": 100, "opacity_reset_interval": 200}
    dens = AlphaDensify(settings, iterations=1000, extent=1.0, means=params["means"])
    params, st = dens.step(params, opt, torch.Generator().manual_seed(0), iteration=iteration)
    widths = torch.exp(params["log_scales"]).max(-1).values
    assert st["pruned"] == 1 + wide_pruned and st["cloned"] == st["split"] == 0
    assert bool((widths > 0.1).any()) != wide_pruned


def _mcmc_params(opacity: np.ndarray) -> dict[str, torch.Tensor]:
    from ctsplat.photos.train import init_params

    rng = np.random.default_rng(0)
    n = len(opacity)
    params = init_params(rng.normal(size=(n, 3)), rng.uniform(size=(n, 3)), photo_settings()["train"], rng)
    with torch.no_grad():
        params["opacity_raw"].copy_(torch.logit(torch.as_tensor(opacity, dtype=torch.float32)))
    return params


@pytest.mark.parametrize(("n", "growth", "want"), [(40, 1.5, 60), (50, 1.05, 52), (40, 2.0, 70)])
def test_mcmc_growth_reaches_growth_times_n_or_the_cap(n: int, growth: float, want: int) -> None:
    """After a step the count is min(cap_max, ⌊growth · n⌋) (cap 70): 60, 52 (⌊52.5⌋) and the cap."""
    from ctsplat.photos.mcmc import MCMCDensify
    from ctsplat.photos.train import _optimizer

    params = _mcmc_params(np.full(n, 0.5))
    opt = _optimizer(params, photo_settings()["train"]["lr"], 1.0)
    d = photo_settings()["train"]
    dens = MCMCDensify(d["densify"], {**d["mcmc"], "cap_max": 70, "growth": growth}, iterations=10)
    params, st = dens.step(params, opt, torch.Generator().manual_seed(0), iteration=1)
    assert st["n"] == params["means"].shape[0] == want == min(70, math.floor(growth * n))
    assert st["cloned"] == want - n and st["pruned"] == 0


def test_mcmc_gaussian_exactly_at_min_opacity_is_dead() -> None:
    """The docstring's dead test is opacity ≤ prune_opacity: Gaussians at exactly 0.5 with prune_opacity 0.5 are
    relocated onto the live ones."""
    from ctsplat.photos.mcmc import MCMCDensify
    from ctsplat.photos.train import _optimizer

    opacity = np.array([0.5, 0.9, 0.5, 0.8, 0.95, 0.5])
    params = _mcmc_params(opacity)
    assert bool((torch.sigmoid(params["opacity_raw"][[0, 2, 5]]) == 0.5).all())
    opt = _optimizer(params, photo_settings()["train"]["lr"], 1.0)
    d = photo_settings()["train"]
    dens = MCMCDensify({**d["densify"], "prune_opacity": 0.5}, {**d["mcmc"], "growth": 1.0}, iterations=10)
    live_means = params["means"].detach()[[1, 3, 4]].clone()
    params, st = dens.step(params, opt, torch.Generator().manual_seed(0), iteration=1)
    assert st["pruned"] == 3 and st["cloned"] == 0 and st["n"] == 6
    for i in (0, 2, 5):  # each former dead row now sits on a live Gaussian
        assert bool((live_means == params["means"].detach()[i]).all(1).any())


@pytest.mark.parametrize(("n", "want"), [(120, "exhaustive"), (121, "sequential"), (3, "exhaustive")])
def test_auto_matching_is_exhaustive_up_to_and_including_the_limit(n: int, want: str) -> None:
    """matching auto: exhaustive for n ≤ exhaustive_max_images (120), sequential above."""
    from ctsplat.photos.sfm import matching_mode

    s = photo_settings()["sfm"]
    assert s["exhaustive_max_images"] == 120
    assert matching_mode(s, n) == want


def test_sfm_summary_registration_rate_counts_the_unregistered_photos(tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """registration_rate = registered / photos (3 of 5 = 0.6) with the two others listed as unregistered; COLMAP
    is replaced by a model that registers 3 of the 5 photos (the summary is what is tested)."""
    import shutil
    from types import SimpleNamespace

    import ctsplat.photos.sfm as sfm

    photos = tmp_path / "photos"
    photos.mkdir()
    names = [f"{i:02d}.jpg" for i in range(5)]
    for i, name in enumerate(names):
        _jpeg(photos / name, seed=i)
    registered = ["00.jpg", "02.jpg", "03.jpg"]
    cam = SimpleNamespace(model=SimpleNamespace(name="PINHOLE"), params=np.array([60.0, 60.0, 32.0, 24.0]),
                          width=64, height=48)
    model = SimpleNamespace(
        images={i: SimpleNamespace(name=n, has_pose=True, camera_id=1) for i, n in enumerate(registered)},
        cameras={1: cam}, num_reg_images=lambda: len(registered), write_binary=lambda path: None,
        compute_mean_reprojection_error=lambda: 0.5, compute_mean_track_length=lambda: 3.0,
        num_points3D=lambda: 100)

    def undistort(out: Path, sparse: Path, image_dir: Path, num_threads: int) -> None:
        (out / "images").mkdir(parents=True)
        for n in registered:
            shutil.copy(image_dir / n, out / "images" / n)

    monkeypatch.setattr(sfm, "_extract_and_match", lambda *a: "exhaustive")
    monkeypatch.setattr(sfm, "_map", lambda *a: {0: model})
    monkeypatch.setattr(sfm, "write_model", lambda *a: None)
    monkeypatch.setattr(sfm, "pycolmap", SimpleNamespace(undistort_images=undistort, Reconstruction=lambda p: model))
    summary = sfm.run_photo_sfm(photos, tmp_path / "sfm")
    assert (summary["n_images"], summary["n_registered"]) == (5, 3)
    assert summary["registered"] == registered and summary["unregistered"] == ["01.jpg", "04.jpg"]
    assert summary["registration_rate"] == pytest.approx(3 / 5, rel=1e-12)
    assert json.loads((tmp_path / "sfm" / "summary.json").read_text())["registration_rate"] == pytest.approx(0.6)
