"""The fused kernels' ctypes boundary: every C entry point has declared argument and return types (one table), the
table matches the C++ sources, and calls with a wrong argument count raise instead of reading garbage."""

from __future__ import annotations

import ctypes
import re
import shutil

import pytest
import torch

from ctsplat.splat import _kernel


def _exported_c_names() -> set[str]:
    """``extern "C"`` function names of csrc/render.cpp (``NAME_##SUF`` expanded for the EXPORT instances)."""
    src = (_kernel.CSRC / "render.cpp").read_text()
    names = set(re.findall(r'extern "C" \w+ ([\w#]+)\(', src))
    sufs = re.findall(r"^EXPORT\(\w+, (\w+)\)", src, flags=re.M)
    assert sufs == ["f32", "f64"]
    out = {n for n in names if "##" not in n}
    for n in names - out:
        out |= {n.replace("##SUF", s) for s in sufs}
    return out


def test_signature_table_matches_the_cpp_exports_and_the_python_calls():
    assert _exported_c_names() == set(_kernel.SIGNATURES)
    # every name the Python side looks up (_fn("name"[, dtype])) is in the table, for each dtype it may use
    called = re.findall(r'_fn\("(\w+)"(, [^)]+)?\)', (_kernel.CSRC.parent / "_kernel.py").read_text())
    assert called
    for name, dtype_arg in called:
        wanted = [f"{name}_f32", f"{name}_f64"] if dtype_arg else [name]
        assert all(w in _kernel.SIGNATURES for w in wanted), name
    for name, (argtypes, restype) in _kernel.SIGNATURES.items():
        assert restype is None, name  # all entry points return void
        assert all(t in (ctypes.c_void_p, ctypes.c_int64, ctypes.c_int, ctypes.c_double) for t in argtypes), name


@pytest.fixture(scope="module")
def lib():
    if not any(shutil.which(c) for c in ("c++", "g++", "clang++")):
        pytest.skip("no C++ compiler on PATH")
    if not _kernel.available():
        pytest.skip(f"C kernel unavailable: {_kernel._failed}")
    return _kernel._get_lib()


def test_every_called_function_has_argtypes_and_restype(lib):
    for name, (argtypes, restype) in _kernel.SIGNATURES.items():
        fn = getattr(lib, name)
        assert fn.argtypes is not None and tuple(fn.argtypes) == tuple(argtypes), name
        assert fn.restype is restype, name


def test_wrong_argument_count_raises(lib):
    # too few: ctypes itself refuses once argtypes is set; too many: the checked wrapper refuses
    with pytest.raises(TypeError):
        lib.splat_fwd_f32(1, None, None)
    for name in ("splat_fwd", "proj_fwd", "alpha_bwd", "vox_bwd"):
        fn = _kernel._fn(name, torch.float32)
        n = len(_kernel.SIGNATURES[f"{name}_f32"][0])
        with pytest.raises(TypeError, match="arguments"):
            fn(*[0] * (n - 1))
        with pytest.raises(TypeError, match="arguments"):
            fn(*[0] * (n + 1))
    with pytest.raises(TypeError, match="arguments"):
        _kernel._fn("alpha_lists_c")(0, None)
    # a correct call still works: an empty image from zero Gaussians
    out = torch.full((2, 3), 7.0)
    empty = torch.zeros(0)
    _kernel._fn("splat_fwd", torch.float32)(0, empty.data_ptr(), empty.data_ptr(), empty.data_ptr(), None, 2, 3,
                                             out.data_ptr(), 1)
    assert torch.equal(out, torch.zeros(2, 3))


_POOL_SCRIPT = r"""
import os, sys, threading
import torch
from ctsplat.geometry import ParallelCamera
from ctsplat.splat.gaussians import Gaussians
from ctsplat.splat.render import render

torch.set_num_threads(3)
g = torch.Generator().manual_seed(0)
n = 8000
gs = Gaussians.from_values((torch.rand(n, 3, generator=g) - 0.5) * 60, 0.5 + torch.rand(n, 3, generator=g),
                           0.1 + torch.rand(n, generator=g), torch.randn(n, 4, generator=g))
cam, R, t = ParallelCamera(64, 64, 1.0), torch.eye(3), torch.tensor([0.0, 0.0, 100.0])
ref = render(gs, cam, R, t, backend="kernel").image
# two Python threads in the kernels at once (ctypes releases the GIL): one uses the pool, the other its own threads
out = [None] * 4
def job(k):
    out[k] = render(gs, cam, R, t, backend="kernel").image
threads = [threading.Thread(target=job, args=(k,)) for k in range(4)]
for th in threads: th.start()
for th in threads: th.join()
assert all(torch.equal(o, ref) for o in out)
# a forked child gets a pool of its own (the parent's workers are not copied into it)
pid = os.fork()
if pid == 0:
    ok = torch.equal(render(gs, cam, R, t, backend="kernel").image, ref)
    os._exit(0 if ok else 3)
_, status = os.waitpid(pid, 0)
assert os.waitstatus_to_exitcode(status) == 0, status
assert torch.equal(render(gs, cam, R, t, backend="kernel").image, ref)  # the parent's pool still works
print("pool ok")
"""


