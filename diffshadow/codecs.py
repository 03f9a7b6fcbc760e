"""Codecs of the stored SIRENs: smaller stores that decode to ordinary SIREN weights, so the renderer and the
viewer need nothing new. Each is one point of the cache's rate (bytes) against its distortion (voxel PSNR);
`diffshadow.caches` measures them beside the diffusion model.

- `HalfCodec`: every weight in 16 bits (fp16 or bf16).
- `BasisCodec`: the SIRENs share one pre-optimised init, so their weights lie close together: the mean, the
  `k` principal directions of the weights standardised per parameter tensor (one SVD), and `k` coefficients per
  light. A weight blend of SIRENs is the same blend of their coefficients.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from diffshadow.layout import WeightLayout


@dataclass(frozen=True)
class Encoded:
    """A store of `count` SIRENs in a codec: its arrays as stored, and their bytes."""

    codec: str
    count: int
    arrays: dict[str, np.ndarray] = field(repr=False)

    @property
    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in self.arrays.values()))


class HalfCodec:
    """Every weight as a 16-bit float: fp16 (10-bit mantissa, range ±65504) or bf16 (fp32's range, 7 bits)."""

    def __init__(self, dtype: str = "float16"):
        if dtype not in ("float16", "bfloat16"):
            raise ValueError(f"HalfCodec: expected float16 or bfloat16, got {dtype!r}")
        self.dtype = dtype
        self.name = "fp16" if dtype == "float16" else "bf16"

    def encode(self, weights: np.ndarray, layout: WeightLayout) -> Encoded:
        w = _weights(weights, layout)
        if self.dtype == "float16":
            if np.abs(w).max(initial=0.0) > np.finfo(np.float16).max:
                raise ValueError("HalfCodec fp16: a weight exceeds fp16's range (65504); use bf16")
            return Encoded(self.name, len(w), {"w": w.astype(np.float16)})
        # bf16 is fp32's upper half: round to nearest even on the 16 bits dropped
        bits = w.astype(np.float32).view(np.uint32)
        rounded = ((bits + 0x7FFF + ((bits >> 16) & 1)) >> 16).astype(np.uint16)
        return Encoded(self.name, len(w), {"w": rounded})

    def decode(self, enc: Encoded, layout: WeightLayout | None = None, rows: ArrayLike | None = None) -> np.ndarray:
        """The SIRENs' weights (N, P) in fp32, or those of `rows` only."""
        w = enc.arrays["w"] if rows is None else enc.arrays["w"][rows]
        if self.dtype == "float16":
            return w.astype(np.float32)
        return (w.astype(np.uint32) << 16).view(np.float32)


class BasisCodec:
    """The mean SIREN, `k` principal directions of the standardised weights, `k` coefficients per light (fp32).
    Standardised per parameter tensor (one scale each, its spread over the lights), so that the small biases
    and the large first-layer weights count alike in the SVD."""

    def __init__(self, k: int):
        if k < 1:
            raise ValueError(f"BasisCodec: k must be at least 1, got {k}")
        self.k = k
        self.name = f"basis-{k}"

    def encode(self, weights: np.ndarray, layout: WeightLayout) -> Encoded:
        w = _weights(weights, layout).astype(np.float64)
        mean = w.mean(0)
        centred = w - mean
        scale = np.ones(len(layout.sizes))
        for i, sl in enumerate(_slices(layout)):
            spread = centred[:, sl].std()
            scale[i] = spread if spread > 0 else 1.0
        z = centred / _per_param(scale, layout)
        _, _, vt = np.linalg.svd(z, full_matrices=False)
        basis = vt[:min(self.k, len(vt))]
        return Encoded(self.name, len(w), {"mean": mean.astype(np.float32), "scale": scale.astype(np.float32),
                                           "basis": basis.astype(np.float32),
                                           "coefficients": (z @ basis.T).astype(np.float32)})

    def decode(self, enc: Encoded, layout: WeightLayout, coefficients: np.ndarray | None = None) -> np.ndarray:
        """The SIRENs' weights (N, P); or those of other `coefficients` (Q, k), e.g. blends of the stored ones."""
        a = enc.arrays
        c = a["coefficients"] if coefficients is None else coefficients
        z = c.astype(np.float64) @ a["basis"].astype(np.float64)
        return (z * _per_param(a["scale"].astype(np.float64), layout) + a["mean"]).astype(np.float32)


def codec_named(name: str) -> HalfCodec | BasisCodec:
    """The codec a `cache` value names (each codec's `name`): fp16, bf16 or basis-<k> (blend, the stored fp32
    SIRENs, has none)."""
    if name in ("fp16", "bf16"):
        return HalfCodec("float16" if name == "fp16" else "bfloat16")
    if name.startswith("basis-") and name[6:].isdigit() and int(name[6:]) >= 1:
        return BasisCodec(int(name[6:]))
    raise ValueError(f"cache: expected blend, fp16, bf16 or basis-<k>, got {name!r}")


def _weights(weights, layout: WeightLayout) -> np.ndarray:
    w = np.asarray(weights)
    if w.ndim != 2 or w.shape[1] != layout.n_params:
        raise ValueError(f"codec: expected weights (N, {layout.n_params}), got {w.shape}")
    if not np.all(np.isfinite(w)):
        raise ValueError("codec: the weights are not all finite")
    return w


def _slices(layout: WeightLayout) -> list[slice]:
    ends = np.cumsum(layout.sizes)
    return [slice(int(e - n), int(e)) for e, n in zip(ends, layout.sizes, strict=True)]


def _per_param(per_tensor: np.ndarray, layout: WeightLayout) -> np.ndarray:
    return np.repeat(per_tensor, layout.sizes)
