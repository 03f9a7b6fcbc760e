"""The geometry loss (paper §3.3): the de-standardised predicted SIRENs evaluated at presampled points
against the true shadow there, and the presampling of those points and values."""

from __future__ import annotations

import numpy as np
import torch

from diffshadow.sampling import PointSampler, seeded
from diffshadow.shadow import ShadowField, transmittance
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


TRAIN_STREAM, POOL_STREAM = 3, 13  # random streams of the training lights' points and the pool lights'


def presample(volume: Volume, tf, lights: np.ndarray, n_points: int, *, seed: int, stream: int = TRAIN_STREAM,
              visible_fraction: float = 0.5, device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """Points (N, M, 3) and their true shadow (N, M) per light, for the geometry loss (paper §3.3); on the
    CPU, whatever device marched them (the points are drawn on the CPU: the same on every device)."""
    field = ShadowField.build(volume, tf, device=device)
    pts = PointSampler(volume, tf, visible_fraction).sample(len(lights), n_points, seeded(seed, stream))
    values = torch.stack([transmittance(field, tf, w, p.to(device)).cpu() for w, p in zip(lights, pts, strict=True)])
    return pts, values
