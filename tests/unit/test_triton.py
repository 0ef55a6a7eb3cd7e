"""The Triton GPU path against the pure-PyTorch reference: forward values and gradients of every compositor (parallel
and cone cameras, with and without the mip filters, RGB and SH colour) and of the voxelizer; backend dispatch and its
errors.

Without a GPU the kernels run on CPU tensors through Triton's interpreter, which must be switched on
(``TRITON_INTERPRET=1``) before the kernels are imported: each check group runs in a child Python started with that
variable (this file run as a script), so neither the variable nor interpreted kernels reach other tests. With CUDA
the same checks also run in-process on the GPU (:class:`TestCuda`).
"""

from __future__ import annotations

import importlib
import importlib.util
import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

HAS_TRITON = importlib.util.find_spec("triton") is not None
D64 = torch.float64
F32 = torch.float32
ROOT = Path(__file__).resolve().parents[2]


# ------------------------------------------------------------------------------------------------ the checks
def _scene(n: int, seed: int, dtype: torch.dtype, device: str, colors: int = 1, sh: bool = False):
    from ctsplat.splat.gaussians import Gaussians

    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=D64) - 0.5) * 30.0
    scales = 0.3 + 2.7 * torch.rand(n, 3, generator=g, dtype=D64)
    dens = 0.2 + torch.rand(n, generator=g, dtype=D64)
    quats = torch.randn(n, 4, generator=g, dtype=D64)
    op = 0.2 + 0.7 * torch.rand(n, generator=g, dtype=D64)
    cols = torch.rand(n, colors, generator=g, dtype=D64)
    gs = Gaussians.from_values(means, scales, dens, quats, opacities=op, colors=cols, dtype=dtype)
    if sh:
        gs.sh_rest = 0.2 * torch.randn(n, 3, colors, generator=g, dtype=D64).to(dtype)
    return gs.to(device)


def _pose(az: float, el: float, dist: float, dtype: torch.dtype, device: str):
    from ctsplat.geometry import pose_from_angles

    R, t = pose_from_angles(az, el, (0.0, 0.0, 0.0), dist)
    return torch.tensor(R, dtype=dtype, device=device), torch.tensor(t, dtype=dtype, device=device)


def _close(x: torch.Tensor, y: torch.Tensor, tol: float, what: str) -> None:
    scale = float(x.abs().max()) if x.numel() else 0.0
    err = float((x - y).abs().max()) if x.numel() else 0.0
    assert err <= tol * max(scale, 1e-12), f"{what}: max |triton - ref| = {err:.3g}, max |ref| = {scale:.3g}"


def _compare_render(g, cam, R, t, params, w, tol, what, **kw) -> None:
    from ctsplat.splat.render import render

    res = {}
    for backend in ("reference", "triton"):
        out = render(g, cam, R, t, backend=backend, **kw)
        grads = torch.autograd.grad((out.image * w).sum(), [*params, out.means2d], allow_unused=True)
        res[backend] = (out.image.detach(), *grads, out.radii, out.visible)
    ref, tri = res["reference"], res["triton"]
    assert ref[0].shape == tri[0].shape, what
    assert torch.equal(ref[-2], tri[-2]) and torch.equal(ref[-1], tri[-1]), f"{what}: radii/visible differ"
    names = ["image", *[f"grad {i}" for i in range(len(params))], "grad means2d"]
    for name, x, y in zip(names, ref[:-2], tri[:-2], strict=True):
        if x is None:
            assert y is None or float(y.abs().max()) == 0.0, f"{what}: {name}"
            continue
        _close(x, y, tol, f"{what}: {name}")


