"""Training on a tiny scene: outputs and log format, evaluation, determinism, resume after a kill, NaN guard,
densification, view sampling, init strategies, poses: colmap (C-arm view set), and bad input."""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from train_helpers import MU, N, tiny_phantom, tiny_train_cfg, write_tiny_scene

from ctsplat import scene as sc
from ctsplat.evaluation import evaluate
from ctsplat.splat.gaussians import quat_to_rotmat
from ctsplat.training import checkpoint, config, loop, seeding, state
from ctsplat.training.densify import GradientDensify
from ctsplat.utils import CtsplatError


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory) -> Path:
    data, aff = tiny_phantom()
    return write_tiny_scene(tmp_path_factory.mktemp("scene"), data, aff, volume_id="tiny01", n_views=12)


_cfg = tiny_train_cfg


def _metric_rows(path: Path) -> list[tuple]:
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    drop = {"timestamp", "iters_per_s"}
    return [tuple((k, v) for k, v in r.items() if k not in drop) for r in rows]


@pytest.fixture(scope="module")
def full_run(scene_dir: Path, tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("run_full")
    trained = loop.train(_cfg(scene_dir, figures=True, turntable_frames=4), out)
    assert not (out / "metrics.json").exists()  # training writes the model; evaluation the metrics
    res = evaluate(out, device="cpu")
    assert res["wall_time_s"] == trained["wall_time_s"] and res["iterations"] == trained["iterations"] == 30
    return out, res


# ------------------------------------------------------------------------------------------ outputs
def test_outputs_log_columns_and_metrics(full_run, scene_dir: Path) -> None:
    out, res = full_run
    with open(out / "train_log.csv", newline="") as fh:
        header = next(csv.reader(fh))
    assert header[:6] == ["iteration", "timestamp", "psnr2d", "ssim2d", "psnr3d", "ssim3d"]
    assert {"loss", "n_gaussians", "lr_means", "iters_per_s"} <= set(header[6:])
    rows = list(csv.DictReader(open(out / "train_log.csv", newline="")))
    assert [int(r["iteration"]) for r in rows] == [10, 20, 30]
    ts = [float(r["timestamp"]) for r in rows]
    assert ts == sorted(ts) and ts[0] >= 0
    # the model learns: 2D PSNR on validation views improves
    assert float(rows[-1]["psnr2d"]) > float(rows[0]["psnr2d"])
    pv = list(csv.DictReader(open(out / "per_view.csv", newline="")))
    assert list(pv[0]) == ["iteration", "view_id", "azimuth_deg", "elevation_deg", "split", "psnr2d", "ssim2d"]
    assert {r["split"] for r in pv} == {"val"}
    pt = list(csv.DictReader(open(out / "per_view_test.csv", newline="")))
    assert list(pt[0]) == list(pv[0]) and {r["split"] for r in pt} == {"test"} and len(pt) == res["n_views"]
    m = json.loads((out / "metrics.json").read_text())
    for key in ("psnr2d", "ssim2d", "lpips", "lpips_reason", "psnr3d", "ssim3d", "wall_time_s", "iters_per_s",
                "time_to_psnr2d_30_s", "time_to_ssim2d_090_s", "fps_forward", "peak_memory_mb", "n_gaussians",
                "model_size_bytes", "uses_reference_volume", "config_hash", "code_version", "platform"):
        assert key in m, key
    assert m["platform"]["threads"] >= 1 and m["platform"]["cpu_capability"]
    assert m["uses_reference_volume"] is True
    assert m["lpips"] is None or math.isfinite(m["lpips"])
    if m["lpips"] is None:
        assert m["lpips_reason"]
    assert m["model_size_bytes"] == os.path.getsize(out / "model.pt")
    from ctsplat.splat.render import resolved_backend

    training = json.loads((out / "training.json").read_text())
    assert training["renderer"] == resolved_backend("auto", "cpu")
    # what decides the rounding, so a run can be matched with one on the same kind of CPU
    assert training["platform"] == {"torch": torch.__version__, "threads": torch.get_num_threads(), "gpu": None,
                                    "cpu_capability": torch.backends.cpu.get_cpu_capability()}
    for name in ("model.pt", "model.ply", "model_volume.nii.gz", "gallery.png", "slices.png", "turntable.gif",
                 "config.json", "training.json"):
        assert (out / name).stat().st_size > 0, name
    # test metrics recomputed independently from the written files
    from ctsplat.evaluation.metrics import psnr3d, psnr3d_r2, ssim3d_r2
    from ctsplat.formats.volume import load_volume
    from ctsplat.splat.gaussians import Gaussians

    g = Gaussians.load(out / "model.pt")
    assert len(g) == m["n_gaussians"]
    mv = load_volume(out / "model_volume.nii.gz")
    ref = load_volume(scene_dir / "volume.nii.gz")
    assert mv.meta["uses_reference_volume"] is True
    assert mv.meta["intensity"] == ref.meta["intensity"]  # the reference's units (here: no kind, a test volume)
    assert psnr3d(mv.data, ref.data) == pytest.approx(m["psnr3d"], abs=1e-4)
    assert psnr3d_r2(mv.data, ref.data) == pytest.approx(m["psnr3d_r2"], abs=1e-4)
    assert ssim3d_r2(mv.data, ref.data) == pytest.approx(m["ssim3d_r2"], abs=1e-4)
    import imageio.v3 as iio

    assert iio.imread(out / "turntable.gif").shape[0] == 4
    # evaluation is deterministic, and the validation split goes to its own file
    e = evaluate(out, device="cpu", write=False)
    assert e["psnr2d"] == m["psnr2d"] and e["psnr3d"] == m["psnr3d"]
    v = evaluate(out, split="val", device="cpu")
    assert v["split"] == "val" and json.loads((out / "metrics_val.json").read_text())["psnr2d"] == v["psnr2d"]
    assert json.loads((out / "metrics.json").read_text())["split"] == "test"


def test_deterministic_and_resume_after_kill(full_run, scene_dir: Path, tmp_path: Path) -> None:
    ref_out, ref_res = full_run
    # same config + seed -> same CSV values (the figures flag does not touch training)
    again = tmp_path / "again"
    loop.train(_cfg(scene_dir), again)
    assert _metric_rows(again / "train_log.csv") == _metric_rows(ref_out / "train_log.csv")
    res2 = evaluate(again, device="cpu", write=False)
    assert res2["psnr3d"] == ref_res["psnr3d"]
    # kill a run (SIGKILL) right after the checkpoint at iteration 20, then resume
    killed = tmp_path / "killed"
    code = (
        "import os, signal, json, sys\n"
        "from ctsplat.training import train\n"
        "cfg = json.loads(sys.argv[1])\n"
        "def cb(it, state):\n"
        "    if it == 20: os.kill(os.getpid(), signal.SIGKILL)\n"
        "train(cfg, sys.argv[2], callback=cb)\n"
    )
    cfg = _cfg(scene_dir)
    env = dict(os.environ, OMP_NUM_THREADS="2")
    proc = subprocess.run([sys.executable, "-c", code, json.dumps(cfg), str(killed)], env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == -9, proc.stderr
    assert not (killed / "metrics.json").exists()
    assert checkpoint.latest_checkpoint(killed).name == "ckpt_00000020.pt"
    ck = checkpoint.latest_checkpoint(killed)
    payload = torch.load(ck, weights_only=False)
    assert 0 < payload["health"]["peak_memory_mb"] < 1e6
    payload["health"]["peak_memory_mb"] = 1e6  # the killed process's peak, above anything this one reaches
    torch.save(payload, ck)
    loop.train(cfg, killed, resume=True)
    assert json.loads((killed / "training.json").read_text())["peak_memory_mb"] == 1e6  # across the resume
    res3 = evaluate(killed, device="cpu", write=False)
    assert _metric_rows(killed / "train_log.csv") == _metric_rows(again / "train_log.csv")
    assert res3["psnr3d"] == res2["psnr3d"] and res3["psnr2d"] == res2["psnr2d"]
    assert res3["n_gaussians"] == res2["n_gaussians"]
    # resuming with a different config is refused
    with pytest.raises(CtsplatError, match="different config"):
        loop.train({**cfg, "lambda_ssim": 0.3}, killed, resume=True)


# ------------------------------------------------------------------------------------------ NaN guard
def test_nan_guard_rolls_back_and_lowers_lr(scene_dir: Path, tmp_path: Path) -> None:
    def poison_once(it: int, state: state.TrainState) -> None:
        if it == 5:
            with torch.no_grad():
                state.params["means"][0, 0] = float("nan")

    res = loop.train(_cfg(scene_dir, iterations=12, eval_every=12), tmp_path / "a", callback=poison_once)
    assert res["nan_events"] == 1
    assert math.isfinite(evaluate(tmp_path / "a", device="cpu", write=False)["psnr3d"])
    rows = list(csv.DictReader(open(tmp_path / "a" / "train_log.csv", newline="")))
    assert int(rows[-1]["nan_events"]) == 1
    base = _cfg(scene_dir)["lr"] if "lr" in _cfg(scene_dir) else config.TRAIN_DEFAULTS["lr"]
    # learning rate halved relative to the schedule: lr_means at 12 < schedule value / 1.9
    voxel = 2.0
    sched = base["means"] * voxel * state.cosine_factor(11, 12, config.TRAIN_DEFAULTS["lr_final_factor"])
    assert float(rows[-1]["lr_means"]) == pytest.approx(0.5 * sched, rel=1e-6)

    def poison_always(it: int, state: state.TrainState) -> None:
        with torch.no_grad():
            state.params["density_raw"][:] = float("inf")

    with pytest.raises(CtsplatError, match="3 non-finite steps in a row"):
        loop.train(_cfg(scene_dir, iterations=12), tmp_path / "b", callback=poison_always)


# ------------------------------------------------------------------------------------------ densification
def _densify(st, cfg, scene, gen):  # noqa: ANN001, ANN202
    """One densify-and-prune step of the run's strategy."""
    return GradientDensify(cfg["densify"], compositor=cfg["compositor"], iterations=cfg["iterations"]).step(
        st, scene.volume, gen)


def _state_from(means, scales, dens, cfg) -> state.TrainState:
    from ctsplat.training.seeding import Seed

    seed = Seed(np.asarray(means, np.float32), np.asarray(scales, np.float32), np.asarray(dens, np.float32),
                False, "test")
    params = state.init_params(seed, cfg, torch.device("cpu"))
    opt = state.make_optimizer(params, cfg, 2.0)
    n = len(seed)
    return state.TrainState(params=params, opt=opt, grad_accum=torch.zeros(n), grad_count=torch.ones(n))


def test_train_views_are_spread_evenly_in_azimuth_from_any_start(tmp_path: Path) -> None:
    """`views: 5` of 20 parallel views at 200° + 9° k: sorted by azimuth mod 360 (2, 11, 200, ..., 353), every
    fourth — the azimuths written out here (the baselines' subset, the same `spread_views`, is checked against
    hand-written azimuths in test_baselines.py)."""
    from ctsplat.projector import render_radiographs

    data, aff = tiny_phantom()
    write_tiny_scene(tmp_path, data, aff, volume_id="tiny01", n_views=4)
    render_radiographs(tmp_path / "volume.nii.gz", tmp_path / "rad200",
                       {"detector_width": 24, "detector_height": 24, "n_views": 20, "start_deg": 200.0,
                        "device": "cpu"})
    scene = sc.load_scene(config.resolve_config(_cfg(tmp_path, radiographs=str(tmp_path / "rad200"), views=5)))
    np.testing.assert_allclose(scene.train.azimuth_deg, [2.0, 218.0, 254.0, 290.0, 326.0], atol=1e-9)


def test_densify_clone_split_prune_and_cap(scene_dir: Path) -> None:
    cfg = config.resolve_config(_cfg(scene_dir, densify={"grad_threshold": 1.0, "clone_max_scale_voxels": 1.5,
                                                     "prune_density": 1e-3, "max_gaussians": 100}))
    scene = sc.load_scene(cfg)
    means = [[0, 0, 0], [5, 0, 0], [-5, 3, 0], [0, 0, 4], [200, 0, 0]]
    scales = [[1, 1, 1], [6, 4, 4], [1, 2, 1], [1, 1, 1], [1, 1, 1]]
    dens = [0.8, 0.6, 0.5, 1e-4, 0.7]
    st = _state_from(means, scales, dens, cfg)
    st.grad_accum = torch.tensor([2.0, 3.0, 0.5, 0.1, 0.1])  # 0 cloned (small), 1 split (large)
    gen = torch.Generator().manual_seed(0)
    counts = _densify(st, cfg, scene, gen)
    assert counts["cloned"] == 1 and counts["split"] == 1
    # pruned: the low-density one (3) and the out-of-volume one (4)
    assert counts["pruned"] == 2
    g = state.as_gaussians({k: v.detach() for k, v in st.params.items()})
    m = g.means.numpy()
    d = g.densities.numpy()
    s = g.scales.numpy()
    assert len(g) == 5  # 0, 2 kept + clone of 0 + two halves of 1
    # clone: exact copy at the same place with half the density each -> mass conserved
    at0 = np.all(np.isclose(m, 0.0, atol=1e-6), axis=1)
    assert at0.sum() == 2 and np.allclose(d[at0], 0.4, rtol=1e-5)
    assert np.allclose(s[at0], 1.0)
    # untouched Gaussian keeps its values
    k2 = np.all(np.isclose(m, [-5, 3, 0], atol=1e-6), axis=1)
    assert k2.sum() == 1 and np.isclose(d[k2][0], 0.5, rtol=1e-5)
    # split: two children with scales / 1.6 drawn from the parent; together they carry the parent's mass
    kids = np.isclose(s[:, 0], 6 / 1.6, rtol=1e-5)
    assert kids.sum() == 2
    assert np.allclose(s[kids], np.array([6, 4, 4]) / 1.6, rtol=1e-5)
    mass = d * (2 * np.pi) ** 1.5 * s.prod(-1)
    assert mass[kids].sum() == pytest.approx(0.6 * (2 * np.pi) ** 1.5 * 96, rel=1e-5)
    assert mass[at0].sum() == pytest.approx(0.8 * (2 * np.pi) ** 1.5, rel=1e-5)
    assert not np.allclose(m[kids][0], m[kids][1])
    assert st.params["means"].shape[0] == st.grad_accum.shape[0] == 5
    # the optimiser follows the new parameter tensors
    assert all(g_["params"][0] is st.params[g_["name"]] for g_ in st.opt.param_groups)

    # the literal "halve" rule for splits
    cfg_h = config.resolve_config(_cfg(scene_dir, densify={"grad_threshold": 1.0, "split_mass": "halve"}))
    st_h = _state_from(means[1:2], scales[1:2], dens[1:2], cfg_h)
    st_h.grad_accum = torch.tensor([3.0])
    _densify(st_h, cfg_h, scene, gen)
    assert np.allclose(torch.nn.functional.softplus(st_h.params["density_raw"]).detach().numpy(), 0.3, rtol=1e-5)

    # cap: only the highest-gradient candidate may grow when one slot is left
    cfg2 = config.resolve_config(_cfg(scene_dir, densify={"grad_threshold": 1.0, "max_gaussians": 4}))
    st2 = _state_from(means[:3], scales[:3], dens[:3], cfg2)
    st2.grad_accum = torch.tensor([2.0, 3.0, 1.5])
    c2 = _densify(st2, cfg2, scene, gen)
    assert c2["cloned"] + c2["split"] == 1 and c2["split"] == 1 and c2["n"] == 4


@pytest.mark.parametrize("rotated", [False, True], ids=["axis-aligned", "rotated"])
def test_split_children_are_drawn_from_the_parent_gaussian(scene_dir: Path, rotated: bool) -> None:
    """The two children of a split sample N(μ, Σ) of their anisotropic parent: the sample covariance of 1200
    children against Σ = R diag(s²) Rᵀ (scipy's rotation; a transposed R would give another Σ), and the children
    keep the parent's rotation."""
    from scipy.spatial.transform import Rotation

    cfg = config.resolve_config(_cfg(scene_dir, densify={"grad_threshold": 1.0, "clone_max_scale_voxels": 1.5,
                                                         "max_gaussians": 10_000}))
    scene = sc.load_scene(cfg)
    m, parent_scales = 600, np.array([6.0, 4.0, 2.5])  # every axis above 1.5 voxels: split, not cloned
    rot = Rotation.from_euler("zyx", [50, 30, 20] if rotated else [0, 0, 0], degrees=True)
    centre = scene.volume.center_mm()
    st = _state_from(np.tile(centre, (m, 1)), np.tile(parent_scales, (m, 1)), [0.6] * m, cfg)
    wxyz = torch.tensor(rot.as_quat()[[3, 0, 1, 2]], dtype=st.params["quats"].dtype)
    st.params["quats"].data.copy_(wxyz.expand(m, 4))
    st.grad_accum = torch.full((m,), 3.0)
    counts = _densify(st, cfg, scene, torch.Generator().manual_seed(0))
    assert counts["split"] == m and 2 * m - 5 <= counts["n"] <= 2 * m  # a far tail sample may leave the volume
    g = state.as_gaussians({k: v.detach() for k, v in st.params.items()})
    np.testing.assert_allclose(g.scales.numpy(), np.tile(parent_scales / 1.6, (len(g), 1)), rtol=1e-5)
    np.testing.assert_allclose(quat_to_rotmat(g.quats).numpy(), np.tile(rot.as_matrix(), (len(g), 1, 1)), atol=1e-6)
    offsets = g.means.double().numpy() - centre
    sigma = rot.as_matrix() @ np.diag(parent_scales**2) @ rot.as_matrix().T
    np.testing.assert_allclose(np.cov(offsets.T), sigma, atol=0.12 * parent_scales[0] ** 2)
    assert abs(offsets.mean(0)).max() < 0.1 * parent_scales[0]


def test_alpha_mode_split_keeps_density(scene_dir: Path) -> None:
    cfg = config.resolve_config(_cfg(scene_dir, compositor="alpha", densify={"grad_threshold": 1.0}))
    scene = sc.load_scene(cfg)
    st = _state_from([[0, 0, 0]], [[1, 1, 1]], [0.8], cfg)
    st.grad_accum = torch.tensor([5.0])
    _densify(st, cfg, scene, torch.Generator().manual_seed(0))
    d = torch.nn.functional.softplus(st.params["density_raw"]).detach().numpy()
    assert d.shape == (2,) and np.allclose(d, 0.8, rtol=1e-5)


def test_view_sampler_is_stratified() -> None:
    az = np.arange(12) * 30.0
    s = state.ViewSampler(az, np.zeros(12), batch=3)
    rng = np.random.default_rng(0)
    epoch = s.refill(rng)
    assert sorted(v for b in epoch for v in b) == list(range(12))
    for b in epoch:  # one view from each 120-degree sector
        assert sorted(az[i] // 120 for i in b) == [0, 1, 2]
    one = state.ViewSampler(az, np.zeros(12), batch=1).refill(rng)
    assert sorted(b[0] for b in one) == list(range(12))


def test_cosine_schedule() -> None:
    assert state.cosine_factor(0, 100, 0.1) == pytest.approx(1.0)
    assert state.cosine_factor(50, 100, 0.1) == pytest.approx(0.55)
    assert state.cosine_factor(100, 100, 0.1) == pytest.approx(0.1)


# ------------------------------------------------------------------------------------------ variants
@pytest.mark.parametrize("kw", [
    {"init": "uniform", "supervision": "transmission", "batch_views": 2},
    {"init": "uniform", "compositor": "alpha", "mip": True, "lambda_tv": 0.1, "tv_size": 6},
])
def test_variants_run_and_learn(scene_dir: Path, tmp_path: Path, kw: dict) -> None:
    loop.train(_cfg(scene_dir, iterations=20, **kw), tmp_path / "v")
    rows = list(csv.DictReader(open(tmp_path / "v" / "train_log.csv", newline="")))
    assert json.loads((tmp_path / "v" / "config.json").read_text())["uses_reference_volume"] is False
    assert all(math.isfinite(float(r["loss"])) for r in rows)
    assert float(rows[-1]["loss"]) < float(rows[0]["loss"]) * 1.5
    if kw.get("lambda_tv"):
        assert float(rows[-1]["tv"]) > 0
    # the PLY carries the radiative density only where the compositor renders it
    from ctsplat.formats.ply import read_ply_vertices

    assert ("density" in read_ply_vertices(tmp_path / "v" / "model.ply")) == (kw.get("compositor") != "alpha")


def test_a_mip_model_is_saved_and_scored_with_the_filter_it_was_trained_with(scene_dir: Path, tmp_path: Path,
                                                                            monkeypatch: pytest.MonkeyPatch,
                                                                            caplog: pytest.LogCaptureFixture) -> None:
    """Mip-Splatting stores its 3D filter with the model: model.pt and model_best.pt carry the filter the training
    rendered them with, and the evaluation scores them with it instead of computing another one from the final
    means (so the validation PSNR logged at the last iteration is the one evaluate gives)."""
    from ctsplat.splat.gaussians import Gaussians
    from ctsplat.training import config as train_config

    run = tmp_path / "mip"
    with caplog.at_level(logging.INFO, logger="ctsplat.training.loop"):
        loop.train(_cfg(scene_dir, iterations=30, mip=True, densify={"interval": 10, "start": 10, "stop": 15}), run)
    # the log names what each step did: densification up to its stop, pruning alone after it
    steps = [r.getMessage().split(":")[0] for r in caplog.records if " at " in r.getMessage()]
    assert steps == ["densify at 10", "prune at 20", "prune at 30"], steps
    last, best = Gaussians.load(run / "model.pt"), Gaussians.load(run / "model_best.pt")
    for g in (last, best):
        assert g.filter_3d_var is not None and g.filter_3d_var.shape == (len(g),) and bool((g.filter_3d_var > 0).all())
    monkeypatch.setattr(train_config, "mip_filter", lambda *a, **k: pytest.fail("the stored filter was not used"))
    val = evaluate(run, split="val", device="cpu", write=False)
    logged = list(csv.DictReader(open(run / "train_log.csv", newline="")))[-1]
    assert int(logged["iteration"]) == 30 and val["psnr2d"] == pytest.approx(float(logged["psnr2d"]), abs=1e-6)
    assert math.isfinite(evaluate(run, device="cpu", write=False, model="best")["psnr2d"])


def test_ctsplat_render_draws_a_trained_model_as_it_was_trained_in_line_integral_units(scene_dir: Path,
                                                                                     tmp_path: Path) -> None:
    """A model records how it renders (compositor, mip, ``mu_scale_per_mm``), so ``ctsplat render`` without options
    draws the model as training and evaluation do, in the radiographs' units (1/mm x mm), not normalised ones."""
    import tifffile

    from ctsplat.cli import main
    from ctsplat.formats.viewset import ViewSet
    from ctsplat.splat.gaussians import Gaussians
    from ctsplat.splat.render import render

    run = tmp_path / "mip"
    loop.train(_cfg(scene_dir, iterations=30, mip=True, densify={"interval": 10, "start": 10, "stop": 15}), run)
    g = Gaussians.load(run / "model.pt")
    assert g.meta["mu_scale_per_mm"] == MU and g.meta["mip"] is True and g.meta["compositor"] == "radiative"
    assert Gaussians.load(run / "model_best.pt").meta["mu_scale_per_mm"] == MU
    out = tmp_path / "render"
    assert main(["render", str(run / "model.pt"), str(scene_dir / "rad" / "views.json"), str(out), "--split",
                 "test"]) == 0
    info = json.loads((out / "render.json").read_text())
    assert info["mu_scale"] == MU and info["mip"] is True and info["compositor"] == "radiative"
    vs = ViewSet.load(scene_dir / "rad" / "views.json")
    rows = vs.indices("test")
    rendered = tifffile.imread(out / "images.tif").reshape(len(rows), vs.camera.height, vs.camera.width)
    v = vs.views[rows[0]]
    ref = render(g, vs.camera, v.R, v.t, filter_3d_var=g.filter_3d_var, mip_2d=True).image.numpy() * MU
    np.testing.assert_allclose(rendered[0], ref, rtol=1e-5, atol=1e-7)
    targets = tifffile.imread(scene_dir / "rad" / "line_integrals.tif")[rows]
    assert 0.5 < rendered.mean() / targets.mean() < 2.0  # the targets' units: normalised ones are 1 / MU = 50x


def test_fbp_init_uses_training_projections_only(scene_dir: Path, tmp_path: Path) -> None:
    pytest.importorskip("ctsplat.baselines")
    cfg = config.resolve_config(_cfg(scene_dir, init="fbp"))
    scene = sc.load_scene(cfg)
    # the reference voxel values are not read: zero them and the seed is unchanged
    rng_a, rng_b = np.random.default_rng(0), np.random.default_rng(0)
    a = seeding.make_seed(cfg, scene, rng_a)
    scene.volume.data = np.zeros_like(scene.volume.data)
    b = seeding.make_seed(cfg, scene, rng_b)
    assert not a.uses_reference_volume
    assert np.array_equal(a.means, b.means) and np.array_equal(a.densities, b.densities)
    assert np.allclose(a.scales, 1.5 * 2.0)  # default fbp seed scale: 1.5 voxels of 2 mm
    cfg_v = config.resolve_config(_cfg(scene_dir, init="volume"))
    v = seeding.make_seed(cfg_v, sc.load_scene(cfg_v), np.random.default_rng(0))
    assert v.uses_reference_volume and np.allclose(v.scales, 0.75 * 2.0)  # the method's 0.75 voxel
    loop.train(_cfg(scene_dir, init="fbp", iterations=10), tmp_path / "f")
    res = evaluate(tmp_path / "f", device="cpu", write=False)
    assert res["init"] == "fbp" and res["uses_reference_volume"] is False


def test_fbp_init_on_cone_beam_uses_fdk_or_sirt(scene_dir: Path, tmp_path: Path) -> None:
    # slice-wise FBP needs a circular parallel orbit; a circular cone-beam scene is seeded from FDK of the training
    # views when ctsplat.recon.fdk exists, else from SIRT
    import importlib.util

    from ctsplat.projector import render_radiographs

    expected = "fdk" if importlib.util.find_spec("ctsplat.recon") and importlib.util.find_spec("ctsplat.recon.fdk") \
        else "sirt"

    render_radiographs(scene_dir / "volume.nii.gz", tmp_path / "cone",
                       {"camera": "cone", "dso_mm": 120.0, "dsd_mm": 240.0, "detector_width": 32,
                        "detector_height": 32, "n_views": 16, "device": "cpu"})
    cfg = config.resolve_config(_cfg(scene_dir, init="fbp", radiographs=str(tmp_path / "cone")))
    scene = sc.load_scene(cfg)
    truth = scene.volume.data.copy()
    recon, method = seeding.fbp_reconstruction(scene)
    assert method == expected and recon.shape == truth.shape
    # the reconstruction is the phantom (correlated with it), not the reference voxels read back
    assert np.corrcoef(recon.ravel(), truth.ravel())[0, 1] > 0.8
    scene.volume.data = np.zeros_like(truth)
    seed = seeding.make_seed(cfg, scene, np.random.default_rng(0))
    assert seed.strategy == f"fbp ({expected})" and not seed.uses_reference_volume
    ijk = np.rint((seed.means - scene.volume.affine[:3, 3]) / 2.0).astype(int).clip(0, N - 1)
    inside = truth[tuple(ijk.T)] > 0
    assert seed.densities[inside].sum() > 0.8 * seed.densities.sum()  # the seeded mass sits in the object



def _cone_scene(scene_dir: Path, tmp_path: Path, **geometry) -> Any:
    from ctsplat.projector import render_radiographs

    render_radiographs(scene_dir / "volume.nii.gz", tmp_path / "cone",
                       {"camera": "cone", "dso_mm": 120.0, "dsd_mm": 240.0, "detector_width": 32,
                        "detector_height": 32, "n_views": 16, "device": "cpu", **geometry})
    cfg = config.resolve_config(_cfg(scene_dir, init="fbp", radiographs=str(tmp_path / "cone")))
    return cfg, sc.load_scene(cfg)


def test_fbp_init_calls_fdk_on_a_circular_cone_beam(scene_dir: Path, tmp_path: Path, monkeypatch) -> None:
    import ctsplat.baselines
    from ctsplat.recon import fdk

    calls, sirt_devices = [], []
    sirt_volume = ctsplat.baselines.sirt_volume

    def fdk_volume(line_integrals, view_set, reference, *, filter_name="ramp", clip=True, device=None):
        calls.append((line_integrals.shape, len(view_set), reference.shape, filter_name, str(device)))
        return np.full(reference.shape, 0.5, np.float32)

    def sirt_spy(*args, device=None, **kwargs):
        sirt_devices.append(device)
        return sirt_volume(*args, device=device, **kwargs)

    monkeypatch.setattr(fdk, "fdk_volume", fdk_volume)
    monkeypatch.setattr(ctsplat.baselines, "sirt_volume", sirt_spy)
    cfg, scene = _cone_scene(scene_dir, tmp_path)
    recon, method = seeding.fbp_reconstruction(scene, "shepp-logan")
    assert method == "fdk" and calls == [((16, 32, 32), 16, (N, N, N), "shepp-logan", "cpu")]
    # the seed reconstructs on the training's device (auto: CUDA where present)
    calls.clear()
    assert seeding.make_seed({**cfg, "device": "auto"}, scene, np.random.default_rng(0)).strategy == "fbp (fdk)"
    assert [c[-1] for c in calls] == ["cuda" if torch.cuda.is_available() else "cpu"]
    # a wobbling cone-beam orbit is not what FDK reconstructs: SIRT on the same device, FDK never called
    calls.clear()
    _, wobbly = _cone_scene(scene_dir, tmp_path / "w", wobble_deg=10.0)
    assert seeding.fbp_reconstruction(wobbly, device="auto")[1] == "sirt" and not calls
    assert sirt_devices == ["cuda" if torch.cuda.is_available() else "cpu"]
    if not torch.cuda.is_available():  # a CUDA seed without a GPU is refused, not silently run on the CPU
        with pytest.raises(CtsplatError, match="no CUDA GPU"):
            seeding.fbp_reconstruction(scene, device="cuda")


def test_sfm_init_reads_points(scene_dir: Path, tmp_path: Path) -> None:
    from ctsplat.formats.ply import read_ply_points

    sfm = tmp_path / "sfm"
    sfm.mkdir()
    pts = np.random.default_rng(0).uniform(-10, 10, size=(40, 3)).astype(np.float32)
    head = "ply\nformat binary_little_endian 1.0\nelement vertex 40\nproperty float x\nproperty float y\n" \
           "property float z\nend_header\n"
    (sfm / "points3d.ply").write_bytes(head.encode() + pts.tobytes())
    assert np.allclose(read_ply_points(sfm / "points3d.ply"), pts)
    (sfm / "summary.json").write_text(json.dumps({"ok": True}))
    cfg = config.resolve_config(_cfg(scene_dir, init="sfm", sfm_dir=str(sfm), n_init=100))
    scene = sc.load_scene(cfg)
    seed = seeding.make_seed(cfg, scene, np.random.default_rng(0))
    assert len(seed) == 100 and np.allclose(seed.means[:40], pts)
    assert seed.strategy == "sfm (40 of 40 points, 60 uniform)"
    # a failed SfM run, or one whose points all lie outside the volume, would seed uniformly under the name sfm
    (sfm / "summary.json").write_text(json.dumps({"ok": False, "reason": "median rotation error 3 deg (need <= 1)"}))
    with pytest.raises(CtsplatError, match=r"init: sfm seeds from the SfM run in .*sfm, which may not be trained on: "
                                           r"median rotation error 3 deg \(need <= 1\); use another init"):
        seeding.make_seed(cfg, scene, np.random.default_rng(0))
    (sfm / "summary.json").unlink()
    with pytest.raises(CtsplatError, match=r"summary\.json does not exist \(the sfm step did not run\)"):
        seeding.make_seed(cfg, scene, np.random.default_rng(0))
    (sfm / "summary.json").write_text(json.dumps({"ok": True}))
    (sfm / "points3d.ply").write_bytes(head.encode() + (pts + 2000.0).astype(np.float32).tobytes())
    with pytest.raises(CtsplatError, match=r"none of the 40 SfM points in .*points3d\.ply lies inside the volume"):
        seeding.make_seed(cfg, scene, np.random.default_rng(0))


# ------------------------------------------------------------------------------------------ poses: colmap
CARM = {"camera": "cone", "orbit": "carm", "n_views": 12, "dso_mm": 120.0, "dsd_mm": 240.0, "detector_width": 24,
        "detector_height": 24, "wobble_deg": 10.0, "orbit_jitter_deg": 1.0, "device": "cpu"}


@pytest.fixture(scope="module")
def carm_dir(scene_dir: Path) -> Path:
    """The C-arm view set, as the workflow's `project` rule renders it for SfM."""
    from ctsplat.projector import render_radiographs

    render_radiographs(scene_dir / "volume.nii.gz", scene_dir / "carm", CARM, seed=3)
    return scene_dir / "carm"


def _sfm_result(carm: Path, sfm: Path, keep_ids: list[int], rate: float, ok: bool = True) -> None:
    """What the sfm step writes for its C-arm view set: aligned_views.json (the registered views, their recovered
    poses — here the true ones shifted by 0.1 mm — and the same ids) and summary.json."""
    from ctsplat.formats.viewset import ViewSet

    sfm.mkdir(parents=True, exist_ok=True)
    vs = ViewSet.load(carm / "views.json")
    aligned = ViewSet(vs.camera, [v for v in vs.views if v.id in keep_ids], vs.volume_id, vs.isocenter_mm, {})
    for v in aligned.views:
        v.t = v.t + 0.1
    aligned.save(sfm / "aligned_views.json")
    (sfm / "summary.json").write_text(json.dumps({"n_views": len(vs), "registration_rate": rate, "ok": ok,
                                                  "reason": "" if ok else "too few", "radiographs": str(carm)}))


def test_colmap_poses_drop_unregistered(scene_dir: Path, carm_dir: Path, tmp_path: Path) -> None:
    keep = [0, 1, 2, 4, 5, 6, 7, 9, 10, 11]
    _sfm_result(carm_dir, tmp_path / "sfm", keep, rate=10 / 12)
    cfg = config.resolve_config(_cfg(scene_dir, poses="colmap", sfm_dir=str(tmp_path / "sfm")))
    scene = sc.load_scene(cfg)
    assert list(scene.train.ids) == keep
    assert scene.info["views_dropped_unregistered"] == 2
    # the poses are the COLMAP ones (perturbed), the targets the C-arm view set's radiographs divided by mu_scale
    from ctsplat.formats.viewset import load_radiographs

    images, vs = load_radiographs(carm_dir)
    assert np.allclose(scene.train.ts[3], vs.views[4].t + 0.1)
    assert np.allclose(scene.train.images[3], images[4] / MU, rtol=1e-6)
    assert scene.train.camera.model == "cone" and scene.test.camera.model == "parallel"
    res = loop.train(_cfg(scene_dir, poses="colmap", sfm_dir=str(tmp_path / "sfm"), iterations=10), tmp_path / "r")
    assert res["n_train_views"] == 10
    m = evaluate(tmp_path / "r", device="cpu", write=False)
    assert m["views_dropped_unregistered"] == 2 and m["poses"] == "colmap"


def test_colmap_poses_honour_views(scene_dir: Path, carm_dir: Path, tmp_path: Path) -> None:
    """`views` picks that many registered views, evenly along the orbit; more than were registered is an error."""
    keep = [0, 1, 2, 4, 5, 6, 7, 9, 10, 11]
    _sfm_result(carm_dir, tmp_path / "sfm", keep, rate=10 / 12)
    cfg = config.resolve_config(_cfg(scene_dir, poses="colmap", views=5, sfm_dir=str(tmp_path / "sfm")))
    assert list(sc.load_scene(cfg).train.ids) == [keep[i] for i in (0, 2, 4, 6, 8)]
    cfg = config.resolve_config(_cfg(scene_dir, poses="colmap", views=11, sfm_dir=str(tmp_path / "sfm")))
    with pytest.raises(CtsplatError, match="asks for 11 training views but SfM registered only 10 of the 12"):
        sc.load_scene(cfg)
    cfg = config.resolve_config(_cfg(scene_dir, views=99))
    with pytest.raises(CtsplatError, match="asks for 99 training views but .* has only"):
        sc.load_scene(cfg)


def test_colmap_cone_poses_train_with_fbp_init(scene_dir: Path, carm_dir: Path, tmp_path: Path) -> None:
    # COLMAP poses are cone-beam views: init fbp then seeds from SIRT of those views (FBP needs parallel beams)
    _sfm_result(carm_dir, tmp_path / "sfm", list(range(12)), rate=1.0)
    cfg = config.resolve_config(_cfg(scene_dir, poses="colmap", init="fbp", sfm_dir=str(tmp_path / "sfm")))
    seed = seeding.make_seed(cfg, sc.load_scene(cfg), np.random.default_rng(0))
    assert seed.strategy == "fbp (sirt)" and not seed.uses_reference_volume
    loop.train(_cfg(scene_dir, poses="colmap", init="fbp", sfm_dir=str(tmp_path / "sfm"), iterations=10),
               tmp_path / "r")
    res = evaluate(tmp_path / "r", device="cpu", write=False)
    assert res["poses"] == "colmap" and res["init"] == "fbp" and res["uses_reference_volume"] is False


def test_colmap_poses_fail_on_low_registration(scene_dir: Path, carm_dir: Path, tmp_path: Path) -> None:
    _sfm_result(carm_dir, tmp_path / "sfm", [0, 1, 2], rate=0.25, ok=True)  # ok, but below train's own minimum
    cfg = _cfg(scene_dir, poses="colmap", sfm_dir=str(tmp_path / "sfm"))
    with pytest.raises(CtsplatError, match=r"the SfM run failed .*registered only 25% of 12 views"):
        loop.train(cfg, tmp_path / "r")
    assert not (tmp_path / "r" / "model.pt").exists()


def test_colmap_poses_refuse_a_failed_sfm_run(scene_dir: Path, carm_dir: Path, tmp_path: Path) -> None:
    """Every view registered, but the SfM step's verdict is not ok (pose error): never trained on those poses."""
    _sfm_result(carm_dir, tmp_path / "sfm", list(range(12)), rate=1.0, ok=False)
    cfg = _cfg(scene_dir, poses="colmap", sfm_dir=str(tmp_path / "sfm"), iterations=10)
    with pytest.raises(CtsplatError, match=r"the SfM run failed \(.*summary\.json\): too few; poses: colmap does not"):
        loop.train(cfg, tmp_path / "r")
    assert not (tmp_path / "r" / "model.pt").exists()


def test_colmap_poses_name_a_removed_pose_file(scene_dir: Path, carm_dir: Path, tmp_path: Path) -> None:
    _sfm_result(carm_dir, tmp_path / "sfm", list(range(12)), rate=1.0, ok=True)
    (tmp_path / "sfm" / "aligned_views.json").unlink()  # an ok run whose poses were removed since
    cfg = _cfg(scene_dir, poses="colmap", sfm_dir=str(tmp_path / "sfm"), iterations=10)
    with pytest.raises(CtsplatError, match=r"aligned_views\.json is missing although .*summary\.json says the SfM run "
                                           r"is ok .*snakemake --forcerun sfm"):
        loop.train(cfg, tmp_path / "r")


# ------------------------------------------------------------------------------------------ bad input
def test_unknown_config_key_names_key_and_allowed(scene_dir: Path, tmp_path: Path) -> None:
    with pytest.raises(CtsplatError, match=r"train\.learning_rate.*allowed keys in train: .*batch_views"):
        loop.train(_cfg(scene_dir, learning_rate=1.0), tmp_path / "r")
    with pytest.raises(CtsplatError, match=r"train\.densify\.intervall.*interval"):
        loop.train(_cfg(scene_dir, densify={"intervall": 3}), tmp_path / "r")
    with pytest.raises(CtsplatError, match="unknown train.init 'random'; allowed: volume, uniform, fbp, sfm"):
        loop.train(_cfg(scene_dir, init="random"), tmp_path / "r")
    assert not (tmp_path / "r").exists() or not any((tmp_path / "r").iterdir())


def test_missing_and_mismatched_inputs(scene_dir: Path, tmp_path: Path) -> None:
    from ctsplat.formats.volume import Volume, load_volume, save_volume

    with pytest.raises(CtsplatError, match="does not exist"):
        loop.train(_cfg(scene_dir, radiographs=str(tmp_path / "nope")), tmp_path / "r")
    with pytest.raises(CtsplatError, match="does not exist"):
        loop.train(_cfg(scene_dir, volume=str(tmp_path / "nope.nii.gz")), tmp_path / "r")
    ref = load_volume(scene_dir / "volume.nii.gz")
    other = Volume(ref.data[:16, :16, :16].copy(), ref.affine, {**ref.meta, "volume_id": "other02"})
    save_volume(other, tmp_path / "other.nii.gz")
    with pytest.raises(CtsplatError, match="rendered from volume tiny01, but train.volume is other02"):
        loop.train(_cfg(scene_dir, volume=str(tmp_path / "other.nii.gz")), tmp_path / "r")
    assert not (tmp_path / "r" / "train_log.csv").exists()


def _moved_split(scene_dir: Path, rad: Path, old: str, new: str) -> Path:
    """A copy of the tiny scene's radiographs with every ``old`` view moved to the ``new`` split."""
    shutil.copytree(scene_dir / "rad", rad)
    d = json.loads((rad / "views.json").read_text())
    for v in d["views"]:
        if v["split"] == old:
            v["split"] = new
    (rad / "views.json").write_text(json.dumps(d))
    return rad


def test_without_validation_views_the_test_views_never_choose_a_model(scene_dir: Path, tmp_path: Path,
                                                                     caplog: pytest.LogCaptureFixture) -> None:
    rad = _moved_split(scene_dir, tmp_path / "rad", "val", "test")
    with pytest.raises(CtsplatError, match="model_selection: best chooses a model on validation views"):
        loop.train(_cfg(scene_dir, radiographs=str(rad), model_selection="best"), tmp_path / "best")
    assert not (tmp_path / "best").exists()
    with caplog.at_level(logging.WARNING, logger="ctsplat.training.loop"):
        loop.train(_cfg(scene_dir, radiographs=str(rad), iterations=10), tmp_path / "last")
    assert "no validation views: the periodic evaluation" in caplog.text


def test_empty_train_split(scene_dir: Path, tmp_path: Path) -> None:
    rad = _moved_split(scene_dir, tmp_path / "rad", "train", "test")
    with pytest.raises(CtsplatError, match="empty train split"):
        loop.train(_cfg(scene_dir, radiographs=str(rad)), tmp_path / "r")


def test_unwritable_output_folder(scene_dir: Path, tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(CtsplatError, match="not writable"):
        loop.train(_cfg(scene_dir), blocker / "run")
    if os.geteuid() != 0:  # permissions do not stop root
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        try:
            with pytest.raises(CtsplatError, match="not writable"):
                loop.train(_cfg(scene_dir), ro)
        finally:
            ro.chmod(0o700)


def test_evaluation_failing_part_way_leaves_no_metrics(full_run, tmp_path: Path) -> None:
    run = tmp_path / "run"
    shutil.copytree(full_run[0], run)
    (run / "turntable.gif").unlink()
    (run / "turntable.gif").mkdir()  # the last figure cannot be written
    with pytest.raises(CtsplatError, match=r"turntable\.gif is a folder, but a file is to be written there"):
        evaluate(run, device="cpu")
    assert not (run / "metrics.json").exists()  # the new gallery and volume are not described by the old metrics
    for settings, needle in (({"fps_width": 0}, "fps_width"), ({"turntable_frames": 0}, "turntable_frames")):
        with pytest.raises(CtsplatError, match=needle):
            evaluate(run, device="cpu", settings=settings)
    (run / "refined_views.json").write_text("{")
    with pytest.raises(CtsplatError, match=r"refined_views\.json is not valid JSON"):
        evaluate(run, device="cpu", write=False)
    (run / "refined_views.json").write_text('{"views": []}')
    with pytest.raises(CtsplatError, match=r"refined_views\.json lacks a training view's pose \(KeyError"):
        evaluate(run, device="cpu", write=False)


def test_cli_train_and_evaluate(scene_dir: Path, tmp_path: Path, capsys) -> None:
    import yaml

    from ctsplat.cli import main

    cfg = _cfg(scene_dir, iterations=10)
    (tmp_path / "c.yaml").write_text(yaml.safe_dump({"train": cfg}))
    rc = main(["train", "--config", str(tmp_path / "c.yaml"), "--out", str(tmp_path / "run"),
               "--set", "densify.interval=5", "--quiet"])
    assert rc == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert printed["psnr3d"] == m["psnr3d"]
    cfg_used = json.loads((tmp_path / "run" / "config.json").read_text())["config"]
    assert cfg_used["densify"]["interval"] == 5
    rc = main(["evaluate", str(tmp_path / "run"), "--device", "cpu"])
    assert rc == 0
    ev = json.loads(capsys.readouterr().out)
    assert ev["psnr3d"] == pytest.approx(m["psnr3d"], abs=1e-6)
    rc = main(["train", "--config", str(tmp_path / "c.yaml"), "--out", str(tmp_path / "r2"), "--set", "bogus=1"])
    assert rc == 2
    assert "unknown config key train.bogus" in capsys.readouterr().err


def test_alpha_seeds_start_at_the_brightest_target_with_the_best_fitting_opacity(scene_dir: Path) -> None:
    """The colour is the brightest training target; the opacity is the grid value whose rendering fits the training
    views best (checked by rendering every candidate here), and the start beats an empty model."""
    from ctsplat.evaluation.run import render_views
    from ctsplat.training.config import render_kwargs
    from ctsplat.training.seeding import make_seed

    chosen = {}
    for init in ("uniform", "fbp"):
        cfg = config.resolve_config(_cfg(scene_dir, compositor="alpha", init=init))
        scene = sc.load_scene(cfg)
        tr = scene.train
        seed = make_seed(cfg, scene, np.random.default_rng(0))
        st = state.TrainState(params=state.init_params(seed, cfg, torch.device("cpu")), opt=None)
        colour, opacity = loop.fit_alpha_seeds(st, cfg, tr, n_views=len(tr.Rs))
        y = np.asarray(tr.images, np.float64)
        assert colour == pytest.approx(float(y.max())) and torch.all(st.params["colors"] == np.float32(colour))
        assert torch.allclose(torch.sigmoid(st.params["opacity_raw"]), torch.tensor(opacity), atol=1e-6)

        def sse(o: float, st: state.TrainState = st, cfg: dict = cfg, tr=tr, y: np.ndarray = y) -> float:
            p = {k: v.detach().clone() for k, v in st.params.items()}
            p["opacity_raw"].fill_(float(np.log(o / (1 - o))))
            pred = render_views(state.as_gaussians(p), tr.camera, tr.Rs, tr.ts, render_kwargs(cfg, None))
            return float(((np.asarray(pred, np.float64) - y) ** 2).sum())

        errors = {o: sse(o) for o in loop.ALPHA_OPACITIES}
        assert opacity == min(errors, key=errors.get) and errors[opacity] < float((y ** 2).sum())
        chosen[init] = opacity
    assert chosen["uniform"] <= chosen["fbp"]  # dense uniform seeds start fainter


def test_fbp_init_refined_by_asd_pocs_is_closer_to_the_object(scene_dir: Path, tmp_path: Path) -> None:
    # noisy sparse cone-beam views: a few ASD-POCS iterations from the FDK volume remove streaks and noise (its
    # error against the phantom falls); still from the training projections only
    cfg, scene = _cone_scene(scene_dir, tmp_path,
                             noise={"enabled": True, "i0": 1e4, "electronic_sigma": 0.0, "model": "tigre",
                                    "splits": ["train"]})
    truth = scene.volume.data.copy()
    fdk_recon, _ = seeding.fbp_reconstruction(scene)
    scene.volume.data = np.zeros_like(truth)
    refined = seeding.asd_pocs_refinement(scene, fdk_recon, iterations=5, alpha=0.1)
    assert refined.shape == truth.shape and refined.min() >= 0.0 and refined.max() <= 1.0
    assert np.mean((refined - truth) ** 2) < 0.75 * np.mean((np.clip(fdk_recon, 0, 1) - truth) ** 2)  # 0.63 here
    cfg["init_asd_pocs"] = {"iterations": 5, "alpha": 0.1}
    seed = seeding.make_seed(cfg, scene, np.random.default_rng(0))
    assert seed.strategy == "fbp (fdk) + asd_pocs x5" and not seed.uses_reference_volume
    cfg["init_asd_pocs"] = {"iterations": 0, "alpha": 0.1}
    assert seeding.make_seed(cfg, scene, np.random.default_rng(0)).strategy == "fbp (fdk)"


def test_evaluate_refuses_a_model_whose_read_out_overflows(full_run, tmp_path: Path) -> None:
    """Finite parameters can still sum past float32 where Gaussians overlap: one line, no metrics written."""
    from ctsplat.splat.gaussians import Gaussians

    run = tmp_path / "run"
    shutil.copytree(full_run[0], run)
    (run / "metrics.json").unlink()
    g = Gaussians.load(run / "model.pt")
    with torch.no_grad():
        g.density_raw.fill_(3.0e38)  # softplus(x) = x: every density just below float32's largest
    g.save(run / "model.pt")
    with pytest.raises(CtsplatError, match=r"model\.pt renders \d+ non-finite (pixel|voxel)\(s\) of \d+ .*; retrain"):
        evaluate(run, device="cpu")
    assert not (run / "metrics.json").exists()


@pytest.mark.parametrize(("settings", "iterations", "warned"), [
    ({"interval": 500, "start": 500, "stop": 0}, 400, True),  # stop 0.75 x 400 = 300 < 500
    ({"interval": 100, "start": 50, "stop": 80}, 1000, True),  # no multiple of 100 in [50, 80]
    ({"interval": 100, "start": 0, "stop": 0}, 100, True),  # iteration 100 is the last: never densified
    ({"interval": 0, "start": 500, "stop": 0}, 400, False),  # turned off on purpose
    ({"interval": 100, "start": 100, "stop": 0}, 400, False),  # 100, 200, 300
    ({"interval": 100, "start": 150, "stop": 200}, 1000, False),  # 200
])
def test_a_densification_that_never_runs_is_reported(caplog, settings: dict, iterations: int, warned: bool) -> None:
    from ctsplat.training.densify import make_densify

    full = {**config.TRAIN_DEFAULTS["densify"], **settings}
    with caplog.at_level(logging.WARNING, logger="ctsplat.training.densify"):
        d = make_densify(full, compositor="radiative", iterations=iterations)
    assert ("train.densify never clones or splits" in caplog.text) == warned
    # the warning says what due() does: no iteration densifies (interval 0 densifies nothing, unwarned)
    assert any(d.due(i) for i in range(1, iterations + 1)) == (not warned and settings["interval"] > 0)
    assert isinstance(d, GradientDensify)
