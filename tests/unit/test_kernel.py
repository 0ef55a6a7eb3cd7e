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
        assert all(t in (ctypes.c_void_p, ctypes.c_int64, ctypes.c_int) for t in argtypes), name


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


def _big_scene(n: int, dtype: torch.dtype):
    from ctsplat.splat.gaussians import Gaussians

    g = torch.Generator().manual_seed(7)
    means = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * 60.0
    scales = 0.3 + 2.5 * torch.rand(n, 3, generator=g, dtype=torch.float64)
    gs = Gaussians.from_values(means, scales, 0.1 + torch.rand(n, generator=g, dtype=torch.float64),
                               torch.randn(n, 4, generator=g, dtype=torch.float64), dtype=dtype)
    for p in (gs.means, gs.log_scales, gs.quats, gs.density_raw):
        p.requires_grad_(True)
    return gs


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_threaded_kernels_match_the_reference_and_do_not_depend_on_the_thread_count(lib, dtype):
    """Above 4096 Gaussians the kernels run threaded: the forward scatters by bands of image rows / voxel planes
    (each output element adds its Gaussians in index order), the backward by dynamically claimed chunks; so the
    results are bitwise the same at 1, 2 and 3 threads, and match the reference."""
    from ctsplat.geometry import ConeCamera, ParallelCamera, pose_from_angles
    from ctsplat.splat.render import render, voxelize

    gs = _big_scene(6000, dtype)
    params = [gs.means, gs.log_scales, gs.quats, gs.density_raw]
    R, t = pose_from_angles(30.0, 10.0, (0.0, 0.0, 0.0), 200.0)
    R, t = torch.tensor(R, dtype=dtype), torch.tensor(t, dtype=dtype)
    affine = torch.eye(4, dtype=torch.float64)
    affine[:3, :3] *= 1.5
    affine[:3, 3] = -30.0
    w = torch.rand(45, 50, generator=torch.Generator().manual_seed(1), dtype=dtype)
    wv = torch.rand(40, 41, 39, generator=torch.Generator().manual_seed(2), dtype=dtype)

    def run(backend: str, threads: int) -> list[torch.Tensor]:
        old = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            res = []
            for cam in (ParallelCamera(50, 45, 1.4), ConeCamera(50, 45, 2.5, 200.0, 400.0)):
                out = render(gs, cam, R, t, backend=backend)
                res += [out.image.detach(), *torch.autograd.grad((out.image * w).sum(), params)]
            v = voxelize(gs, (40, 41, 39), affine, backend=backend)
            res += [v.detach(), *torch.autograd.grad((v * wv).sum(), params)]
            return res
        finally:
            torch.set_num_threads(old)

    one = run("kernel", 1)
    for k in (2, 3):
        for a, b in zip(one, run("kernel", k), strict=True):
            assert torch.equal(a, b), f"{k} threads differ from 1 thread"
    tol = 1e-9 if dtype == torch.float64 else 2e-4
    for a, b in zip(run("reference", 1), one, strict=True):
        assert float((a - b).abs().max()) <= tol * float(a.abs().max())


def _splat_inputs(n: int) -> list[torch.Tensor]:
    """Projected footprints of a big scene (means2d, conics, amps, bbox) for direct calls of splat_fwd."""
    from ctsplat.geometry import ParallelCamera, pose_from_angles
    from ctsplat.splat.render import project

    R, t = pose_from_angles(30.0, 10.0, (0.0, 0.0, 0.0), 200.0)
    with torch.no_grad():
        p = project(_big_scene(n, torch.float32), ParallelCamera(50, 45, 1.4), R, t)
    return [p.means2d.contiguous(), p.conics.contiguous(), p.amps.contiguous(), p.bbox.contiguous()]


def _splat_direct(ins: list[torch.Tensor], threads: int) -> torch.Tensor:
    """splat_fwd through ctypes only (no torch op runs here: torch's OpenMP is not fork-safe, the kernel must be)."""
    m, c, a, b = ins
    out = torch.empty(45, 50)
    _kernel._fn("splat_fwd", torch.float32)(m.shape[0], m.data_ptr(), c.data_ptr(), a.data_ptr(), b.data_ptr(), 45,
                                            50, out.data_ptr(), threads)
    return out


def _child_splat(ins, conn) -> None:  # noqa: ANN001
    conn.send(_splat_direct(ins, 2).numpy().tobytes())
    conn.close()


def test_worker_pool_serves_concurrent_callers_and_forked_children(lib):
    """The kernels' persistent worker threads: Python threads calling at once (one gets the pool, the others start
    their own threads) and a forked child (the parent's workers do not exist there) all finish, with the same
    result."""
    import multiprocessing as mp
    import threading

    ins = _splat_inputs(6000)
    want = _splat_direct(ins, 1)
    assert float(want.max()) > 0
    assert torch.equal(_splat_direct(ins, 2), want)  # the pool now exists in this process
    results: list[torch.Tensor] = []
    callers = [threading.Thread(target=lambda: results.extend(_splat_direct(ins, 2) for _ in range(20)))
               for _ in range(3)]
    for th in callers:
        th.start()
    for th in callers:
        th.join(timeout=120)
    assert len(results) == 60 and all(torch.equal(r, want) for r in results)
    ctx = mp.get_context("fork")
    recv, send = ctx.Pipe(duplex=False)
    child = ctx.Process(target=_child_splat, args=(ins, send))
    child.start()
    try:
        assert recv.poll(60), "forked child did not finish (waiting on the parent's worker pool?)"
        assert recv.recv() == want.numpy().tobytes()
    finally:
        child.join(timeout=10)
        if child.is_alive():
            child.kill()
    assert child.exitcode == 0