def check_raster(model: str, device: str = "cpu") -> None:
    """Every compositor, with and without the 3D / 2D mip filters, float32 (and float64 once) vs the reference."""
    from ctsplat.geometry import ConeCamera, ParallelCamera

    n = 80
    # 24 x 20 px: tiles of 16 px leave partial tiles on both axes
    cam = ParallelCamera(24, 20, 1.0) if model == "parallel" else ConeCamera(24, 20, 2.0, 200.0, 400.0)
    for dtype, tol in ((F32, 2e-5), (D64, 1e-11)):
        fv = 0.2 * torch.rand(n, generator=torch.Generator().manual_seed(1), dtype=dtype).to(device)
        # cone at 40 mm: some Gaussians off to the side (clamped linearisation point), some behind the source
        R, t = _pose(60.0, -20.0, 200.0 if model == "parallel" else 40.0, dtype, device)
        for comp in ("radiative", "radiative_unrectified", "alpha"):
            combos = ((False, None), (True, fv)) if dtype == F32 else ((True, fv),)
            for mip, filt in combos:
                colors = 3 if comp == "alpha" else 1
                g = _scene(n, 11, dtype, device, colors=colors, sh=(comp == "alpha" and mip))
                if comp == "alpha":
                    params = [g.means, g.log_scales, g.quats, g.opacity_raw, g.colors]
                    params += [g.sh_rest] if g.sh_rest is not None else []
                    shape = (20, 24, 3)
                else:
                    params = [g.means, g.log_scales, g.quats, g.density_raw]
                    shape = (20, 24)
                for p in params:
                    p.requires_grad_(True)
                w = torch.rand(*shape, generator=torch.Generator().manual_seed(0), dtype=dtype).to(device)
                _compare_render(g, cam, R, t, params, w, tol, f"{model} {comp} mip={mip} {dtype}", compositor=comp,
                                mip_2d=mip, filter_3d_var=filt)
        # transmission and mu_scale are applied after the rasteriser, the same on both paths
        g = _scene(n, 12, dtype, device)
        params = [g.means, g.density_raw]
        for p in params:
            p.requires_grad_(True)
        w = torch.ones(20, 24, dtype=dtype, device=device)
        _compare_render(g, cam, R, t, params, w, tol, f"{model} transmission", transmission=True, mu_scale=0.05)


def check_raster_edges(device: str = "cpu") -> None:
    """Deep alpha stacks (transmittance far below float32's range), Gaussians spanning many tiles, nothing visible."""
    from ctsplat.geometry import ParallelCamera
    from ctsplat.splat.gaussians import Gaussians
    from ctsplat.splat.render import render

    cam = ParallelCamera(20, 18, 1.0)
    R, t = _pose(0.0, 0.0, 200.0, F32, device)
    # 70 coincident opaque Gaussians: T reaches 0.1^70 (underflows float32), the front ones still get gradients
    n = 70
    gen = torch.Generator().manual_seed(4)
    means = torch.randn(n, 3, generator=gen, dtype=D64) * 0.5
    g = Gaussians.from_values(means, torch.full((n, 3), 2.5, dtype=D64), torch.ones(n, dtype=D64),
                              torch.randn(n, 4, generator=gen, dtype=D64), opacities=torch.full((n,), 0.9, dtype=D64),
                              colors=torch.rand(n, 1, generator=gen, dtype=D64), dtype=F32).to(device)
    params = [g.means, g.log_scales, g.opacity_raw, g.colors]
    for p in params:
        p.requires_grad_(True)
    w = torch.rand(18, 20, generator=gen, dtype=F32).to(device)
    _compare_render(g, cam, R, t, params, w, 2e-5, "deep alpha stack", compositor="alpha")
    # one Gaussian wider than the image plus small ones (additive): lists of one tile and of every tile
    g = _scene(30, 5, F32, device)
    with torch.no_grad():
        g.log_scales[0] = torch.log(torch.tensor([15.0, 12.0, 9.0]))
    params = [g.means, g.log_scales, g.quats, g.density_raw]
    for p in params:
        p.requires_grad_(True)
    _compare_render(g, cam, R, t, params, w, 2e-5, "large footprint", compositor="radiative")
    # everything off-screen: a zero image and zero gradients, no kernel reads out of bounds
    with torch.no_grad():
        g.means += 1000.0
    out = render(g, cam, R, t, backend="triton")
    assert float(out.image.detach().abs().max()) == 0.0 and not bool(out.visible.any())
    (gm,) = torch.autograd.grad(out.image.sum(), [g.means], allow_unused=True)
    assert gm is None or float(gm.abs().max()) == 0.0


