"""Reproducible randomness: generators seeded from tuples of ints, every random stream of a run by name
(`Stream`), and the random box points that stage 1, the data INR and the evaluation draw (a share of them
around visible voxels).
"""

from __future__ import annotations

import hashlib
import json
from enum import IntEnum

import torch

from diffshadow.transfer import TransferFunction
from diffshadow.volume import Volume


class Stream(IntEnum):
    """Every random stream a run draws from, by name: `seeded(seed, Stream.X, ...)`. The numbers are part of the
    results (the README run's bytes), so a stream is renamed, never renumbered; a new draw takes a number no
    member has. Stage 1's subset k draws its points from stream k (0, 1, ...), and its pool lights' pick of each
    step from `FIT_POOL_PICK - k`: both ranges stay clear of the members."""

    # stage 1 (fit): below zero, apart from the subsets' own 0, 1, ...
    PREOPTIMIZE = -1  # the shared init's random SIREN and its fit
    FIT_SHARED_POINTS = -2  # fit.shared_points: the points every SIREN of a step sees
    PROBE = -3  # the size ladder's probe fit
    FIT_BLEND_POOL = -4  # the blend pool's lights and their exact shadows
    FIT_POOL_PICK = -5  # minus the subset's stream: each step's pick of pool lights
    # stage 2 (diffusion)
    DIFFUSION_EPOCH = 1  # an epoch's batches, timesteps, noise and geometry points
    SAMPLE_NOISE = 2  # DDPM/DDIM's starting noise per batch of lights
    TRAIN_POINTS = 3  # presampled points with exact shadows, training lights
    FINETUNE_EPOCH = 11  # an epoch's order of lights
    FINETUNE_LIGHT = 12  # a light's timestep, noise and pixels in an epoch
    POOL_POINTS = 13  # presampled points with exact shadows, pool lights
    CHECK_POINTS = 23  # the seen-light gap's held-out points
    # evaluation and the data INR
    EVAL_POINTS = 4  # eval_truth's fixed evaluation points (box, visible)
    DATA_INR_INIT = 7  # the data INR's initial weights
    DATA_INR_STEP = 8  # the data INR's points of a step
    HELD_OUT = 0x5EED  # stage 1's stored PSNR: fresh points no training step draws


def seeded(*parts: int) -> torch.Generator:
    """A generator seeded from a tuple of ints (stable across runs and platforms)."""
    digest = hashlib.sha256(json.dumps([int(x) for x in parts]).encode()).digest()
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
