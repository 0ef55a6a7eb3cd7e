"""The benchmark scripts' options take effect or are refused with one line (real processes)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from ctsplat.cli import main

ROOT = Path(__file__).resolve().parents[2]


def bench(script: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), *map(str, args)], capture_output=True,
                          text=True, env=env, cwd=cwd, timeout=600)


def last_line(res: subprocess.CompletedProcess) -> str:
    assert "Traceback" not in res.stderr, res.stderr
    return res.stderr.strip().splitlines()[-1]


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--set", "init=volume"], "--set init is set by this benchmark per run; use --inits"),
        (["--set", "iterations=5"], "use --iterations"),
        (["--set", "compositor=radiative_rectified"], "train.compositor: 'radiative_rectified' is not one of"),
        (["--set", "lr.means=fast"], "train.lr.means: 'fast' is not of type 'number'"),
        (["--n-init", "0"], "train.n_init: 0 is less than the minimum of 1"),
    ],
)
def test_quality_refuses_overrides_it_would_ignore(tmp_path, args, needle):
    res = bench("quality.py", "--data", tmp_path / "no_data", "--out", tmp_path / "q", *args, cwd=tmp_path)
    assert res.returncode == 2
    assert needle in last_line(res)
    assert not (tmp_path / "q").exists()


@pytest.fixture(scope="module")
def phantom_dicom(tmp_path_factory):
    out = tmp_path_factory.mktemp("data") / "ph"
    assert main(["phantom", str(out), "--size", "16", "--no-beads"]) == 0
    return out


@pytest.mark.slow
def test_quality_compositor_override_takes_effect(tmp_path, phantom_dicom):
    out = tmp_path / "q"
    res = bench("quality.py", "--data", phantom_dicom, "--out", out, "--views", "6", "--inits", "fbp",
                "--iterations", "2", "--n-init", "100", "--detector", "16", "--threads", "1",
                "--set", "compositor=radiative_unrectified", "--set", "figures=false", "--set", "eval_every=2",
                cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    run_cfg = json.loads((out / "run_fbp_n006" / "config.json").read_text())["config"]
    assert run_cfg["compositor"] == "radiative_unrectified"
    table = pd.read_csv(out / "quality.csv")
    assert table.loc[table["method"] == "gs:fbp", "compositor"].tolist() == ["radiative_unrectified"]
    # the best baseline is picked against the reference: labelled as the oracle's pick it is
    assert table.loc[table["method"] == "gs:fbp", "best_baseline"].iloc[0].endswith(" (oracle)")


def test_baselines_arc_takes_effect_and_bad_options_are_refused(tmp_path, phantom_dicom):
    res = bench("baselines.py", "--source", phantom_dicom, "--grid", "16", "--views", "4", "--sart-iterations", "1",
                "--arc", "360", "--work", tmp_path / "work", "--out", tmp_path / "b.csv", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    table = pd.read_csv(tmp_path / "b.csv")
    assert (table["arc_deg"] == 360).all()
    rad = next((tmp_path / "work").glob("*/circular_parallel_4_arc360"))
    assert json.loads((rad / "views.json").read_text())["meta"]["arc_deg"] == 360
    for args, needle in ((["--arc", "400"], "--arc must be in (0, 360]"),
                         (["--source", tmp_path / "missing"], "does not exist"),
                         (["--views", "0"], "--views and --sart-iterations >= 1")):
        res = bench("baselines.py", "--work", tmp_path / "w2", *args, cwd=tmp_path)
        assert res.returncode == 2 and needle in last_line(res)
    assert not (tmp_path / "w2").exists()


@pytest.mark.parametrize(
    ("script", "args", "needle"),
    [
        ("sfm.py", ["--set", "geometry=carm"], "--set geometry: the sweep renders its own C-arm view set"),
        ("sfm.py", ["--set", "n_views=abc"], "radiographs.n_views: 'abc' is not of type 'integer'"),
        ("sfm.py", ["--set", "max_ratio=2"], "sfm.max_ratio: 2 is greater than the maximum of 1"),
        ("sfm.py", ["--set", "nviews=90"], "--set nviews: unknown key"),
        ("sfm.py", ["--only", "nothing"], "--only 'nothing' matches no configuration"),
        ("render.py", ["--only-voxelize"], "--only-voxelize needs --voxelize"),
        ("render.py", ["--voxelize", "500000:256", "--only-voxelize", "--reference"], "--only-voxelize skips"),
        ("render.py", ["--voxelize", "lots"], "expected N:S"),
        ("render.py", ["--compositor", "rectified"], "invalid choice: 'rectified'"),
        ("projector.py", ["--size", "4"], "--size must be >= 8"),
        ("projector.py", ["--device", "tpu"], "unknown device 'tpu'"),
        ("ingest.py", ["--repeats", "0"], "--repeats must be >= 1"),
        ("gpu.py", ["--train-sizes", "4"], "--train-sizes must be >= 8"),
        ("host_reads.py", ["--set", "nviews=3"], "unknown config key train.nviews"),
        ("photo_step.py", ["sfm", "model.pt", "--iterations", "0"], "--iterations and --threads must be at least 1"),
        ("photo_step.py", ["sfm", "model.pt"], "sfm is not a photo SfM folder"),
        ("threads.py", ["--threads", "1,x"], "--threads '1,x': expected comma-separated integers"),
        ("threads.py", ["--reps", "0"], "--threads, --reps, --n, --size and --grid must be at least 1"),
        ("sfm.py", ["--threads", "0"], "--threads must be >= 1"),
        ("gpu.py", ["--reps", "0"], "--reps must be >= 1"),
        ("photo_blame.py", ["run", "--threads", "0"], "--threads must be >= 1, got 0"),
        ("baselines.py", ["--source", "phantom", "--set", "nosuchkey=1", "--work", "w"],
         "unknown config key baselines.nosuchkey"),
    ],
)
def test_benchmark_options_are_checked(tmp_path, script, args, needle):
    extra = ["--csv", tmp_path / "sfm.csv"] if script == "sfm.py" else []
    res = bench(script, *args, *extra, cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    assert needle in last_line(res)
    assert list(tmp_path.iterdir()) == []


BENCHMARKS = sorted(p.name for p in (ROOT / "benchmarks").glob("*.py") if not p.name.startswith("_"))


@pytest.mark.parametrize("script", BENCHMARKS)
def test_every_benchmark_exits_through_the_shared_clean_exit(script):
    """A benchmark killed by SIGTERM (a cluster's time limit) or Ctrl-C must remove its temporary files and say so
    in one line; each script's entry point goes through ``_common.cli_main``, which does that (the test below)."""
    import ast

    tree = ast.parse((ROOT / "benchmarks" / script).read_text())
    calls = {n.func.id for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)}
    assert "cli_main" in calls, f"{script} does not call _common.cli_main"


