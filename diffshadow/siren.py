"""The shadow INR: a NeurComp-style SIREN (paper §3.2, docs/design.md §3), and K of them evaluated at once.

    x ∈ [-1, 1]³ → sin(ω0 (W0 x + b0))                      first sine layer, 3 → H
                 → x ← ½ (x + sin(ω0 L2(sin(ω0 L1(½ x)))))   residual blocks (NeurComp's averaging)
                 → ½ (W x + b) + ½                            linear H → 1, output around [0, 1]

Every parameter tensor is a named entry of a `WeightLayout` (`diffshadow.layout`); a SIREN's weights travel as one flat
float32 vector in that order (the Zarr store, the diffusion model's tokens). `BatchedSiren` evaluates K
weight vectors on K point sets with batched matmuls: the one implementation used by fitting, the
diffusion geometry loss and the renderer.
"""

from __future__ import annotations

import contextlib
import functools
import math
from typing import Protocol

import torch
from numpy.typing import ArrayLike
from torch import nn

from diffshadow.layout import SirenConfig, WeightLayout


class CosineSchedule(Protocol):
    """What `cosine_lr` reads of a stage's settings (`fit.FitConfig`, `data_inr.DataInrConfig`)."""

    @property
    def lr(self) -> float: ...

    @property
    def lr_final(self) -> float: ...

    @property
    def steps(self) -> int: ...


OMEGA = 30.0  # sine frequency ω0 (SIREN)
RES_WEIGHT = 0.5  # NeurComp's averaging weight on residual blocks


