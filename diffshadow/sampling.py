"""Reproducible randomness: generators seeded from tuples of ints, every random draw of a run by name (`Stream`,
`LightStream`, the derived seeds `*_SEED`), and the random box points that stage 1, the data INR and the
evaluation draw (a share of them around visible voxels).

Imports torch only where a generator or points are made: `lights` (the light-sets job, which starts without
torch) takes its streams from here.
"""

from __future__ import annotations

import hashlib
import json
from enum import IntEnum, unique
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Iterator

    import torch

    from diffshadow.transfer import TransferFunction
    from diffshadow.volume import Volume


@unique
class Stream(IntEnum):
    """Every random stream a run draws from, by name: `seeded(seed, Stream.X, ...)`. The numbers are part of the
    results (the README run's bytes), so a stream is renamed, never renumbered; a new draw takes a number no
    member has. Stage 1's subset k draws its points from stream k (0, 1, ...) of fit.seed, and its pool lights' pick
    of each step from `FIT_POOL_PICK - k`, below every member. Stage 1's members are negative, so no subset
    meets them; the positive ones are stage 2's and the evaluation's, drawn from their own sections' seeds (at
    equal seeds, subset k and member k draw equal numbers for unrelated uses: a point's position, a batch's
    order)."""

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
    BOOTSTRAP = 24  # the evaluation's resampled lights: the interval of a median gap
    DATA_INR_INIT = 7  # the data INR's initial weights
    DATA_INR_STEP = 8  # the data INR's points of a step
    HELD_OUT = 0x5EED  # stage 1's stored PSNR: fresh points no training step draws


@unique
class LightStream(IntEnum):
    """numpy's draws of random directions in the training lights' cap (`lights.unseen_directions`), seeded
    [seed, member]; the unseen test set draws from the bare `lights.seed`. Renamed, never renumbered."""

    POOL = 1  # pool lights: stage 2's from diffusion.seed, stage 1's blend pool from fit.seed + FIT_BLEND_POOL_SEED
    VALIDATION = 2  # the validation lights of fine-tuning's model choice and of `cache: auto`
    WIDE = 3  # evaluate_voxels' further test lights (`evaluate.wide_lights`)
    CORRECTION = 4  # the lights the blend's correction is fitted on, and its steps' draws (correction.seed)


# Derived seeds: a draw that repeats another's stream with fresh values takes the config seed plus one of these.
# Part of the results too. Two that feed one stream never meet: subset k's held-out seed, 7919 (k + 1), is never
# the probe's (104729 is prime).
VALIDATION_POINTS_SEED = 1  # the validation lights' exact-shadow points (EvalTruth; eval_truth's own: the seed)
FIT_BLEND_POOL_SEED = 7919  # stage 1's blend-pool lights (LightStream.POOL; stage 2's pool: the seed itself)
SUBSET_HELD_OUT_SEED = 7919  # stage 1's held-out points of subset k: fit.seed + 7919 (k + 1) (Stream.HELD_OUT)
PROBE_HELD_OUT_SEED = 104729  # the size probe's held-out points (Stream.HELD_OUT)
# the blend correction's held-out lights (LightStream.CORRECTION) and their points: correction.seed + 7919, never
# a chunk of its fitted lights' points (correction.seed + a multiple of 64)
CORRECTION_HELD_OUT_SEED = 7919


def seeded(*parts: int) -> torch.Generator:
    """A generator seeded from a tuple of ints (stable across runs and platforms)."""
    import torch

    digest = hashlib.sha256(json.dumps([int(x) for x in parts]).encode()).digest()
    return torch.Generator().manual_seed(int.from_bytes(digest[:8], "little") & (2**63 - 1))


def to_device(draw: torch.Tensor, device: torch.device) -> torch.Tensor:
    """A draw made on the host, on `device` without waiting for it. On CUDA, PyTorch's copy from ordinary host
    memory first waits for every kernel queued before it (it synchronizes the stream), so a training step's draws
    would hold the host until the previous step had run; a pinned draw is copied asynchronously instead, and
    PyTorch keeps the pinned block until its copy is done. The same values on every device."""
    if device.type == "cuda":
        draw = draw.pin_memory()
    return draw.to(device, non_blocking=True)


def visible_voxels(volume: Volume, tf: TransferFunction) -> Iterator[torch.Tensor]:
    """(z, y, x) indices (V, 3) of the voxels the TF makes visible (opacity > 0), in the voxels' order, a slab of
    planes at a time (`volume.plane_slabs`; a slab without any gives an empty array)."""
    import torch

    from diffshadow.volume import plane_slabs

    data = torch.as_tensor(volume.data, device="cpu")
    for sl in plane_slabs(data.shape):
        zyx = torch.nonzero(tf.opacity(data[sl]) > 0)
        zyx[:, 0] += sl.start
        yield zyx


class PointSampler:
    """Random box points; a share of them jittered around visible voxels. Drawn on the CPU (the same
    points on every device); the caller moves them."""

    def __init__(self, volume: Volume, tf: TransferFunction, visible_fraction: float):
        import torch

        self.extent = torch.as_tensor(volume.extent, dtype=torch.float32, device="cpu")
        self.voxel = torch.as_tensor(volume.voxel_size, dtype=torch.float32, device="cpu")
        # (V, 3) box coordinates of visible voxels, in the voxels' order
        self.visible = torch.cat([zyx.flip(1).float() * self.voxel for zyx in visible_voxels(volume, tf)])
        self.visible_fraction = visible_fraction if len(self.visible) else 0.0

    def sample(self, k: int, n: int, generator: torch.Generator) -> torch.Tensor:
        """(k, n, 3) points in box coordinates."""
        import torch

        n_vis = int(round(n * self.visible_fraction))
        pts = torch.rand(k, n, 3, generator=generator, device=generator.device) * self.extent
        if n_vis:
            idx = torch.randint(len(self.visible), (k, n_vis), generator=generator, device=generator.device)
            jitter = (torch.rand(k, n_vis, 3, generator=generator, device=generator.device) - 0.5) * self.voxel
            pts[:, :n_vis] = torch.minimum(torch.clamp(self.visible[idx] + jitter, min=0), self.extent)
        return pts
