"""`ctsplat gather` / `ctsplat analyse` on synthetic run folders."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd

from ctsplat.analysis import ANALYSIS_OUTPUTS
from ctsplat.cli import main
from ctsplat.grid import run_relpath


def _run(root, seed):
    cell = {"init": "fbp", "compositor": "radiative", "mip": "on", "poses": "gt", "views": 8, "seed": seed}
    rd = root / "results" / "phantom" / "runs" / run_relpath(cell)
    rd.mkdir(parents=True)
    it = np.arange(0, 501, 50)
    pd.DataFrame({"iteration": it, "timestamp": it / 10, "psnr2d": 20 + it / 25, "ssim2d": 0.5 + it / 1000,
                  "psnr3d": 15 + it / 100, "ssim3d": 0.4 + it / 2000}).to_csv(rd / "train_log.csv", index=False)
    (rd / "metrics.json").write_text(json.dumps({"psnr3d": 20.0 + seed}))
    return rd


def test_gather_searches_folders_and_analyse_writes_figures(tmp_path, capsys):
    for s in (0, 1):
        _run(tmp_path, s)
    out = tmp_path / "summary.csv"
    assert main(["gather", str(tmp_path / "results"), "--out", str(out), "--milestone", "psnr2d=35"]) == 0
    df = pd.read_csv(out)
    assert sorted(df["seed"]) == [0, 1]
    # psnr2d = 20 + it/25 >= 35 first at it = 375 -> logged at 400
    assert (df["iter_to_psnr2d_35"] == 400).all()
    figs = tmp_path / "figs"
    assert main(["analyse", str(out), "--out-dir", str(figs), "--window", "3"]) == 0
    assert all((figs / fname).exists() for fname, _ in ANALYSIS_OUTPUTS.values())


def test_gather_of_a_results_folder_skips_the_photo_runs(tmp_path, capsys):
    _run(tmp_path, 0)
    photo = tmp_path / "results" / "skull" / "photos" / "run"  # a photo run writes train_log.csv too
    photo.mkdir(parents=True)
    (photo / "train_log.csv").write_text("iteration,timestamp,psnr2d\n0,0,20\n")
    (photo / "metrics.json").write_text("{}")
    assert main(["gather", str(tmp_path / "results"), "--out", str(tmp_path / "s.csv")]) == 0
    assert list(pd.read_csv(tmp_path / "s.csv")["volume"]) == ["phantom"]


def test_cli_errors_are_one_line(tmp_path, capsys):
    assert main(["gather", str(tmp_path / "nothing")]) == 2
    assert main(["gather", str(tmp_path)]) == 2
    assert "no run folders" in capsys.readouterr().err
    assert main(["analyse", str(tmp_path / "missing.csv")]) == 2
    err = capsys.readouterr().err.strip()
    assert "run `ctsplat gather` first" in err and "\n" not in err
    _run(tmp_path, 0)
    assert main(["gather", str(tmp_path), "--out", str(tmp_path / "s.csv"), "--milestone", "psnr2d"]) == 2
    assert "must look like metric=value" in capsys.readouterr().err
    assert not (tmp_path / "s.csv").exists()


def test_gather_and_analyse_replace_only_their_own_files_and_read_every_input_first(tmp_path, capsys):
    rd = _run(tmp_path, 0)
    out = tmp_path / "summary.csv"
    # a run named twice (itself and under its results folder) is one row
    assert main(["gather", str(rd), str(tmp_path / "results"), "--out", str(out)]) == 0
    assert len(pd.read_csv(out)) == 1
    # bad baselines tables: one line naming the file, before anything is written
    bad = {"empty.csv": "", "trials.csv": "method,n_views,val_psnr\nfbp,8,20\n",
           "nan.csv": "method,n_views,psnr3d,ssim3d\nfbp,8,,0.5\n", "latin1.csv": "method,n_views\n\xe9,1\n"}
    for name, text in bad.items():
        path = tmp_path / name
        path.write_bytes(text.encode("latin-1"))
        before = out.read_bytes()
        assert main(["gather", str(rd), "--out", str(out), "--baselines", str(path)]) == 2
        err = capsys.readouterr().err.strip()
        assert name in err and "\n" not in err and "Traceback" not in err, err
        assert out.read_bytes() == before
        figs = tmp_path / "figs"
        assert main(["analyse", str(out), "--out-dir", str(figs), "--baselines", str(path)]) == 2
        assert name in capsys.readouterr().err and not figs.exists()
    # --out naming another step's table, and --out-dir holding figures analyse did not write, are refused
    table = tmp_path / "baselines.csv"
    table.write_text("method,n_views,psnr3d,ssim3d\nfbp,8,20,0.5\n")
    assert main(["gather", str(rd), "--out", str(table)]) == 2
    assert "exists and is not a summary of `ctsplat gather`" in capsys.readouterr().err
    assert table.read_text() == "method,n_views,psnr3d,ssim3d\nfbp,8,20,0.5\n"
    (rd / "figures").mkdir()
    (rd / "figures" / "acf.png").write_bytes(b"run figure")
    assert main(["analyse", str(out), "--out-dir", str(rd / "figures")]) == 2
    assert "holds acf.png, which analyse would replace but did not write" in capsys.readouterr().err
    assert (rd / "figures" / "acf.png").read_bytes() == b"run figure"
    figs = tmp_path / "figs"
    assert main(["analyse", str(out), "--out-dir", str(figs), "--baselines", str(table)]) == 0
    assert main(["analyse", str(out), "--out-dir", str(figs)]) == 0  # its own earlier output is replaced


def test_analyse_runs_again_after_it_was_interrupted(tmp_path, capsys, monkeypatch):
    import ctsplat.analysis.plots as plots

    _run(tmp_path, 0)
    out = tmp_path / "summary.csv"
    assert main(["gather", str(tmp_path / "results"), "--out", str(out)]) == 0
    figs = tmp_path / "figs"

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(plots, "plot_ablation", interrupted)  # after some outputs, before the others
    assert main(["analyse", str(out), "--out-dir", str(figs)]) == 130
    assert (figs / "analysis.json").is_file() and (figs / "velocity.png").is_file()  # written before the stop
    assert not (figs / "ablation.png").exists()
    monkeypatch.undo()
    assert main(["analyse", str(out), "--out-dir", str(figs)]) == 0  # its own half-written folder is replaced
    assert all((figs / fname).exists() for fname, _ in ANALYSIS_OUTPUTS.values())
