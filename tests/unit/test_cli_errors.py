"""Bad input, blocked paths and interrupts through the real ``ctsplat`` entry point: one line on stderr, exit status
2 (130 for Ctrl-C), and no half-written output."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ctsplat.cli import main
from ctsplat.evaluation.run import _RUN_CONFIG_KEYS
from ctsplat.formats.volume import Volume, load_volume, save_volume
from ctsplat.utils import LOCK_NAME

ROOT = Path(__file__).resolve().parents[2]
CTSPLAT = [sys.executable, "-c", "import sys; from ctsplat.cli import main; sys.exit(main())"]  # the console script


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}


def ctsplat(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """``ctsplat ARGS`` in a fresh Python process."""
    return subprocess.run([*CTSPLAT, *map(str, args)], capture_output=True, text=True, env=_env(), cwd=cwd,
                          timeout=300)


def assert_one_line_error(stderr: str, command: str, *needles: str) -> None:
    """The last stderr line is the error (INFO logs may precede it); no traceback."""
    assert "Traceback" not in stderr, stderr
    last = stderr.strip().splitlines()[-1]
    assert last.startswith(f"ctsplat {command}: error: "), stderr
    for needle in needles:
        assert needle in last, last


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A 16³ sphere volume and 8 + 2 + 2 parallel-beam radiographs of it."""
    root = tmp_path_factory.mktemp("scene")
    n = 16
    g = (np.arange(n) - (n - 1) / 2) / (n / 2)
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    data = (0.5 * (X**2 + Y**2 + Z**2 < 0.6)).astype(np.float32)
    vol = root / "volume.nii.gz"
    meta = {"volume_id": "cli", "intensity": {"mu_scale_per_mm": 0.02}}
    save_volume(Volume(data, np.diag([2.0, 2.0, 2.0, 1.0]), meta), vol)
    rad = root / "rad"
    assert main(["project", "--volume", str(vol), "--out", str(rad), "--set", "n_views=8", "--set", "detector_width=16",
                 "--set", "detector_height=16", "--set", "device=cpu"]) == 0
    return vol, rad


TINY_TRAIN = ["--set", "n_init=100", "--set", "eval_every=2", "--set", "checkpoint_every=2", "--set", "eval_views=2",
              "--set", "turntable_frames=2", "--set", "fps_width=32", "--set", "fps_height=32", "--device", "cpu",
              "--quiet"]


# ------------------------------------------------------------------------------------------------ file-system errors
def test_blocked_output_path_is_one_line_and_leaves_no_json(scene, tmp_path):
    vol, _ = scene
    blocked = tmp_path / "blocked"
    (blocked / "vol.nii.gz").mkdir(parents=True)  # a folder where the volume file is to go
    res = ctsplat("ingest", vol, blocked / "vol.nii.gz", "--grid", "8")
    assert res.returncode == 2
    assert_one_line_error(res.stderr, "ingest", "vol.nii.gz is a folder, but a file is to be written there")
    assert sorted(p.name for p in blocked.iterdir()) == ["vol.nii.gz"]  # no vol.json beside it, no temp files


