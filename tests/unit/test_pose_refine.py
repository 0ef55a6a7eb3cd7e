"""Joint pose–density refinement: the corrected camera equals the moved Gaussians (both beams, every CPU backend),
gradients with respect to the correction match finite differences, the gauge fix, perturbed poses, refinement
that lowers the pose error and raises validation PSNR on a tiny phantom, exact resume, and config errors."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from train_helpers import N, write_tiny_scene

from ctsplat.evaluation import evaluate
from ctsplat.geometry.cameras import ConeCamera, ParallelCamera, pose_from_angles
from ctsplat.grid import needs_sfm, uses_colmap
from ctsplat.splat.gaussians import Gaussians
from ctsplat.splat.render import render
from ctsplat.training import config, loop, poses
from ctsplat.training.poses import PoseCorrection, correct_pose, transform_gaussians
from ctsplat.utils import CtsplatError

ISO = np.array([1.0, -2.0, 0.5])
CAMERAS = {"parallel": (ParallelCamera(20, 16, 1.5), 40.0), "cone": (ConeCamera(20, 16, 1.0, 200.0, 300.0), 200.0)}


def _params(n: int = 30, dtype: torch.dtype = torch.float64) -> dict[str, torch.Tensor]:
    rng = np.random.default_rng(0)
    g = Gaussians.from_values(rng.normal(0, 5, (n, 3)) + ISO, rng.uniform(1.0, 2.5, (n, 3)), rng.uniform(0.05, 0.2, n),
                              dtype=dtype)
    p = {k: v.detach().clone() for k, v in g.tensors().items()}
    p["quats"] = torch.nn.functional.normalize(torch.as_tensor(rng.normal(size=(n, 4)), dtype=dtype), dim=-1)
    return p


def _pose(model: str, dtype: torch.dtype = torch.float64) -> tuple[object, torch.Tensor, torch.Tensor, torch.Tensor]:
    cam, dist = CAMERAS[model]
    R, t = pose_from_angles(30.0, 10.0, ISO, dist)
    return cam, torch.as_tensor(R, dtype=dtype), torch.as_tensor(t, dtype=dtype), torch.as_tensor(ISO, dtype=dtype)


def _corr(model: str, dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    om = torch.tensor([0.02, -0.03, 0.05], dtype=dtype)
    ta = torch.tensor([0.7, -0.4, 0.3 if model == "cone" else 0.0], dtype=dtype)
    return om, ta


# ------------------------------------------------------------------------------------- equivalence
@pytest.mark.parametrize("backend", ["reference", "kernel"])
@pytest.mark.parametrize("model", ["parallel", "cone"])
def test_corrected_camera_equals_moved_gaussians(model: str, backend: str) -> None:
    cam, R, t, iso = _pose(model)
    p = _params()
    om, ta = _corr(model)
    R2, t2 = correct_pose(R, t, om, ta, iso)
    a = render(Gaussians(**p), cam, R2, t2, backend=backend).image
    b = render(Gaussians(**transform_gaussians(p, R, om, ta, iso)), cam, R, t, backend=backend).image
    assert float(a.abs().max()) > 0.5
    torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-10)
    # and the correction really moves the image (the test is not vacuous)
    c = render(Gaussians(**p), cam, R, t, backend=backend).image
    assert float((a - c).abs().max()) > 1e-2


def test_corrected_pose_is_rigid_about_the_isocentre() -> None:
    _, R, t, iso = _pose("cone")
    om, _ = _corr("cone")
    R2, t2 = correct_pose(R, t, om, torch.zeros(3, dtype=torch.float64), iso)
    torch.testing.assert_close(R2 @ R2.T, torch.eye(3, dtype=torch.float64))
    # a pure rotation keeps the isocentre where the camera saw it
    torch.testing.assert_close(R2 @ iso + t2, R @ iso + t)


# ---------------------------------------------------------------------------------------- gradients
@pytest.mark.parametrize("model", ["parallel", "cone"])
def test_gradcheck_reference_float64(model: str) -> None:
    cam, R, t, iso = _pose(model)
    p = _params(12)
    w = torch.as_tensor(np.random.default_rng(1).normal(size=(cam.height, cam.width)))
    om0, ta0 = _corr(model)

    def f(om: torch.Tensor, ta: torch.Tensor) -> torch.Tensor:
        img = render(Gaussians(**transform_gaussians(p, R, om, ta, iso)), cam, R, t, backend="reference").image
        return (img * w).sum()

    assert torch.autograd.gradcheck(f, (om0.clone().requires_grad_(), ta0.clone().requires_grad_()), eps=1e-6,
                                    atol=1e-5, rtol=1e-4)
    # at zero too (the rotation vector's quaternion is smooth there)
    assert torch.autograd.gradcheck(f, (torch.zeros(3, dtype=torch.float64, requires_grad=True),
                                        torch.zeros(3, dtype=torch.float64, requires_grad=True)),
                                    eps=1e-6, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("model", ["parallel", "cone"])
def test_kernel_float32_gradient_matches_finite_differences(model: str) -> None:
    cam, R, t, iso = _pose(model, torch.float32)
    p = _params(30, torch.float32)
    w = torch.as_tensor(np.random.default_rng(2).normal(size=(cam.height, cam.width)), dtype=torch.float32)
    om0, ta0 = _corr(model, torch.float32)
    x0 = torch.cat([om0, ta0])

    def f(x: torch.Tensor) -> torch.Tensor:
        img = render(Gaussians(**transform_gaussians(p, R, x[:3], x[3:], iso)), cam, R, t, backend="kernel").image
        return (img * w).sum()

    x = x0.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(f(x), x)
    steps = [1e-3] * 3 + [1e-2] * 3
    fd = []
    with torch.no_grad():
        for k, h in enumerate(steps):
            e = torch.zeros(6)
            e[k] = h
            fd.append(float(f(x0 + e) - f(x0 - e)) / (2 * h))
    fd_t = torch.tensor(fd)
    active = slice(0, 6) if model == "cone" else [0, 1, 2, 3, 4]
    scale = float(fd_t[active].abs().max())
    assert scale > 1.0
    torch.testing.assert_close(grad[active], fd_t[active], atol=2e-2 * scale, rtol=2e-2)


# -------------------------------------------------------------------------------------------- gauge
def _ring(n: int = 8, model: str = "parallel") -> tuple[np.ndarray, np.ndarray]:
    out = [pose_from_angles(a, 5.0 * np.sin(np.radians(a)), ISO, 100.0) for a in np.linspace(0, 170, n)]
    return np.stack([r for r, _ in out]), np.stack([t for _, t in out])


@pytest.mark.parametrize(("model", "cone_model"), [("parallel", "rigid"), ("cone", "rigid"), ("cone", "carm")])
def test_gauge_fix_removes_the_common_motion(model: str, cone_model: str) -> None:
    Rs, ts = _ring(model=model)
    pc = PoseCorrection(Rs, ts, ISO, model, cone_model=cone_model)
    Rt = torch.as_tensor(Rs, dtype=torch.float32)
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        pc.omega.copy_(0.01 * torch.randn(len(pc), 3, generator=gen) + Rt @ torch.tensor([0.02, -0.01, 0.03]))
        pc.tau.copy_(torch.randn(len(pc), 3, generator=gen) + Rt @ torch.tensor([1.0, 2.0, -1.5]))
    pc.fix_gauge()
    # no common world rotation or shift is left
    mean_w = torch.einsum("vji,vj->i", Rt, pc.omega.detach()) / len(pc)
    assert float(mean_w.abs().max()) < 1e-6
    PR = pc.mask[None, :, None] * Rt
    assert float(torch.einsum("vki,vk->i", PR, pc.tau.detach()).abs().max()) < 1e-4
    if model == "parallel" or cone_model == "carm":
        assert float(pc.tau.detach()[:, 2].abs().max()) == 0.0
    # idempotent, and a pure common motion is removed entirely
    before = pc.state()
    pc.fix_gauge()
    torch.testing.assert_close(pc.omega.detach(), before["omega"], atol=1e-6, rtol=0)
    with torch.no_grad():
        pc.omega.copy_(Rt @ torch.tensor([0.02, -0.01, 0.03]))
        pc.tau.copy_(pc.mask * (Rt @ torch.tensor([1.0, 2.0, -1.5])))
    pc.fix_gauge()
    assert float(pc.omega.detach().abs().max()) < 1e-6 and float(pc.tau.detach().abs().max()) < 1e-4


@pytest.mark.parametrize("model", ["parallel", "cone"])
def test_gauge_motion_recovers_a_common_rigid_motion(model: str) -> None:
    """Poses of a frame moved by m = G x + b (plus small per-view noise): gauge_motion finds G and b, and the model
    moved back by gauge_aligned_model is the true-frame model."""
    from scipy.spatial.transform import Rotation

    from ctsplat.evaluation.run import gauge_aligned_model
    from ctsplat.training.poses import gauge_motion

    Rs_true, ts_true = _ring(n=24, model=model)
    G = Rotation.from_rotvec(np.radians([0.3, -0.2, 0.5])).as_matrix()
    b = np.array([0.4, -0.3, 0.25])
    rng = np.random.default_rng(0)
    noise = Rotation.from_rotvec(np.radians(0.05) * rng.standard_normal((24, 3))).as_matrix()
    Rs = np.einsum("vij,vjk,lk->vil", noise, Rs_true, G)  # R_i G = noise_i R_true_i
    ts = ts_true - np.einsum("vij,j->vi", Rs, b)
    G_est, b_est = gauge_motion(Rs, ts, Rs_true, ts_true, model)
    assert np.degrees(np.arccos(np.clip((np.trace(G_est @ G.T) - 1) / 2, -1, 1))) < 0.03
    np.testing.assert_allclose(b_est, b, atol=0.05 if model == "cone" else 0.1)
    g_true = Gaussians.from_values(torch.tensor([[10.0, -5.0, 3.0], [0.0, 2.0, -7.0]], dtype=torch.float64),
                                   torch.tensor([[1.0, 2.0, 0.5], [0.7, 0.7, 1.5]], dtype=torch.float64),
                                   torch.tensor([0.3, 0.6], dtype=torch.float64),
                                   torch.tensor([[1.0, 0.2, -0.1, 0.3], [0.5, -0.5, 0.5, 0.5]], dtype=torch.float64),
                                   dtype=torch.float64)
    Gt = torch.as_tensor(G)
    q = torch.as_tensor(Rotation.from_matrix(G).as_quat()[[3, 0, 1, 2]])
    g_model = dataclasses.replace(g_true.detach(), means=g_true.means.detach() @ Gt.T + torch.as_tensor(b),
                                  quats=poses.quat_mul(q.expand(2, 4), g_true.quats.detach()))
    back = gauge_aligned_model(g_model, G, b)
    torch.testing.assert_close(back.means, g_true.means.detach(), atol=1e-9, rtol=0)
    torch.testing.assert_close(back.covariances, g_true.covariances.detach(), atol=1e-9, rtol=0)
    torch.testing.assert_close(g_model.means, g_true.means.detach() @ Gt.T + torch.as_tensor(b))  # input kept


def test_perturbed_poses_and_errors() -> None:
    Rs, ts = _ring(40)
    R2, t2 = poses.perturb_poses(Rs, ts, ISO, 1.0, 0.5, seed=3)
    again = poses.perturb_poses(Rs, ts, ISO, 1.0, 0.5, seed=3)
    np.testing.assert_array_equal(R2, again[0])
    err = poses.pose_errors(R2, t2, Rs, ts, ISO, "cone")
    # azimuth and elevation errors of 1 deg each: the angle's median is about 1.18 deg
    assert 0.7 < err["rot_err_median_deg"] < 1.8 and err["rot_err_p90_deg"] > err["rot_err_median_deg"]
    assert 0.2 < err["iso_err_median_mm"] < 1.5
    assert poses.pose_errors(Rs, ts, Rs, ts, ISO, "parallel")["rot_err_p90_deg"] < 1e-6
    # a common rotation of every camera is the gauge: the aligned error ignores it
    from scipy.spatial.transform import Rotation

    G = Rotation.from_rotvec([0.01, -0.02, 0.015]).as_matrix()
    moved = poses.pose_errors(Rs @ G, ts, Rs, ts, ISO, "cone")
    assert moved["rot_err_median_deg"] > 1.0 and moved["rot_err_aligned_p90_deg"] < 1e-6


# ------------------------------------------------------------------------------------ training run
def _phantom() -> tuple[np.ndarray, np.ndarray]:
    x = np.stack(np.meshgrid(*[np.arange(N)] * 3, indexing="ij"), -1).astype(float)
    c = (N - 1) / 2
    data = 0.4 * (np.linalg.norm((x - c) / np.array([7.5, 6.5, 6.0]), axis=-1) < 1)
    for centre, r, v in (((7, 9, 10), 2.5, 0.4), ((12, 8, 6), 2.0, 0.3), ((10, 13, 12), 1.5, 0.5),
                         ((8, 6, 7), 1.5, 0.4)):
        data = data + v * (np.linalg.norm(x - np.array(centre), axis=-1) < r)
    aff = np.diag([2.0, 2.0, 2.0, 1.0])
    aff[:3, 3] = -19.0
    return data.astype(np.float32), aff


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory) -> Path:
    data, aff = _phantom()
    return write_tiny_scene(tmp_path_factory.mktemp("pose_scene"), data, aff, volume_id="tinypose", n_views=24)


def _cfg(scene: Path, **kw) -> dict:
    cfg = {
        "volume": str(scene / "volume.nii.gz"), "radiographs": str(scene / "rad"), "init": "fbp", "n_init": 600,
        "iterations": 200, "eval_every": 100, "checkpoint_every": 100, "device": "cpu", "densify": {"interval": 0},
        "figures": False, "progress": False, "lambda_tv": 0.0, "perturb_rot_deg": 2.0, "perturb_trans_mm": 0.5,
        "fps_width": 32, "fps_height": 18,
        "pose_refine": {"start": 60, "lr_rot_deg": 0.05, "lr_trans_mm": 0.05},
    }
    cfg.update(kw)
    return cfg


def _last_psnr(run: Path) -> float:
    import csv

    with open(run / "train_log.csv") as fh:
        return float(list(csv.DictReader(fh))[-1]["psnr2d"])


def test_refinement_lowers_pose_error_and_raises_val_psnr(scene_dir: Path, tmp_path: Path) -> None:
    # 400 iterations (about 5 s): the median rotation error drops from 2.0 to about 1.7 deg and validation PSNR
    # rises by about 0.7 dB; the azimuth part of a parallel-beam error is the slowest to go (sparse views)
    kw = {"iterations": 400, "eval_every": 200, "checkpoint_every": 200}
    plain = loop.train(_cfg(scene_dir, poses="perturbed", **kw), tmp_path / "plain")
    refined = loop.train(_cfg(scene_dir, poses="perturbed+refine", **kw), tmp_path / "refined")
    assert plain["pose_rot_err_median_deg_before"] > 1.0
    assert plain["pose_rot_err_median_deg_after"] == plain["pose_rot_err_median_deg_before"]
    assert refined["pose_rot_err_median_deg_before"] == plain["pose_rot_err_median_deg_before"]
    assert refined["pose_rot_err_median_deg_after"] < refined["pose_rot_err_median_deg_before"] - 0.15
    assert refined["pose_iso_err_median_mm_after"] < refined["pose_iso_err_median_mm_before"]
    assert _last_psnr(tmp_path / "refined") > _last_psnr(tmp_path / "plain") + 0.3
    rv = json.loads((tmp_path / "refined" / "refined_views.json").read_text())
    assert len(rv["views"]) == refined["n_train_views"] and not (tmp_path / "plain" / "refined_views.json").exists()
    # the gauge: no common world rotation is left in the corrections the run ended with
    om = np.radians([v["omega_deg"] for v in rv["views"]])
    R0 = np.array([v["R_start"] for v in rv["views"]])
    assert np.abs(np.einsum("vji,vj->i", R0, om)).max() / len(om) < 1e-5 < np.abs(om).max()
    # the pose errors reach metrics.json, with the 3D metrics after the unobservable common motion is undone
    res = evaluate(tmp_path / "refined", device="cpu", write=False)
    assert res["pose_rot_err_median_deg_after"] == refined["pose_rot_err_median_deg_after"]
    assert 0 < res["gauge_rotation_deg"] < 2.0 and np.isfinite(res["psnr3d_gauge_aligned"])


def test_model_best_is_evaluated_at_the_poses_it_was_fitted_at(scene_dir: Path, tmp_path: Path) -> None:
    """A refining run saves the poses ``model_best.pt`` was fitted at, with their errors; ``evaluate(model='best')``
    reports those and undoes their gauge motion, not the final poses'."""
    from ctsplat.scene import load_scene

    run = tmp_path / "run"
    rec = loop.train(_cfg(scene_dir, poses="perturbed+refine", eval_every=50), run)
    saved = json.loads((run / "refined_views_best.json").read_text())
    assert saved["iteration"] == rec["best_iteration"]
    scene = load_scene(json.loads((run / "config.json").read_text())["config"])
    tr = scene.train
    Rs_true, ts_true = tr.truth()
    by_id = {int(v["id"]): v for v in saved["views"]}
    Rs = np.stack([np.asarray(by_id[int(i)]["R"]) for i in tr.ids])
    ts = np.stack([np.asarray(by_id[int(i)]["t"]) for i in tr.ids])
    errs = poses.pose_errors(Rs, ts, Rs_true, ts_true, scene.isocenter_mm, tr.camera.model)
    for key, value in errs.items():
        assert rec["best_model_poses"][f"pose_{key}_after"] == pytest.approx(value, abs=1e-9)
    best = evaluate(run, device="cpu", model="best", write=False)
    last = evaluate(run, device="cpu", write=False)
    for key in errs:
        assert best[f"pose_{key}_after"] == rec["best_model_poses"][f"pose_{key}_after"]
        assert last[f"pose_{key}_after"] == rec[f"pose_{key}_after"]
    assert "gauge_rotation_deg" in best and "gauge_rotation_deg" in last
    # the best model's poses moved onto the true ones: no gauge motion is left for it, the final model keeps its own
    for i, view_id in enumerate(tr.ids):
        by_id[int(view_id)].update(R=Rs_true[i].tolist(), t=ts_true[i].tolist())
    (run / "refined_views_best.json").write_text(json.dumps(saved))
    assert "gauge_rotation_deg" not in evaluate(run, device="cpu", model="best", write=False)
    assert evaluate(run, device="cpu", write=False)["gauge_rotation_deg"] == last["gauge_rotation_deg"]
    # a run folder without them (another version) is refused in one line
    (run / "refined_views_best.json").unlink()
    with pytest.raises(CtsplatError, match=r"lacks refined_views_best\.json, the poses model_best\.pt was fitted "
                                           r"at .*; evaluate model: last, or train the run again"):
        evaluate(run, device="cpu", model="best", write=False)


