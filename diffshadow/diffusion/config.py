"""The diffusion model's settings (config `diffusion`) and how they build the model and its optimiser."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass

import torch

from diffshadow.adam import Adam, fused_supported
from diffshadow.config import section
from diffshadow.diffusion.model import PRESETS, WeightTransformer
from diffshadow.siren import PRECISIONS, WeightLayout

AUTO_PRESETS = ((32, "small"), (64, "medium"))


class DiffusionError(ValueError):
    """Training or sampling that cannot go on; the message says why and what was kept."""


@dataclass(frozen=True)
class DiffusionConfig:
    preset: str  # a PRESETS name, or "auto": the one AUTO_PRESETS gives the SIREN width (for_siren)
    epochs: int  # paper: 7000 (geometry stage)
    batch_size: int
    lr: float  # AdamW, paper §3.4
    weight_decay: float
    lr_step_epochs: int  # StepLR, paper §3.4
    lr_gamma: float
    grad_clip: float
    ema: float  # EMA decay of the weights used for sampling (warmed up, see ema_decay); 0: off
    geometry_weight: float
    geometry_points: int  # per light per step, drawn from the presampled set (authors: 4096)
    presample_points: int  # per light in geometry_points.zarr (paper: 500,000)
    checkpoint_every: int  # epochs
    ddim_steps: int
    standardize: str  # "token": paper; "param": per weight across lights (see README)
    light_freqs: int  # NeRF encoding of the light direction; 3 interpolates best between lights (README)
    temperature: float  # DDIM start noise scale; 0: one deterministic path per light (see README)
    seed: int
    # lights with no fitted SIREN, drawn by presample in the training lights' cap and trained alongside
    # them on exact shadows (PoolLights); 0: off
    pool_lights: int
    pool_points: int  # presampled points per pool light
    pool_x0_weight: float  # x0 loss towards the blend of the nearest training SIRENs (geometry: towards truth)
    tensor_tokens: int  # tokens per weight tensor wider than the model (G.pt's chunks); 1: one per tensor (paper)
    # after `epochs`, train on (checking every checkpoint_every epochs) while the generated seen lights lie more
    # than target_gap dB under stage 1, up to max_epochs; 0 target_gap: exactly `epochs`
    target_gap: float
    max_epochs: int
    # the training forward's matrix products: "bfloat16" runs them under autocast (losses, SIRENs and the optimiser
    # stay float32); sampling always runs float32. "auto": bfloat16 on a CPU with native bfloat16 products, else
    # float32 (for_device); a checkpoint records the precision its steps ran in
    precision: str
    # the optimizer step as a replayed CUDA graph (diffshadow.graphs): one launch for its ~420 kernels at the
    # README's sizes. "auto": where the device is CUDA; True: also asked for elsewhere (the step then runs eagerly,
    # saying so); False: never. A trained model records what was done (True or False)
    cuda_graph: bool | str

    @classmethod
    def from_config(cls, d: dict | None = None) -> DiffusionConfig:
        """defaults.yaml's `diffusion` section overridden by `d`."""
        cfg = section(cls, "diffusion", d)
        if cfg.preset not in PRESETS and cfg.preset != "auto":
            raise ValueError(f"diffusion.preset: expected auto or one of {sorted(PRESETS)}, got {cfg.preset!r}")
        if cfg.precision not in (*PRECISIONS, "auto"):
            raise ValueError(f"diffusion.precision: expected auto or one of {', '.join(PRECISIONS)}, "
                             f"got {cfg.precision!r}")
        return cfg

    @property
    def products(self) -> str:
        """The training forward's precision where it is not float32, as a description's tail ("" for float32)."""
        return "" if self.precision == "float32" else f"; {self.precision} products"

    def for_device(self, device: torch.device) -> DiffusionConfig:
        """This config with `precision: auto` made concrete for `device`: bfloat16 on a CPU whose kernels have
        native bfloat16 products (`native_bfloat16`), where the README's geometry stage took 0.8x float32's time
        for the same quality (docs/performance.md); float32 on other CPUs, which emulate bfloat16, and on CUDA,
        where bfloat16 is not yet the default (timed at the paper's sizes only). A set precision is kept."""
        if self.precision != "auto":
            return self
        fast = device.type == "cpu" and native_bfloat16()
        return dataclasses.replace(self, precision="bfloat16" if fast else "float32")

    def for_siren(self, width: int) -> DiffusionConfig:
        """This config with `preset: auto` made concrete for SIRENs of `width` (the smallest AUTO_PRESETS entry
        that covers it); a named preset is kept. Checkpoints store the concrete name."""
        if self.preset != "auto":
            return self
        preset = next((name for top, name in AUTO_PRESETS if width <= top), AUTO_PRESETS[-1][1])
        return dataclasses.replace(self, preset=preset)

    @classmethod
    def of_checkpoint(cls, state: dict) -> DiffusionConfig:
        """The config a checkpoint was trained with; one written before `tensor_tokens` existed had one token
        per tensor, and one before `precision` ran float32, whatever config.yaml says now."""
        return cls.from_config({"tensor_tokens": 1, "precision": "float32", **state["config"]})


def native_bfloat16() -> bool:
    """Whether this CPU multiplies bfloat16 natively (AVX512-BF16 or AMX tiles): oneDNN's bfloat16 products there
    took 0.47x float32's time at the small model's shapes; elsewhere it converts to float32 and gains nothing."""
    cpu = torch.cpu
    return any(getattr(cpu, name, lambda: False)() for name in ("_is_avx512_bf16_supported", "_is_amx_tile_supported"))


def make_optimizer(params: Iterable[torch.Tensor], lr: float, weight_decay: float, *,
                   capturable: bool = False) -> Adam:
    """AdamW, fused where this torch has the kernel for the device (CPU since torch 2.4): on the small
    preset's 3.5M parameters the per-tensor loop took 27 ms of a 270 ms CPU step, the fused one 5 ms.
    `capturable` (for a CUDA graph): the learning rate is a tensor on the parameters' device, which `step_lr`
    fills in place, so a replayed step reads the current one."""
    params = list(params)
    fused = True if capturable else fused_supported(params) or None
    return Adam(params, lr, weight_decay=weight_decay, decoupled=True, fused=fused, capturable=capturable)


def build_model(layout: WeightLayout, cfg: DiffusionConfig) -> WeightTransformer:
    """The model, initialised on the CPU (the same seed gives the same weights on every device)."""
    if cfg.preset not in PRESETS:
        raise ValueError(f"diffusion.preset {cfg.preset!r}: no model of that name (resolve 'auto' with for_siren)")
    with torch.device("cpu"):
        return WeightTransformer(layout, dataclasses.replace(PRESETS[cfg.preset], light_freqs=cfg.light_freqs,
                                                                tensor_tokens=cfg.tensor_tokens))
