"""Quality metrics (paper §4: PSNR on values in [0, 1])."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from diffshadow.transfer import FOREGROUND_ALPHA  # a pixel is foreground where the reference's opacity shows


def psnr(pred: torch.Tensor, target: torch.Tensor, *, dim: int | tuple[int, ...] | None = None,
         data_range: float = 1.0) -> torch.Tensor:
    """10·log10(range² / MSE), over all values or along `dim`; a perfect match gives +inf."""
    mse = ((pred.double() - target.double()) ** 2).mean(dim=dim) if dim is not None else \
        ((pred.double() - target.double()) ** 2).mean()
    return 10.0 * torch.log10(data_range**2 / mse)


# --------------------------------------------------------------------------------------- image metrics

def foreground(alpha: torch.Tensor, threshold: float = FOREGROUND_ALPHA) -> torch.Tensor:
    """(H, W) bool: the pixels the reference image covers."""
    return alpha >= threshold


def image_psnr(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """PSNR of (H, W, 3) images in [0, 1] over the `mask` pixels (all when None)."""
    if pred.shape != target.shape:
        raise ValueError(f"image_psnr: shapes differ, {tuple(pred.shape)} vs {tuple(target.shape)}")
    if mask is not None:
        if not bool(mask.any()):
            raise ValueError("image_psnr: the foreground mask is empty (the reference image shows nothing)")
        pred, target = pred[mask], target[mask]
    return float(psnr(pred, target))


# The standard window of SSIM and MS-SSIM (Wang et al. 2003, 2004): Gaussian, sigma 1.5, 11 pixels wide
SSIM_SIGMA = 1.5
MS_SSIM_WINDOW = 11
MS_SSIM_MIN_SIDE = (MS_SSIM_WINDOW - 1) * 2**4 + 1  # 5 scales: the window must fit the coarsest (161 px)


def ssim(pred: torch.Tensor, target: torch.Tensor) -> float:
    """SSIM of (H, W, 3) images in [0, 1] with the standard window (Gaussian, sigma 1.5; scikit-image's
    settings that match Wang et al.)."""
    from skimage.metrics import structural_similarity

    a, b = (np.asarray(x.detach().cpu().double()) for x in (pred, target))
    if min(a.shape[:2]) < MS_SSIM_WINDOW:
        raise ValueError(f"ssim: images of {a.shape[:2]} pixels are smaller than the {MS_SSIM_WINDOW}-pixel window")
    return float(structural_similarity(a, b, channel_axis=-1, data_range=1.0, gaussian_weights=True,
                                       sigma=SSIM_SIGMA, use_sample_covariance=False))


def ms_ssim(pred: torch.Tensor, target: torch.Tensor) -> float | None:
    """MS-SSIM as published (pytorch-msssim: 5 scales, the standard 11-pixel window and weights, data range
    1); None for images under 161 pixels, where the window does not fit the coarsest scale. A shrunk window
    would give numbers that are not comparable with published MS-SSIM."""
    from pytorch_msssim import ms_ssim as _ms_ssim

    if min(pred.shape[:2]) < MS_SSIM_MIN_SIDE:
        return None
    a, b = (x.detach().cpu().float().permute(2, 0, 1)[None] for x in (pred, target))
    return float(_ms_ssim(a, b, data_range=1.0, win_size=MS_SSIM_WINDOW))


def ms_ssim_status(side: int) -> str:
    """Whether images `side` pixels wide get an MS-SSIM, in words for the metrics file."""
    if side >= MS_SSIM_MIN_SIDE:
        return "standard (5 scales, 11-pixel Gaussian window)"
    return f"not computed: {side}-pixel images are below the {MS_SSIM_MIN_SIDE} pixels that 5 scales of the " \
           "standard window need"


def lpips_model() -> tuple[torch.nn.Module | None, str | None]:
    """(model, None) when LPIPS with VGG weights can be built from files on this machine, else
    (None, reason). Never downloads: these machines are offline, and a fake score would be worse than none."""
    try:
        import lpips  # noqa: F401
    except ImportError:
        return None, "the lpips package is not installed"
    hub = Path(torch.hub.get_dir()) / "checkpoints"
    if not any(hub.glob("vgg16-*.pth")):
        return None, f"no VGG16 weights in {hub} (LPIPS needs them; this machine cannot download)"
    import lpips

    return lpips.LPIPS(net="vgg", verbose=False), None


def image_metrics(pred: torch.Tensor, target: torch.Tensor, target_alpha: torch.Tensor,
                  lpips: torch.nn.Module | None = None) -> dict:
    """Foreground PSNR, SSIM, MS-SSIM (and LPIPS when a model is given) of one image against a reference, on the
    reference's device (a stored image, e.g. a naive one read back, is on the CPU)."""
    pred = pred.to(target.device)
    out = {"psnr": image_psnr(pred, target, foreground(target_alpha)), "ssim": ssim(pred, target),
           "ms_ssim": ms_ssim(pred, target)}
    if lpips is not None:
        a, b = (x.detach().cpu().float().permute(2, 0, 1)[None] * 2 - 1 for x in (pred, target))
        with torch.no_grad():
            out["lpips"] = float(lpips(a, b))
    return out
