"""``ctsplat render``: a saved model's views rendered to a TIFF stack + PNGs, equal to direct render calls."""

from __future__ import annotations

import json
import sys

import imageio.v3 as iio
import numpy as np
import pytest
import tifffile
import torch

from ctsplat.cli import main
from ctsplat.formats.viewset import View, ViewSet
from ctsplat.geometry import ParallelCamera, pose_from_angles
from ctsplat.splat.gaussians import Gaussians
from ctsplat.splat.render import compute_3d_filter, render


def _setup(tmp_path, camera=None, distances=(200.0, 200.0, 200.0), scales=(1, 3)):
    """20 Gaussians and three views (two train, one test) at azimuths 0, 60, 120 and the given distances (mm)."""
    rng = np.random.default_rng(0)
    g = Gaussians.from_values(rng.normal(size=(20, 3)) * 5, rng.uniform(*scales, (20, 3)), rng.uniform(0.1, 1, 20),
                              rng.normal(size=(20, 4)))
    g.save(tmp_path / "model.pt")
    views = []
    for i, (az, dist) in enumerate(zip((0.0, 60.0, 120.0), distances, strict=True)):
        R, t = pose_from_angles(az, 10.0, (0, 0, 0), dist)
        views.append(View(i, R, t, az, 10.0, "train" if i < 2 else "test"))
    vs = ViewSet(camera or ParallelCamera(24, 20, 1.5), views)
    vs.save(tmp_path / "views.json")
    return g, vs


def test_render_cli_writes_images_equal_to_render(tmp_path):
    g, vs = _setup(tmp_path)
    out = tmp_path / "out"
    rc = main(["render", str(tmp_path / "model.pt"), str(tmp_path / "views.json"), str(out), "--mip",
               "--mu-scale", "0.5"])
    assert rc == 0
    stack = tifffile.imread(out / "images.tif")
    assert stack.shape == (3, 20, 24)
    train = vs.subset("train")
    fv = compute_3d_filter(g, vs.camera, train.Rs(), train.ts())
    for k, v in enumerate(vs.views):
        ref = render(g, vs.camera, v.R, v.t, filter_3d_var=fv, mip_2d=True).image * 0.5
        np.testing.assert_allclose(stack[k], ref.numpy(), rtol=1e-5, atol=1e-6)
        png = iio.imread(out / "png" / f"view_{v.id:04d}.png")
        assert png.dtype == np.uint16
        np.testing.assert_allclose(png / 65535.0, np.exp(-stack[k]), atol=1 / 65535)
    info = json.loads((out / "render.json").read_text())
    assert info["n_views"] == 3 and info["mip"] is True and info["mu_scale"] == 0.5


def test_render_cli_split_and_bad_model(tmp_path, capsys):
    g, vs = _setup(tmp_path)
    for compositor in ("alpha", "radiative_unrectified"):
        out = tmp_path / f"o_{compositor}"
        assert main(["render", str(tmp_path / "model.pt"), str(tmp_path / "views.json"), str(out), "--split", "test",
                     "--compositor", compositor]) == 0
        image = np.squeeze(tifffile.imread(out / "images.tif"))
        assert image.shape == (20, 24)  # a single view, rendered by the compositor asked for
        test = vs.views[2]
        np.testing.assert_allclose(image, render(g, vs.camera, test.R, test.t, compositor=compositor).image.numpy(),
                                   rtol=1e-5, atol=1e-6)
    out = tmp_path / "o2"
    assert main(["render", str(tmp_path / "nope.pt"), str(tmp_path / "views.json"), str(out)]) == 2
    assert "model file not found" in capsys.readouterr().err
    assert torch.is_tensor(Gaussians.load(tmp_path / "model.pt").means)


