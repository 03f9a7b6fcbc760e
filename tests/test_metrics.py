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
    img = torch.rand(176, 176, 3, generator=torch.Generator().manual_seed(0))
    m = image_metrics(img, img, torch.ones(176, 176))
    assert m["psnr"] == math.inf and m["ssim"] == pytest.approx(1.0) and m["ms_ssim"] == pytest.approx(1.0)
    noisy = (img + 0.05 * torch.randn(176, 176, 3, generator=torch.Generator().manual_seed(1))).clamp(0, 1)
    assert ssim(noisy, img) < 0.99 and ms_ssim(noisy, img) < 0.999


def test_ssim_uses_the_standard_window():
    # two implementations of Wang et al.'s SSIM (Gaussian window, sigma 1.5) agree; a 7-pixel uniform
    # window (scikit-image's default) gives 0.9463 here, not 0.9454
    from pytorch_msssim import ssim as reference

    g = torch.Generator().manual_seed(0)
    img = torch.rand(64, 64, 3, generator=g)
    noisy = (img + 0.1 * torch.randn(64, 64, 3, generator=g)).clamp(0, 1)
    expected = float(reference(noisy.permute(2, 0, 1)[None], img.permute(2, 0, 1)[None], data_range=1.0))
    assert ssim(noisy, img) == pytest.approx(expected, abs=1e-6)


def test_ms_ssim_needs_room_for_the_standard_window_at_five_scales():
    # 161 pixels is the smallest side where the 11-pixel window fits the 5th scale; below it, no value
    # (a shrunk window would not be the published MS-SSIM)
    assert ms_ssim(torch.ones(160, 160, 3), torch.ones(160, 160, 3)) is None
    assert ms_ssim(torch.ones(161, 161, 3), torch.ones(161, 161, 3)) == pytest.approx(1.0)


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="shapes differ"):
        image_psnr(torch.zeros(4, 4, 3), torch.zeros(4, 5, 3))
    with pytest.raises(ValueError, match="mask is empty"):
        image_psnr(torch.zeros(4, 4, 3), torch.zeros(4, 4, 3), torch.zeros(4, 4, dtype=torch.bool))


def test_lpips_is_reported_unavailable_not_faked(monkeypatch, tmp_path):
    """Without the package or its weights: no model and a reason naming what is missing, never a made-up score;
    with them: 0 for an image against itself and more for a different one."""
    import sys

    monkeypatch.setitem(sys.modules, "lpips", None)  # as if not installed
    assert lpips_model() == (None, "the lpips package is not installed")
    monkeypatch.undo()
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))  # no weights there
    model, reason = lpips_model()
    if reason != "the lpips package is not installed":
        assert model is None and reason.startswith(f"no VGG16 weights in {tmp_path / 'checkpoints'}")
    monkeypatch.undo()
    model, reason = lpips_model()
    if model is not None:
        a, b = torch.rand(32, 32, 3, generator=torch.Generator().manual_seed(0)), torch.zeros(32, 32, 3)
        alpha = torch.ones(32, 32)
        assert image_metrics(a, a, alpha, model)["lpips"] == pytest.approx(0.0, abs=1e-6)
        assert image_metrics(a, b, alpha, model)["lpips"] > 0.1
