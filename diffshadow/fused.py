"""A fused SIREN for inference (issue 16): one Triton kernel evaluates a whole SIREN per tile of points,
activations kept on chip, so a layer costs its matrix product and its sines and no trip through GPU memory.

The eager SIREN (`siren._forward`) is the CPU path and the reference: the kernel applies the same
pre-scaled weights (`siren.fold`) in the same order,
the first layer as three fp32 multiply-adds (ω0 = 30 amplifies its rounding) and the hidden layers as
`tl.dot` in `precision` ("ieee": fp32, "tf32": tensor cores). Tests run the kernel on the CPU through
Triton's interpreter (`TRITON_INTERPRET=1`) when Triton is installed.

Opt-in while its speed is unmeasured on a GPU: `DIFFSHADOW_FUSED_SIREN=1` (fp32) or `=tf32`;
`scripts/render_plans.py` compares it with the eager SIREN side by side.
"""

from __future__ import annotations

import functools
import importlib.util
import os

import torch

from diffshadow.siren import RES_WEIGHT, fold


def block_points(width: int) -> int:
    """Points per program: tiles of 64 x 64 activations (a 64-point tile at width 64), to keep them on chip."""
    return max(16, min(128, 4096 // width))


class FusedSirenError(RuntimeError):
    pass


def fused_setting() -> str | None:
    """DIFFSHADOW_FUSED_SIREN: unset or "0" → None (eager), "1" or "ieee" → "ieee", "tf32" → "tf32"."""
    value = os.environ.get("DIFFSHADOW_FUSED_SIREN", "0").strip().lower()
    if value in ("", "0"):
        return None
    if value in ("1", "ieee"):
        return "ieee"
    if value == "tf32":
        return "tf32"
    raise FusedSirenError(f"DIFFSHADOW_FUSED_SIREN: expected 0, 1, ieee or tf32, got {value!r}")


def available(device: torch.device) -> bool:
    """Whether the kernel can run on `device`: CUDA with Triton, or Triton's interpreter on the CPU."""
    if importlib.util.find_spec("triton") is None:  # Triton ships with CUDA builds of PyTorch, not CPU ones
        return False
    return device.type == "cuda" or (device.type == "cpu" and os.environ.get("TRITON_INTERPRET") == "1")


@functools.cache
def _kernel():
    """The kernel, compiled on first use (importing Triton costs every process that renders a second)."""
    import triton
    import triton.language as tl

    @triton.jit
    def siren_kernel(x_ptr, w0_ptr, b0_ptr, wh_ptr, bh_ptr, wl_ptr, bl_ptr, out_ptr, n,
                     W: tl.constexpr, BLOCKS: tl.constexpr, BLOCK: tl.constexpr, PRECISION: tl.constexpr,
                     RES: tl.constexpr):
        rows = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        live = rows < n
        c = tl.arange(0, W)
        x0 = tl.load(x_ptr + rows * 3, mask=live, other=0.0)
        x1 = tl.load(x_ptr + rows * 3 + 1, mask=live, other=0.0)
        x2 = tl.load(x_ptr + rows * 3 + 2, mask=live, other=0.0)
        h = (x0[:, None] * tl.load(w0_ptr + c)[None, :] + x1[:, None] * tl.load(w0_ptr + W + c)[None, :]
             + x2[:, None] * tl.load(w0_ptr + 2 * W + c)[None, :] + tl.load(b0_ptr + c)[None, :])
        h = tl.sin(h)
        square = c[:, None] * W + c[None, :]  # (in, out) layout: h @ w
        for i in tl.static_range(BLOCKS):
            wa = tl.load(wh_ptr + (2 * i) * W * W + square)
            ba = tl.load(bh_ptr + (2 * i) * W + c)
            inner = tl.sin(tl.dot(h, wa, input_precision=PRECISION) + ba[None, :])
            wb = tl.load(wh_ptr + (2 * i + 1) * W * W + square)
            bb = tl.load(bh_ptr + (2 * i + 1) * W + c)
            outer = tl.sin(tl.dot(inner, wb, input_precision=PRECISION) + bb[None, :])
            h = RES * (h + outer)
        y = tl.sum(h * tl.load(wl_ptr + c)[None, :], axis=1) + tl.load(bl_ptr)
        tl.store(out_ptr + rows, 0.5 * y + 0.5, mask=live)

    return triton.cdiv, siren_kernel


class FusedSiren:
    """One SIREN (`named` tensors as `Siren.named_tensors()` or `WeightLayout.unflatten` give them, for one
    SIREN) as a callable (N, 3) → (N,), the same as `siren._forward` up to float32 summation order."""

    def __init__(self, named: dict[str, torch.Tensor], blocks: int, precision: str = "ieee"):
        if importlib.util.find_spec("triton") is None:
            raise FusedSirenError("the fused SIREN needs Triton (it ships with CUDA builds of PyTorch)")
        if precision not in ("ieee", "tf32"):
            raise FusedSirenError(f"precision: expected 'ieee' or 'tf32', got {precision!r}")
        first = named["first.weight"].detach().float()
        width = first.shape[0]
        if width < 16 or width & (width - 1) or first.shape[1] != 3:
            raise FusedSirenError(f"the fused SIREN needs a power-of-two width >= 16 and 3 inputs, got weights "
                                  f"{tuple(first.shape)}")
        with torch.no_grad():
            layers = [(w.detach().float(), b.detach().float()) for w, b in fold(named, blocks)]
            (w0, b0), hidden, (wl, bl) = layers[0], layers[1:-1], layers[-1]
            self.w0, self.b0 = w0.t().contiguous(), b0.contiguous()
            device = first.device
            self.wh = (torch.stack([w.t() for w, _ in hidden]) if hidden
                       else torch.zeros(1, width, width, device=device)).contiguous()
            self.bh = (torch.stack([b for _, b in hidden]) if hidden
                       else torch.zeros(1, width, device=device)).contiguous()
            self.wl, self.bl = wl.reshape(-1).contiguous(), bl.reshape(1).contiguous()
        self.width, self.blocks, self.precision = width, blocks, precision
        self.block = block_points(width)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        x = x.float().contiguous()
        out = torch.empty(len(x), dtype=torch.float32, device=x.device)
        if len(x):
            cdiv, kernel = _kernel()
            kernel[(cdiv(len(x), self.block),)](
                x, self.w0, self.b0, self.wh, self.bh, self.wl, self.bl, out, len(x),
                W=self.width, BLOCKS=self.blocks, BLOCK=self.block, PRECISION=self.precision, RES=RES_WEIGHT)
        return out
