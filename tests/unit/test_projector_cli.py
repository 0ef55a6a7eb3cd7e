"""``ctsplat project`` / ``ctsplat baseline`` through the real command-line entry point."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd

from ctsplat.cli import main
from ctsplat.formats.viewset import load_radiographs
from ctsplat.formats.volume import Volume, save_volume


def test_project_and_baseline_commands(tmp_path, capsys):
    n = 16
    g = (np.arange(n) - (n - 1) / 2) / (n / 2)
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    data = (0.5 * (X**2 + Y**2 + Z**2 < 0.6)).astype(np.float32)
    vol = tmp_path / "volume.nii.gz"
    meta = {"volume_id": "cli", "intensity": {"mu_scale_per_mm": 0.02}}
    save_volume(Volume(data, np.diag([2.0, 2.0, 2.0, 1.0]), meta), vol)
    cfg = tmp_path / "rad.yaml"
    cfg.write_text("radiographs:\n  detector_width: 16\n  detector_height: 18\n")
    rad = tmp_path / "rad"
    assert main(["project", "--volume", str(vol), "--out", str(rad), "--config", str(cfg),
                 "--set", "n_views=20", "--set", "noise.enabled=false", "--seed", "4"]) == 0
    p, vs = load_radiographs(rad)
    assert p.shape == (20 + 4 + 4, 18, 16) and len(vs.indices("train")) == 20
    assert json.loads((rad / "radiographs.json").read_text())["seed"] == 4
    out = tmp_path / "base"
    assert main(["baseline", "--volume", str(vol), "--radiographs", str(rad), "--out", str(out),
                 "--set", "sart_max_iterations=2", "--set", "n_views=[10,20]"]) == 0
    df = pd.read_csv(out / "baselines.csv", keep_default_na=False)
    assert list(df["n_views"]) == [10] * 4 + [20] * 4  # fbp, sart, asd_pocs, mbir
    assert "psnr3d" in capsys.readouterr().out
    # user errors: one line, exit status 2, nothing written
    assert main(["project", "--volume", str(vol), "--out", str(tmp_path / "bad"), "--set", "camera=cone",
                 "--set", "dsd_mm=10", "--set", "dso_mm=20"]) == 2
    assert "must be larger than dso_mm" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
    assert main(["project", "--volume", str(tmp_path / "missing.nii.gz"), "--out", str(tmp_path / "x")]) == 2


def test_a_truncation_warning_is_printed_once(tmp_path):
    import subprocess
    import sys

    n = 16
    data = np.full((n, n, n), 0.5, np.float32)
    vol = tmp_path / "volume.nii.gz"
    save_volume(Volume(data, np.diag([2.0, 2.0, 2.0, 1.0]), {"volume_id": "w", "intensity": {"mu_scale_per_mm": 0.02}}),
                vol)
    cli = "import sys; from ctsplat.cli import main; sys.exit(main())"
    args = ["project", "--volume", str(vol), "--out", str(tmp_path / "rad"), "--set", "n_views=4", "--set",
            "detector_width=8", "--set", "detector_height=8", "--set", "pixel_spacing_mm=2.0", "--set",
            "allow_truncation=true", "--set", "noise.enabled=false"]
    proc = subprocess.run([sys.executable, "-c", cli, *args], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.count("detector does not cover the volume") == 1, proc.stderr