def check_voxelize(device: str = "cpu") -> None:
    """Voxelizer values and gradients (means, log-scales, quats, densities), full grid and a region, with a 3D filter,
    a sheared anisotropic affine, float32 and float64."""
    from ctsplat.splat.render import voxelize

    A = torch.tensor([[0.9, 0.1, 0.0, -9.0], [0.0, 1.1, 0.05, -10.0], [0.02, 0.0, 1.0, -8.0], [0, 0, 0, 1]], dtype=D64)
    for dtype, tol in ((F32, 5e-5), (D64, 1e-11)):
        g = _scene(40, 5, dtype, device)
        with torch.no_grad():
            g.means.mul_(8.0 / 15.0)
            g.log_scales.sub_(0.3)
        params = [g.means, g.log_scales, g.quats, g.density_raw]
        for p in params:
            p.requires_grad_(True)
        fv = 0.3 * torch.rand(40, generator=torch.Generator().manual_seed(1), dtype=dtype).to(device)
        # 18 x 20 x 17: bricks of 8 leave partial bricks on every axis
        for region in (None, ((3, 15), (2, 19), (5, 12))):
            res = {}
            for backend in ("reference", "triton"):
                v = voxelize(g, (18, 20, 17), A, region=region, filter_3d_var=fv, backend=backend)
                w = torch.rand(v.shape, generator=torch.Generator().manual_seed(0), dtype=dtype).to(device)
                res[backend] = (v.detach(), *torch.autograd.grad((v * w).sum(), params))
            assert float(res["reference"][0].max()) > 0.5
            for i, (x, y) in enumerate(zip(res["reference"], res["triton"], strict=True)):
                _close(x, y, tol, f"voxelize {dtype} region={region} output {i}")


PATHS = ("other", "triton")


def _tiny_scene(prefix: str, volume_id: str) -> Path:
    """A temporary folder with a 16³ ellipsoid (``volume.nii.gz``, 2 mm voxels) and 8 parallel 16² views (``rad``)."""
    import tempfile

    import numpy as np

    from ctsplat.formats.volume import Volume, save_volume
    from ctsplat.projector import render_radiographs

    root = Path(tempfile.mkdtemp(prefix=prefix))
    n = 16
    x = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).astype(float)
    data = (np.linalg.norm((x - 7.5) / np.array([6.0, 5.0, 4.0]), axis=-1) < 1).astype(np.float32) * 0.8
    aff = np.diag([2.0, 2.0, 2.0, 1.0])
    aff[:3, 3] = -15.0
    save_volume(Volume(data, aff, {"volume_id": volume_id, "intensity": {"mu_scale_per_mm": 0.02}}),
                root / "volume.nii.gz")
    render_radiographs(root / "volume.nii.gz", root / "rad",
                       {"detector_width": 16, "detector_height": 16, "n_views": 8, "device": "cpu"})
    return root


def check_train(device: str = "cpu") -> None:
    """Training and evaluation end to end through the Triton kernels (radiative compositor, TV term through the
    voxelizer, densification reading ``means2d.grad``): the run finishes, the model learns, and its metrics are
    close to the same run on the fused C++ kernel / reference (on CPU the interpreter stands in for CUDA:
    ``auto`` is pointed at the Triton kernels)."""
    import csv
    import importlib

    from ctsplat.evaluation import evaluate
    from ctsplat.training import loop

    render_mod = importlib.import_module("ctsplat.splat.render")
    root = _tiny_scene("ctsplat_triton_train_", "tiny_triton")
    cfg = {"volume": str(root / "volume.nii.gz"), "radiographs": str(root / "rad"), "init": "volume", "n_init": 100,
           "iterations": 12, "eval_every": 6, "checkpoint_every": 6, "device": device,
           "densify": {"interval": 6, "start": 6}, "figures": False, "fps_width": 16, "fps_height": 16,
           "progress": False, "lambda_tv": 0.05}
    results = {}
    for path in PATHS:
        if path == "triton" and device == "cpu":
            render_mod._use_triton = lambda backend, dev: backend in ("auto", "triton")
            render_mod._use_kernel = lambda backend, dev: False
        run_dev = device if path == "triton" else "cpu"  # "other": the CPU path (fused kernel) to compare with
        out = root / f"run_{path}"
        loop.train({**cfg, "device": run_dev}, out)
        results[path] = evaluate(out, device=run_dev)
        rows = list(csv.DictReader(open(out / "train_log.csv", newline="")))
        assert float(rows[-1]["psnr2d"]) > float(rows[0]["psnr2d"]), f"{path}: the model does not learn"
    for key in ("psnr2d", "psnr3d"):
        a, b = results["other"][key], results["triton"][key]
        assert abs(a - b) < 0.05, f"{key}: triton {b:.3f} vs CPU path {a:.3f}"


#: host reads of device values per training iteration on the Triton path (parameter, gradient and loss finite
#: checks, one flag each; the render's and the TV read-out's input checks): each read waits for the GPU's queue
HOST_READS_PER_ITERATION = 5