def test_carm_model_keeps_the_source_distance() -> None:
    """Cone beam, ``cone_model: carm``: no view moves along its central ray; ``rigid`` moves them along it."""
    Rs, ts = _ring(model="cone")
    for cone_model, moves in (("carm", False), ("rigid", True)):
        pc = PoseCorrection(Rs, ts, ISO, "cone", cone_model=cone_model)
        with torch.no_grad():
            pc.tau.copy_(torch.tensor([0.3, -0.2, 1.0]).expand(len(pc), 3))
        R1, t1 = pc.corrected_poses()
        # the isocentre's depth in each camera (its distance from the source plane) before and after
        depth0 = np.einsum("vij,j->vi", Rs, ISO)[:, 2] + ts[:, 2]
        depth1 = np.einsum("vij,j->vi", R1, ISO)[:, 2] + t1[:, 2]
        assert bool(np.abs(depth1 - depth0).max() > 0.5) == moves, cone_model
        # the prior sees only the free shifts
        assert float(pc.prior().detach()) == pytest.approx(0.5 * pc.prior_weight * (0.13 + (1.0 if moves else 0.0))
                                                           / pc.sigma_trans ** 2, rel=1e-5)


def test_resume_continues_the_corrections_exactly(scene_dir: Path, tmp_path: Path) -> None:
    cfg = _cfg(scene_dir, poses="perturbed+refine", iterations=60, eval_every=30, checkpoint_every=30,
               pose_refine={"start": 10, "lr_rot_deg": 0.05, "lr_trans_mm": 0.05})
    full = tmp_path / "full"
    loop.train(cfg, full)

    class Stop(Exception):
        pass

    def stop(it: int, _state: object) -> None:
        if it == 30:
            raise Stop

    cut = tmp_path / "cut"
    with pytest.raises(Stop):
        loop.train(cfg, cut, callback=stop)
    loop.train(cfg, cut, resume=True)
    a = json.loads((full / "refined_views.json").read_text())
    b = json.loads((cut / "refined_views.json").read_text())
    assert a["views"] == b["views"]


