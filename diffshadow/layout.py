"""A SIREN's size and the layout of its parameters as one flat vector: what a weight store records beside its
rows. Kept apart from `siren` and free of torch at import, so the jobs that only move stored weights
(`collect_weights`) start without it; `siren` builds the networks on these.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from diffshadow.config import check_keys

if TYPE_CHECKING:
    import torch


@dataclass(frozen=True)
class SirenConfig:
    """SIREN size: `width` H (paper 128, 64 for small data) and residual `blocks`."""

    width: int
    blocks: int

    @classmethod
    def from_config(cls, d: dict) -> SirenConfig:
        """A SIREN size as stored (no defaults: a layout is what was fitted)."""
        check_keys(cls, "siren", d)
        return cls(width=int(d["width"]), blocks=int(d["blocks"]))

    def to_config(self) -> dict:
        return {"width": self.width, "blocks": self.blocks}


@dataclass(frozen=True)
class WeightLayout:
    """Ordered (name, shape) of every parameter tensor; flat vector ↔ named tensors."""

    entries: tuple[tuple[str, tuple[int, ...]], ...]

    @classmethod
    def for_siren(cls, cfg: SirenConfig) -> WeightLayout:
        h = cfg.width
        entries = [("first.weight", (h, 3)), ("first.bias", (h,))]
        for i in range(cfg.blocks):
            for j in (1, 2):
                entries += [(f"blocks.{i}.l{j}.weight", (h, h)), (f"blocks.{i}.l{j}.bias", (h,))]
        entries += [("last.weight", (1, h)), ("last.bias", (1,))]
        return cls(tuple(entries))

    @classmethod
    def from_config(cls, rows: Iterable[tuple[str, Iterable[int]]]) -> WeightLayout:
        return cls(tuple((str(name), tuple(int(s) for s in shape)) for name, shape in rows))

    def to_config(self) -> list:
        return [[name, list(shape)] for name, shape in self.entries]

    @property
    def sizes(self) -> list[int]:
        return [math.prod(shape) for _, shape in self.entries]

    @property
    def n_params(self) -> int:
        return sum(self.sizes)

    def flatten(self, tensors: dict[str, torch.Tensor]) -> torch.Tensor:
        """Named tensors (each with optional leading batch dims) → (..., n_params)."""
        import torch  # here, not at the top: readers of a store's layout need no torch

        parts = []
        for name, shape in self.entries:
            t = tensors[name]
            parts.append(t.reshape(*t.shape[: t.ndim - len(shape)], -1))
        return torch.cat(parts, dim=-1)

    def unflatten(self, flat: torch.Tensor) -> dict[str, torch.Tensor]:
        """(..., n_params) → named tensors of shape (..., *shape); views, so gradients flow."""
        if flat.shape[-1] != self.n_params:
            raise ValueError(f"weight vector has {flat.shape[-1]} values, layout needs {self.n_params}")
        out = {}
        for (name, shape), part in zip(self.entries, flat.split(self.sizes, dim=-1), strict=True):
            out[name] = part.reshape(*flat.shape[:-1], *shape)
        return out
