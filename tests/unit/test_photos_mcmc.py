"""The MCMC density control of the photo path: the relocation rule against quadrature and the renderer, the
relocation and growth steps, the position noise, and training with it."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from ctsplat.config import check_section
from ctsplat.geometry.cameras import look_at
from ctsplat.photos.config import photo_settings
from ctsplat.photos.dataset import PinholeCamera
from ctsplat.photos.mcmc import MAX_COPIES, MCMCDensify, relocation
from ctsplat.photos.train import _optimizer, init_params, render_view, to_gaussians, train_scene
from ctsplat.utils import CtsplatError

sys.path.insert(0, str(Path(__file__).parent))
from test_photos import _synthetic_scene  # noqa: E402


@pytest.mark.parametrize("copies", [1, 2, 3, 7, 20, MAX_COPIES])
@pytest.mark.parametrize("opacity", [0.02, 0.3, 0.8, 0.99])
def test_copies_keep_the_peak_and_the_integrated_alpha(opacity: float, copies: int) -> None:
    s = 0.7
    o, sc = relocation(torch.tensor([opacity]), torch.full((1, 3), s), torch.tensor([copies]))
    o, s_new = float(o[0]), float(sc[0, 0])
    assert 1 - (1 - o) ** copies == pytest.approx(opacity, rel=1e-5)  # alpha at the centre
    x = np.linspace(-30 * s, 30 * s, 600_001)
    one = np.trapezoid(opacity * np.exp(-0.5 * (x / s) ** 2), x)
    many = np.trapezoid(1 - (1 - o * np.exp(-0.5 * (x / s_new) ** 2)) ** copies, x)
    assert many == pytest.approx(one, rel=1e-6)
    if copies == 1:
        assert (o, s_new) == pytest.approx((opacity, s), rel=1e-6)
    assert np.allclose(sc[0].numpy(), s_new)  # the same factor on every axis


def test_more_copies_than_the_limit_take_the_limit() -> None:
    args = torch.tensor([0.6, 0.6]), torch.ones(2, 3)
    a = relocation(*args, torch.tensor([MAX_COPIES, MAX_COPIES]))
    b = relocation(*args, torch.tensor([MAX_COPIES, 500]))
    assert torch.equal(a[0][0], b[0][1]) and torch.equal(a[1][0], b[1][1])


def _settings(**mcmc: float) -> dict:
    return photo_settings({"train": {"densify": {"strategy": "mcmc", "start": 0, "interval": 1},
                                     "mcmc": {"stop_fraction": 1.0, **mcmc}}})["train"]


def _params(n: int, opacity: np.ndarray | None = None, seed: int = 0) -> dict[str, torch.Tensor]:
    rng = np.random.default_rng(seed)
    s = _settings()
    m = max(n, 4)  # the seeding needs 4 points
    params = init_params(rng.normal(size=(m, 3)), rng.uniform(size=(m, 3)), s, rng)
    params = {k: v.detach()[:n].clone().requires_grad_(True) for k, v in params.items()}
    if opacity is not None:
        with torch.no_grad():
            params["opacity_raw"].copy_(torch.logit(torch.as_tensor(opacity, dtype=torch.float32)))
    return params


def _adam_after_one_step(params: dict[str, torch.Tensor]) -> torch.optim.Adam:
    opt = _optimizer(params, photo_settings()["train"]["lr"], 1.0)
    sum(v.square().sum() for v in params.values()).backward()
    opt.step()
    opt.zero_grad(set_to_none=True)
    return opt


def test_dead_gaussians_move_onto_live_ones_and_the_count_grows_to_the_cap() -> None:
    n = 40
    opacity = np.full(n, 0.5)
    opacity[:10] = 0.001  # dead
    opacity[10] = 0.95  # drawn most often
    params = _params(n, opacity)
    opt = _adam_after_one_step(params)
    before = {k: v.detach().clone() for k, v in params.items()}
    dens = MCMCDensify(_settings()["densify"], _settings(cap_max=43, growth=1.5)["mcmc"], iterations=10)
    params, stats = dens.step(params, opt, torch.Generator().manual_seed(0), iteration=1)
    assert stats == {"cloned": 3, "split": 0, "pruned": 10, "n": 43}
    o = torch.sigmoid(params["opacity_raw"].detach())
    assert bool((o > 0.005).all())
    # every row is a copy of a live Gaussian, with its opacity and scale changed by the rule only
    for i in range(43):
        j = int(torch.argmin((before["means"][10:] - params["means"][i].detach()).norm(dim=1))) + 10
        assert torch.equal(params["colors"][i].detach(), before["colors"][j])
        assert float(o[i]) <= float(torch.sigmoid(before["opacity_raw"][j])) + 1e-6
    # moved and copied rows restart their Adam moments; the untouched live rows keep theirs
    moments = opt.state[params["means"]]["exp_avg"]
    means = params["means"].detach()
    untouched = [i for i in range(10, 40) if torch.equal(means[i], before["means"][i])
                 and bool((means == means[i]).all(1).sum() == 1)]
    assert untouched and bool((moments[untouched] != 0).any(1).all())
    assert bool((moments[:10] == 0).all()) and bool((moments[40:] == 0).all())
    assert params["means"].requires_grad and opt.param_groups[0]["params"][0] is params["means"]


def test_a_copied_gaussian_renders_the_same_centre_and_nearly_the_same_image() -> None:
    cam = PinholeCamera(64, 64, 80.0, 80.0, 32.5, 32.5)  # the mean projects onto the centre of pixel (32, 32)
    R, t = look_at(np.array([0.0, -4.0, 0.0]), np.zeros(3), (0, 0, 1))
    params = _params(1, np.array([0.7]))
    with torch.no_grad():
        params["means"].zero_()
        params["log_scales"].fill_(np.log(0.3))
        params["colors"].fill_(1.0)
    one = render_view(to_gaussians(params, 0), None, cam, R, t).image.detach()
    opt = _adam_after_one_step(params)
    with torch.no_grad():
        params["means"].zero_()  # the Adam step moved it
        before = render_view(to_gaussians(params, 0), None, cam, R, t).image.detach()
    dens = MCMCDensify(_settings()["densify"], _settings(cap_max=3, growth=3.0)["mcmc"], iterations=10)
    params, stats = dens.step(params, opt, torch.Generator().manual_seed(0), iteration=1)
    assert stats["n"] == 3
    after = render_view(to_gaussians(params, 0), None, cam, R, t).image.detach()
    assert float(after[32, 32, 0]) == pytest.approx(float(before[32, 32, 0]), rel=1e-5)
    assert float(after.sum()) == pytest.approx(float(before.sum()), rel=0.05)
    assert float(one.sum()) > 0


def test_position_noise_follows_the_covariance_and_spares_opaque_gaussians() -> None:
    n = 20000
    opacity = np.where(np.arange(n) < n // 2, 0.004, 0.3)  # the gate opens only near zero opacity
    params = _params(n, opacity)
    with torch.no_grad():
        params["quats"].copy_(torch.tensor([1.0, 0.0, 0.0, 0.0]))
        params["log_scales"].copy_(torch.log(torch.tensor([0.1, 0.2, 0.4])))
    before = params["means"].detach().clone()
    dens = MCMCDensify(_settings()["densify"], _settings(noise_lr=100.0)["mcmc"], iterations=10)
    dens.perturb(params, torch.Generator().manual_seed(0), 0.5)
    d = (params["means"].detach() - before).numpy()
    assert np.abs(d[n // 2:]).max() < 1e-9  # the gate is 1.5e-13 at opacity 0.3
    gate = 1 / (1 + np.exp(-100 * (0.996 - 0.995)))
    expected = np.array([0.1, 0.2, 0.4]) ** 2 * gate * 0.5 * 100.0
    assert np.allclose(d[: n // 2].std(0), expected, rtol=0.03)
    assert np.abs(np.corrcoef(d[: n // 2].T) - np.eye(3)).max() < 0.03


def test_regulariser_is_the_weighted_mean_opacity_and_scale() -> None:
    params = _params(5, np.array([0.1, 0.2, 0.3, 0.4, 0.5]))
    dens = MCMCDensify(_settings()["densify"], _settings(opacity_reg=0.5, scale_reg=2.0)["mcmc"], iterations=10)
    expected = 0.5 * 0.3 + 2.0 * float(torch.exp(params["log_scales"].detach()).mean())
    assert float(dens.regularisation(params).detach()) == pytest.approx(expected, rel=1e-6)


def test_training_with_mcmc_learns_the_scene_and_is_deterministic() -> None:
    torch.set_num_threads(2)
    scene, _ = _synthetic_scene()
    s = photo_settings({"train": {"iterations": 400, "log_every": 1000, "sh_interval": 100, "init_opacity": 0.5,
                                  "init_scale": 0.5,
                                  "densify": {"strategy": "mcmc", "start": 100, "interval": 50},
                                  "mcmc": {"cap_max": 90, "growth": 1.2}}})["train"]
    model, report = train_scene(scene, s)
    assert report["n_gaussians"] == 90  # grown to the cap
    assert report["final_test_psnr"] > report["initial_test_psnr"] + 8 and report["final_test_psnr"] > 24
    again, _ = train_scene(scene, s)
    assert torch.equal(model.means, again.means) and torch.equal(model.colors, again.colors)


@pytest.mark.parametrize(("key", "value", "needle"), [
    ("densify", {"strategy": "mcm"}, "photos.train.densify.strategy"),
    ("mcmc", {"growth": 0.9}, "photos.train.mcmc.growth"),
    ("mcmc", {"cap_max": 0}, "photos.train.mcmc.cap_max"),
    ("init_scale", 0.0, "photos.train.init_scale"),
])
def test_bad_mcmc_settings_fail_naming_the_key(key: str, value: object, needle: str) -> None:
    with pytest.raises(CtsplatError, match=needle.replace(".", r"\.")):
        check_section("photos", {"train": {key: value}})


# ------------------------------------------------------------------------ growth and the dead rule
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