def test_worker_pool_serves_concurrent_callers_and_forked_children(lib, tmp_path):
    """The kernels' worker pool: concurrent Python threads and a forked child render the same bits, never hang."""
    import subprocess
    import sys

    script = tmp_path / "pool.py"
    script.write_text(_POOL_SCRIPT)
    res = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=240)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "pool ok" in res.stdout


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_voxel_boxes_match_the_tensor_arithmetic(dtype, monkeypatch):
    """The threaded C boxes and voxelize's PyTorch boxes (used where the kernel is off) give the same boxes, hence
    the same volume through the same reference splat, with and without a 3D filter and a region."""
    import importlib

    if not _kernel.available():
        pytest.skip(f"C kernel unavailable: {_kernel._failed}")
    render_mod = importlib.import_module("ctsplat.splat.render")
    from ctsplat.splat.gaussians import Gaussians

    gen = torch.Generator().manual_seed(4)
    n = 3000
    means = (torch.rand(n, 3, generator=gen, dtype=dtype) - 0.5) * 40
    scales = torch.exp(torch.empty(n, 3, dtype=dtype).uniform_(-1.0, 1.0, generator=gen))
    g = Gaussians.from_values(means, scales, 0.5, torch.randn(n, 4, generator=gen, dtype=dtype))
    A = torch.eye(4, dtype=torch.float64)
    A[:3, :3] = torch.tensor([[1.1, 0.1, 0.0], [0.0, 0.9, 0.05], [0.0, 0.0, 1.3]], dtype=torch.float64)
    A[:3, 3] = -20.0
    fv = torch.rand(n, generator=gen, dtype=dtype)
    for region in (None, ((10, 22), (5, 30), (12, 20))):
        for filt in (None, fv):
            kw = {"region": region, "filter_3d_var": filt, "backend": "reference"}
            with_c = render_mod.voxelize(g, (32, 40, 28), A, **kw)
            monkeypatch.setattr(_kernel, "available", lambda: False)
            with_torch = render_mod.voxelize(g, (32, 40, 28), A, **kw)
            monkeypatch.undo()
            assert float(with_torch.abs().max()) > 0.1
            assert torch.equal(with_c, with_torch), (region, filt is None)
    lo, ext = _kernel.voxel_boxes(g.means, g.log_scales, g.quats, None, torch.linalg.inv(A[:3, :3]).to(dtype),
                                  A[:3, 3], torch.tensor([[0, 32], [0, 40], [0, 28]]), 3.0)
    assert lo.shape == ext.shape == (n, 3) and bool((ext >= 0).all()) and bool((lo >= 0).all())
    assert bool(((lo + ext) <= torch.tensor([32, 40, 28])).all()) and bool((ext.prod(-1) == 0).any())


def test_loading_the_kernel_keeps_subnormal_numbers_in_the_process():
    """The library is compiled with -ffast-math but linked without it: GCC would otherwise link crtfastmath.o,
    whose constructor turns on flush-to-zero for the whole process on load (numpy and torch then round subnormals
    to 0, and a reference-path gradient could turn NaN depending on what ran before)."""
    import numpy as np
    import torch

    from ctsplat.splat import _kernel

    if not _kernel.available():
        pytest.skip(f"C kernel unavailable: {_kernel._failed}")
    tiny = 1e-310  # a float64 subnormal
    assert tiny * 1.0 == tiny and np.float64(tiny) * 1.0 == tiny
    assert float(torch.tensor([1e-40], dtype=torch.float32)[0] * 1.0) > 0.0  # a float32 subnormal


@pytest.mark.parametrize(("threads", "n", "rows"), [(1, 400, 48), (2, 400, 48), (5, 400, 48), (64, 400, 48),
                                                    (2, 3000, 48), (4, 400, 3), (2, 0, 48)])
def test_alpha_lists_hold_each_pixels_gaussians_in_depth_order(lib, threads, n, rows):
    """The per-pixel lists of the alpha compositor against a NumPy loop over the boxes in depth order: empty and
    one-pixel boxes, boxes on the image edge, enough entries (over 65,536) for the fill to run in row bands, more
    bands than threads (3000 Gaussians), more threads than rows, and no Gaussians at all."""
    import numpy as np

    rng = np.random.default_rng(7)
    h, w = rows, 61
    u0 = rng.integers(0, w, n)
    v0 = rng.integers(0, h, n)
    bb = np.stack([u0, np.minimum(u0 + rng.integers(0, 40, n), w), v0, np.minimum(v0 + rng.integers(0, 40, n), h)], 1)
    if n:
        bb[:5, 1] = bb[:5, 0]  # empty boxes
        bb[5:10, 1] = bb[5:10, 0] + 1
        bb[5:10, 3] = np.minimum(bb[5:10, 2] + 1, h)
        bb[10] = (0, w, 0, h)  # the whole image
    order = rng.permutation(n)
    want: list[list[int]] = [[] for _ in range(h * w)]
    for i in order:
        for v in range(bb[i, 2], bb[i, 3]):
            for u in range(bb[i, 0], bb[i, 1]):
                want[v * w + u].append(int(i))
    total = sum(map(len, want))
    if n and rows > 3:
        assert total > 65536
    offsets = torch.empty(h * w + 1, dtype=torch.int64)
    ids = torch.empty(max(total, 1), dtype=torch.int32)
    b = torch.from_numpy(np.ascontiguousarray(bb.reshape(-1, 4), dtype=np.int64))
    o = torch.from_numpy(order.astype(np.int64))
    _kernel._fn("alpha_lists_c")(n, o.data_ptr(), b.data_ptr(), h, w, offsets.data_ptr(), ids.data_ptr(), threads)
    assert offsets.tolist() == np.concatenate([[0], np.cumsum([len(x) for x in want])]).tolist()
    assert ids[:total].tolist() == [i for x in want for i in x]
