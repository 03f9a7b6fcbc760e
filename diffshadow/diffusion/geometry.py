"""The geometry loss (paper §3.3): the de-standardised predicted SIRENs evaluated at presampled points
against the true shadow there, and the presampling of those points and values."""

from __future__ import annotations

import numpy as np
import torch

from diffshadow.sampling import PointSampler, seeded
from diffshadow.shadow import ShadowField, transmittance_per_light
from diffshadow.siren import BatchedSiren, SirenConfig, WeightLayout, box_to_siren
from diffshadow.volume import Volume


def geometry_error(pred_weights: torch.Tensor, layout: WeightLayout, siren: SirenConfig, points: torch.Tensor,
                   values: torch.Tensor, extent: torch.Tensor) -> torch.Tensor:
    """Per light (B,): MSE between the predicted SIRENs at presampled points (B, G, 3) and the true shadow (B, G)."""
    pred = BatchedSiren(pred_weights, layout, siren.blocks)(box_to_siren(points, extent))
    return ((pred - values) ** 2).mean(1)


def geometry_loss(pred_weights: torch.Tensor, layout: WeightLayout, siren: SirenConfig, points: torch.Tensor,
                  values: torch.Tensor, extent: torch.Tensor) -> torch.Tensor:
    """MSE between the predicted SIRENs at presampled points (B, G, 3) and the true shadow there (B, G)."""
    return geometry_error(pred_weights, layout, siren, points, values, extent).mean()


TRAIN_STREAM, POOL_STREAM, CHECK_STREAM = 3, 13, 23  # random streams: training lights' points, pool lights', checks'


def presample(volume: Volume, tf, lights: np.ndarray, n_points: int, *, seed: int, stream: int = TRAIN_STREAM,
              visible_fraction: float = 0.5, device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """Points (N, M, 3) and their true shadow (N, M) per light, for the geometry loss (paper §3.3); on the
    CPU, whatever device marched them (the points are drawn on the CPU: the same on every device)."""
    field = ShadowField.build(volume, tf, device=device)
    pts = PointSampler(volume, tf, visible_fraction).sample(len(lights), n_points, seeded(seed, stream))
    values = transmittance_per_light(field, tf, lights, pts).cpu()
    return pts, values


CHECK_POINTS = 4096  # held-out points per scene at which the seen-light gap is measured (diffusion.target_gap)
CHECK_LIGHTS = 64  # training lights (evenly spaced rows) whose gap is measured: all of the default run's


def check_rows(n: int) -> torch.Tensor:
    """The rows of `n` training lights whose seen-light gap is measured: up to CHECK_LIGHTS, evenly spaced."""
    return torch.unique(torch.linspace(0, n - 1, min(n, CHECK_LIGHTS), device="cpu").round().long())


def check_points(volume: Volume, tf, lights: np.ndarray, n_points: int = CHECK_POINTS, *, seed: int,
                 device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """Points (C, 3) uniform in the box — how evaluate_voxels' "box" set is drawn, but other draws — and the
    true shadow (R, C) there of the lights `check_rows` picks. The geometry stage never trains on them, so the
    seen-light gap it measures there is the evaluation's: on tooth the presampled (training) points read 1.0 dB
    where the evaluation found 3.1 (docs/tuning.md). On the CPU, whatever device marched them."""
    field = ShadowField.build(volume, tf, device=device)
    extent = torch.as_tensor(volume.extent, dtype=torch.float32)
    gen = seeded(seed, CHECK_STREAM)
    pts = torch.rand(n_points, 3, generator=gen, device=gen.device) * extent
    checked = np.asarray(lights)[check_rows(len(lights)).numpy()]
    values = transmittance_per_light(field, tf, checked, pts).cpu()
    return pts, values
