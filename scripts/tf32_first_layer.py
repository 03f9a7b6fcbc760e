"""The first SIREN layer's error on tensor cores, emulated on the CPU: how far its pre-activations (the sines'
arguments, ω0 = 30 folded into the weights) land from float64 when computed as fp32 multiply-adds (the "ieee"
kernels), as one TF32 product, or as three TF32 products of split operands (hi·hi + hi·lo + lo·hi, the "tf32"
kernels' `_kernels.first_layer`). A tensor core reads TF32 operands, fp32 with the low 13 mantissa bits dropped;
the emulation drops them from every operand and sums the products in float64 (the cores accumulate in fp32,
~2e-6 here).

    python scripts/tf32_first_layer.py
"""

from __future__ import annotations

import numpy as np
import torch

from diffshadow.siren import Siren, SirenConfig, fold


def tf32(a: np.ndarray) -> np.ndarray:
    return (np.ascontiguousarray(a, dtype=np.float32).view(np.int32) & np.int32(-8192)).view(np.float32)


def main() -> None:
    model = Siren(SirenConfig(64, 2), torch.Generator().manual_seed(0))
    with torch.no_grad():
        for p in model.parameters():
            p.mul_(1.5)  # trained-looking weights, as tests/test_fused.py uses
        w = np.ascontiguousarray(fold(model.named_tensors(), 2)[0][0].numpy().T, dtype=np.float32)  # (3, W)
    x = (np.random.default_rng(0).random((100_000, 3)) * 2 - 1).astype(np.float32)
    exact = x.astype(np.float64) @ w.astype(np.float64)
    x_hi, w_hi = tf32(x), tf32(w)
    x_lo, w_lo = x - x_hi, w - w_hi

    def core(a, b):  # one tensor-core product: TF32 operands, exact products
        return tf32(a).astype(np.float64) @ tf32(b).astype(np.float64)

    ways = {"fp32 multiply-adds": (x[:, :1] * w[0] + x[:, 1:2] * w[1] + x[:, 2:3] * w[2]).astype(np.float32),
            "one TF32 product": core(x, w).astype(np.float32),
            "three TF32 products": (core(x_hi, w_hi) + core(x_hi, w_lo) + core(x_lo, w_hi)).astype(np.float32)}
    print(f"first-layer weights up to {np.abs(w).max():.1f} (ω0 folded in), {len(x):,} points")
    for name, z in ways.items():
        arg = np.abs(z - exact).max()
        out = np.abs(np.sin(z.astype(np.float64)) - np.sin(exact)).max()
        print(f"{name:20s} max |argument error| {arg:.1e}   max |sine error| {out:.1e}")


if __name__ == "__main__":
    main()