def test_a_terminated_benchmark_leaves_no_table_and_says_so(tmp_path, phantom_dicom):
    """SIGTERM while the baselines run: exit 143, one line, no table, no temporary file in the cache."""
    import signal
    import time

    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([sys.executable, str(ROOT / "benchmarks" / "baselines.py"), "--source", str(phantom_dicom),
                             "--grid", "16", "--views", "40", "--sart-iterations", "200", "--work",
                             str(tmp_path / "work"), "--out", str(tmp_path / "b.csv")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path)
    assert proc.stdout is not None
    line = ""
    while not line.startswith("volume "):  # ingested: the baselines run next
        line = proc.stdout.readline()
        assert line or proc.poll() is None, proc.communicate()
    time.sleep(1.0)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith("baselines.py: terminated;"), err
    assert not (tmp_path / "b.csv").exists()
    assert [p for p in (tmp_path / "work").rglob("*") if ".tmp" in p.name] == []


@pytest.mark.parametrize(("beam", "n"), [("parallel", 50), ("cone", 8)])
def test_pose_benchmark_renders_the_split_it_describes(tmp_path, monkeypatch, phantom_dicom, beam, n):
    """``n`` training, 10 validation and 100 test views (a circular orbit's ``n_views`` counts training views)."""
    import importlib.util
    from collections import Counter

    from ctsplat.volume import ingest

    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    spec = importlib.util.spec_from_file_location("poses_benchmark", ROOT / "benchmarks" / "poses.py")
    poses = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(poses)
    ingest(phantom_dicom, tmp_path / "v.nii.gz", {"grid": 16})
    rad = poses.training_views(tmp_path / "v.nii.gz", tmp_path, beam, n, 16)
    views = json.loads((rad / "views.json").read_text())["views"]
    assert Counter(v["split"] for v in views) == {"train": n, "val": 10, "test": 100}


@pytest.mark.parametrize(
    ("script", "args"),
    [
        ("protocol.py", ["--volumes", "phantom", "--out", "{f}"]),
        ("features.py", ["--data", "{d}", "--out", "{f}"]),
        ("quality.py", ["--data", "{d}", "--out", "{f}"]),
        ("poses.py", ["--data", "phantom", "--out", "{f}"]),
        ("host_reads.py", ["--out", "{f}"]),
        ("baselines.py", ["--source", "phantom", "--work", "{f}"]),
    ],
)
def test_an_output_folder_that_is_a_file_is_named_in_one_line(tmp_path, script, args):
    (tmp_path / "afile").write_text("not a folder\n")
    (tmp_path / "data").mkdir()
    args = [a.format(f=tmp_path / "afile" / "out", d=tmp_path / "data") for a in args]
    res = bench(script, *args, cwd=tmp_path)
    assert res.returncode == 2, res.stderr[-2000:]
    assert f"{tmp_path / 'afile'} is a file, not a folder; give a folder" in last_line(res)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "data"]


