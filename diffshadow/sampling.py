"""Reproducible randomness: generators seeded from tuples of ints, and the random box points that stage 1,
the data INR and the evaluation draw (a share of them around visible voxels).
"""

from __future__ import annotations

import hashlib
import json

import torch

from diffshadow.transfer import TransferFunction
from diffshadow.volume import Volume


def seeded(*parts: int) -> torch.Generator:
    """A generator seeded from a tuple of ints (stable across runs and platforms)."""
    digest = hashlib.sha256(json.dumps(list(parts)).encode()).digest()
    return torch.Generator().manual_seed(int.from_bytes(digest[:8], "little") & (2**63 - 1))


class PointSampler:
    """Random box points; a share of them jittered around visible voxels. Drawn on the CPU (the same
    points on every device); the caller moves them."""

    def __init__(self, volume: Volume, tf: TransferFunction, visible_fraction: float):
        self.extent = torch.as_tensor(volume.extent, dtype=torch.float32, device="cpu")
        self.voxel = torch.as_tensor(volume.voxel_size, dtype=torch.float32, device="cpu")
        opacity = tf.opacity(torch.as_tensor(volume.data, device="cpu"))
        zyx = torch.nonzero(opacity > 0)
        self.visible = zyx.flip(1).float() * self.voxel  # (V, 3) box coordinates of visible voxels
        self.visible_fraction = visible_fraction if len(self.visible) else 0.0

    def sample(self, k: int, n: int, generator: torch.Generator) -> torch.Tensor:
        """(k, n, 3) points in box coordinates."""
        n_vis = int(round(n * self.visible_fraction))
        pts = torch.rand(k, n, 3, generator=generator, device=generator.device) * self.extent
        if n_vis:
            idx = torch.randint(len(self.visible), (k, n_vis), generator=generator, device=generator.device)
            jitter = (torch.rand(k, n_vis, 3, generator=generator, device=generator.device) - 0.5) * self.voxel
            pts[:, :n_vis] = torch.minimum(torch.clamp(self.visible[idx] + jitter, min=0), self.extent)
        return pts
