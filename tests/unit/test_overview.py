"""Overview figures of the report (volume slices, contact sheets, SfM verdict) on tiny synthetic inputs."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from ctsplat.analysis.overview import (
    FAILED_COLOUR,
    plot_contact_sheet,
    plot_sfm,
    plot_volume_slices,
    radiographs_figure,
    sfm_title,
    volume_figure,
)
from ctsplat.utils import CtsplatError


def _colorbar_labels(fig):
    return [ax.get_ylabel() for ax in fig.axes if ax.get_label() == "<colorbar>"]


def test_volume_slices_have_three_panels_and_a_unit_colour_bar(tmp_path):
    vol = np.zeros((6, 8, 10), np.float32)
    vol[2:4, 3:5, 4:6] = 0.8
    fig = plot_volume_slices(vol, tmp_path / "v.png", spacing_mm=(1, 1, 2), title="tiny")
    assert (tmp_path / "v.png").stat().st_size > 1000
    images = [ax.images[0] for ax in fig.axes if ax.images]
    assert len(images) == 3
    # central slices, transposed so the second index runs up: I slice is (K, J), K slice is (J, I)
    assert images[0].get_array().shape == (10, 8) and images[2].get_array().shape == (8, 6)
    assert images[0].get_clim() == pytest.approx((0.0, 0.8))  # one shared scale over the volume's range
    assert _colorbar_labels(fig) == ["normalised attenuation (0-1)"]


def test_volume_slices_reject_non_3d(tmp_path):
    with pytest.raises(CtsplatError, match="3-D volume"):
        plot_volume_slices(np.zeros((4, 4)), tmp_path / "v.png")
    assert not (tmp_path / "v.png").exists()


def test_contact_sheet_shows_at_most_16_evenly_spread_views(tmp_path):
    stack = np.stack([np.full((5, 7), float(i), np.float32) for i in range(40)])
    labels = [f"view {i}" for i in range(40)]
    fig = plot_contact_sheet(stack, tmp_path / "c.png", labels=labels)
    shown = [ax for ax in fig.axes if ax.images]
    assert len(shown) == 16
    assert [ax.get_title() for ax in shown][:3] == ["view 0", "view 2", "view 5"]  # floor(k * 40 / 16)
    assert _colorbar_labels(fig) == ["line integral (dimensionless)"]
    small = plot_contact_sheet(stack[:3], tmp_path / "s.png")
    assert len([ax for ax in small.axes if ax.images]) == 3


def _poses(registered):
    n = len(registered)
    return pd.DataFrame({"view_id": range(n), "azimuth_deg": np.linspace(0, 330, n), "registered": registered,
                         "rot_err_deg": [0.5 if r else np.nan for r in registered],
                         "centre_err_mm": [1.0 if r else np.nan for r in registered],
                         "plausible": registered})


def test_sfm_figure_title_says_ok_with_the_median():
    text, colour = sfm_title({"ok": True, "rot_err_deg_median": 0.4321, "n_registered": 11, "n_views": 12})
    assert text.startswith("SfM OK: median rotation error 0.43 deg") and colour != FAILED_COLOUR


def test_sfm_figure_failed_run_has_a_red_title_with_the_reason(tmp_path):
    summary = {"ok": False, "reason": "registration rate 0.25 (need >= 0.8)"}
    fig = plot_sfm(_poses([True, True, True] + [False] * 9), summary, tmp_path / "s.png")
    assert fig._suptitle.get_text() == "SfM FAILED: registration rate 0.25 (need >= 0.8)"
    assert fig._suptitle.get_color() == FAILED_COLOUR
    # the registration strip: 3 registered, 9 not, each at its azimuth
    strip = fig.axes[1]
    counts = sorted(len(c.get_offsets()) for c in strip.collections)
    assert counts == [3, 9]
    # nothing registered at all still draws (the failure case the report must show)
    fig = plot_sfm(_poses([False] * 6), summary, tmp_path / "none.png")
    assert (tmp_path / "none.png").stat().st_size > 1000 and fig._suptitle.get_color() == FAILED_COLOUR


def test_sfm_figure_needs_the_poses_columns(tmp_path):
    with pytest.raises(CtsplatError, match="rot_err_deg"):
        plot_sfm(pd.DataFrame({"view_id": [0], "azimuth_deg": [0.0], "registered": [True]}), {"ok": True},
                 tmp_path / "s.png")


def test_file_wrappers_read_the_workflow_files(tmp_path):
    from ctsplat.formats.volume import Volume, save_volume
    from ctsplat.projector import render_radiographs

    vol = np.zeros((8, 8, 8), np.float32)
    vol[2:6, 2:6, 2:6] = 0.5
    save_volume(Volume(data=vol, affine=np.diag([2.0, 2.0, 2.0, 1.0]), meta={}), tmp_path / "volume.nii.gz")
    fig = volume_figure(tmp_path / "volume.nii.gz", tmp_path / "v.png")
    assert fig._suptitle.get_text() == tmp_path.name
    for kind, unit in (("attenuation_normalised", "normalised attenuation (0-1)"),
                       ("attenuation_per_mm", "attenuation μ (1/mm)"), ("hu", "HU")):  # the colour bar's label
        save_volume(Volume(data=vol, affine=np.diag([2.0, 2.0, 2.0, 1.0]), meta={"intensity": {"kind": kind}}),
                    tmp_path / "k" / "volume.nii.gz")
        labels = {ax.get_ylabel() for ax in volume_figure(tmp_path / "k" / "volume.nii.gz", tmp_path / "k.png").axes}
        assert unit in labels, (kind, labels)
    assert (tmp_path / "v.png").stat().st_size > 1000
    render_radiographs(tmp_path / "volume.nii.gz", tmp_path / "rad",
                       {"n_views": 10, "detector_width": 8, "detector_height": 8, "device": "cpu"})
    fig = radiographs_figure(tmp_path / "rad", tmp_path / "r.png")
    shown = [ax for ax in fig.axes if ax.images]
    import json

    views = json.loads((tmp_path / "rad/views.json").read_text())["views"]
    train = [v for v in views if v["split"] == "train"]
    assert len(shown) == min(16, len(train)) and shown[0].get_title().startswith(f"view {train[0]['id']}, az ")
    assert len([ax for ax in radiographs_figure(tmp_path / "rad", tmp_path / "all.png", split=None).axes
                if ax.images]) == min(16, len(views))
    with pytest.raises(CtsplatError, match="does not exist"):
        radiographs_figure(tmp_path / "missing", tmp_path / "m.png")