def test_tables_a_benchmark_adds_to_are_checked_before_the_work(tmp_path):
    """sfm.py's and photo_step.py's --csv: a folder or another benchmark's table is refused before the sweep or the
    timing, not after it."""
    (tmp_path / "other.csv").write_text("a,b\n1,2\n")
    (tmp_path / "folder").mkdir()
    for csv, needle in ((tmp_path / "folder", "is a folder; give a CSV file"),
                        (tmp_path / "other.csv", "is not a table of this sweep")):
        res = bench("sfm.py", "--only", "beads_in_air", "--quick", "--csv", csv, cwd=tmp_path)
        assert res.returncode == 2 and needle in last_line(res), res.stderr[-2000:]
    res = bench("photo_step.py", "sfm", "model.pt", "--csv", tmp_path / "other.csv", cwd=tmp_path)
    assert res.returncode == 2 and "holds columns a,b, not this benchmark's" in last_line(res)
    assert (tmp_path / "other.csv").read_text() == "a,b\n1,2\n"


def test_a_terminated_benchmark_passes_the_signal_to_its_child(tmp_path):
    """``_common.run_child``: SIGTERM of the benchmark reaches its child as SIGTERM (whose handler removes its
    temporary files), not as the SIGKILL ``subprocess.run`` sends after a quarter second."""
    import signal
    import textwrap
    import time

    child = tmp_path / "child.py"
    child.write_text(textwrap.dedent(f"""
        import pathlib, signal, sys, time
        def bye(*_):
            time.sleep(0.5)  # longer than subprocess.run's grace
            pathlib.Path({str(tmp_path / "cleaned")!r}).touch()
            sys.exit(143)
        signal.signal(signal.SIGTERM, bye)
        pathlib.Path({str(tmp_path / "started")!r}).touch()
        time.sleep(60)
    """))
    parent = (f"import sys; sys.path.insert(0, {str(ROOT / 'benchmarks')!r})\n"
              "from _common import cli_main, run_child\n"
              f"sys.exit(cli_main(lambda a: run_child([sys.executable, {str(child)!r}]).returncode, None, 'p.py'))\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([sys.executable, "-c", parent], stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + 60
    while not (tmp_path / "started").exists():
        assert proc.poll() is None and time.monotonic() < deadline
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143 and err.strip().splitlines()[-1].startswith("p.py: terminated;"), err
    assert (tmp_path / "cleaned").exists()