def check_host_reads() -> None:
    """A training iteration on the Triton path reads device values back to the host at most
    ``HOST_READS_PER_ITERATION`` times from ctsplat code (``bool``/``int``/``float``/``item``/``tolist`` on a
    tensor; a 20- minus a 5-iteration run, no validation or densification in between). Reads of values that live
    on the CPU also on a GPU run are not counted: the TV region's draws from its CPU generator and its bounds."""
    import importlib

    from ctsplat.training import loop
    from ctsplat.utils import count_host_reads

    render_mod = importlib.import_module("ctsplat.splat.render")
    render_mod._use_triton = lambda backend, dev: backend in ("auto", "triton")
    render_mod._use_kernel = lambda backend, dev: False
    root = _tiny_scene("ctsplat_triton_reads_", "tiny_reads")
    cpu_resident = {"random_region", "voxelize"}  # voxelize: only its region bounds are read directly
    counts = {}
    for its in (5, 20):
        cfg = {"volume": str(root / "volume.nii.gz"), "radiographs": str(root / "rad"), "init": "volume",
               "n_init": 100, "iterations": its, "eval_every": 100, "checkpoint_every": 100, "device": "cpu",
               "densify": {"interval": 100, "start": 100}, "figures": False, "progress": False, "lambda_tv": 0.05}
        with count_host_reads() as reads:
            loop.train(cfg, root / f"run{its}")
        counts[its] = {k: v for k, v in reads.items() if k[2] not in cpu_resident}
    per_iteration = {k: (counts[20][k] - counts[5].get(k, 0)) / 15 for k in counts[20]}
    per_iteration = {f"{k[1]} {k[0]}": v for k, v in per_iteration.items() if v}
    total = sum(per_iteration.values())
    assert total <= HOST_READS_PER_ITERATION, f"{total} host reads per iteration: {per_iteration}"
    assert total > 0, "no read counted: the counting itself is broken"


def check_compile() -> None:
    """Every kernel through Triton's real compiler for data-centre GPUs (float32: sm_80 and sm_90, float64: sm_80)
    down to a cubin: no GPU needed, and it catches what the interpreter lets through (e.g. a non-constexpr global)."""
    import inspect

    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    from ctsplat.splat import _triton_kernels as K

    assert not K.INTERPRETED
    for dt in ("fp32", "fp64"):
        p = f"*{dt}"
        rast = {"params_ptr": p, "bbox_ptr": "*i32", "offsets_ptr": "*i32", "ids_ptr": "*i32"}
        vox = {"means_ptr": p, "prec_ptr": p, "dens_ptr": p, "lo_ptr": "*i64", "hi_ptr": "*i64", "aff_ptr": p,
               "offsets_ptr": "*i32", "ids_ptr": "*i32", "org_ptr": "*i64"}
        kernels = [
            (K.additive_fwd, {**rast, "out_ptr": p}, {"TILE": 16, "G": 8}),
            (K.additive_bwd, {**rast, "grad_ptr": p, "pair_ptr": p}, {"TILE": 16, "G": 8}),
            (K.alpha_fwd, {**rast, "col_ptr": p, "out_ptr": p, "logt_ptr": p}, {"TILE": 16, "G": 8, "CP": 4}),
            (K.alpha_bwd, {**rast, "col_ptr": p, "logt_ptr": p, "grad_ptr": p, "pair_ptr": p},
             {"TILE": 16, "G": 8, "CP": 1}),
            (K.voxel_fwd, {**vox, "out_ptr": p}, {"B": 8, "G": 8}),
            (K.voxel_bwd, {**vox, "grad_ptr": p, "pair_ptr": p}, {"B": 8, "G": 8}),
        ]
        proj = {"cam_ptr": "*fp64", "means_ptr": p, "ls_ptr": p, "q_ptr": p, "draw_ptr": p, "fv_ptr": p}
        for flags in ({"MODE": 0, "MIP": False, "HAS_F": True, "CONE": True, "BLOCK": 128},
                      {"MODE": 2, "MIP": True, "HAS_F": False, "CONE": False, "BLOCK": 128}):
            kernels.append((K.project_fwd, {**proj, "m2d_ptr": p, "con_ptr": p, "amp_ptr": p, "depth_ptr": p,
                                            "bb_ptr": "*i64", "radii_ptr": "*i32", "valid_ptr": "*i8",
                                            "visible_ptr": "*i8", "bad_ptr": "*i8"}, flags))
            kernels.append((K.project_bwd, {**proj, **{f"g{k}_ptr": p for k in ("m2d", "con", "amp", "means", "ls",
                                                                                  "q", "draw")}}, flags))
        for fn, types, consts in kernels:
            names = list(inspect.signature(fn.fn).parameters)
            sig = {n: "constexpr" if n in consts else types.get(n, "i32") for n in names}
            src = ASTSource(fn=fn, signature=sig, constexprs={(names.index(k),): v for k, v in consts.items()})
            for arch in (80, 90) if dt == "fp32" else (80,):  # one arch for float64 keeps the test short
                compiled = triton.compile(src, target=GPUTarget("cuda", arch, 32), options={"num_warps": 8})
                assert len(compiled.asm["cubin"]) > 1000, (fn.__name__, dt, arch)
    # Compiled for a GPU, floating-point contraction is on: a finiteness test written as (x - x) == 0 turns, for a
    # product x, into an FMA computing the product's rounding error (not 0), so the projection's pixel boxes would
    # all be empty on a GPU while the interpreter, which never contracts, agrees with the reference.
    from _triton_probe import finite_of_product

    for dt in ("fp32", "fp64"):
        src = ASTSource(fn=finite_of_product, signature={"a_ptr": f"*{dt}", "b_ptr": f"*{dt}", "out_ptr": "*i8"})
        ptx = triton.compile(src, target=GPUTarget("cuda", 90, 32)).asm["ptx"]
        assert "fma." not in ptx, f"the finiteness test of a {dt} product compiles to an FMA:\n{ptx}"