# --------------------------------------------------------------------------------------- config, grid
@pytest.mark.parametrize(("override", "match"), [
    ({"poses": "jittered"}, "unknown train.poses"),
    ({"pose_refine": {"prior_rot_deg": 0}}, r"train\.pose_refine\.prior_rot_deg must be a number > 0"),
    ({"pose_refine": {"prior_trans_mm": 0.0}}, r"train\.pose_refine\.prior_trans_mm must be a number > 0"),
    ({"pose_refine": {"lr_rot_deg": -1}}, r"train\.pose_refine\.lr_rot_deg must be"),
    ({"pose_refine": {"start": -5}}, r"train\.pose_refine\.start must be an integer >= 0"),
    ({"pose_refine": {"enabled": "yes"}}, r"train\.pose_refine\.enabled must be true or false"),
    ({"pose_refine": {"warmup": 3}}, "warmup"),
    ({"pose_refine": {"cone_model": "isocentric"}}, "unknown train.pose_refine.cone_model 'isocentric'"),
    ({"perturb_rot_deg": -1.0}, r"train\.perturb_rot_deg must be"),
    ({"poses": "colmap+refine"}, "sfm_dir is empty"),
    ({"poses": "gt+refine", "iterations": 100, "pose_refine": {"start": 100}},
     r"train\.pose_refine\.start \(100\) is not before train\.iterations \(100\): the poses would never be refined"),
    ({"iterations": 50, "pose_refine": {"enabled": True, "start": 400}}, r"pose_refine\.start \(400\) is not before"),
])
def test_bad_keys_are_one_line_errors(override: dict, match: str) -> None:
    cfg = {"volume": "v.nii.gz", "radiographs": "rad", **override}
    with pytest.raises(CtsplatError, match=match) as exc:
        config.resolve_config(cfg)
    assert "\n" not in str(exc.value)


