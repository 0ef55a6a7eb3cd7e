"""The method's training features, each behind a config key: pose/target augmentation (training views only), the
early density-regulariser schedule, error-driven densification, redundant-coverage pruning, the best-validation
model and the method's optimiser preset; plus their config errors."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from train_helpers import tiny_phantom, tiny_train_cfg, write_tiny_scene

from ctsplat.evaluation import evaluate
from ctsplat.geometry.cameras import ParallelCamera, look_at, project_points
from ctsplat.splat.gaussians import Gaussians
from ctsplat.splat.render import render
from ctsplat.training import config, features, loop, state
from ctsplat.training.densify import ErrorDensify, GradientDensify, make_densify, reset_stats
from ctsplat.utils import CtsplatError


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory) -> Path:
    data, aff = tiny_phantom()
    return write_tiny_scene(tmp_path_factory.mktemp("scene"), data, aff, volume_id="tiny01", n_views=12)


_cfg = tiny_train_cfg


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra @ Rb.T) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


# --- 1. augmentation ---------------------------------------------------------------------------------------------

def test_perturb_pose_stays_within_bounds_and_is_seeded():
    cam = ParallelCamera(32, 32, 1.5)
    R, t = look_at(np.array([300.0, 20.0, 10.0]), np.array([5.0, -3.0, 2.0]))
    center = np.array([5.0, -3.0, 2.0])
    u0, _ = project_points(cam, R, t, center[None])
    rng = np.random.default_rng(0)
    angles, shifts = [], []
    for _ in range(300):
        R2, t2 = features.perturb_pose(R, t, center, 1.0, 1.0 * features.pixel_mm(cam), rng)
        assert np.allclose(R2 @ R2.T, np.eye(3), atol=1e-12)
        angles.append(_angle_deg(R2, R))
        u1, _ = project_points(cam, R2, t2, center[None])
        shifts.append(float(np.linalg.norm(u1 - u0)))  # the centre moves by the shift only (rotation about it)
    assert max(angles) <= 1.0 + 1e-9 and max(shifts) <= 1.0 + 1e-9
    assert max(angles) > 0.8 and max(shifts) > 0.8  # the bounds are reached, not a no-op
    again = features.perturb_pose(R, t, center, 1.0, 1.5, np.random.default_rng(7))
    assert all(np.array_equal(a, b) for a, b in zip(again, features.perturb_pose(R, t, center, 1.0, 1.5,
                                                                               np.random.default_rng(7)), strict=True))


def test_augmenter_disabled_draws_nothing_and_noise_has_its_std():
    cam = ParallelCamera(16, 16, 2.0)
    R, t = torch.eye(3), torch.zeros(3)
    off = features.Augmenter({"enabled": False, "rot_deg": 1.0, "shift_px": 1.0, "target_noise": 0.1}, cam,
                             np.zeros(3))
    rng = np.random.default_rng(3)
    before = rng.bit_generator.state
    assert off.pose(R, t, rng) == (R, t) and rng.bit_generator.state == before
    ref = torch.zeros(4, 64, 64)
    assert off.target(ref, torch.Generator().manual_seed(0)) is ref
    on = features.Augmenter({"enabled": True, "rot_deg": 0.0, "shift_px": 0.0, "target_noise": 0.01}, cam,
                            np.zeros(3))
    noisy = on.target(ref, torch.Generator().manual_seed(0))
    assert abs(float(noisy.std()) - 0.01) < 5e-4 and abs(float(noisy.mean())) < 5e-4


def test_training_renders_perturbed_poses_and_validation_the_true_ones(scene_dir, tmp_path, monkeypatch):
    from ctsplat.scene import load_scene

    train_poses, val_poses = [], []
    real_render, real_views = loop.render, loop.render_views

    def rec_render(g, cam, R, t, **kw):
        train_poses.append((R.detach().numpy().astype(float), t.detach().numpy().astype(float)))
        return real_render(g, cam, R, t, **kw)

    def rec_views(g, cam, Rs, ts, rk):
        val_poses.append((np.array(Rs), np.array(ts)))
        return real_views(g, cam, Rs, ts, rk)

    monkeypatch.setattr(loop, "render", rec_render)
    monkeypatch.setattr(loop, "render_views", rec_views)
    cfg = _cfg(scene_dir, iterations=12, augment={"enabled": True, "rot_deg": 1.0, "shift_px": 1.0})
    loop.train(cfg, tmp_path / "run")
    scene = load_scene(config.resolve_config(cfg))
    assert len(train_poses) == 12 and val_poses
    for R, _ in train_poses:
        nearest = min(_angle_deg(R, Rt) for Rt in scene.train.Rs)
        assert 0 < nearest <= 1.0 + 1e-4  # moved, within the bound
    for Rs, ts in val_poses:  # validation: exactly the recorded poses of the validation views
        assert all(any(np.array_equal(R, Rv) and np.array_equal(t, tv) for Rv, tv in zip(scene.val.Rs, scene.val.ts,
                                                                                       strict=True))
                   for R, t in zip(Rs, ts, strict=True))


# --- 2. density-regulariser schedule ------------------------------------------------------------------------------

def test_density_lambda_schedule_values():
    w = {"factor": 10.0, "fraction": 0.15, "decay": 0.05}
    lam = [features.density_lambda(2e-5, i, 1000, w) for i in range(1000)]
    assert lam[0] == lam[150] == pytest.approx(2e-4)
    assert lam[175] == pytest.approx(2e-5 * (1 + 9 * 0.5))
    assert lam[200] == lam[999] == pytest.approx(2e-5)
    assert all(a >= b for a, b in zip(lam, lam[1:], strict=False))  # never increases
    assert features.density_lambda(2e-5, 0, 1000, {**w, "factor": 1.0}) == 2e-5  # factor 1: off


def test_loop_uses_the_density_schedule(scene_dir, tmp_path, monkeypatch):
    from ctsplat.training import losses

    seen = []
    real = losses.total_loss

    def rec(*a, **kw):
        seen.append(kw["lambda_density"])
        return real(*a, **kw)

    monkeypatch.setattr(losses, "total_loss", rec)
    loop.train(_cfg(scene_dir, iterations=10, lambda_density=1e-3,
                    lambda_density_warmup={"factor": 5.0, "fraction": 0.2, "decay": 0.2}), tmp_path / "run")
    want = [features.density_lambda(1e-3, i, 10, {"factor": 5.0, "fraction": 0.2, "decay": 0.2}) for i in range(10)]
    assert seen == pytest.approx(want) and seen[0] == pytest.approx(5e-3) and seen[-1] == pytest.approx(1e-3)


# --- 3. error-driven densification ---------------------------------------------------------------------------------

def _box_volume(side_mm: int = 40):
    """An empty volume of 1 mm voxels centred on the origin (extent ``side_mm``)."""
    from ctsplat.formats.volume import Volume

    aff = np.diag([1.0, 1.0, 1.0, 1.0])
    aff[:3, 3] = -side_mm / 2
    return Volume(np.zeros((side_mm,) * 3, np.float32), aff, {})


def _state_of(means, scales, dens) -> state.TrainState:
    g = Gaussians.from_values(np.asarray(means, float), np.asarray(scales, float), np.asarray(dens, float))
    params = {k: v.detach().clone().requires_grad_(True) for k, v in g.tensors().items() if k in state.PARAM_GROUPS}
    st = state.TrainState(params=params, opt=state.make_optimizer(params, {"lr": config.TRAIN_DEFAULTS["lr"]}, 1.0))
    reset_stats(st)
    return st


def _plane_scene() -> tuple[dict, ParallelCamera, torch.Tensor, torch.Tensor, np.ndarray]:
    """A 6 x 6 grid of Gaussians seen face-on by a parallel camera; returns params, camera, pose and pixel centres."""
    xs = np.linspace(-15, 15, 6)
    means = np.array([[0.0, x, y] for x in xs for y in xs])
    g = Gaussians.from_values(means, 1.0, 0.5)
    params = {k: v.detach().clone().requires_grad_(True) for k, v in g.tensors().items()
              if k in state.PARAM_GROUPS}
    cam = ParallelCamera(48, 48, 1.0)
    R, t = look_at(np.array([200.0, 0.0, 0.0]), np.zeros(3))
    uv, _ = project_points(cam, R, t, means)
    return params, cam, torch.as_tensor(R, dtype=torch.float32), torch.as_tensor(t, dtype=torch.float32), uv


@pytest.mark.parametrize("strategy", ["error", "both"])
def test_error_densify_selects_the_gaussians_under_a_planted_residual(strategy):
    params, cam, R, t, uv = _plane_scene()
    st = state.TrainState(params=params, opt=state.make_optimizer(params, {"lr": config.TRAIN_DEFAULTS["lr"]}, 1.0))
    reset_stats(st)
    settings = {**config.TRAIN_DEFAULTS["densify"], "strategy": strategy, "grad_threshold": 1e9}
    dens = make_densify(settings, compositor="radiative", iterations=100)
    assert isinstance(dens, ErrorDensify) and dens.wants_error
    out = render(state.as_gaussians(params), cam, R, t)
    residual = torch.full_like(out.image, 1e-3)
    planted = [7, 22]  # 4 x 4 px patches of large residual centred on these Gaussians' projections
    for i in planted:
        u, v = (int(round(x)) for x in uv[i])
        residual[v - 2:v + 2, u - 2:u + 2] = 1.0
    ratios = dens.error_ratios(st, out.image, residual, out.visible)
    dens.accumulate_error(st, ratios)
    cand, _ = dens.candidates(st)
    inside = np.isin(np.arange(len(uv)), planted)
    assert np.array_equal(cand.numpy(), inside)
    # the graph is still usable for the loss's backward, and a step densifies exactly those Gaussians
    out.image.sum().backward()
    n0 = params["means"].shape[0]
    counts = dens.step(st, _box_volume(), torch.Generator().manual_seed(0))
    assert counts["cloned"] + counts["split"] == int(inside.sum()) and counts["n"] == n0 + int(inside.sum())


def test_error_statistic_of_alpha_is_the_blending_weighted_mean_residual():
    """For alpha the weights are the blending weights α_i T_i (the colour's derivative), not the opacity's
    derivative, which changes sign across a footprint: a dark Gaussian in front of a bright one."""
    from types import SimpleNamespace

    g = Gaussians.from_values(np.array([[0.0, 0.0, -5.0], [3.0, 0.0, 5.0]]), np.array([4.0, 3.0]),
                              np.array([1.0, 1.0]), opacities=np.array([0.6, 0.9]), colors=np.array([[0.1], [1.0]]))
    params = {k: v.detach().clone().requires_grad_(True) for k, v in g.tensors().items()}
    cam = ParallelCamera(32, 32, 1.0)
    R, t = torch.eye(3), torch.tensor([0.0, 0.0, 100.0])
    out = render(Gaussians(**params), cam, R, t, compositor="alpha")
    residual = torch.rand(32, 32, generator=torch.Generator().manual_seed(0))
    dens = make_densify({**config.TRAIN_DEFAULTS["densify"], "strategy": "error"}, compositor="alpha",
                        iterations=100)
    cover, ratio = dens.error_ratios(SimpleNamespace(params=params), out.image, residual, out.visible)
    # brute force: each Gaussian's weight map is the change of the image when its colour alone moves
    e = []
    for i in range(2):
        bumped = {k: v.detach().clone() for k, v in params.items()}
        bumped["colors"][i] += 1.0
        with torch.no_grad():
            w = render(Gaussians(**bumped), cam, R, t, compositor="alpha").image - out.image.detach()
        assert (w >= -1e-6).all()
        e.append(float((w * residual).sum() / w.sum()))
    assert cover.tolist() == [True, True]
    np.testing.assert_allclose(ratio.numpy(), np.array(e) / np.mean(e), rtol=1e-4)
    assert all(float(residual.min()) <= x <= float(residual.max()) for x in e)


def test_gradient_statistic_does_not_depend_on_the_batch_size():
    # a loss averaged over a batch of views gives each view 1/B of its own loss's gradient; `loss_views` scales it
    # back, so a batch of two views adds the same statistic as the two views one at a time
    params, cam, R, t, _ = _plane_scene()
    side = [torch.as_tensor(a, dtype=torch.float32) for a in look_at(np.array([0.0, 200.0, 0.0]), np.zeros(3))]
    poses = [(R, t), tuple(side)]
    ndc = torch.tensor([cam.width / 2, cam.height / 2], dtype=torch.float32)
    target = torch.zeros(cam.height, cam.width)

    def statistic(batches: list[list[int]]) -> torch.Tensor:
        st = state.TrainState(params=params, opt=state.make_optimizer(params, {"lr": config.TRAIN_DEFAULTS["lr"]},
                                                                       1.0))
        reset_stats(st)
        for batch in batches:
            outs = [render(state.as_gaussians(params), cam, *poses[k]) for k in batch]
            loss = torch.stack([(o.image - target).abs().mean() for o in outs]).mean()
            loss.backward()
            for o in outs:
                GradientDensify.accumulate(st, o.means2d.grad, o.visible, ndc, loss_views=len(outs))
            for p in params.values():
                p.grad = None
        return st.grad_accum.clone()

    one_at_a_time, batched = statistic([[0], [1]]), statistic([[0, 1]])
    assert float(one_at_a_time.max()) > 0
    torch.testing.assert_close(batched, one_at_a_time, rtol=1e-5, atol=1e-12)


def test_gradient_strategy_is_the_default():
    d = make_densify(config.TRAIN_DEFAULTS["densify"], compositor="radiative", iterations=10)
    assert type(d) is GradientDensify and not d.wants_error


def test_error_densify_trains_and_densifies(scene_dir, tmp_path):
    res = loop.train(_cfg(scene_dir, iterations=20, densify={"interval": 10, "start": 10, "strategy": "error",
                                                             "error_ratio": 1.2}), tmp_path / "run")
    assert res["densify_cloned"] + res["densify_split"] > 0


# --- 4. redundant-coverage pruning -----------------------------------------------------------------------------------

@pytest.mark.parametrize("offset", [0.0, 0.05])
def test_redundant_pruning_removes_a_duplicate_and_keeps_the_image(offset):
    rng = np.random.default_rng(1)
    means = rng.uniform(-12, 12, (40, 3))
    scales = rng.uniform(1.0, 2.5, (40, 3))
    dens = rng.uniform(0.2, 1.0, 40)
    # Gaussian 5 split into two halves, the copy shifted by `offset` x its mean scale
    means = np.vstack([means, means[5] + offset * scales[5].mean() * np.array([1.0, 0.0, 0.0])])
    scales = np.vstack([scales, scales[5]])
    dens = np.append(dens, dens[5] / 2)
    dens[5] /= 2
    st = _state_of(means, scales, dens)
    cam = ParallelCamera(40, 40, 1.0)
    poses = [look_at(200.0 * np.array([math.cos(a), math.sin(a), 0.1]), np.zeros(3)) for a in (0.0, 1.0, 2.2)]
    before = [render(state.as_gaussians(st.params), cam, R, t).image.detach() for R, t in poses]
    settings = {**config.TRAIN_DEFAULTS["densify"], "prune_redundant": {"enabled": True, "distance": 0.1,
                                                                        "scale_tol": 0.1, "cov_tol": 0.1}}
    removed = GradientDensify(settings, compositor="radiative", iterations=10).merge(st)
    assert removed == 1 and st.params["means"].shape[0] == 40
    after = [render(state.as_gaussians(st.params), cam, R, t).image.detach() for R, t in poses]
    for a, b in zip(before, after, strict=True):
        err = float((a - b).abs().max() / a.abs().max())
        assert err < (1e-5 if offset == 0 else 0.05)
    # disabled, or nothing coincident: nothing removed
    assert GradientDensify(config.TRAIN_DEFAULTS["densify"], compositor="radiative", iterations=10).merge(st) == 0
    assert GradientDensify(settings, compositor="radiative", iterations=10).merge(st) == 0


def test_redundant_merge_under_alpha_keeps_the_pair_s_combined_opacity():
    """Two coincident Gaussians of opacities o1, o2 cover their centre pixel by 1 - (1 - o1)(1 - o2) under alpha
    compositing; the kept one takes that opacity, every other Gaussian is left as it was."""
    rng = np.random.default_rng(2)
    means = np.vstack([rng.uniform(-12, 12, (6, 3)), [[1.0, 2.0, 3.0]] * 2])
    g = Gaussians.from_values(means, np.full((8, 3), 1.5), 1.0, opacities=[0.2, 0.4, 0.6, 0.8, 0.5, 0.9, 0.3, 0.5])
    params = {k: v.detach().clone() for k, v in g.tensors().items() if k in state.PARAM_GROUPS}
    settings = {"enabled": True, "distance": 0.1, "scale_tol": 0.1, "cov_tol": 0.1}
    drop, updates = features.merge_redundant(params, settings, "alpha")
    assert drop.tolist() == [False] * 7 + [True] and set(updates) == {"opacity_raw"}
    kept = torch.sigmoid(updates["opacity_raw"]).numpy()
    assert kept[6] == pytest.approx(1 - (1 - 0.3) * (1 - 0.5), abs=1e-6)
    np.testing.assert_allclose(kept[:6], [0.2, 0.4, 0.6, 0.8, 0.5, 0.9], atol=1e-6)


def test_prune_until_end_removes_what_grew_after_densification_stopped():
    rng = np.random.default_rng(0)
    means = rng.uniform(-10, 10, (12, 3))
    scales = np.full((12, 3), 1.0)
    scales[3] = [1.0, 9.0, 1.0]  # longer than 0.2 x the 40 mm extent
    dens = np.full(12, 0.5)
    dens[7] = 1e-6  # below prune_density
    st = _state_of(means, scales, dens)
    # an Adam step so that the moments exist and must follow the pruned rows
    sum(v.sum() for v in st.params.values()).backward()
    st.opt.step()
    settings = {**config.TRAIN_DEFAULTS["densify"], "interval": 10, "start": 10, "stop": 20, "prune_until_end": True}
    dens_rule = GradientDensify(settings, compositor="radiative", iterations=35)
    assert [i for i in range(1, 36) if dens_rule.prune_due(i)] == [30, 35]
    assert [i for i in range(1, 36) if dens_rule.due(i)] == [10, 20]
    before = st.params["means"].detach().clone()
    assert dens_rule.maybe_step(st, 25, _box_volume(), torch.Generator()) is None
    counts = dens_rule.maybe_step(st, 30, _box_volume(), torch.Generator())
    assert counts == {"cloned": 0, "split": 0, "pruned": 2, "merged": 0, "n": 10}
    kept = [i for i in range(12) if i not in (3, 7)]
    assert torch.equal(st.params["means"].detach(), before[kept])
    for group in st.opt.param_groups:
        for prm in group["params"]:
            assert st.opt.state[prm]["exp_avg"].shape == prm.shape
    # off: nothing after densification stops
    off = GradientDensify({**settings, "prune_until_end": False}, compositor="radiative", iterations=35)
    assert not any(off.prune_due(i) for i in range(1, 36))


def test_alpha_pruning_reads_the_opacity_that_is_rendered_not_the_unused_density():
    rng = np.random.default_rng(1)
    st = _state_of(rng.uniform(-10, 10, (6, 3)), np.full((6, 3), 1.0), [1e-6, 1.0, 1.0, 1.0, 1.0, 1.0])
    opacity = torch.tensor([0.95, 1e-6, 0.5, 0.5, 0.5, 0.5])
    st.params["opacity_raw"] = torch.logit(opacity).requires_grad_(True)  # Gaussian 0 opaque, Gaussian 1 invisible
    st.params["colors"] = torch.full((6, 1), 0.5, requires_grad=True)
    st.opt = state.make_optimizer(st.params, {"lr": config.TRAIN_DEFAULTS["lr"]}, 1.0)
    reset_stats(st)
    settings = {**config.TRAIN_DEFAULTS["densify"], "interval": 10, "start": 10, "stop": 20, "prune_until_end": True}
    alpha = GradientDensify(settings, compositor="alpha", iterations=30)
    assert torch.equal(state.amplitude(st.params, "alpha"), torch.sigmoid(st.params["opacity_raw"].detach()))
    counts = alpha.maybe_step(st, 30, _box_volume(), torch.Generator())
    assert counts["pruned"] == 1 and counts["n"] == 5
    kept = torch.sigmoid(st.params["opacity_raw"].detach())
    assert float(kept[0]) == pytest.approx(0.95) and float(kept.min()) > 0.4  # the opaque one stays
    assert torch.equal(state.amplitude(st.params, "radiative"),
                       torch.nn.functional.softplus(st.params["density_raw"].detach()))


# --- 5. best-validation model ----------------------------------------------------------------------------------------

def test_model_best_is_the_best_validation_checkpoint_and_evaluate_uses_it(scene_dir, tmp_path):
    out = tmp_path / "run"

    def spoil(it: int, st: state.TrainState) -> None:  # after iteration 20 the model loses most of its mass
        if it == 20:
            with torch.no_grad():
                st.params["density_raw"] -= 4.0

    trained = loop.train(_cfg(scene_dir, iterations=40, collapse_psnr_drop_db=0.0, densify={"interval": 0}), out,
                         callback=spoil)
    rows = _rows(out / "train_log.csv")
    psnr = [float(r["psnr2d"]) for r in rows]
    best_it = int(rows[int(np.argmax(psnr))]["iteration"])
    assert best_it == 20 and psnr[-1] < psnr[1]  # the best is not the last
    assert (out / "model_best.pt").is_file()
    assert trained["best_iteration"] == best_it and trained["best_val_psnr"] == pytest.approx(max(psnr))
    best = Gaussians.load(out / "model_best.pt")
    assert best.meta["iteration"] == best_it
    # the validation PSNR of the stored best model is the logged maximum (all validation views are logged here)
    m_best = evaluate(out, split="val", device="cpu", model="best", write=False)
    assert m_best["model"] == "best" and m_best["model_iteration"] == best_it
    assert m_best["psnr2d"] == pytest.approx(max(psnr), abs=1e-4)
    m_last = evaluate(out, device="cpu")
    assert m_last["model"] == "last" and m_last["model_iteration"] == 40
    assert json.loads((out / "metrics.json").read_text())["model"] == "last"
    m = evaluate(out, device="cpu", model="best")
    assert json.loads((out / "metrics.json").read_text())["model"] == "best" and m["model_iteration"] == best_it
    assert {r["iteration"] for r in _rows(out / "per_view_test.csv")} == {str(best_it)}  # the model's own iteration
    # its size is its own: a best model of half the Gaussians reports the PLY half of them make, not model.ply's
    half = best[torch.arange(len(best) // 2)]
    half.save(out / "model_best.pt")
    half.to_ply(tmp_path / "half.ply")
    m_half = evaluate(out, device="cpu", model="best", write=False)
    assert m_half["n_gaussians"] == len(half)
    assert m_half["model_ply_size_bytes"] == (tmp_path / "half.ply").stat().st_size < (out / "model.ply").stat().st_size
    assert m_last["model_ply_size_bytes"] == (out / "model.ply").stat().st_size
    (out / "model_best.pt").unlink()
    with pytest.raises(CtsplatError, match="no model_best.pt"):
        evaluate(out, device="cpu", model="best", write=False)
    with pytest.raises(CtsplatError, match="unknown model"):
        evaluate(out, device="cpu", model="first", write=False)
    with pytest.raises(CtsplatError, match=r"'lr' is not an evaluation key; allowed: figures, turntable_frames"):
        evaluate(out, device="cpu", settings={"lr": 1.0}, write=False)


def test_evaluating_again_scores_with_the_recorded_settings(scene_dir, tmp_path):
    """The workflow evaluates with settings the run's config.json does not hold: metrics.json records them and the
    milestones, and an evaluation without settings (``ctsplat evaluate RUN``) scores the run alike."""
    out = tmp_path / "run"
    loop.train(_cfg(scene_dir, iterations=20), out)
    first = evaluate(out, device="cpu", settings={"fps_width": 40, "fps_height": 20, "model_selection": "best"},
                     milestones={"psnr2d": 5.0})
    assert first["fps_resolution"] == [40, 20] and first["model"] == "best"
    again = evaluate(out, device="cpu", write=False)
    assert again["fps_resolution"] == [40, 20] and again["model"] == "best"
    assert again["evaluation_settings"] == first["evaluation_settings"]
    assert again["evaluation_milestones"] == {"psnr2d": 5.0}
    assert {k: v for k, v in again.items() if k.startswith("iter_to_")} == \
        {k: v for k, v in first.items() if k.startswith("iter_to_")}
    given = evaluate(out, device="cpu", settings={"fps_width": 24, "fps_height": 16}, write=False)
    assert given["fps_resolution"] == [24, 16] and given["model"] == "best"  # the rest stays as recorded
    # a nested key is set alone: the recorded radius stays beside the given amounts
    nested = evaluate(out, device="cpu", settings={"sharpen": {"amounts": [0.0, 0.5]}}, write=False)
    assert nested["evaluation_settings"]["sharpen"] == {"amounts": [0.0, 0.5],
                                                        "radius_voxels": first["evaluation_settings"]["sharpen"][
                                                            "radius_voxels"]}
    assert nested["sharpen_amount"] in (0.0, 0.5)
    # settings are checked as train checks them, given or recorded (an edited metrics.json)
    for bad, needle in (({"sharpen": 5}, r"train\.sharpen: 5 is not of type 'object'"),
                        ({"figures": "maybe"}, r"train\.figures: 'maybe' is not of type 'boolean'"),
                        ({"sharpen": {"foo": 1}}, r"unknown config key train\.sharpen\.foo")):
        with pytest.raises(CtsplatError, match=needle):
            evaluate(out, device="cpu", settings=bad, write=False)
    record = json.loads((out / "metrics.json").read_text())
    edited = {**record, "evaluation_settings": {**record["evaluation_settings"], "figures": "maybe"}}
    (out / "metrics.json").write_text(json.dumps(edited))
    with pytest.raises(CtsplatError, match=r"metrics\.json evaluation_settings\.figures: 'maybe' is not of type"):
        evaluate(out, device="cpu", write=False)
    (out / "metrics.json").write_text(json.dumps({**record, "evaluation_milestones": {"psnr2d": "abc"}}))
    with pytest.raises(CtsplatError, match=r"evaluation milestone 'psnr2d' must be a finite number, got 'abc' \(an "
                                           r"earlier metrics file that was edited\? remove metrics\.json"):
        evaluate(out, device="cpu", write=False)
    (out / "metrics.json").write_text(json.dumps(record))
    val = evaluate(out, split="val", device="cpu")  # each split keeps its own record
    assert val["fps_resolution"] == [_cfg(scene_dir)["fps_width"], _cfg(scene_dir)["fps_height"]]
    # a new run in the folder removes every split's metrics: no earlier record is left to score it with
    loop.train(_cfg(scene_dir, iterations=20, lambda_ssim=0.3), out, resume="auto")
    assert not (out / "metrics.json").exists() and not (out / "metrics_val.json").exists()
    assert not (out / "per_view_val.csv").exists()


# --- 6. optimiser preset -----------------------------------------------------------------------------------------

def test_method_preset_sets_one_learning_rate_and_the_cosine(scene_dir, tmp_path):
    params = {"means": torch.zeros(3, 3, requires_grad=True), "log_scales": torch.zeros(3, 3, requires_grad=True),
              "quats": torch.zeros(3, 4, requires_grad=True), "density_raw": torch.zeros(3, requires_grad=True)}
    cfg = {"lr": config.TRAIN_DEFAULTS["lr"], "optimizer_preset": "method"}
    opt = state.make_optimizer(params, cfg, voxel_mm=2.0, half_extent_mm=20.0)
    lrs = {g["name"]: g["lr"] for g in opt.param_groups}
    assert lrs == pytest.approx({"means": 3e-3 * 20.0, "log_scales": 3e-3, "quats": 3e-3, "density_raw": 3e-3})
    per_group = state.make_optimizer(params, {**cfg, "optimizer_preset": "per_group"}, voxel_mm=2.0)
    assert {g["name"]: g["lr"] for g in per_group.param_groups}["means"] == pytest.approx(0.02 * 2.0)
    # in a run: the logged mean learning rate follows the cosine from 3e-3 x half-extent (20 voxels of 2 mm)
    out = tmp_path / "run"
    loop.train(_cfg(scene_dir, iterations=20, optimizer_preset="method"), out)
    for r in _rows(out / "train_log.csv"):
        it = int(r["iteration"])
        want = 3e-3 * 20.0 * state.cosine_factor(it - 1, 20, 0.1)
        assert float(r["lr_means"]) == pytest.approx(want, rel=1e-6)


# --- all features together: deterministic; bad input --------------------------------------------------------------

def test_all_features_on_are_deterministic(scene_dir, tmp_path):
    kw = {"iterations": 20, "augment": {"enabled": True}, "optimizer_preset": "method",
          "lambda_density_warmup": {"factor": 10.0},
          "densify": {"interval": 10, "start": 10, "strategy": "both", "prune_redundant": {"enabled": True}}}
    a = loop.train(_cfg(scene_dir, **kw), tmp_path / "a")
    b = loop.train(_cfg(scene_dir, **kw), tmp_path / "b")
    drop = ("timestamp", "iters_per_s")
    ra = [{k: v for k, v in r.items() if k not in drop} for r in _rows(tmp_path / "a" / "train_log.csv")]
    rb = [{k: v for k, v in r.items() if k not in drop} for r in _rows(tmp_path / "b" / "train_log.csv")]
    assert ra == rb and a["n_gaussians"] == b["n_gaussians"]


def test_resume_with_features_continues_bit_for_bit(scene_dir, tmp_path):
    # error statistics accumulate from 11 to 20 and are in the checkpoint at 10..; augmentation draws from the
    # checkpointed generators
    kw = {"iterations": 30, "augment": {"enabled": True}, "densify": {"interval": 20, "start": 20,
                                                                     "strategy": "error", "error_ratio": 1.2}}
    full = loop.train(_cfg(scene_dir, **kw), tmp_path / "full")

    class Stop(Exception):
        pass

    def stop(it: int, _st: state.TrainState) -> None:
        if it == 15:
            raise Stop

    with pytest.raises(Stop):
        loop.train(_cfg(scene_dir, **kw), tmp_path / "cut", callback=stop)
    resumed = loop.train(_cfg(scene_dir, **kw), tmp_path / "cut", resume=True)
    drop = ("timestamp", "iters_per_s")
    rows = [[{k: v for k, v in r.items() if k not in drop} for r in _rows(tmp_path / d / "train_log.csv")]
            for d in ("full", "cut")]
    assert rows[0] == rows[1] and full["densify_cloned"] + full["densify_split"] > 0
    assert resumed["n_gaussians"] == full["n_gaussians"] and resumed["best_iteration"] == full["best_iteration"]


def test_resume_is_bit_for_bit_with_the_mip_filter_and_after_a_non_finite_step(tmp_path):
    # cone beam: the 3D filter depends on the means, so the resumed run must use the filter of the last densify
    # step, not one recomputed from the checkpoint's means; a non-finite step after the resume must roll back to
    # the same state as the uninterrupted run's
    from train_helpers import MU

    from ctsplat.formats.volume import Volume, save_volume
    from ctsplat.projector import render_radiographs

    data, aff = tiny_phantom()
    save_volume(Volume(data, aff, {"volume_id": "tinycone", "intensity": {"mu_scale_per_mm": MU}}),
                tmp_path / "volume.nii.gz")
    render_radiographs(tmp_path / "volume.nii.gz", tmp_path / "rad", {
        "camera": "cone", "dso_mm": 100.0, "dsd_mm": 150.0, "detector_width": 24, "detector_height": 24,
        "n_views": 12, "device": "cpu"})
    cfg = _cfg(tmp_path, n_init=200, iterations=16, eval_every=8, checkpoint_every=6, mip=True,
               densify={"interval": 10, "start": 10})

    class Stop(Exception):
        pass

    def poison(it: int, st: state.TrainState) -> None:
        if it == 7:
            with torch.no_grad():
                st.params["means"][0, 0] = float("nan")

    def stop(it: int, _st: state.TrainState) -> None:
        if it == 6:
            raise Stop

    for name, callback in (("clean", None), ("nan", poison)):
        full = loop.train(cfg, tmp_path / f"{name}_full", callback=callback)
        with pytest.raises(Stop):
            loop.train(cfg, tmp_path / f"{name}_cut", callback=stop)
        resumed = loop.train(cfg, tmp_path / f"{name}_cut", resume=True, callback=callback)
        assert resumed["nan_events"] == full["nan_events"] == (1 if callback else 0)
        a, b = (Gaussians.load(tmp_path / f"{name}_{d}" / "model.pt") for d in ("full", "cut"))
        for k, v in a.tensors().items():
            assert torch.equal(v, b.tensors()[k]), (name, k)


@pytest.mark.parametrize(("kw", "msg"), [
    ({"augment": {"rot_deg": -0.5}}, r"train\.augment\.rot_deg must be a number in \[0, 1\], got -0.5"),
    ({"augment": {"shear": 1}}, "unknown config key train.augment.shear"),
    ({"augment": {"enabled": "yes"}}, "train.augment.enabled must be true or false"),
    ({"lambda_density_warmup": {"factor": 0.5}}, r"lambda_density_warmup\.factor must be a number >= 1"),
    ({"lambda_density_warmup": {"ramp": 1}}, "unknown config key train.lambda_density_warmup.ramp"),
    ({"densify": {"strategy": "random"}}, "unknown train.densify.strategy 'random'; allowed: gradient, error, both"),
    ({"densify": {"prune_redundant": {"distance": -1}}}, "prune_redundant.distance must be a number in"),
    ({"densify": {"prune_until_end": "yes"}}, "train.densify.prune_until_end must be true or false, got 'yes'"),
    ({"optimizer_preset": "sgd"}, "unknown train.optimizer_preset 'sgd'"),
    ({"tv_size": 1}, r"train\.tv_size must be an integer >= 2, got 1"),
    ({"model_selection": "median"}, "unknown train.model_selection 'median'"),
])
def test_bad_feature_settings_fail_with_one_line(scene_dir, kw, msg):
    with pytest.raises(CtsplatError, match=msg) as exc:
        config.resolve_config(_cfg(scene_dir, **kw))
    assert "\n" not in str(exc.value)


def test_schema_knows_the_new_keys():
    from ctsplat.config import validate_config

    cfg = validate_config({"train": {"augment": {"enabled": True}, "densify": {"strategy": "both"},
                                     "optimizer_preset": "method", "model_selection": "best"}})
    assert cfg["train"]["augment"]["rot_deg"] == 0.5
    with pytest.raises(CtsplatError, match="strategy"):
        validate_config({"train": {"densify": {"strategy": "nope"}}})


def test_features_benchmark_refuses_keys_its_variants_set(tmp_path):
    import os
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    res = subprocess.run([sys.executable, str(root / "benchmarks" / "features.py"), "--data", str(tmp_path / "none"),
                          "--out", str(tmp_path / "o"), "--set", "densify.strategy=error"], capture_output=True,
                         text=True, env=env, timeout=300)
    assert res.returncode == 2 and not (tmp_path / "o").exists()
    assert res.stderr.strip().splitlines()[-1] == ("features.py: error: --set densify.strategy is set by this "
                                                   "benchmark per run; use --variants")


# --- grid axes -----------------------------------------------------------------------------------------------------

def test_feature_axes_expand_into_run_folders_and_train_settings(scene_dir):
    from ctsplat.config import validate_config
    from ctsplat.grid import expand_grid, parse_run_dir, run_relpath, with_train_overrides

    axes = {"init": ["fbp"], "compositor": ["radiative"], "mip": ["on"], "poses": ["gt"], "views": [8], "seed": [0],
            "augment": [True, "off"], "densify": ["gradient", "both"], "density_warmup": [1, 10],
            "prune_redundant": ["on"], "optimizer": ["method"]}
    runs = expand_grid(axes, ["ph"], exclude=[{"augment": "on", "densify": "both"}])
    assert len(runs) == 6 and list(runs.columns[-5:]) == ["augment", "density_warmup", "densify", "prune_redundant",
                                                          "optimizer"]
    row = runs.iloc[-1].to_dict()
    rel = run_relpath(row)
    assert rel == ("init~fbp/compositor~radiative/mip~on/poses~gt/views~8/seed~0/augment~off/density_warmup~10/"
                   "densify~both/prune_redundant~on/optimizer~method")
    assert parse_run_dir(f"results/ph/runs/{rel}") == {**row, "density_warmup": 10.0}
    base = config.resolve_config(_cfg(scene_dir, densify={"interval": 7}))
    cfg = config.resolve_config(with_train_overrides(base, row))
    assert cfg["augment"]["enabled"] is False and cfg["densify"]["strategy"] == "both"
    assert cfg["densify"]["interval"] == 7 and cfg["densify"]["prune_redundant"]["enabled"] is True
    assert cfg["lambda_density_warmup"]["factor"] == 10.0 and cfg["optimizer_preset"] == "method"
    # the six-axis layout is unchanged without feature axes; the schema accepts them and their exclusions
    plain = expand_grid({k: axes[k] for k in list(axes)[:6]}, ["ph"])
    assert run_relpath(plain.iloc[0].to_dict()) == "init~fbp/compositor~radiative/mip~on/poses~gt/views~8/seed~0"
    validate_config({"grid": {"axes": {"augment": ["on", "off"], "densify": ["error"]},
                              "exclude": [{"augment": "on"}]}})
    with pytest.raises(CtsplatError, match="grid.axes.densify"):
        validate_config({"grid": {"axes": {"densify": ["random"]}}})


def test_workflow_dry_run_with_a_feature_axis(tmp_path, monkeypatch):
    import yaml

    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "workflow"))
    from smk_helpers import ROOT, job_counts, snakemake, write_config

    cfg = yaml.safe_load((ROOT / "config" / "test_tiny.yaml").read_text())
    cfg["grid"]["axes"].update(init=["uniform"], mip=["off"], augment=["on", "off"], densify=["error"])
    proc = snakemake(tmp_path, "-n", configfile=write_config(tmp_path / "c.yaml", cfg))
    assert job_counts(proc.stdout)["train"] == 2
    assert "seed~0/augment~on/densify~error/model.pt" in proc.stdout
    assert "seed~0/augment~off/densify~error/model.pt" in proc.stdout


def test_a_view_set_without_test_views_is_scored_on_its_validation_views_and_says_so(tmp_path, caplog):
    import logging

    from train_helpers import MU

    from ctsplat.formats.volume import Volume, save_volume
    from ctsplat.projector import render_radiographs

    data, aff = tiny_phantom()
    save_volume(Volume(data, aff, {"volume_id": "notest", "intensity": {"mu_scale_per_mm": MU}}),
                tmp_path / "volume.nii.gz")
    render_radiographs(tmp_path / "volume.nii.gz", tmp_path / "rad", {
        "detector_width": 24, "detector_height": 24, "n_views": 12, "device": "cpu", "orbit": "sphere",
        "split": {"train": 0.75, "val": 0.25, "test": 0.0}})
    loop.train(_cfg(tmp_path, iterations=4, eval_every=2, checkpoint_every=4), tmp_path / "run")
    with caplog.at_level(logging.WARNING, logger="ctsplat.evaluation.run"):
        m = evaluate(tmp_path / "run", device="cpu", write=False)
    assert m["split"] == "test" and m["views_from"] == "val"
    assert any("no test views" in r.getMessage() for r in caplog.records)


def test_prune_mask_keeps_centres_within_two_voxels_of_the_grid_box():
    """The box rule against the grid's edges worked out by hand: 2 mm voxels, 20 per axis, first centre at -20 mm,
    so the voxel edges span [-21, 19] mm and the 2-voxel margin [-25, 23] mm."""
    from ctsplat.formats.volume import Volume

    aff = np.diag([2.0, 2.0, 2.0, 1.0])
    aff[:3, 3] = -20.0
    vol = Volume(np.zeros((20, 20, 20), np.float32), aff, {})
    x = [-24.5, -25.5, 22.5, 23.5, 0.0]  # inside, outside, inside, outside the margin; the centre
    means = torch.zeros(10, 3)
    means[:5, 0] = torch.tensor(x)
    means[5:, 2] = torch.tensor(x)  # the same along the third axis
    log_scales = torch.full((10, 3), float(np.log(0.5)))
    rule = GradientDensify(config.TRAIN_DEFAULTS["densify"], compositor="radiative", iterations=10)
    pruned = rule.prune_mask(means, log_scales, torch.ones(10), vol)
    assert pruned.tolist() == [False, True, False, True, False] * 2