def check_needles(device: str = "cpu") -> None:
    """Needle-like Gaussians in float32 against the float64 reference (the 2D determinant without cancellation)."""
    from needle_helpers import assert_needles_accurate

    for model in ("parallel", "cone"):
        assert_needles_accurate("triton", model, device=device)


GROUPS = {
    "raster-parallel": lambda: check_raster("parallel"),
    "raster-cone": lambda: check_raster("cone"),
    "raster-edges": check_raster_edges,
    "needles": check_needles,
    "voxelize": check_voxelize,
    "train": check_train,
    "host-reads": check_host_reads,
    "compile": check_compile,
}


# ------------------------------------------------------------------------------------------------ interpreter
@pytest.mark.skipif(not HAS_TRITON, reason="triton is not installed (the 'gpu' extra)")
@pytest.mark.parametrize("group", sorted(set(GROUPS) - {"compile"}))
def test_interpreter_matches_reference(group):
    env = {**os.environ, "TRITON_INTERPRET": "1", "PYTHONPATH": os.pathsep.join(
        p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)}
    proc = subprocess.run([sys.executable, __file__, group], env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-6000:]
    assert f"ok {group}" in proc.stdout


@pytest.mark.skipif(not HAS_TRITON, reason="triton is not installed (the 'gpu' extra)")
def test_kernels_compile_for_cuda_gpus_without_a_gpu():
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
    proc = subprocess.run([sys.executable, __file__, "compile"], env=env, capture_output=True, text=True, timeout=600)
    if proc.returncode != 0 and ("ImportError" in proc.stderr or "ModuleNotFoundError" in proc.stderr):
        pytest.skip(f"this triton has no ahead-of-time compile API: {proc.stderr.strip().splitlines()[-1]}")
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-6000:]
    assert "ok compile" in proc.stdout


def test_interpreter_flag_does_not_leak_into_this_process():
    assert os.environ.get("TRITON_INTERPRET") != "1"
    from ctsplat.splat import _triton

    assert _triton._kernels is None or not _triton._kernels.INTERPRETED


# ------------------------------------------------------------------------------------------------ dispatch / errors
def test_triton_on_cpu_without_interpreter_is_a_one_line_error(monkeypatch):
    from ctsplat.geometry import ParallelCamera
    from ctsplat.splat import _triton
    from ctsplat.splat.render import render, voxelize
    from ctsplat.utils import CtsplatError

    monkeypatch.delenv("TRITON_INTERPRET", raising=False)
    monkeypatch.setattr(_triton, "_kernels", None)
    g = _scene(5, 0, F32, "cpu")
    R, t = _pose(0.0, 0.0, 200.0, F32, "cpu")
    for call in (lambda: render(g, ParallelCamera(8, 8, 1.0), R, t, backend="triton"),
                 lambda: voxelize(g, (8, 8, 8), torch.eye(4), backend="triton")):
        with pytest.raises(CtsplatError) as exc:
            call()
        msg = str(exc.value)
        assert "\n" not in msg
        assert ("TRITON_INTERPRET=1" in msg) if HAS_TRITON else ("ctsplat[gpu]" in msg)


