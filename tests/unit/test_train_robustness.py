"""Training robustness: out-of-range settings fail at once, non-finite steps are counted over a window, a collapsed
model fails the run instead of being written, damaged checkpoints fall back to the previous one, a run folder is
locked against a second process, and the CLI does not silently restart a folder that holds a run."""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
import yaml
from test_train import _cfg, _metric_rows, scene_dir  # noqa: F401 - scene_dir is a fixture

from ctsplat.training import checkpoint, config, loop
from ctsplat.utils import LOCK_NAME, CtsplatError, run_lock

ROOT = Path(__file__).resolve().parents[2]
ENV = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
FINAL = ("model.pt", "model.ply", "training.json")


def _set(cfg: dict, dotted: str, value: object) -> dict:
    node = cfg
    *parents, last = dotted.split(".")
    for part in parents:
        node = node.setdefault(part, {})
    node[last] = value
    return cfg


def _outside(bound: config.Bound) -> list[object]:
    """Values just outside a bound on each limited side, and a non-number."""
    bad: list[object] = ["abc", True, float("nan")]
    if bound.low is not None:
        bad.append(bound.low if bound.low_open else bound.low - 1)
    if bound.high is not None:
        bad.append(bound.high if bound.high_open else bound.high + 1)
    if bound.kind == "integer":
        bad.append(2.5)
    if not bound.nullable:
        bad.append(None)
    return bad


# ------------------------------------------------------------------------------------------ bounds
@pytest.mark.parametrize("key", sorted(config.TRAIN_BOUNDS))
def test_every_numeric_key_is_bounded(key: str, scene_dir: Path, tmp_path: Path) -> None:  # noqa: F811
    bound = config.TRAIN_BOUNDS[key]
    base = _cfg(scene_dir)
    default = config._get(config.TRAIN_DEFAULTS, key)
    config.resolve_config(_set(json.loads(json.dumps(base)), key, default))  # the default is inside
    for value in _outside(bound):
        cfg = _set(json.loads(json.dumps(base)), key, value)
        with pytest.raises(CtsplatError) as err:
            loop.train(cfg, tmp_path / "run")
        msg = str(err.value)
        assert "\n" not in msg and f"train.{key} must be {bound.describe()}, got" in msg, (value, msg)
    assert not (tmp_path / "run").exists()  # nothing created before the settings are checked


