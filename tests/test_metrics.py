"""Image metrics: analytic PSNR on the foreground, identities, bad input."""

import math

import pytest
import torch

from diffshadow.metrics import foreground, image_metrics, image_psnr, lpips_model, ms_ssim, ssim


def test_foreground_psnr_ignores_the_background():
    target = torch.full((32, 32, 3), 0.5)
    alpha = torch.zeros(32, 32)
    alpha[8:24, 8:24] = 1.0
    pred = target.clone()
    pred[8:24, 8:24] += 0.1  # every foreground value off by 0.1: PSNR = 20 dB exactly
    pred[:4] = 0.0  # background differences do not count
    assert math.isclose(image_psnr(pred, target, foreground(alpha)), 20.0, abs_tol=1e-4)  # float32 0.6 - 0.5
    assert image_psnr(pred, target) < 20.0


def test_identical_images_score_perfectly():
    img = torch.rand(128, 128, 3, generator=torch.Generator().manual_seed(0))
    m = image_metrics(img, img, torch.ones(128, 128))
    assert m["psnr"] == math.inf and m["ssim"] == pytest.approx(1.0) and m["ms_ssim"] == pytest.approx(1.0)
    noisy = (img + 0.05 * torch.randn(128, 128, 3, generator=torch.Generator().manual_seed(1))).clamp(0, 1)
    assert ssim(noisy, img) < 0.99 and ms_ssim(noisy, img) < 0.999


def test_small_images_have_no_ms_ssim():
    img = torch.rand(30, 30, 3)  # the coarsest of 5 scales holds no 3-pixel window
    assert ms_ssim(img, img) is None


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="shapes differ"):
        image_psnr(torch.zeros(4, 4, 3), torch.zeros(4, 5, 3))
    with pytest.raises(ValueError, match="mask is empty"):
        image_psnr(torch.zeros(4, 4, 3), torch.zeros(4, 4, 3), torch.zeros(4, 4, dtype=torch.bool))


def test_lpips_is_reported_unavailable_not_faked():
    model, reason = lpips_model()
    assert (model is None) == (reason is not None)