def test_triton_missing_is_a_one_line_error_naming_the_extra(monkeypatch):
    from ctsplat.geometry import ParallelCamera
    from ctsplat.splat.render import render
    from ctsplat.utils import CtsplatError

    monkeypatch.setitem(sys.modules, "triton", None)  # find_spec -> None: as if not installed
    g = _scene(5, 0, F32, "cpu")
    R, t = _pose(0.0, 0.0, 200.0, F32, "cpu")
    with pytest.raises(CtsplatError, match=r"triton is not installed.*pip install 'ctsplat\[gpu\]'"):
        render(g, ParallelCamera(8, 8, 1.0), R, t, backend="triton")


def test_auto_on_cuda_without_triton_falls_back_with_one_warning(monkeypatch, caplog):
    render_mod = importlib.import_module("ctsplat.splat.render")  # the module, not the function of that name
    monkeypatch.setitem(sys.modules, "triton", None)
    monkeypatch.setattr(render_mod, "_triton_fallback_logged", False)
    cuda = torch.device("cuda")
    with caplog.at_level(logging.WARNING, logger="ctsplat.splat.render"):
        assert render_mod._use_triton("auto", cuda) is False
        assert render_mod._use_triton("auto", cuda) is False
    warnings = [r for r in caplog.records if "ctsplat[gpu]" in r.getMessage()]
    assert len(warnings) == 1
    assert render_mod.resolved_backend("auto", cuda) == "reference"
    # CPU tensors keep the C++ kernel / reference under auto, whatever triton's state
    assert render_mod._use_triton("auto", torch.device("cpu")) is False


def test_resolved_backend_names_what_runs(monkeypatch):
    from ctsplat.splat import _kernel
    from ctsplat.splat.render import resolved_backend
    from ctsplat.utils import CtsplatError

    assert resolved_backend("reference", "cpu") == "reference"
    assert resolved_backend("kernel", "cpu") == "kernel"
    monkeypatch.setattr(_kernel, "available", lambda: True)
    assert resolved_backend("auto", "cpu") == "kernel"
    monkeypatch.setattr(_kernel, "available", lambda: False)
    assert resolved_backend("auto", "cpu") == "reference"
    with pytest.raises(CtsplatError, match="expected auto, reference, kernel or triton"):
        resolved_backend("cuda", "cpu")


def test_unknown_backend_names_the_choices():
    from ctsplat.geometry import ParallelCamera
    from ctsplat.splat.render import render
    from ctsplat.utils import CtsplatError

    g = _scene(3, 0, F32, "cpu")
    R, t = _pose(0.0, 0.0, 200.0, F32, "cpu")
    with pytest.raises(CtsplatError, match="auto, reference, kernel or triton"):
        render(g, ParallelCamera(8, 8, 1.0), R, t, backend="cuda")


# ------------------------------------------------------------------------------------------------ on a GPU
@pytest.mark.skipif(not (HAS_TRITON and torch.cuda.is_available()), reason="needs CUDA and triton")
class TestCuda:
    """The same checks, compiled for the GPU (tolerances as in the interpreter)."""

    def test_raster_parallel(self):
        check_raster("parallel", "cuda")

    def test_raster_cone(self):
        check_raster("cone", "cuda")

    def test_raster_edges(self):
        check_raster_edges("cuda")

    def test_needles(self):
        check_needles("cuda")

    def test_voxelize(self):
        check_voxelize("cuda")

    def test_train(self):
        check_train("cuda")

    def test_auto_picks_triton_on_cuda(self, monkeypatch):
        from ctsplat.splat import _triton
        render_mod = importlib.import_module("ctsplat.splat.render")
        calls = []
        orig = _triton.SplatAdditive.apply
        monkeypatch.setattr(_triton.SplatAdditive, "apply", lambda *a: calls.append(1) or orig(*a))
        from ctsplat.geometry import ParallelCamera

        g = _scene(10, 0, F32, "cuda")
        R, t = _pose(0.0, 0.0, 200.0, F32, "cuda")
        render_mod.render(g, ParallelCamera(16, 16, 1.0), R, t)
        assert calls
        assert render_mod.resolved_backend("auto", "cuda") == "triton"


if __name__ == "__main__":  # a check group in a child process (TRITON_INTERPRET=1 set by the parent, but for compile)
    assert (os.environ.get("TRITON_INTERPRET") == "1") == (sys.argv[1] != "compile"), "run through pytest"
    GROUPS[sys.argv[1]]()
    print(f"ok {sys.argv[1]}")