def test_file_where_a_folder_is_needed(scene, tmp_path, capsys):
    vol, _ = scene
    afile = tmp_path / "afile"
    afile.write_text("x")
    assert main(["ingest", str(vol), str(afile / "vol.nii.gz"), "--grid", "8"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("ctsplat ingest: error: ") and str(afile) in err
    assert main(["project", "--volume", str(vol), "--out", str(afile / "rad")]) == 2
    assert str(afile) in capsys.readouterr().err
    assert afile.read_text() == "x" and sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_output_folder(scene, tmp_path, capsys):
    vol, _ = scene
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        assert main(["ingest", str(vol), str(ro / "vol.nii.gz"), "--grid", "8"]) == 2
        assert "Permission denied" in capsys.readouterr().err
        assert list(ro.iterdir()) == []
    finally:
        ro.chmod(0o755)


# ------------------------------------------------------------------------------------------------ wrong-typed --set
@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["project", "--set", "n_views=abc"], "radiographs.n_views: 'abc' is not of type 'integer'"),
        (["train", "--set", "eval_every=abc"], "train.eval_every: 'abc' is not of type 'integer'"),
        (["train", "--set", "lr.means=fast"], "train.lr.means: 'fast' is not of type 'number'"),
        (["train", "--set", "nan_lr_decay=2"], "train.nan_lr_decay: 2 is greater than or equal to the maximum of 1"),
        (["baseline", "--set", "sart_relaxation=-1"], "baselines.sart_relaxation: -1 is less than or equal"),
        (["project", "--set", "split={train: 0.9, val: 0.25, test: 0.25}"], "fractions must sum to 1, got 1.4"),
        (["project", "--set", "wobble_deg=NaN"], "radiographs.wobble_deg: not a finite number"),
        (["train", "--set", "lr.means=Infinity"], "train.lr.means: not a finite number"),
        (["baseline", "--set", "asd_pocs_alpha=[0.1, .nan]"], "baselines.asd_pocs_alpha[1]: not a finite number"),
    ],
)
def test_wrong_set_values_are_refused_before_running(scene, tmp_path, capsys, args, needle):
    vol, rad = scene
    out = tmp_path / "out"
    paths = {"project": ["--volume", vol, "--out", out],
             "train": ["--volume", vol, "--radiographs", rad, "--out", out, "--iterations", "2", "--quiet"],
             "baseline": ["--volume", vol, "--radiographs", rad, "--out", out]}[args[0]]
    assert main([args[0], *map(str, paths), *args[1:]]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"ctsplat {args[0]}: error: invalid config at ") and needle in err and "\n" not in err
    assert not out.exists()