def test_render_cli_split_keeps_the_training_views_3d_filter(tmp_path):
    from ctsplat.geometry import ConeCamera

    # cone beam, the test view far off: a filter from the test view alone would differ from the train views' one
    _setup(tmp_path, ConeCamera(24, 20, 0.5, 60.0, 90.0), distances=(60.0, 60.0, 400.0), scales=(0.2, 1))
    full, test = tmp_path / "all", tmp_path / "test"
    for out, extra in ((full, []), (test, ["--split", "test"])):
        assert main(["render", str(tmp_path / "model.pt"), str(tmp_path / "views.json"), str(out), "--mip",
                     *extra]) == 0
    # the test view renders the same alone as among all views: the filter comes from the train views either way
    alone = np.squeeze(tifffile.imread(test / "images.tif"))
    np.testing.assert_array_equal(alone, tifffile.imread(full / "images.tif")[2])


def test_render_cli_uses_the_filter_a_model_was_saved_with(tmp_path):
    g, vs = _setup(tmp_path)
    g.filter_3d_var = torch.linspace(0.5, 4.0, len(g), dtype=g.means.dtype)  # not what the views would give
    g.save(tmp_path / "model.pt")
    out = tmp_path / "stored"
    assert main(["render", str(tmp_path / "model.pt"), str(tmp_path / "views.json"), str(out), "--mip"]) == 0
    v = vs.views[0]
    ref = render(g, vs.camera, v.R, v.t, filter_3d_var=g.filter_3d_var, mip_2d=True).image.numpy()
    np.testing.assert_allclose(tifffile.imread(out / "images.tif")[0], ref, rtol=1e-5, atol=1e-6)


def test_render_cli_defaults_to_how_the_model_was_trained(tmp_path):
    """Without --compositor / --mip / --mu-scale, a model is drawn with the compositor, mip filters and density
    factor it records; the options still override them."""
    g, vs = _setup(tmp_path)
    g.meta.update(compositor="alpha", mip=True, mu_scale_per_mm=0.25)
    g.save(tmp_path / "model.pt")
    args = [str(tmp_path / "model.pt"), str(tmp_path / "views.json")]
    train = vs.subset("train")
    fv = compute_3d_filter(g, vs.camera, train.Rs(), train.ts())
    v = vs.views[0]
    assert main(["render", *args, str(tmp_path / "as_trained")]) == 0
    ref = render(g, vs.camera, v.R, v.t, compositor="alpha", filter_3d_var=fv, mip_2d=True).image
    np.testing.assert_allclose(tifffile.imread(tmp_path / "as_trained" / "images.tif")[0], ref.numpy(), rtol=1e-5,
                               atol=1e-6)
    assert main(["render", *args, str(tmp_path / "asked"), "--compositor", "radiative", "--no-mip"]) == 0
    ref = render(g, vs.camera, v.R, v.t).image * 0.25
    np.testing.assert_allclose(tifffile.imread(tmp_path / "asked" / "images.tif")[0], ref.numpy(), rtol=1e-5,
                               atol=1e-6)
    info = json.loads((tmp_path / "asked" / "render.json").read_text())
    assert info["compositor"] == "radiative" and info["mip"] is False and info["mu_scale"] == 0.25