def test_bounds_named_in_the_issue(scene_dir: Path, tmp_path: Path) -> None:  # noqa: F811
    cases = {
        ("nan_lr_decay", 0): r"train\.nan_lr_decay must be a number in \(0, 1\), got 0",
        ("nan_lr_decay", 2): r"train\.nan_lr_decay must be a number in \(0, 1\), got 2",
        ("lr.means", -0.01): r"train\.lr\.means must be a number > 0, got -0\.01",
        ("lambda_ssim", -0.2): r"train\.lambda_ssim must be a number >= 0",
        ("init_asd_pocs.iterations", -1): r"train\.init_asd_pocs\.iterations must be an integer >= 0, got -1",
        ("init_asd_pocs.alpha", 0): r"train\.init_asd_pocs\.alpha must be a number > 0, got 0",
        ("checkpoint_every", 0): r"train\.checkpoint_every must be an integer >= 1, got 0",
        ("eval_every", -5): r"train\.eval_every must be an integer >= 1, got -5",
        ("eval_every", "abc"): r"train\.eval_every must be an integer >= 1, got 'abc'",
        ("densify.grad_threshold", -1e-4): r"train\.densify\.grad_threshold must be a number >= 0",
        ("lambda_density", "5e-5"): r"got '5e-5' \(text: YAML reads 5e-5 as a string; write 5\.0e-5\)",
    }
    for (key, value), pattern in cases.items():
        with pytest.raises(CtsplatError, match=pattern):
            loop.train(_set(_cfg(scene_dir), key, value), tmp_path / "run")
    with pytest.raises(CtsplatError, match="no data term"):
        loop.train(_cfg(scene_dir, lambda_l1=0.0, lambda_ssim=0), tmp_path / "run")
    with pytest.raises(CtsplatError, match=r"train\.lr must be a mapping"):
        loop.train(_cfg(scene_dir, lr=0.01), tmp_path / "run")
    with pytest.raises(CtsplatError, match=r"train\.mip must be true or false, got 'yes'"):
        loop.train(_cfg(scene_dir, mip="yes"), tmp_path / "run")
    with pytest.raises(CtsplatError, match="unknown train.fbp_filter 'box'"):
        loop.train(_cfg(scene_dir, fbp_filter="box"), tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_bounds_have_a_json_schema_form() -> None:
    assert config.TRAIN_BOUNDS["nan_lr_decay"].json_schema() == {
        "type": "number", "exclusiveMinimum": 0, "exclusiveMaximum": 1}
    assert config.TRAIN_BOUNDS["init_scale_voxels"].json_schema() == {"type": ["number", "null"],
                                                                     "exclusiveMinimum": 0}
    assert config.TRAIN_BOUNDS["eval_every"].json_schema() == {"type": "integer", "minimum": 1}
    assert config.TRAIN_BOUNDS["sharpen.amounts"].json_schema() == {
        "type": "array", "minItems": 1, "items": {"type": "number", "minimum": 0, "maximum": 4}}
    # every numeric default (or list of numbers) has a bound, and nothing else does
    numeric = set()

    def is_number(v: object) -> bool:
        return isinstance(v, int | float) and not isinstance(v, bool)

    def walk(d: dict, prefix: str = "") -> None:
        for k, v in d.items():
            if isinstance(v, dict):
                walk(v, f"{prefix}{k}.")
            elif is_number(v) or v is None or (isinstance(v, list) and v and all(map(is_number, v))):
                numeric.add(prefix + k)

    walk(config.TRAIN_DEFAULTS)
    assert numeric == set(config.TRAIN_BOUNDS)


# ------------------------------------------------------------------------------------------ non-finite steps
def test_alternating_nan_steps_stop_the_run(scene_dir: Path, tmp_path: Path) -> None:  # noqa: F811
    def every_other(it: int, st) -> None:  # noqa: ANN001
        if it % 2 == 0:  # the next step sees a non-finite parameter; the one after is fine again
            with torch.no_grad():
                st.params["means"][0, 0] = float("nan")

    with pytest.raises(CtsplatError, match=r"5 non-finite steps within 100 iterations \(iterations 3\.\.11"):
        loop.train(_cfg(scene_dir, iterations=40), tmp_path / "a", callback=every_other)
    assert not any((tmp_path / "a" / n).exists() for n in FINAL)
    # the window is a setting: 5 events spread over more than nan_window iterations do not stop a run
    res = loop.train(_cfg(scene_dir, iterations=40, nan_window=8, eval_every=40, collapse_psnr_drop_db=0.0,
                          collapse_empty_margin_db=0.0), tmp_path / "b", callback=every_other)
    assert res["nan_events"] == 19


# ------------------------------------------------------------------------------------------ collapse
HUGE = {k: v * 1e4 for k, v in config.TRAIN_DEFAULTS["lr"].items()}


@pytest.mark.parametrize(("kw", "reason"), [
    ({"lr": {"density": 100.0}}, r"only 0 of \d+ Gaussians have a density >= densify\.prune_density"),
    ({"lr": HUGE}, r"the final validation PSNR 11\.\d\d dB is more than collapse_psnr_drop_db \(5 dB\) below"),
    ({"init": "uniform", "lr": {"means": 100.0, "scales": 100.0}},
     r"the final validation PSNR .* within collapse_empty_margin_db \(0\.1 dB\) of an empty model's"),
], ids=["no-density", "psnr-drop", "empty"])
def test_collapsed_model_fails_the_run(scene_dir: Path, tmp_path: Path, kw: dict, reason: str) -> None:  # noqa: F811
    out = tmp_path / "run"
    with pytest.raises(CtsplatError, match=r"^training collapsed at iteration \d+: " + reason) as err:
        loop.train(_cfg(scene_dir, **kw), out)
    assert "\n" not in str(err.value)
    assert not any((out / n).exists() for n in FINAL)
    assert (out / "train_log.csv").stat().st_size > 0 and (out / "config.json").exists()  # kept for diagnosis


def test_loss_stuck_high_fails_the_run(scene_dir: Path, tmp_path: Path) -> None:  # noqa: F811
    def flood(it: int, st) -> None:  # noqa: ANN001
        if it >= 10:  # every Gaussian far too dense from here on: the loss jumps and stays up
            with torch.no_grad():
                st.params["density_raw"].fill_(5.0)

    with pytest.raises(CtsplatError, match=r"training collapsed at iteration 25: the mean loss stayed above 2 x its "
                                           r"first interval's .* for 3 validations in a row"):
        loop.train(_cfg(scene_dir, iterations=60, eval_every=5, collapse_loss_evals=3), tmp_path / "a",
                   callback=flood)
    # disabled checks: the same run writes its (bad) model
    loop.train(_cfg(scene_dir, iterations=60, eval_every=5, collapse_loss_evals=0, collapse_psnr_drop_db=0.0,
                    collapse_empty_margin_db=0.0), tmp_path / "b", callback=flood)
    assert (tmp_path / "b" / "model.pt").exists()


# ------------------------------------------------------------------------------------------ checkpoints
@pytest.fixture(scope="module")
def reference(scene_dir: Path, tmp_path_factory) -> Path:  # noqa: F811
    out = tmp_path_factory.mktemp("ref")
    loop.train(_cfg(scene_dir, keep_checkpoints=3), out)
    return out


@pytest.mark.parametrize("damage", ["empty", "truncated", "garbage"])
def test_damaged_newest_checkpoint_falls_back(scene_dir: Path, reference: Path, tmp_path: Path,  # noqa: F811
                                              caplog, damage: str) -> None:
    out = tmp_path / "run"

    def stop_at_20(it: int, st) -> None:  # noqa: ANN001
        if it == 20:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        loop.train(_cfg(scene_dir, keep_checkpoints=3), out, callback=stop_at_20)
    newest = checkpoint.latest_checkpoint(out)
    assert newest.name == "ckpt_00000020.pt"
    data = newest.read_bytes()
    newest.write_bytes({"empty": b"", "truncated": data[: len(data) // 2], "garbage": b"\x00junk" * 10}[damage])
    with caplog.at_level(logging.WARNING, logger="ctsplat.training.checkpoint"):
        loop.train(_cfg(scene_dir, keep_checkpoints=3), out, resume=True)
    assert "ckpt_00000020.pt" in caplog.text and "moved aside" in caplog.text
    bad = out / "checkpoints" / "ckpt_00000020.pt.corrupt"
    with pytest.raises(CtsplatError, match="cannot read checkpoint .*ckpt_00000020.pt.corrupt: ") as err:
        checkpoint.read_checkpoint(bad)
    assert "\n" not in str(err.value)
    # resumed from iteration 10: the same result as the uninterrupted run
    assert _metric_rows(out / "train_log.csv") == _metric_rows(reference / "train_log.csv")
    assert _metric_rows(out / "per_view.csv") == _metric_rows(reference / "per_view.csv")
    assert sorted(p.name for p in checkpoint.list_checkpoints(out)) == \
        sorted(p.name for p in checkpoint.list_checkpoints(reference))


def test_only_damaged_checkpoints_start_over(scene_dir: Path, tmp_path: Path, caplog) -> None:  # noqa: F811
    out = tmp_path / "run"
    (out / "checkpoints").mkdir(parents=True)
    (out / "checkpoints" / "ckpt_00000010.pt").write_bytes(b"")
    with caplog.at_level(logging.WARNING):
        res = loop.train(_cfg(scene_dir, iterations=10), out, resume=True)
    assert res["iterations"] == 10
    assert "the file is empty" in caplog.text and "no readable checkpoint" in caplog.text


def test_resume_restores_logs_a_workflow_manager_deleted(scene_dir: Path, reference: Path,  # noqa: F811
                                                          tmp_path: Path) -> None:
    out = tmp_path / "run"

    def stop_at_25(it: int, st) -> None:  # noqa: ANN001
        if it == 25:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        loop.train(_cfg(scene_dir, keep_checkpoints=3), out, callback=stop_at_25)
    for name in ("train_log.csv", "per_view.csv", "config.json"):  # Snakemake removes a failed job's outputs
        (out / name).unlink()
    loop.train(_cfg(scene_dir, keep_checkpoints=3), out, resume="auto")
    assert _metric_rows(out / "train_log.csv") == _metric_rows(reference / "train_log.csv")
    assert _metric_rows(out / "per_view.csv") == _metric_rows(reference / "per_view.csv")


def test_auto_resume_starts_over_for_another_config(scene_dir: Path, tmp_path: Path, caplog) -> None:  # noqa: F811
    out = tmp_path / "run"
    loop.train(_cfg(scene_dir, iterations=20), out)
    with caplog.at_level(logging.INFO):
        loop.train(_cfg(scene_dir, iterations=20, lambda_ssim=0.3), out, resume="auto")
    assert "belong to another config" in caplog.text and "resuming" not in caplog.text
    assert json.loads((out / "config.json").read_text())["config"]["lambda_ssim"] == 0.3
    caplog.clear()
    with caplog.at_level(logging.INFO):
        loop.train(_cfg(scene_dir, iterations=20, lambda_ssim=0.3), out, resume="auto")
    assert "resuming from" in caplog.text
    with pytest.raises(CtsplatError, match=r"different config, .*ctsplat train --restart"):
        loop.train(_cfg(scene_dir, iterations=20), out, resume=True)


def test_a_resumed_run_writes_model_best_after_a_workflow_manager_removed_the_outputs(
        scene_dir: Path, tmp_path: Path) -> None:  # noqa: F811
    """Snakemake removes a job's declared outputs before it reruns it (and after it fails): the best validation model
    is kept beside the checkpoints, so a resumed run, finished or killed part-way, still writes it."""
    from ctsplat.splat.gaussians import Gaussians

    outputs = ("model.pt", "model_best.pt", "model.ply", "training.json", "config.json", "train_log.csv",
               "per_view.csv")
    full = tmp_path / "full"
    loop.train(_cfg(scene_dir, keep_checkpoints=3), full)
    best = Gaussians.load(full / "model_best.pt")
    for name in outputs:  # a rerun of the finished job: resumed from its last checkpoint, nothing left to train
        (full / name).unlink()
    loop.train(_cfg(scene_dir, keep_checkpoints=3), full, resume="auto")
    again = Gaussians.load(full / "model_best.pt")
    assert again.meta["iteration"] == best.meta["iteration"] and torch.equal(again.means, best.means)

    def stop_at_25(it: int, st) -> None:  # noqa: ANN001
        if it == 25:
            raise KeyboardInterrupt

    cut = tmp_path / "cut"
    with pytest.raises(KeyboardInterrupt):
        loop.train(_cfg(scene_dir, keep_checkpoints=3), cut, callback=stop_at_25)
    assert not (cut / "model_best.pt").exists()  # an output only once the run has ended
    for name in outputs:
        (cut / name).unlink(missing_ok=True)
    loop.train(_cfg(scene_dir, keep_checkpoints=3), cut, resume="auto")
    resumed = Gaussians.load(cut / "model_best.pt")
    assert resumed.meta["iteration"] == best.meta["iteration"] and torch.equal(resumed.means, best.means)


def test_auto_resume_starts_over_when_the_inputs_or_the_code_changed(tmp_path: Path, caplog,
                                                                      monkeypatch) -> None:
    """The config names its inputs by path: radiographs rendered again under the same path (a Snakemake rerun after
    an input changed) or another code version must train again, not resume the finished run's last checkpoint."""
    from train_helpers import tiny_phantom, write_tiny_scene

    data, aff = tiny_phantom()
    scene = write_tiny_scene(tmp_path / "scene", data, aff, volume_id="first", n_views=12)
    out = tmp_path / "run"
    cfg = _cfg(scene, iterations=20)
    first = loop.train(cfg, out)
    model = (out / "model.pt").read_bytes()
    with caplog.at_level(logging.INFO):  # unchanged: the finished run is continued (nothing left to do)
        loop.train(cfg, out, resume="auto")
    assert "resuming from" in caplog.text and (out / "model.pt").read_bytes() == model
    caplog.clear()
    write_tiny_scene(tmp_path / "scene", 0.8 * data, aff, volume_id="second", n_views=12)  # same paths
    with caplog.at_level(logging.INFO):
        again = loop.train(cfg, out, resume="auto")
    assert "resuming" not in caplog.text and "other inputs or other code" in caplog.text
    assert (out / "model.pt").read_bytes() != model and again["best_val_psnr"] != first["best_val_psnr"]
    caplog.clear()
    monkeypatch.setattr(loop, "code_version", lambda: "0.0.0+gother")
    with caplog.at_level(logging.INFO):
        loop.train(cfg, out, resume="auto")
    assert "resuming" not in caplog.text and "other inputs or other code" in caplog.text
    with pytest.raises(CtsplatError, match=r"different config, other inputs or other code .*--restart"):
        monkeypatch.setattr(loop, "code_version", lambda: "0.0.0+gthird")
        loop.train(cfg, out, resume=True)


def test_code_version_tells_two_edits_of_one_commit_apart(tmp_path: Path) -> None:
    """A checkpoint resumes only under its own code version: an edit in a tree that already differs from its
    commit must give another version, and files outside the code (results) must not."""
    from ctsplat.utils import code_version

    def git(*args: str) -> None:
        subprocess.run(["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@t", *args],
                       check=True, capture_output=True)

    (tmp_path / "ctsplat").mkdir()
    (tmp_path / "ctsplat" / "a.py").write_text("x = 1\n")
    git("init", "-q")
    git("add", ".")
    git("commit", "-q", "-m", "c")
    clean = code_version(tmp_path)
    assert "+g" in clean and "dirty" not in clean
    (tmp_path / "results.csv").write_text("not code\n")
    assert code_version(tmp_path) == clean
    (tmp_path / "ctsplat" / "a.py").write_text("x = 2\n")
    first = code_version(tmp_path)
    (tmp_path / "ctsplat" / "a.py").write_text("x = 3\n")
    second = code_version(tmp_path)
    assert first.startswith(clean + "-dirty-") and second.startswith(clean + "-dirty-") and first != second
    assert code_version(tmp_path) == second  # the same tree, the same version
    (tmp_path / "ctsplat" / "new.py").write_text("y = 1\n")
    third = code_version(tmp_path)
    (tmp_path / "ctsplat" / "new.py").write_text("y = 2\n")
    assert len({second, third, code_version(tmp_path)}) == 3  # a new file counts by its content


# ------------------------------------------------------------------------------------------ lock
HOLD = """
import sys, time
from pathlib import Path
from ctsplat.utils import run_lock
with run_lock(sys.argv[1]):
    Path(sys.argv[2]).touch()
    while not Path(sys.argv[3]).exists():
        time.sleep(0.02)
"""

TRAIN_AND_WAIT = """
import json, sys, time
from pathlib import Path
from ctsplat.training import train
def wait(it, state):
    if it == 1:
        Path(sys.argv[3]).touch()
        while not Path(sys.argv[4]).exists():
            time.sleep(0.02)
train(json.loads(sys.argv[1]), sys.argv[2], callback=wait)
"""


def _wait_for(path: Path, proc: subprocess.Popen) -> None:
    deadline = time.monotonic() + 120
    while not path.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline
        time.sleep(0.02)


def _cli(*args: str) -> subprocess.CompletedProcess:
    code = "import sys; from ctsplat.cli import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.run([sys.executable, "-c", code, *args], env=ENV, capture_output=True, text=True, timeout=300)


def test_second_training_into_a_busy_folder_fails_fast(scene_dir: Path, tmp_path: Path) -> None:  # noqa: F811
    out = tmp_path / "run"
    cfg = _cfg(scene_dir, iterations=10)
    first = subprocess.Popen([sys.executable, "-c", TRAIN_AND_WAIT, json.dumps(cfg), str(out), str(tmp_path / "busy"),
                              str(tmp_path / "go")], env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True)
    try:
        _wait_for(tmp_path / "busy", first)
        (tmp_path / "c.yaml").write_text(yaml.safe_dump({"train": _cfg(scene_dir, iterations=10, seed=7)}))
        t0 = time.monotonic()
        second = _cli("train", "--config", str(tmp_path / "c.yaml"), "--out", str(out), "--quiet")
        assert time.monotonic() - t0 < 60
        assert second.returncode == 2
        err = second.stderr.strip().splitlines()
        assert len(err) == 1 and f"is in use by another ctsplat process (pid {first.pid}" in err[0], second.stderr
        third = _cli("evaluate", str(out), "--device", "cpu")
        assert third.returncode == 2 and f"(pid {first.pid}" in third.stderr
    finally:
        (tmp_path / "go").touch()
        _, stderr = first.communicate(timeout=300)
    assert first.returncode == 0, stderr
    # the folder is the first run's alone
    run_cfg = json.loads((out / "config.json").read_text())
    assert run_cfg["config"]["seed"] == 0
    assert json.loads((out / "training.json").read_text())["config_hash"] == run_cfg["config_hash"]
    assert not (out / "metrics.json").exists()


def test_evaluation_and_lock_release_with_real_processes(scene_dir: Path, tmp_path: Path) -> None:  # noqa: F811
    out = tmp_path / "run"
    loop.train(_cfg(scene_dir, iterations=10), out)
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(out), str(tmp_path / "held"), str(tmp_path / "go")],
                              env=ENV, text=True, stderr=subprocess.PIPE)
    _wait_for(tmp_path / "held", holder)
    try:
        res = _cli("evaluate", str(out), "--device", "cpu")
        assert res.returncode == 2 and f"(pid {holder.pid}" in res.stderr
        assert not (out / "metrics.json").exists()
        with pytest.raises(CtsplatError, match=f"in use by another ctsplat process \\(pid {holder.pid}"):
            loop.train(_cfg(scene_dir, iterations=10), out, resume=True)
    finally:
        os.kill(holder.pid, signal.SIGKILL)  # a killed holder leaves no stale lock
        holder.wait()
    assert (out / LOCK_NAME).exists()
    assert _cli("evaluate", str(out), "--device", "cpu").returncode == 0
    assert (out / "metrics.json").exists()


def test_lock_is_reentrant_within_a_process(tmp_path: Path) -> None:
    with run_lock(tmp_path / "r") as a, run_lock(tmp_path / "r") as b:
        assert a == b and a.read_text().split()[0] == str(os.getpid())
    with run_lock(tmp_path / "r"):
        pass
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(CtsplatError, match="not writable"):
        with run_lock(blocker / "run"):
            pass


# ------------------------------------------------------------------------------------------ CLI
def test_cli_refuses_to_silently_restart_a_run(scene_dir: Path, tmp_path: Path, capsys) -> None:  # noqa: F811
    from ctsplat.cli import main

    (tmp_path / "c.yaml").write_text(yaml.safe_dump({"train": _cfg(scene_dir, iterations=10)}))
    base = ["train", "--config", str(tmp_path / "c.yaml"), "--out", str(tmp_path / "run"), "--quiet", "--no-evaluate"]
    assert main(base) == 0
    before = (tmp_path / "run" / "model.pt").read_bytes()
    capsys.readouterr()
    assert main(base) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "already holds a training run (checkpoints/ckpt_00000010.pt, model.pt, training.json)" in err
    assert "pass --resume to continue it or --restart to discard it" in err
    assert (tmp_path / "run" / "model.pt").read_bytes() == before  # untouched
    assert main([*base, "--resume"]) == 0
    assert main([*base, "--set", "seed=3", "--restart"]) == 0
    assert json.loads((tmp_path / "run" / "config.json").read_text())["config"]["seed"] == 3
    with pytest.raises(SystemExit):
        main([*base, "--resume", "--restart"])
    capsys.readouterr()
    # bad settings fail before the run folder is touched, in one line naming the key
    assert main(["train", "--config", str(tmp_path / "c.yaml"), "--out", str(tmp_path / "new"),
                 "--set", "nan_lr_decay=2"]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "train.nan_lr_decay" in err and "2" in err
    assert not (tmp_path / "new").exists()


def test_bad_inputs_leave_no_run_folder(tmp_path) -> None:
    """A run that fails on its inputs, before anything is trained, does not leave an empty folder behind."""
    from ctsplat.training import train
    from ctsplat.utils import CtsplatError

    out = tmp_path / "run"
    with pytest.raises(CtsplatError, match="does not exist"):
        train({"volume": str(tmp_path / "nope.nii.gz"), "radiographs": str(tmp_path / "rad"), "device": "cpu",
               "progress": False}, out)
    assert not out.exists()


def test_lock_removes_a_folder_it_created_when_the_step_fails_before_writing(tmp_path: Path) -> None:
    new = tmp_path / "a" / "run"
    with pytest.raises(ValueError), run_lock(new):
        raise ValueError("bad input")
    assert not new.exists()  # created here, nothing written: gone
    kept = tmp_path / "kept"
    with pytest.raises(ValueError), run_lock(kept):
        (kept / "log.csv").write_text("x")
        raise ValueError("failed after writing")
    assert (kept / "log.csv").exists()  # something written: kept for the user to look at
    existing = tmp_path / "existing"
    existing.mkdir()
    with pytest.raises(ValueError), run_lock(existing):
        raise ValueError("bad input")
    assert existing.is_dir()  # not created by the lock: never removed
    with run_lock(new):
        pass
    assert (new / LOCK_NAME).exists()  # a step that succeeds keeps its folder
    if os.geteuid() != 0:  # permissions do not stop root
        new.chmod(0o500)
        try:
            with pytest.raises(CtsplatError, match="not writable"), run_lock(new):
                pass
        finally:
            new.chmod(0o700)


def test_all_finite_finds_every_kind_of_non_finite_element() -> None:
    """NaN, +Inf, -Inf and an Inf beside a -Inf (whose sum is NaN) in any tensor of the list; finite tensors whose
    sum would overflow are finite."""
    from ctsplat.training.state import all_finite

    gen = torch.Generator().manual_seed(0)
    base = [torch.randn(50, 3, generator=gen), None, torch.randn(7, generator=gen), torch.tensor(2.5)]
    assert all_finite(base)
    assert all_finite([]) and all_finite([None])
    for bad in (float("nan"), float("inf"), float("-inf")):
        for k in (0, 2, 3):
            tensors = [t.clone() if t is not None else None for t in base]
            tensors[k].view(-1)[-1] = bad
            assert not all_finite(tensors), (bad, k)
    both = torch.zeros(4)
    both[0], both[3] = float("inf"), float("-inf")
    assert not all_finite([both])
    huge = torch.full((4,), 1.7e308, dtype=torch.float64)
    assert not bool(torch.isfinite(huge.sum())) and all_finite([huge])
    assert all_finite([torch.full((10_000,), 3.4e38)])  # float32 maxima: the float64 sum stays finite


def test_train_refuses_a_folder_holding_files_that_are_not_a_runs(scene_dir: Path,  # noqa: F811
                                                                   tmp_path: Path) -> None:
    # a new run replaces the checkpoints and outputs in its folder: someone else's checkpoints/ or metrics.json
    # beside their own files are refused before the lock file or anything else is written
    out = tmp_path / "mlproj"
    (out / "checkpoints").mkdir(parents=True)
    (out / "checkpoints" / "epoch_10.pt").write_bytes(b"mine")
    (out / "metrics.json").write_text('{"mine": 1}')
    cfg = _cfg(scene_dir, iterations=2)
    with pytest.raises(CtsplatError, match=r"mlproj holds checkpoints/epoch_10\.pt, which this step does not "
                       r"write, and its outputs would be mixed with it"):
        loop.train(cfg, out)
    (out / "checkpoints" / "epoch_10.pt").unlink()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(CtsplatError, match=r"mlproj holds notes\.txt, which this step does not write"):
        loop.train(cfg, out)
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*")) == ["checkpoints", "metrics.json",
                                                                            "notes.txt"]
    from ctsplat.cli import main  # the command refuses it before its lock file goes in

    assert main(["train", "--out", str(out), "--volume", cfg["volume"], "--radiographs", cfg["radiographs"]]) == 2
    assert not (out / ".ctsplat.lock").exists()
    with pytest.raises(CtsplatError, match=r"is, or holds, the input"):
        loop.train(cfg, Path(cfg["radiographs"]).parent)


def test_an_evaluated_run_with_its_figures_trains_again(scene_dir: Path, tmp_path: Path) -> None:  # noqa: F811
    # everything the workflow writes into a run folder (evaluation, read-out sidecars, figures, logs) belongs to the
    # run: training it again, as a changed config or --restart does, must not be refused
    from ctsplat.analysis import RUN_FIGURES
    from ctsplat.analysis.plots import run_figures
    from ctsplat.evaluation import evaluate

    out = tmp_path / "run"
    cfg = _cfg(scene_dir, iterations=20, figures=True, turntable_frames=2)
    loop.train(cfg, out)
    evaluate(out)
    run_figures(out, {name: out / "figures" / f"{name}.png" for name in RUN_FIGURES})
    (out / "logs").mkdir()
    (out / "logs" / "train.log").write_text("log")
    for leftover in ("checkpoints/.ckpt_00000005.q1w2e3r4.tmp.pt", ".model_volume.k2j3h4.tmp.nii.gz"):
        (out / leftover).write_bytes(b"")  # what a killed (SIGKILL) write leaves
    assert (out / "model_volume.json").is_file() and (out / "figures" / "acf.png").is_file()
    made = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()}
    loop.train({**cfg, "iterations": 10}, out)
    assert json.loads((out / "training.json").read_text())["iterations"] == 10
    # what the earlier evaluation and figures made of the earlier model is gone, not left beside the new one
    for name in ("model_volume.json", "gallery.png", "slices.png", "figures/acf.png", "metrics.json"):
        assert name in made and not (out / name).exists(), name
    assert (out / "logs" / "train.log").read_text() == "log"


def test_changed_evaluation_settings_do_not_stop_a_run_resuming(scene_dir: Path, tmp_path: Path,  # noqa: F811
                                                                 caplog) -> None:
    """figures, progress, sharpening and the other evaluation keys do not change the trained model: a run resumes
    under other values of them (``ctsplat train --resume --quiet``)."""
    out = tmp_path / "run"
    cfg = _cfg(scene_dir, iterations=20, checkpoint_every=10, figures=False, progress=False)

    def stop_at_15(it: int, st) -> None:  # noqa: ANN001
        if it == 15:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        loop.train(cfg, out, callback=stop_at_15)
    with caplog.at_level(logging.INFO):
        loop.train({**cfg, "figures": True, "progress": True, "turntable_frames": 3}, out, resume=True)
    assert "resuming from" in caplog.text
    assert json.loads((out / "training.json").read_text())["iterations"] == 20


def test_ssim_on_radiographs_smaller_than_its_window_is_refused_before_training(tmp_path: Path) -> None:
    from train_helpers import tiny_phantom, tiny_train_cfg

    from ctsplat.formats.volume import Volume, save_volume
    from ctsplat.projector import render_radiographs

    data, aff = tiny_phantom()
    save_volume(Volume(data, aff, {"volume_id": "small", "intensity": {"mu_scale_per_mm": 0.02}}),
                tmp_path / "volume.nii.gz")
    render_radiographs(tmp_path / "volume.nii.gz", tmp_path / "rad",
                       {"detector_width": 8, "detector_height": 8, "n_views": 6, "device": "cpu"})
    cfg = tiny_train_cfg(tmp_path, iterations=2, lambda_ssim=0.2)
    with pytest.raises(CtsplatError, match=r"lambda_ssim needs radiographs of at least 11 x 11 pixels .* got 8 x 8"):
        loop.train(cfg, tmp_path / "run")
    assert not (tmp_path / "run" / "model.pt").exists()
    # without the SSIM loss the scores still need a 3 px window: refused before anything is written
    render_radiographs(tmp_path / "volume.nii.gz", tmp_path / "rad2",
                       {"detector_width": 2, "detector_height": 8, "n_views": 6, "device": "cpu"})
    with pytest.raises(CtsplatError, match=r"^the radiographs are 2 x 8: the SSIM scores need at least 3 on a side; "
                                           r"render larger ones$"):
        loop.train({**cfg, "lambda_ssim": 0.0, "radiographs": str(tmp_path / "rad2")}, tmp_path / "run2")
    assert not (tmp_path / "run2").exists()
    # the key types: a path that is not text, a device that is not one
    for key, value, needle in (("volume", 5, "train.volume must be a path"), ("device", "cudax", "train.device"),
                               ("seed", 2**64, "train.seed")):
        with pytest.raises(CtsplatError, match=needle):
            config.resolve_config({**cfg, key: value})