@pytest.mark.parametrize("value", ["010", "08", "1:30"])
def test_a_set_number_yaml_would_read_in_another_base_is_refused(scene, tmp_path, capsys, value):
    """YAML 1.1 reads 010 as 8 and 1:30 as 90: ``--set n_views=010`` rendered 8 views."""
    vol, _ = scene
    out = tmp_path / "out"
    assert main(["project", "--volume", str(vol), "--out", str(out), "--set", f"n_views={value}"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"ctsplat project: error: --set n_views: {value!r} would be read in base 8 or 60, or as text "
                   "(YAML 1.1); write the number in decimal without leading zeros")
    assert not out.exists()


# ------------------------------------------------------------------------------------------------ unreadable TIFFs
def test_truncated_radiographs_tiff(scene, tmp_path, capsys):
    vol, rad = scene
    bad = tmp_path / "rad"
    bad.mkdir()
    for name in ("views.json", "radiographs.json"):
        (bad / name).write_bytes((rad / name).read_bytes())
    data = (rad / "line_integrals.tif").read_bytes()
    (bad / "line_integrals.tif").write_bytes(data[: len(data) // 2])
    assert main(["train", "--volume", str(vol), "--radiographs", str(bad), "--out", str(tmp_path / "run"),
                 "--iterations", "2", *TINY_TRAIN]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "line_integrals.tif is not a readable TIFF file" in err and "re-render" in err
    assert main(["baseline", "--volume", str(vol), "--radiographs", str(bad), "--out", str(tmp_path / "b")]) == 2
    assert "is not a readable TIFF file" in capsys.readouterr().err
    assert not (tmp_path / "b").exists()


def test_random_bytes_named_tif(tmp_path, capsys):
    tif = tmp_path / "scan.tif"
    tif.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    assert main(["ingest", str(tif), str(tmp_path / "v.nii.gz"), "--tiff-voxel-size", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "is not a readable TIFF file" in err
    assert not (tmp_path / "v.nii.gz").exists()


# ------------------------------------------------------------------------------------------------ Ctrl-C
def test_ctrl_c_exits_130_with_one_line(scene, tmp_path):
    vol, rad = scene
    run = tmp_path / "run"
    cmd = [*CTSPLAT, "train", "--volume", str(vol), "--radiographs", str(rad), "--out",
           str(run), "--iterations", "1000000", "--no-evaluate", *TINY_TRAIN]
    # a background job (nohup, `cmd &`) inherits SIGINT ignored, and Python then never raises KeyboardInterrupt: give
    # the child the default disposition a terminal's foreground job has
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env(),
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            if (run / "checkpoints").is_dir() and any((run / "checkpoints").iterdir()):
                break
            time.sleep(0.2)
        assert proc.poll() is None, proc.communicate()[1]
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1].startswith("ctsplat train: interrupted;")
    assert not [p for p in run.rglob("*") if ".tmp" in p.name]  # no temp files of interrupted writes


# ------------------------------------------------------------------------------------------------ checks of values
def test_more_views_than_available(scene, tmp_path, capsys):
    vol, rad = scene
    assert main(["train", "--volume", str(vol), "--radiographs", str(rad), "--out", str(tmp_path / "run"),
                 "--views", "50", "--iterations", "2", *TINY_TRAIN]) == 2
    assert "asks for 50 training views" in capsys.readouterr().err


def test_cone_source_inside_the_object(scene, tmp_path, capsys):
    vol, _ = scene
    out = tmp_path / "cone"
    assert main(["project", "--volume", str(vol), "--out", str(out), "--set", "camera=cone", "--set", "dso_mm=5",
                 "--set", "dsd_mm=10", "--set", "n_views=4"]) == 2
    assert "dso_mm (5.0) must exceed the object's radius" in capsys.readouterr().err
    assert not out.exists()
    assert main(["project", "--volume", str(vol), "--out", str(out), "--set", "camera=cone", "--set", "orbit=sphere",
                 "--set", "dso_mm=5", "--set", "dsd_mm=10", "--set", "n_views=12"]) == 2
    assert "must exceed the object's radius" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------------ ignored options
@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["ingest", "{vol}", "{tmp}/v.nii.gz", "--native", "--grid", "8"], "--native keeps the scan's spacing"),
        (["ingest", "{vol}", "{tmp}/v.nii.gz", "--voxel-size", "2", "--grid", "8"], "not both"),
        (["ingest", "{vol}", "{tmp}/v.nii.gz", "--window", "40,80"], "--window only applies to intensity window"),
        (["ingest", "{vol}", "{tmp}/v.nii.gz", "--series-uid", "3"], "--series-uid applies to DICOM input only"),
        (["ingest", "{vol}", "{tmp}/v.nii.gz", "--tiff-voxel-size", "1"], "--tiff-voxel-size applies to TIFF"),
        (["ingest", "{vol}", "{tmp}/v.nii.gz", "--voxel-size", "-1"], "preprocessing.voxel_size_mm: -1.0 is less"),
        (["phantom", "{tmp}/ph", "--no-beads", "--n-beads", "3"], "--n-beads has no effect with --no-beads"),
        (["phantom", "{tmp}/ph", "--n-beads", "-1"], "phantom.n_beads: -1 is less than the minimum of 0"),
        # 28 PiB: more than any address space, so the allocation fails at once on every machine
        (["phantom", "{tmp}/ph", "--size", "100000"], "out of memory (Unable to allocate"),
        (["sfm", "{rad}", "{tmp}/sfm", "--volume", "{vol}"], "--volume is only read with naive_slices"),
        (["sfm", "{rad}", "{tmp}/sfm", "--set", "geometry=carm"], "drop geometry"),
        (["render", "{tmp}/m.pt", "{rad}/views.json", "{tmp}/r", "--mu-scale", "0"], "--mu-scale must be a finite"),
        (["train", "--volume", "{vol}", "--radiographs", "{rad}", "--out", "{tmp}/t", "--init", "sfm"],
         "needs the sfm step's folder (ctsplat train: --sfm-dir)"),
        (["ingest", "{vol}", "{tmp}/v.nii.gz", "--voxel-size", "nan"], "voxel_size_mm: not a finite number"),
        (["ingest", "{vol}", "{vol}", "--grid", "8"], "is, or lies inside, the source"),
        (["ingest", "{vol}", "--list-series"], "is a file, not a DICOM folder"),
        (["gather", "{rad}", "--out", "{tmp}/s.csv", "--milestone", "psnr2d=nan"], "psnr2d: not a finite number"),
        (["gather", "{rad}", "--out", "{tmp}/s.csv", "--milestone", "psnr9d=3"],
         "key analysis.milestones.psnr9d (did you mean psnr3d?)"),
        (["gather", "{rad}", "--out", "{tmp}/s.csv", "--max-gap-iters", "-1"], "analysis.max_gap_iters: -1"),
        (["analyse", "{tmp}/s.csv", "--kde-windows", "0"], "analysis.kde_windows: 0 is less than the minimum"),
        (["analyse", "{summary}", "--out-dir", "{tmp}/f", "--baselines", "{tmp}/b.csv"], "b.csv does not exist"),
    ],
)
def test_options_that_would_be_ignored_or_are_out_of_range_are_refused(scene, tmp_path, capsys, args, needle):
    vol, rad = scene
    summary = tmp_path.parent / f"{tmp_path.name}_summary.csv"  # outside tmp_path, which must stay empty
    summary.write_text("volume,init\nphantom,fbp\n")
    argv = [a.format(vol=vol, rad=rad, tmp=tmp_path, summary=summary) for a in args]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"ctsplat {args[0]}: error: ") and needle in err and "\n" not in err
    assert list(tmp_path.iterdir()) == []
    assert load_volume(vol).volume_id == "cli"  # an output path that is the input leaves it as it was


@pytest.mark.parametrize("value", ["1,2", "nan", "1,2,inf", "0"])
def test_tiff_voxel_size_must_be_one_or_three_finite_positive_numbers(tmp_path, capsys, value):
    with pytest.raises(SystemExit) as stop:
        main(["ingest", str(tmp_path / "stack.tif"), str(tmp_path / "v.nii.gz"), "--tiff-voxel-size", value])
    assert stop.value.code == 2
    assert f"voxel size must be S or X,Y,Z in mm, each a finite number > 0 (e.g. 0.5,0.5,1.25), got {value}" in (
        capsys.readouterr().err)


@pytest.mark.parametrize(("args", "needle"), [
    (["--grid", "abc"], "argument --grid: must be N or I,J,K (whole numbers, e.g. 128 or 128,128,96), got 'abc'"),
    (["--grid", "64,64"], "argument --grid: must be N or I,J,K (e.g. 128 or 128,128,96), got '64,64'"),
    (["--rescale", "1,x"], "argument --rescale: must be SLOPE,INTERCEPT (e.g. 1,-1024), got '1,x'"),
    (["--window", "40,wide"], "argument --window: must be a preset name or LEVEL,WIDTH in HU (e.g. 40,80)"),
    (["--window", "1,2,3"], "argument --window: must be a preset name or LEVEL,WIDTH in HU (e.g. 40,80), got '1,2,3'"),
    (["--tiff-voxel-size", "0.5mm"], "argument --tiff-voxel-size: must be S or X,Y,Z in mm (e.g. 0.5,0.5,1.25)"),
    (["--bogus"], "unknown option --bogus"),
    (["--gird", "64"], "unknown option --gird (did you mean --grid?)"),
])
def test_a_malformed_option_is_one_line_naming_the_option_and_the_help(tmp_path, capsys, args, needle):
    """argparse's own errors too: one line, the option and the form it takes, not the usage block or the name of
    the function that parsed it."""
    try:
        code = main(["ingest", str(tmp_path / "src"), str(tmp_path / "v.nii.gz"), *args])
    except SystemExit as stop:
        code = stop.code
    assert code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("ctsplat ingest: error: ") and needle in err, err
    assert err.rstrip().endswith("see `ctsplat ingest --help`") and "invalid _" not in err
    assert list(tmp_path.iterdir()) == []


def test_an_argument_after_an_option_is_explained(tmp_path, capsys):
    """argparse fills an optional positional (ingest's OUT) before the options and then finds OUT unrecognized;
    a command without one just has too many arguments."""
    assert main(["ingest", str(tmp_path / "src"), "--grid", "16", str(tmp_path / "v.nii.gz")]) == 2
    err = capsys.readouterr().err
    assert err == (f"ctsplat ingest: error: unrecognized arguments: {tmp_path / 'v.nii.gz'} (give the positional "
                   "arguments before the options); see `ctsplat ingest --help`\n")
    assert main(["render", "m.pt", "v.json", "out", "extra"]) == 2
    assert capsys.readouterr().err == ("ctsplat render: error: unrecognized arguments: extra; see `ctsplat render "
                                       "--help`\n")
    assert not list(tmp_path.iterdir())


# ------------------------------------------------------------------------------------------------ run outputs
def test_csvs_use_lf_and_figures_off_removes_stale_figures(scene, tmp_path, capsys):
    vol, rad = scene
    run = tmp_path / "run"
    assert main(["train", "--volume", str(vol), "--radiographs", str(rad), "--out", str(run), "--iterations", "4",
                 *TINY_TRAIN]) == 0
    figures = ("gallery.png", "slices.png", "turntable.gif")
    assert all((run / f).exists() for f in figures)
    assert main(["baseline", "--volume", str(vol), "--radiographs", str(rad), "--out", str(tmp_path / "base"),
                 "--set", "sart_max_iterations=1", "--set", "save_volumes=false"]) == 0
    csvs = sorted(tmp_path.rglob("*.csv"))
    assert {"train_log.csv", "per_view.csv", "per_view_test.csv", "baselines.csv"} <= {p.name for p in csvs}
    for path in csvs:
        text = path.read_bytes()
        assert b"\r" not in text and text.endswith(b"\n"), path.name  # one line ending: LF
    # the same run evaluated again with figures: false keeps no figures of the earlier evaluation
    assert main(["evaluate", str(run), "--device", "cpu", "--set", "figures=false"]) == 0
    assert json.loads((run / "metrics.json").read_text())["evaluation_settings"]["figures"] is False
    assert not any((run / f).exists() for f in figures)
    # evaluated again without settings: as recorded (no figures), other settings as the run's
    assert main(["evaluate", str(run), "--device", "cpu", "--set", "fps_width=40"]) == 0
    recorded = json.loads((run / "metrics.json").read_text())
    assert recorded["evaluation_settings"]["figures"] is False and recorded["fps_resolution"][0] == 40
    assert not any((run / f).exists() for f in figures)
    assert main(["evaluate", str(run), "--device", "cpu", "--set", "lr=1"]) == 2
    assert "'lr' is not an evaluation key" in capsys.readouterr().err.strip().splitlines()[-1]


def test_a_run_config_json_is_read_back_with_its_exponent_floats(tmp_path):
    """json.dumps writes 5e-05, which YAML 1.1 reads as text: a .json config is parsed as JSON."""
    from ctsplat.cli._common import load_section
    from ctsplat.utils import CtsplatError

    path = tmp_path / "config.json"
    path.write_text(json.dumps({"train": {"lambda_density": 5e-05, "lr": {"means": 1e-3}}}))
    assert "5e-05" in path.read_text()
    cfg = load_section(str(path), "train")
    assert cfg["lambda_density"] == 5e-05 and cfg["lr"]["means"] == 1e-3
    path.write_text("{not json")
    with pytest.raises(CtsplatError, match=r"config\.json is not valid YAML/JSON"):
        load_section(str(path), "train")


def test_step_configs_are_read_from_a_workflow_config():
    """`--config config/ct0051_head.yaml` (a workflow config) gives project, baseline and sfm their sections:
    sfm.settings, baselines.settings (+ n_views) and, with one geometry, that geometry; two geometries are refused
    naming them."""
    from ctsplat.cli._common import load_section
    from ctsplat.config import check_section
    from ctsplat.utils import CtsplatError

    head = str(ROOT / "config" / "ct0051_head.yaml")
    sfm = check_section("sfm", load_section(head, "sfm"))
    assert sfm["pose_prior"] == "isocentric" and sfm["geometry"] == "carm"
    assert check_section("baselines", load_section(str(ROOT / "config" / "full_protocol.yaml"), "baselines")) == {
        "n_views": [25, 50, 75, 150]}
    with pytest.raises(CtsplatError, match=r"holds 2 radiographs geometries \(circular, carm\); give a file with one"):
        load_section(head, "radiographs")


@pytest.mark.parametrize("name", ["config.yaml", "ct0051_head.yaml", "full_protocol.yaml"])
def test_ctsplat_sfm_takes_a_workflow_config_whose_geometry_names_the_view_set(name):
    """A workflow config's sfm.settings name the C-arm view set (geometry); `ctsplat sfm` registers its RADIOGRAPHS
    argument instead, so it reads the other settings and leaves geometry out; `--set geometry=...` is refused."""
    import yaml

    from ctsplat.cli.sfm import sfm_settings
    from ctsplat.utils import CtsplatError

    path = ROOT / "config" / name
    workflow = yaml.safe_load(path.read_text())["sfm"]["settings"]
    assert workflow["geometry"] == "carm"
    cfg = sfm_settings(str(path), ["matching=sequential"])
    assert cfg == {**{k: v for k, v in workflow.items() if k != "geometry"}, "matching": "sequential"}
    with pytest.raises(CtsplatError, match="drop geometry"):
        sfm_settings(str(path), ["geometry=carm"])


def test_hu_max_sets_where_mu_clips(tmp_path):
    from ctsplat.formats.sources import write_dicom_series
    from ctsplat.formats.volume import load_volume

    hu = np.full((8, 8, 4), 4000.0)  # dense metal, above the default hu_max of 3000
    hu[:4] = 0.0  # water
    write_dicom_series(hu, tmp_path / "dicom", spacing_mm=(1.0, 1.0, 1.0), origin_lps=(0.0, 0.0, 0.0))
    for hu_max, top in ((None, 0.019 * 4), ("5000", 0.019 * 5)):
        out = tmp_path / f"v{hu_max}.nii.gz"
        extra = ["--hu-max", hu_max] if hu_max else []
        assert main(["ingest", str(tmp_path / "dicom"), str(out), "--intensity", "mu", "--native", *extra]) == 0
        data = load_volume(out).data
        assert float(data.max()) == pytest.approx(top, rel=1e-4)  # mu clips at mu(hu_max)
        assert float(data.min()) == pytest.approx(0.019, rel=1e-4)


def test_a_failed_train_or_evaluate_leaves_no_folder_or_lock_behind(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["train", "--out", str(out), "--volume", str(tmp_path / "nope.nii.gz"), "--radiographs",
                 str(tmp_path / "rad")]) == 2
    assert "nope.nii.gz does not exist" in capsys.readouterr().err and not out.exists()
    mine = tmp_path / "mine"
    mine.mkdir()
    assert main(["evaluate", str(mine)]) == 2
    assert "is not a finished training run" in capsys.readouterr().err and list(mine.iterdir()) == []
    for name, text, needle in (("config.json", "{", "run config"), ("config.json", "[1]", "holds a JSON array"),
                               ("config.json", '{"config_hash": "x"}', "has no 'config' object"),
                               ("config.json", '{"config": {"volume": "v.nii.gz"}}', "has no 'radiographs' entry"),
                               ("training.json", "{", "training record")):
        run = tmp_path / f"broken_{name}_{len(text)}"
        run.mkdir()
        for file in ("config.json", "training.json"):
            (run / file).write_text(text if file == name else '{"config": {}}')
        (run / "model.pt").write_bytes(b"")
        assert main(["evaluate", str(run)]) == 2
        err = capsys.readouterr().err.strip()
        assert f"{run / name}" in err and needle in err and "train the run again" in err and "\n" not in err
        written = sorted(p.name for p in run.iterdir() if p.name != LOCK_NAME)  # the lock file stays, unlocked
        assert written == ["config.json", "model.pt", "training.json"]
    # a complete run config beside a training record of another version: named, not a KeyError
    run = tmp_path / "old_record"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"config": dict.fromkeys(_RUN_CONFIG_KEYS, 1)}))
    (run / "training.json").write_text('{"iterations": 10}')
    (run / "model.pt").write_bytes(b"")
    assert main(["evaluate", str(run)]) == 2
    err = capsys.readouterr().err.strip()
    assert f"{run / 'training.json'} has no 'wall_time_s' entry" in err and "\n" not in err