def layout_scales(layout: WeightLayout, device: torch.device | str = "cpu",
                  dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(n_params,) what `fold` multiplies each parameter of `layout` by, on `device` (cached)."""
    return _layout_scales(layout, str(device), dtype)


@functools.cache
def _layout_scales(layout: WeightLayout, device: str, dtype: torch.dtype) -> torch.Tensor:
    values = [torch.full((size,), _scale(name)) for (name, _), size in zip(layout.entries, layout.sizes, strict=True)]
    return torch.cat(values).to(device=device, dtype=dtype)


def init_siren(cfg: SirenConfig, generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
    """SIREN initialisation: first layer U(±1/in), others U(±√(6/in)/ω0); biases likewise by fan-in."""
    out = {}
    host = generator.device if generator is not None else torch.device("cpu")  # the same on every device
    for name, shape in WeightLayout.for_siren(cfg).entries:
        fan_in = shape[-1] if name.endswith("weight") else (3 if name.startswith("first") else cfg.width)
        bound = 1.0 / fan_in if name.startswith("first") else math.sqrt(6.0 / fan_in) / OMEGA
        if name.endswith("bias"):
            bound = 1.0 / math.sqrt(fan_in)  # PyTorch's default bias init, as in SIREN/NeurComp code
        out[name] = (torch.rand(shape, generator=generator, device=host) * 2 - 1) * bound
    return out


def _scale(name: str) -> float:
    """What `fold` multiplies a parameter by: ω0 on every sine layer, and the residual weight ½ on the input of
    a block's first layer (applied to its weights); the last, linear layer as stored."""
    if name.startswith("last."):
        return 1.0
    return OMEGA * (RES_WEIGHT if name.endswith("l1.weight") else 1.0)


def _layer_names(blocks: int) -> list[str]:
    return ["first"] + [f"blocks.{i}.l{j}" for i in range(blocks) for j in (1, 2)] + ["last"]


def _layers(p: dict[str, torch.Tensor], blocks: int) -> list[tuple[torch.Tensor, torch.Tensor]]:
    return [(p[f"{n}.weight"], p[f"{n}.bias"]) for n in _layer_names(blocks)]


def fold(p: dict[str, torch.Tensor], blocks: int) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """(weight, bias) of every layer with ω0 and the residual weight folded in, last layer as stored: the
    scales applied to the (out, in) weights rather than to the (N, out) activations, two fewer passes over the
    activations forward and two backward (docs/performance.md). Inference folds once per network, not per call."""
    return [(w, b) if n == "last" else (w * _scale(f"{n}.weight"), b * _scale(f"{n}.bias"))
            for n, (w, b) in zip(_layer_names(blocks), _layers(p, blocks), strict=True)]


def fold_flat(weights: torch.Tensor, layout: WeightLayout, blocks: int) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """`fold` of flat weight vectors (..., n_params) in one product with the layout's scales: the same values,
    one kernel instead of two per layer (forward and backward)."""
    return _layers(layout.unflatten(weights * layout_scales(layout, weights.device, weights.dtype)), blocks)


def _linear(h: torch.Tensor, w: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    if w.ndim == 2:
        return torch.addmm(b, h, w.t()) if h.ndim == 2 else h @ w.t() + b
    return torch.baddbmm(b.unsqueeze(1), h, w.transpose(1, 2))  # (K, N, out)


def forward_folded(layers: list[tuple[torch.Tensor, torch.Tensor]], x: torch.Tensor) -> torch.Tensor:
    """One SIREN (weights (out, in)) or K of them (weights (K, out, in), x (K, N, 3)) from `fold`'s layers."""
    h = torch.sin(_linear(x, *layers[0]))
    for i in range(1, len(layers) - 1, 2):
        inner = torch.sin(_linear(h, *layers[i]))
        h = RES_WEIGHT * (h + torch.sin(_linear(inner, *layers[i + 1])))
    return (0.5 * _linear(h, *layers[-1]) + 0.5).squeeze(-1)


# Activations per pass of a SIREN's inference on a CPU (512 KiB of float32). A pass over a march's 65,536 samples
# streamed each layer's (N, width) activations through memory, once per elementwise op; in passes that stay in
# the core's cache the same values came 1.5x faster in the naive baseline's job at one thread, 1.2x at two, and
# 4x for 32 SIRENs at 16,384 points (e2b8699). A GPU takes one pass.
CPU_PASS_ELEMENTS = 1 << 17
MIN_PASS_ROWS = 64  # MKL's batched product of 12 rows or fewer took another kernel, with other bits


def passes(n: int, size: int, least: int | None = None) -> list[slice]:
    """`n` rows in slices of `size`; a last slice shorter than `least` (default `size`) joins the one before it, so
    that none is shorter unless `n` is."""
    starts = list(range(0, n, size))
    if len(starts) > 1 and n - starts[-1] < (size if least is None else least):
        starts.pop()
    return [slice(a, b) for a, b in zip(starts, [*starts[1:], n], strict=False)]  # n = 0: none


class FoldedSiren:
    """A SIREN for inference from `fold`'s or `fold_flat`'s layers, folded once: the same float32 operations as a
    training forward (`forward_folded`), so the same values. (N, 3) → (N,), or (K, N, 3) → (K, N) for K weight
    sets.

    On a CPU the points go through in passes of about `CPU_PASS_ELEMENTS` activations (`passes`), each row's
    values those of one pass over all (MKL's products give a row the same bits whatever the rows beside it, under
    the jobs' `MKL_CBWR=AUTO,STRICT`)."""

    def __init__(self, layers: list[tuple[torch.Tensor, torch.Tensor]]):
        self.layers = [(w.detach(), b.detach()) for w, b in layers]
        w = self.layers[0][0]  # (width, 3) or (K, width, 3)
        self.rows = CPU_PASS_ELEMENTS // w.shape[-2] if w.device.type == "cpu" else None  # a pass's rows, one SIREN

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        if self.rows is None:
            return forward_folded(self.layers, x)
        rows = max(MIN_PASS_ROWS, self.rows // (x.shape[0] if x.ndim == 3 else 1))
        slices = passes(x.shape[-2], rows)
        if len(slices) == 1:
            return forward_folded(self.layers, x)
        out = x.new_empty(x.shape[:-1])
        for sl in slices:
            out[..., sl] = forward_folded(self.layers, x[..., sl, :])
        return out


class Siren(nn.Module):
    """One shadow SIREN: (N, 3) points in [-1, 1]³ → (N,) shadow coefficients."""

    def __init__(self, cfg: SirenConfig, generator: torch.Generator | None = None):
        super().__init__()
        self.cfg = cfg
        self.layout = WeightLayout.for_siren(cfg)
        self.params = nn.ParameterDict({k.replace(".", "_"): nn.Parameter(v)
                                        for k, v in init_siren(cfg, generator).items()})

    def named_tensors(self) -> dict[str, torch.Tensor]:
        return {name: self.params[name.replace(".", "_")] for name, _ in self.layout.entries}

    def flat(self) -> torch.Tensor:
        return self.layout.flatten(self.named_tensors())

    @classmethod
    def from_flat(cls, vector: torch.Tensor | ArrayLike, layout: WeightLayout, cfg: SirenConfig | None = None) -> Siren:
        """A SIREN whose weights are `vector` in `layout` (the store's format)."""
        vector = torch.as_tensor(vector, dtype=torch.float32,
                                 device=vector.device if isinstance(vector, torch.Tensor) else "cpu")
        if cfg is None:
            cfg = SirenConfig(width=layout.entries[0][1][0], blocks=(len(layout.entries) - 4) // 4)
        if WeightLayout.for_siren(cfg) != layout:
            raise ValueError(f"layout does not match a SIREN of width {cfg.width} with {cfg.blocks} blocks")
        model = cls(cfg)
        with torch.no_grad():
            for name, t in layout.unflatten(vector).items():
                model.params[name.replace(".", "_")].copy_(t)
        return model

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return _evaluate(fold(self.named_tensors(), self.cfg.blocks), x, list(self.params.values()))


def _evaluate(layers: list[tuple[torch.Tensor, torch.Tensor]], x: torch.Tensor, weights: list[torch.Tensor]):
    """`layers` at `x`: in one pass where autograd records it (training: the gradients sum as they always did), else
    as inference (`FoldedSiren`: in passes on a CPU)."""
    if torch.is_grad_enabled() and (x.requires_grad or any(w.requires_grad for w in weights)):
        return forward_folded(layers, x)
    return FoldedSiren(layers)(x)


class BatchedSiren:
    """K SIRENs from a (K, n_params) weight matrix, evaluated on (K, N, 3) points → (K, N).

    The weights may carry a graph (the diffusion model's prediction) or be leaf parameters (fitting).
    """

    def __init__(self, weights: torch.Tensor, layout: WeightLayout, blocks: int):
        if weights.ndim != 2:
            raise ValueError(f"BatchedSiren: weights must be (K, n_params), got {tuple(weights.shape)}")
        self.weights = weights
        self.layout = layout
        self.blocks = blocks

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        if x.ndim != 3 or x.shape[0] != self.weights.shape[0]:
            raise ValueError(f"BatchedSiren: points must be (K={self.weights.shape[0]}, N, 3), got {tuple(x.shape)}")
        return _evaluate(fold_flat(self.weights, self.layout, self.blocks), x, [self.weights])


def box_to_siren(points: torch.Tensor, extent: torch.Tensor) -> torch.Tensor:
    """Box coordinates (x, y, z) in [0, extent] → SIREN input in [-1, 1]³ per axis."""
    return points / extent * 2 - 1


LR_WIDTH = 64  # the widest SIREN that the configured lr (1e-3) trains stably


PRECISIONS = ("float32", "bfloat16")  # of a training forward: fit.precision (the SIRENs), diffusion.precision


def forward_precision(precision: str, device: torch.device) -> contextlib.AbstractContextManager:
    """The context a training forward runs in under a precision setting: bfloat16 autocast on `device`'s type, or
    nothing for float32 (the same ops, the same bytes as without it). Autocast keeps no cache of cast weights: a
    CUDA graph cannot capture one (`diffshadow.graphs`), and each weight is cast once per forward anyway."""
    if precision == "float32":
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=torch.bfloat16, cache_enabled=False)


def cosine_lr(step: int, cfg: CosineSchedule, width: int) -> float:
    """Cosine decay from lr to lr · cfg.lr_final over cfg.steps (the authors' schedule), where lr is cfg.lr
    scaled by LR_WIDTH / width above LR_WIDTH: Adam's step is the same size for every weight, while the
    initial weights shrink as 1/√fan-in, so a wider SIREN takes relatively larger steps. At lr 1e-3 the
    tooth's data INR collapsed at width 128 (32 → 18 dB batch PSNR at step 1800) and never trained at 256;
    width 128 at 5e-4 reached 40.4 dB (f52f9af)."""
    lr = cfg.lr * min(1.0, LR_WIDTH / width)
    final = lr * cfg.lr_final
    return final + 0.5 * (lr - final) * (1 + math.cos(math.pi * step / max(1, cfg.steps)))
