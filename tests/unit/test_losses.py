"""Losses: SSIM against scikit-image, TV against a NumPy reference, gradients by gradcheck."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from ctsplat.training import losses


@pytest.fixture(params=["band", "conv"])
def blur_path(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Both ways the SSIM blurs: products with banded matrices, and conv2d (images longer than BAND_MAX_PX)."""
    if request.param == "conv":
        monkeypatch.setattr(losses, "BAND_MAX_PX", 0)
    return request.param


def test_band_matrix_is_numpy_valid_correlation() -> None:
    rng = np.random.default_rng(5)
    w = torch.from_numpy(rng.random(5))
    x = rng.random(13)
    got = (losses.band_matrix(13, w) @ torch.from_numpy(x)).numpy()
    np.testing.assert_allclose(got, np.correlate(x, w.numpy(), mode="valid"), rtol=1e-14)
    assert losses.band_matrix(13, w).shape == (9, 13)


@pytest.mark.parametrize("data_range", [1.0, 7.5])
def test_ssim_matches_skimage_gaussian(data_range: float, blur_path: str) -> None:
    rng = np.random.default_rng(0)
    a = rng.random((24, 31)) * data_range
    b = np.clip(a + rng.normal(0, 0.1 * data_range, a.shape), 0, None)
    ref = structural_similarity(
        b, a, data_range=data_range, gaussian_weights=True, sigma=1.5, use_sample_covariance=False
    )
    got = losses.ssim(torch.from_numpy(b), torch.from_numpy(a), data_range)
    assert float(got) == pytest.approx(ref, abs=1e-10)


def test_ssim_batch_is_mean_of_images_and_identity_is_one(blur_path: str) -> None:
    rng = np.random.default_rng(1)
    a = torch.from_numpy(rng.random((3, 16, 16)))
    b = torch.from_numpy(rng.random((3, 16, 16)))
    each = [float(losses.ssim(b[i], a[i])) for i in range(3)]
    assert float(losses.ssim(b, a)) == pytest.approx(np.mean(each), abs=1e-12)
    assert float(losses.ssim(a, a)) == pytest.approx(1.0, abs=1e-12)


def test_ssim_too_small_image_fails() -> None:
    with pytest.raises(ValueError, match="smaller than"):
        losses.ssim(torch.zeros(8, 8), torch.zeros(8, 8))


def test_ssim_gradcheck(blur_path: str) -> None:
    rng = np.random.default_rng(2)
    a = torch.from_numpy(rng.random((12, 13)))
    b = torch.from_numpy(rng.random((12, 13))).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: losses.ssim(x, a, 1.0), (b,))


def test_tv3d_matches_numpy_and_is_zero_for_constant() -> None:
    rng = np.random.default_rng(3)
    v = rng.random((5, 6, 7))
    ref = sum(np.abs(np.diff(v, axis=a)).mean() for a in range(3))
    assert float(losses.tv3d(torch.from_numpy(v))) == pytest.approx(ref, rel=1e-12)
    assert float(losses.tv3d(torch.full((4, 4, 4), 3.0))) == 0.0
    with pytest.raises(ValueError):
        losses.tv3d(torch.zeros(1, 4, 4))


def test_total_loss_weights_terms() -> None:
    rng = np.random.default_rng(4)
    ref = torch.from_numpy(rng.random((16, 16)))
    img = ref + 0.05 * torch.from_numpy(rng.standard_normal((16, 16)))
    rho = torch.tensor([0.5, 1.5])
    s = torch.tensor([[3.0, 4.0, 0.0], [0.0, 0.0, 1.0]])
    tv_vol = torch.from_numpy(rng.random((4, 4, 4)))
    loss, terms = losses.total_loss(
        img, ref, density=rho, scales=s, lambda_l1=2.0, lambda_ssim=0.5, lambda_density=0.1,
        lambda_scale=0.01, lambda_tv=0.3, tv_volume=tv_vol,
    )
    assert all(t.ndim == 0 and not t.requires_grad for t in terms.values())
    terms = {k: float(v) for k, v in terms.items()}
    assert terms["density"] == pytest.approx(1.0)
    assert terms["scale"] == pytest.approx(3.0)  # (5 + 1) / 2
    assert terms["l1"] == pytest.approx(float((img - ref).abs().mean()))
    assert terms["dssim"] == pytest.approx(1 - float(losses.ssim(img, ref)))
    assert terms["tv"] == pytest.approx(float(losses.tv3d(tv_vol)))
    expect = 2 * terms["l1"] + 0.5 * terms["dssim"] + 0.1 * 1.0 + 0.01 * 3.0 + 0.3 * terms["tv"]
    assert float(loss) == pytest.approx(expect, rel=1e-6)
    with pytest.raises(ValueError, match="tv_volume"):
        losses.total_loss(img, ref, density=rho, scales=s, lambda_tv=1.0)