def test_render_cli_writes_the_whole_folder_or_nothing(tmp_path, capsys, monkeypatch):
    """A failure while writing leaves no folder (and an earlier render as it was); a non-finite density factor and
    an output folder that holds other files (the radiographs themselves) are refused before anything is written."""
    _setup(tmp_path)
    args = [str(tmp_path / "model.pt"), str(tmp_path / "views.json")]
    out = tmp_path / "render"
    assert main(["render", *args, str(out), "--mu-scale", "inf"]) == 2
    assert "--mu-scale must be a finite number > 0" in capsys.readouterr().err and not out.exists()
    assert main(["render", *args, str(tmp_path)]) == 2  # the folder of model.pt and views.json
    assert "holds, the input" in capsys.readouterr().err
    other = tmp_path / "radiographs"
    other.mkdir()
    (other / "line_integrals.tif").write_bytes(b"not a render")
    assert main(["render", *args, str(other)]) == 2
    assert "not an earlier output" in capsys.readouterr().err
    assert (other / "line_integrals.tif").read_bytes() == b"not a render"

    assert main(["render", *args, str(out)]) == 0
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert len(before) == 5  # images.tif, render.json and one PNG per view

    def fail_on_the_third_png(path, image, **kwargs):
        if path.name == "view_0002.png":
            raise OSError(28, "No space left on device")
        return real_imwrite(path, image, **kwargs)

    real_imwrite = iio.imwrite
    monkeypatch.setattr(iio, "imwrite", fail_on_the_third_png)
    assert main(["render", *args, str(out), "--mu-scale", "2"]) == 2
    assert "No space left on device" in capsys.readouterr().err
    assert {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []  # no scratch folder left
    assert main(["render", *args, str(tmp_path / "new"), "--mu-scale", "2"]) == 2
    assert not (tmp_path / "new").exists()


def test_render_cli_names_a_view_set_folder_and_a_gpu_out_of_memory(tmp_path, capsys, monkeypatch):
    _setup(tmp_path)
    assert main(["render", str(tmp_path / "model.pt"), str(tmp_path), str(tmp_path / "r")]) == 2
    assert f"view set {tmp_path} is a folder, not a JSON file" in capsys.readouterr().err

    def oom(*args, **kwargs):
        raise torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB. GPU 0 has 1.2 GiB free.")

    module = sys.modules["ctsplat.splat.render"]  # the package's ``render`` is the function, not the module
    monkeypatch.setattr(module, "render_to_folder", oom)
    assert main(["render", str(tmp_path / "model.pt"), str(tmp_path / "views.json"), str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == ("ctsplat render: error: out of memory (CUDA out of memory); choose smaller sizes (grid, size, "
                   "views, image size) or run on a machine with more memory")

    def cpu_oom(*args, **kwargs):
        return torch.empty(10**13)  # 40 TB: torch's CPU allocator refuses it with a RuntimeError

    monkeypatch.setattr(module, "render_to_folder", cpu_oom)
    assert main(["render", str(tmp_path / "model.pt"), str(tmp_path / "views.json"), str(tmp_path / "r")]) == 2
    assert capsys.readouterr().err.strip() == (
        "ctsplat render: error: out of memory (a CPU allocation failed); choose smaller sizes (grid, size, views, "
        "image size) or run on a machine with more memory")

    def bug(*args, **kwargs):
        raise RuntimeError("shape mismatch")

    monkeypatch.setattr(module, "render_to_folder", bug)
    with pytest.raises(RuntimeError, match="shape mismatch"):  # a bug keeps its traceback
        main(["render", str(tmp_path / "model.pt"), str(tmp_path / "views.json"), str(tmp_path / "r")])


@pytest.mark.parametrize(("edit", "args", "needle"), [
    (lambda p: p.update(version=99), [], "is a Gaussian model of format version 99; this ctsplat reads version 1"),
    (lambda p: p["meta"].update(mu_scale_per_mm=-2.0), [],
     "records mu_scale_per_mm -2.0, not a finite number > 0; give the scale to 1/mm with --mu-scale"),
    (lambda p: None, ["--mu-scale", "1e308"], "gave non-finite pixels (mu_scale 1e+308); use a smaller --mu-scale"),
])
def test_render_refuses_what_it_cannot_render_right(tmp_path, capsys, edit, args, needle):
    """A model of another format version, a recorded scale that is no scale, and a scale that overflows: one line,
    nothing written (each rendered images of nonsense, NaN or zeros before, with exit status 0)."""
    _setup(tmp_path)
    payload = torch.load(tmp_path / "model.pt", weights_only=True)
    edit(payload)
    torch.save(payload, tmp_path / "edited.pt")
    out = tmp_path / "out"
    assert main(["render", str(tmp_path / "edited.pt"), str(tmp_path / "views.json"), str(out), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and "\n" not in err, err
    assert not out.exists() and not list(tmp_path.glob(".out*"))
