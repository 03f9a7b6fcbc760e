"""What the marcher samples: the scalar field (raw grid or data INR) and the shadow source (a shadow grid or a
shadow INR), each evaluated by the kernel `Networks` chose (eager or fused)."""

from __future__ import annotations

import warnings

import numpy as np
import torch
import torch.nn.functional as F
from numpy.typing import ArrayLike

from diffshadow.grid import box, trilinear
from diffshadow.render.fused import FUSED, FusedSiren, FusedSirenError
from diffshadow.siren import FoldedSiren, Siren, WeightLayout, box_to_siren, fold, fold_flat
from diffshadow.volume import Volume


class GridScalar:
    """The raw volume: trilinear value, and (central-difference) gradient from one 4-channel lookup. The gradient
    channels are made on the first gradient asked for (Phong shading): a render without them (every `gt` target,
    view and naive image) kept 4 float32 grids and made them from float64 ones, ~24 grids' bytes at once (12 GiB
    in render_targets on a 512³ volume)."""

    def __init__(self, volume: Volume, device: torch.device | str = "cpu"):
        self.extent = box(volume.extent, device)
        self.voxel = torch.as_tensor(volume.voxel_size, dtype=torch.float32, device=device)
        self.volume, self.device = volume, device
        data = np.ascontiguousarray(volume.data, dtype=np.float32)
        if not data.flags.writeable:  # torch warns on a read-only array; on a CPU it is shared otherwise
            data = data.copy()
        self.values = torch.as_tensor(data, device=device)[None]  # (1, Z, Y, X)
        self._channels: torch.Tensor | None = None

    @property
    def channels(self) -> torch.Tensor:
        """(1, 4, Z, Y, X): the value and its gradient (x, y, z), central differences in float64, one axis at a
        time (the same values as `np.gradient` over all three at once, with one float64 gradient held)."""
        if self._channels is None:
            data = self.volume.data.astype(np.float64)
            spacing = self.volume.voxel_size  # (x, y, z)
            stack = np.empty((4, *data.shape), dtype=np.float32)
            stack[0] = data
            for channel, axis in ((1, 2), (2, 1), (3, 0)):  # gx along x (the last axis), gy, gz
                stack[channel] = np.gradient(data, spacing[2 - axis], axis=axis)
            del data
            self._channels = torch.as_tensor(stack, device=self.device)[None]
        return self._channels

    def _lookup(self, p: torch.Tensor, channels: slice) -> torch.Tensor:
        return trilinear(self.channels[0, channels], p / self.voxel)

    def value(self, p: torch.Tensor) -> torch.Tensor:
        return trilinear(self.values, p / self.voxel)[0]

    def value_and_grad(self, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self._lookup(p, slice(0, 4))
        return out[0], out[1:].t()


class InrScalar:
    """The data INR (a SIREN of the scalar field); gradients by autograd through the network. `kernel`: "fused" for
    the fused kernel for values (`diffshadow.render.fused`), None for the eager SIREN."""

    def __init__(self, model: Siren, extent: ArrayLike, device: torch.device | str = "cpu", kernel: str | None = None):
        self.model = model.to(device).eval()
        for q in self.model.parameters():
            q.requires_grad_(False)
        self.extent = box(extent, device)
        self.box = tuple(np.asarray(extent, dtype=float).tolist())  # on the host, to compare without a sync
        named, blocks = self.model.named_tensors(), self.model.cfg.blocks  # parameters without gradients
        self.fast = _fast_siren(named, blocks, kernel, lambda: fold(named, blocks))

    def value(self, p: torch.Tensor) -> torch.Tensor:
        return self.fast(box_to_siren(p, self.extent))

    def value_and_grad(self, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.enable_grad():
            p = p.detach().requires_grad_(True)
            s = self.model(box_to_siren(p, self.extent))
            (g,) = torch.autograd.grad(s.sum(), p)
        return s.detach(), g


def _fast_siren(named: dict, blocks: int, kernel: str | None, layers) -> FusedSiren | FoldedSiren:
    """A SIREN for inference: the fused kernel for `kernel` = "fused", else the folded eager SIREN
    (`layers()`: its folded layers). A SIREN the kernel cannot take (a width
    that is not a power of two >= 16) falls back to the eager one, with a warning: the setting is a speed-up, not
    a result."""
    if kernel == FUSED:
        try:
            return FusedSiren(named, blocks)
        except FusedSirenError as e:
            warnings.warn(f"render.kernel=fused: {e}; using the eager SIREN", stacklevel=3)
    return FoldedSiren(layers())


class GridShadow:
    """Shadow coefficients looked up trilinearly in a (Z, Y, X) grid (`shadow_grid`'s output)."""

    def __init__(self, grid: torch.Tensor, extent: ArrayLike, device: torch.device | str = "cpu"):
        self.grid = torch.as_tensor(grid, dtype=torch.float32, device=device)[None, None]
        self.extent = box(extent, device)

    def __call__(self, p: torch.Tensor) -> torch.Tensor:
        g = box_to_siren(p, self.extent).view(1, 1, 1, -1, 3)
        return F.grid_sample(self.grid, g, mode="bilinear", padding_mode="border", align_corners=True).view(-1)


class SirenShadow:
    """A shadow INR (one flat weight vector in `layout`), evaluated in the same pass as the data INR."""

    def __init__(self, weights: ArrayLike, layout: WeightLayout, blocks: int, extent: ArrayLike,
                 device: torch.device | str = "cpu", kernel: str | None = None):
        w = torch.as_tensor(np.asarray(weights), dtype=torch.float32, device=device).reshape(1, -1)
        # eager: one SIREN with a leading K = 1, the batched matmuls of fitting, so the same values
        self.fast = _fast_siren({k: v[0] for k, v in layout.unflatten(w).items()}, blocks, kernel,
                                lambda: fold_flat(w, layout, blocks))
        self.batched = not isinstance(self.fast, FusedSiren)
        self.extent = box(extent, device)
        self.box = tuple(np.asarray(extent, dtype=float).tolist())

    def __call__(self, p: torch.Tensor) -> torch.Tensor:
        x = box_to_siren(p, self.extent)
        return (self.fast(x[None])[0] if self.batched else self.fast(x)).clamp(0.0, 1.0)
