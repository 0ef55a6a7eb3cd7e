"""The ``baseline`` rule on a cone-beam grid geometry: FDK, SART and ASD-POCS, parameters chosen on validation."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from smk_helpers import snakemake, write_config

pytestmark = pytest.mark.workflow

SIZE = 16
CONFIG = {
    "volumes": {"tiny": {"source": "phantom", "phantom": {"size": SIZE, "beads": False, "seed": 0}}},
    "preprocessing": {"grid": SIZE},
    "radiographs": {"cone": {"camera": "cone", "detector_width": 2 * SIZE, "detector_height": 2 * SIZE,
                             "n_views": 12, "dso_mm": 400.0, "dsd_mm": 560.0}},
    "baselines": {"enabled": True, "settings": {"sart_max_iterations": 2, "sart_relaxation": 1.0,
                                                "asd_pocs_iterations": 2, "asd_pocs_alpha": 0.02,
                                                "asd_pocs_tv_steps": 3, "save_volumes": True}},
    "grid": {"axes": {"init": ["fbp"], "compositor": ["radiative"], "mip": ["on"], "poses": ["gt"],
                      "views": [6, 12], "seed": [0]}},
}


def test_baseline_rule_runs_on_a_cone_beam_geometry(tmp_path):
    write_config(tmp_path / "config.yaml", CONFIG)
    target = "results/tiny/baselines/cone/baselines.csv"
    snakemake(tmp_path, target, "--allowed-rules", "phantom", "ingest", "project", "baseline",
              configfile=tmp_path / "config.yaml")
    df = pd.read_csv(tmp_path / target, keep_default_na=False)
    assert list(df["method"]) == ["fdk", "sart", "asd_pocs"] * 2
    assert list(df["n_views"]) == [6] * 3 + [12] * 3  # the grid's view counts
    assert np.isfinite(df["psnr3d"]).all() and np.isfinite(df["val_psnr"].astype(float)).all()
    assert {json.loads(p)["filter"] for p in df["params"][df["method"] == "fdk"]} <= {"ramp", "shepp-logan"}
    assert (tmp_path / "results/tiny/baselines/cone/fdk_n012.nii.gz").is_file()
    assert (tmp_path / "results/tiny/baselines/cone/trials.csv").is_file()