def test_a_late_refinement_start_is_refused_only_when_refinement_is_on() -> None:
    base = {"volume": "v.nii.gz", "radiographs": "rad", "iterations": 100}
    assert config.resolve_config({**base, "poses": "gt+refine", "pose_refine": {"start": 99}})["iterations"] == 100
    # without refinement the start is unused: no error for a value that only matters when refining
    assert config.resolve_config({**base, "pose_refine": {"start": 500}})["pose_refine"]["start"] == 500


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"model": "pinhole"}, "pose refinement supports parallel and cone cameras, not 'pinhole'"),
    ({"model": "cone", "cone_model": "isocentric"}, "unknown train.pose_refine.cone_model 'isocentric'"),
    ({"model": "cone", "prior_rot_deg": 0.0}, "a zero prior would freeze the poses"),
])
def test_pose_correction_refuses_what_it_cannot_refine(kwargs: dict, match: str) -> None:
    """A camera without a rigid-correction model, an unknown cone model or a zero prior: one-line errors."""
    Rs, ts = _ring()
    with pytest.raises(CtsplatError, match=match) as exc:
        PoseCorrection(Rs, ts, ISO, **kwargs)
    assert "\n" not in str(exc.value)


def test_colmap_refine_needs_sfm() -> None:
    import pandas as pd

    assert uses_colmap("colmap+refine") and not uses_colmap("perturbed+refine")
    cells = pd.DataFrame({"poses": ["perturbed+refine", "gt"], "init": ["fbp", "fbp"]})
    assert not needs_sfm(cells)
    assert needs_sfm(pd.DataFrame({"poses": ["colmap+refine"], "init": ["fbp"]}))