def test_train_reads_a_run_folders_config_json(tmp_path):
    from ctsplat.cli.train import load_train_config

    record = {"config": {"iterations": 400, "init": "fbp", "lr": {"means": 1e-4}}, "config_hash": "abc",
              "code_version": "1234567", "scene": {}, "uses_reference_volume": False}
    (tmp_path / "config.json").write_text(json.dumps(record))
    cfg = load_train_config(str(tmp_path / "config.json"), ["iterations=800"])
    assert cfg == {"iterations": 800, "init": "fbp", "lr": {"means": 1e-4}}  # the settings it trained with


def test_terminated_command_removes_its_temporary_outputs(tmp_path):
    """SIGTERM (kill, a cluster's cancel or time limit) ends a step like Ctrl-C: exit 143, one line, and no
    hidden staging folder left beside the output."""
    import signal
    import subprocess
    import sys
    import time

    code = "import sys; from ctsplat.cli import main; sys.exit(main(sys.argv[1:]))"
    subprocess.run([sys.executable, "-c", code, "phantom", str(tmp_path / "dicom")], check=True, capture_output=True)
    subprocess.run([sys.executable, "-c", code, "ingest", str(tmp_path / "dicom"), str(tmp_path / "v.nii.gz"),
                    "--grid", "48"], check=True, capture_output=True)
    out = tmp_path / "rad"
    proc = subprocess.Popen([sys.executable, "-c", code, "project", "--volume", str(tmp_path / "v.nii.gz"), "--out",
                             str(out), "--set", "n_views=2000", "--set", "detector_width=192",
                             "--set", "detector_height=192"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    deadline = time.monotonic() + 60
    while not list(tmp_path.glob(".rad.*")) and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.05)
    assert list(tmp_path.glob(".rad.*")), "the projector never opened its staging folder"
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err
    assert "ctsplat project: terminated; files are written whole or not at all" in err
    assert not list(tmp_path.glob(".rad.*")) and not out.exists()


def test_a_warning_the_library_logs_is_said_once(tmp_path):
    """A slice gap is logged by the reader and raised as a warning for library callers; the command's log, which
    also carries Python warnings, says it once."""
    from ctsplat.formats.sources import write_dicom_series

    hu = np.zeros((8, 8, 6))
    files = write_dicom_series(hu, tmp_path / "dicom", spacing_mm=(1.0, 1.0, 1.0), origin_lps=(0.0, 0.0, 0.0))
    Path(sorted(files)[2]).unlink()  # a missing slice: a gap of twice the spacing
    done = ctsplat("ingest", tmp_path / "dicom", tmp_path / "v.nii.gz", "--grid", "8")
    assert done.returncode == 0, done.stderr
    assert done.stderr.count("gap(s) larger than") == 1, done.stderr


@pytest.mark.parametrize(("command", "seed", "needle"), [
    ("project", "-5", "-5 is outside 0 .. 4294967295"),
    ("sfm", "4294967296", "4294967296 is outside 0 .. 4294967295"),
    ("phantom", "1.5", "'1.5' is not an integer"),
    ("train", "-1", "-1 is outside 0 .. 4294967295"),
])
def test_a_seed_outside_what_the_generators_accept_is_refused_by_the_parser(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str, seed: str, needle: str) -> None:
    args = {"project": ["--volume", "v.nii.gz", "--out", "o"], "sfm": ["rad", "o"], "phantom": ["o"],
            "train": ["--out", "o"]}[command]
    with pytest.raises(SystemExit) as exc:
        main([command, *[str(tmp_path / a) if a in ("v.nii.gz", "o", "rad") else a for a in args], "--seed", seed])
    assert exc.value.code == 2
    assert_one_line_error(capsys.readouterr().err, command, f"argument --seed: {needle}")
    assert list(tmp_path.iterdir()) == []


def test_an_interrupted_training_says_whether_there_is_a_checkpoint_to_resume(tmp_path, monkeypatch, capsys):
    """Ctrl-C before the first checkpoint leaves nothing to resume: the message says to run again, not --resume."""
    import ctsplat.training
    from ctsplat.cli import main

    def interrupted(cfg, out, resume=False):
        raise KeyboardInterrupt

    monkeypatch.setattr(ctsplat.training, "train", interrupted)
    out = tmp_path / "run"
    argv = ["train", "--volume", str(tmp_path / "v.nii.gz"), "--radiographs", str(tmp_path / "rad"), "--out", str(out)]
    assert main(argv) == 130
    err = capsys.readouterr().err.strip()
    assert err == ("ctsplat train: interrupted; files are written whole or not at all: no checkpoint was saved yet: "
                   "run the command again")
    (out / "checkpoints").mkdir(parents=True)
    (out / "checkpoints" / "ckpt_00000250.pt").write_bytes(b"")
    assert main([*argv, "--resume"]) == 130
    assert capsys.readouterr().err.strip().endswith("continue with `ctsplat train --resume`")
