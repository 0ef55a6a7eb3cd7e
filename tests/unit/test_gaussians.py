"""Gaussian container: activations, covariances, SH basis, .pt round trip, 3DGS PLY export, validation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from ctsplat.formats.ply import read_ply_vertices
from ctsplat.splat.gaussians import SH_C0, Gaussians, eval_sh, inverse_softplus, quat_to_rotmat
from ctsplat.utils import CtsplatError

# the vertex properties a standard 3DGS viewer reads (for SH degree 3), in the reference implementation's order
STANDARD_3DGS = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    + [f"f_rest_{i}" for i in range(45)]
    + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
)


def _random(n: int = 7, seed: int = 0, **kw) -> Gaussians:
    rng = np.random.default_rng(seed)
    return Gaussians.from_values(
        rng.normal(size=(n, 3)) * 10, rng.uniform(0.5, 3, size=(n, 3)), rng.uniform(0.1, 2, size=n),
        rng.normal(size=(n, 4)), opacities=rng.uniform(0.05, 0.95, size=n), **kw,
    )


def test_activations_round_trip_values():
    means = torch.tensor([[1.0, 2, 3], [-4, 5, 6]])
    g = Gaussians.from_values(means, [[1.0, 2, 3], [0.5, 0.5, 4]], [0.3, 7.0], opacities=[0.2, 0.9],
                              dtype=torch.float64)
    torch.testing.assert_close(g.scales, torch.tensor([[1.0, 2, 3], [0.5, 0.5, 4]], dtype=torch.float64))
    torch.testing.assert_close(g.densities, torch.tensor([0.3, 7.0], dtype=torch.float64))
    torch.testing.assert_close(g.opacities, torch.tensor([0.2, 0.9], dtype=torch.float64))
    torch.testing.assert_close(torch.nn.functional.softplus(inverse_softplus(torch.tensor([1e-4, 30.0]))),
                               torch.tensor([1e-4, 30.0]))
    # mass = ρ (2π)^{3/2} s_x s_y s_z
    assert float(g.masses()[0]) == pytest.approx(0.3 * (2 * math.pi) ** 1.5 * 6.0)
    with pytest.raises(CtsplatError, match="scales"):
        Gaussians.from_values(means, 0.0, 1.0)
    with pytest.raises(CtsplatError, match="densities"):
        Gaussians.from_values(means, 1.0, -1.0)


def test_rotation_and_covariance_match_scipy():
    q = Rotation.random(5, random_state=3)
    xyzw = q.as_quat()
    wxyz = torch.tensor(xyzw[:, [3, 0, 1, 2]]) * 2.5  # unnormalised on purpose
    np.testing.assert_allclose(quat_to_rotmat(wxyz).numpy(), q.as_matrix(), atol=1e-12)
    g = Gaussians.from_values(torch.zeros(5, 3), [[1.0, 2.0, 3.0]] * 5, 1.0, wxyz, dtype=torch.float64)
    ref = q.as_matrix() @ np.diag([1.0, 4.0, 9.0]) @ q.as_matrix().transpose(0, 2, 1)
    np.testing.assert_allclose(g.covariances.numpy(), ref, atol=1e-12)


def test_sh_basis_is_orthonormal_on_the_sphere():
    """∫ Y_i Y_j dΩ = δ_ij for the degree-0..3 basis used by eval_sh (independent check of all constants)."""
    n = 20_000  # Fibonacci sphere: quadrature error ~4e-6 for these degree <= 6 products
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z * z)
    d = torch.tensor(np.stack([r * np.cos(phi), r * np.sin(phi), z], -1))
    # coefficient k of channel k = 1 -> channel k returns Y_k
    rest = eval_sh(torch.eye(15, dtype=torch.float64).expand(n, 15, 15), d)
    B = torch.cat([torch.full((n, 1), SH_C0, dtype=torch.float64), rest], -1)
    gram = (B.T @ B) * (4 * math.pi / n)
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=1e-4, rtol=0)


def test_sh_basis_signs_follow_3dgs_from_scipy_spherical_harmonics():
    """Each basis function, sign included, against scipy's complex Y_l^m (Condon–Shortley phase): 3DGS's real basis
    at index l² + l + m is √2 Im Y_l^|m| for m < 0, Y_l^0, √2 Re Y_l^m for m > 0 (the phase kept, so -C1 y, C1 z,
    -C1 x at degree 1). Orthonormality alone cannot see a flipped sign; a PLY read by 3DGS viewers would."""
    from scipy.special import sph_harm_y

    rng = np.random.default_rng(4)
    d = rng.normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    polar, azimuth = np.arccos(d[:, 2]), np.arctan2(d[:, 1], d[:, 0])
    want = []
    for degree in (1, 2, 3):
        for m in range(-degree, degree + 1):
            y = sph_harm_y(degree, abs(m), polar, azimuth)
            want.append(math.sqrt(2) * (y.imag if m < 0 else y.real) if m else y.real)
    rest = eval_sh(torch.eye(15, dtype=torch.float64).expand(50, 15, 15), torch.tensor(d))
    np.testing.assert_allclose(rest.numpy(), np.stack(want, -1), atol=1e-12)
    np.testing.assert_allclose(SH_C0, sph_harm_y(0, 0, 0.0, 0.0).real, rtol=1e-12)


def test_save_load_round_trip(tmp_path):
    g = _random(sh_degree=2, colors=np.random.default_rng(1).uniform(size=(7, 3)))
    g.meta["step"] = 12
    g.sh_rest.normal_()
    path = tmp_path / "model.pt"
    g.save(path)
    h = Gaussians.load(path)
    for name, t in g.tensors().items():
        assert torch.equal(t, getattr(h, name)), name
    assert h.meta == {"step": 12} and h.sh_degree == 2
    g.save(tmp_path / "again.pt")  # the same model, the same bytes (no temporary name inside the archive)
    assert (tmp_path / "again.pt").read_bytes() == path.read_bytes()
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CtsplatError, match=r"junk\.pt \(.*\): it is not a \.pt model written by ctsplat") as err:
        Gaussians.load(tmp_path / "junk.pt")
    assert "weights_only" not in str(err.value)  # torch's advice to load untrusted files unsafely is not passed on
    with pytest.raises(CtsplatError, match="not found"):
        Gaussians.load(tmp_path / "missing.pt")
    base = torch.load(path, weights_only=True)
    for odd, needle in (({**base, "tensors": {**base["tensors"], "features_extra": torch.zeros(7)}},
                         "holds 'features_extra', which is not a Gaussian parameter tensor"),
                        ({**base, "meta": [1, 2]}, "tensors and meta must be mappings"),
                        ({**base, "tensors": {**base["tensors"], "sh_rest": torch.zeros(7, 3)}},
                         r"sh_rest has shape \(7, 3\), expected \(N, K, C\)")):
        torch.save(odd, tmp_path / "odd.pt")
        with pytest.raises(CtsplatError, match=needle):
            Gaussians.load(tmp_path / "odd.pt")


def test_ply_has_3dgs_layout_and_values(tmp_path):
    g = _random(sh_degree=3, colors=np.random.default_rng(2).uniform(size=(7, 1)))
    g.sh_rest.normal_()
    path = tmp_path / "model.ply"
    g.to_ply(path)
    header = path.read_bytes().split(b"end_header\n")[0].decode()
    props = [ln.split()[-1] for ln in header.splitlines() if ln.startswith("property")]
    assert props == STANDARD_3DGS + ["density"]
    assert "binary_little_endian" in header and "element vertex 7" in header
    # raw numpy read of the body (independent of read_ply_vertices)
    body = path.read_bytes()[len(header) + len("end_header\n"):]
    arr = np.frombuffer(body, dtype=np.float32).reshape(7, len(props))
    col = dict(zip(props, arr.T, strict=True))
    np.testing.assert_allclose(np.stack([col["x"], col["y"], col["z"]], -1), g.means.numpy(), rtol=1e-6)
    np.testing.assert_allclose(np.exp(np.stack([col[f"scale_{i}"] for i in range(3)], -1)), g.scales.numpy(),
                               rtol=1e-5)
    q = np.stack([col[f"rot_{i}"] for i in range(4)], -1)
    np.testing.assert_allclose(q, (g.quats / g.quats.norm(dim=-1, keepdim=True)).numpy(), atol=1e-6)
    np.testing.assert_allclose(1 / (1 + np.exp(-col["opacity"])), g.opacities.numpy(), rtol=1e-5)
    np.testing.assert_allclose(col["density"], g.densities.numpy(), rtol=1e-6)
    grey = g.colors.numpy()[:, 0]
    for c in range(3):
        np.testing.assert_allclose(SH_C0 * col[f"f_dc_{c}"] + 0.5, grey, atol=1e-6)
    # f_rest is channel-major: f_rest_{c*15 + k} = sh_rest[:, k, c]
    np.testing.assert_allclose(col["f_rest_16"], g.sh_rest[:, 1, 0].numpy(), rtol=1e-6)
    assert read_ply_vertices(path)["density"].shape == (7,)
    assert "comment ctsplat Gaussians (3DGS layout + radiative density)" in header
    # an alpha-compositing model renders no density: the plain 3DGS layout, every other column the same
    g.to_ply(tmp_path / "alpha.ply", density=False)
    alpha_header = (tmp_path / "alpha.ply").read_bytes().split(b"end_header\n")[0].decode()
    assert [ln.split()[-1] for ln in alpha_header.splitlines() if ln.startswith("property")] == STANDARD_3DGS
    assert "radiative" not in alpha_header
    alpha = read_ply_vertices(tmp_path / "alpha.ply")
    for name in STANDARD_3DGS:
        np.testing.assert_array_equal(alpha[name], col[name])


def test_ply_of_a_density_only_model(tmp_path):
    g = Gaussians.from_values(np.zeros((3, 3)), 1.0, [0.5, 1.0, 2.0])
    g.to_ply(tmp_path / "m.ply")
    p = read_ply_vertices(tmp_path / "m.ply")
    assert [k for k in p if k.startswith("f_rest")] == []
    np.testing.assert_allclose(SH_C0 * p["f_dc_0"] + 0.5, [0.25, 0.5, 1.0], atol=1e-6)
    assert np.all(np.isfinite(p["opacity"]))


@pytest.mark.parametrize("name", ["means", "log_scales", "quats", "density_raw", "opacity_raw"])
def test_validate_names_the_bad_parameter(name):
    g = _random()
    t = getattr(g, name).clone()
    t.view(-1)[-1] = float("inf")
    setattr(g, name, t)
    with pytest.raises(CtsplatError, match=f"Gaussians.{name} contains NaN/Inf"):
        g.validate()


def test_subset_and_to():
    g = _random()
    h = g[torch.tensor([0, 3])].to(dtype=torch.float64)
    assert len(h) == 2 and h.means.dtype == torch.float64
    torch.testing.assert_close(h.means.float(), g.means[[0, 3]])


def test_from_values_takes_one_scale_per_gaussian_and_names_a_shape_that_does_not_fit():
    g = Gaussians.from_values(np.zeros((3, 3)), np.array([1.0, 2.0, 3.0]), 1.0)  # (N,) with N = 3: per Gaussian
    np.testing.assert_allclose(torch.exp(g.log_scales).numpy(), [[1.0] * 3, [2.0] * 3, [3.0] * 3], rtol=1e-6)
    for kw, msg in ((dict(densities=np.ones(2)), r"densities of shape \(2,\) does not fit 3 Gaussians \(expected "
                                                  r"\(3,\)\)"),
                    (dict(densities=1.0, quats=np.ones((2, 4))), r"quats of shape \(2, 4\) does not fit 3 Gaussians"),
                    (dict(densities=1.0, scales_mm=np.ones((3, 2))), r"scales_mm of shape \(3, 2\)")):
        with pytest.raises(CtsplatError, match=msg):
            Gaussians.from_values(np.zeros((3, 3)), **{"scales_mm": 1.0, **kw})


def test_ply_refuses_colours_it_cannot_store(tmp_path):
    g = Gaussians.from_values(np.zeros((2, 3)), 1.0, 1.0, colors=np.full((2, 2), 0.5))
    with pytest.raises(CtsplatError, match=r"to_ply: colours of 2 channels; 3DGS PLY stores grey \(1\) or RGB \(3\)"):
        g.to_ply(tmp_path / "g.ply")
    assert not (tmp_path / "g.ply").exists()


def _from_ply(path) -> Gaussians:
    """A model rebuilt from a PLY's columns alone (what a viewer reads)."""
    p = read_ply_vertices(path)
    col = lambda names: torch.tensor(np.stack([p[k] for k in names], -1), dtype=torch.float64)  # noqa: E731
    n_rest = len([k for k in p if k.startswith("f_rest_")])
    sh = col([f"f_rest_{i}" for i in range(n_rest)]).reshape(-1, 3, n_rest // 3).transpose(1, 2) if n_rest else None
    return Gaussians(means=col("xyz"), log_scales=col(["scale_0", "scale_1", "scale_2"]),
                     quats=col(["rot_0", "rot_1", "rot_2", "rot_3"]),
                     density_raw=inverse_softplus(torch.tensor(p["density"], dtype=torch.float64)),
                     opacity_raw=torch.tensor(p["opacity"], dtype=torch.float64),
                     colors=SH_C0 * col(["f_dc_0", "f_dc_1", "f_dc_2"]) + 0.5, sh_rest=sh)


@pytest.mark.parametrize("compositor", ["radiative", "alpha"])
def test_ply_of_a_mip_model_renders_what_the_model_renders(tmp_path, compositor):
    """A viewer has no 3D filter: the PLY carries it fused in, so the PLY's Gaussians alone give the model's
    filtered images (Mip-Splatting's export) and its volume; the header's third line is the vertex count (SIBR)."""
    from ctsplat.geometry import ConeCamera, pose_from_angles
    from ctsplat.splat.render import render, voxelize

    rng = np.random.default_rng(4)
    n = 40
    g = Gaussians.from_values(rng.normal(size=(n, 3)) * 8, rng.uniform(0.3, 4, size=(n, 3)), rng.uniform(0.1, 2, n),
                              rng.normal(size=(n, 4)), opacities=rng.uniform(0.05, 0.95, n),
                              colors=rng.uniform(size=(n, 3)), sh_degree=1, dtype=torch.float64)
    g.sh_rest.normal_(0, 0.2)
    g.filter_3d_var = torch.tensor(rng.uniform(0.5, 4.0, n), dtype=torch.float64)
    g.meta.update({"mip": True, "compositor": compositor, "mu_scale_per_mm": 0.0475})
    g.to_ply(tmp_path / "m.ply", density=True)
    lines = (tmp_path / "m.ply").read_bytes().split(b"end_header\n")[0].decode().splitlines()
    assert lines[2] == f"element vertex {n}" and any("3D filter fused in" in ln for ln in lines)
    assert any("x mu_scale_per_mm 0.0475 = attenuation in 1/mm" in ln for ln in lines)
    h = _from_ply(tmp_path / "m.ply")
    cam = ConeCamera(48, 40, 1.0, 120.0, 180.0)
    R, t = pose_from_angles(30.0, 10.0, [0.0, 0.0, 0.0], 120.0)
    kw = {"compositor": compositor, "backend": "reference", "mip_2d": True}
    want = render(g, cam, R, t, filter_3d_var=g.filter_3d_var, **kw).image
    got = render(h, cam, R, t, **kw).image
    assert float(want.abs().max()) > 0.05
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6 * float(want.abs().max()))
    affine = np.diag([2.0, 2.0, 2.0, 1.0])
    affine[:3, 3] = -24.0
    vol = voxelize(g, (24, 24, 24), affine, filter_3d_var=g.filter_3d_var, backend="reference")
    torch.testing.assert_close(voxelize(h, (24, 24, 24), affine, backend="reference"), vol, rtol=1e-5,
                               atol=1e-6 * float(vol.max()))
    # without the filter the model renders differently: the check above could fail
    assert not torch.allclose(render(g, cam, R, t, **kw).image, want, rtol=1e-3)