_TRITON_CHILD = """
import numpy as np, torch
import test_pose_refine as T
from ctsplat.splat.gaussians import Gaussians
from ctsplat.splat.render import render
from ctsplat.training.poses import transform_gaussians
for model in ("parallel", "cone"):
    cam, R, t, iso = T._pose(model, torch.float32)
    p = T._params(30, torch.float32)
    w = torch.as_tensor(np.random.default_rng(2).normal(size=(cam.height, cam.width)), dtype=torch.float32)
    om0, ta0 = T._corr(model, torch.float32)
    grads = {}
    for backend in ("reference", "triton"):
        x = torch.cat([om0, ta0]).requires_grad_(True)
        g = Gaussians(**transform_gaussians(p, R, x[:3], x[3:], iso))
        img = render(g, cam, R, t, backend=backend).image
        (grads[backend],) = torch.autograd.grad((img * w).sum(), x)
    scale = float(grads["reference"].abs().max())
    err = float((grads["triton"] - grads["reference"]).abs().max())
    assert scale > 1.0 and err < 1e-3 * scale, (model, err, scale)
print("ok")
"""


@pytest.mark.skipif(importlib.util.find_spec("triton") is None, reason="triton is not installed")
def test_triton_backend_pose_gradient_matches_reference() -> None:
    # the interpreter must be on before the kernels are imported: a child process keeps it away from other tests
    env = dict(os.environ, TRITON_INTERPRET="1",
               PYTHONPATH=os.pathsep.join([str(Path(__file__).parent), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-c", _TRITON_CHILD], env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0 and proc.stdout.strip().endswith("ok"), proc.stderr[-2000:]


@pytest.mark.parametrize("model", ["parallel", "cone"])
def test_gauge_motion_does_not_depend_on_where_the_world_origin_is(model: str) -> None:
    """Per-view errors that are no pure common motion (1°, 0.5 mm): the motion fitted at the isocentre is the same
    motion whether the scan's coordinates put the origin at the isocentre or 800 mm from it."""
    from scipy.spatial.transform import Rotation

    from ctsplat.training.poses import gauge_motion

    Rs_true, ts_true = _ring(n=24, model=model)
    rng = np.random.default_rng(1)
    noise = Rotation.from_rotvec(np.radians(1.0) * rng.standard_normal((24, 3))).as_matrix()
    Rs = np.einsum("vij,vjk->vik", noise, Rs_true)
    ts = ts_true + 0.5 * rng.standard_normal((24, 3))
    G, b = gauge_motion(Rs, ts, Rs_true, ts_true, model, center_mm=np.zeros(3))
    s = np.array([0.0, -150.0, -800.0])  # the same scene in coordinates whose origin is moved: x' = x + s
    moved = gauge_motion(Rs, ts - Rs @ s, Rs_true, ts_true - Rs_true @ s, model, center_mm=s)
    np.testing.assert_allclose(moved[0], G, atol=1e-12)
    np.testing.assert_allclose(moved[1], b + s - G @ s, atol=1e-6)  # m' = m + s
    origin = gauge_motion(Rs, ts - Rs @ s, Rs_true, ts_true - Rs_true @ s, model)  # fitted at the far origin
    assert np.linalg.norm(origin[1] - (b + s - G @ s)) > 0.1  # what the fit at the isocentre is for
