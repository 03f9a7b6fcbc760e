"""The geometry loss (paper §3.3): the de-standardised predicted SIRENs evaluated at presampled points
against the true shadow there (the points and values: `truth.presample`)."""

from __future__ import annotations

import torch

from diffshadow.siren import BatchedSiren, SirenConfig, WeightLayout, box_to_siren


def geometry_error(pred_weights: torch.Tensor, layout: WeightLayout, siren: SirenConfig, points: torch.Tensor,
                   values: torch.Tensor, extent: torch.Tensor) -> torch.Tensor:
    """Per light (B,): MSE between the predicted SIRENs at presampled points (B, G, 3) and the true shadow (B, G)."""
    pred = BatchedSiren(pred_weights, layout, siren.blocks)(box_to_siren(points, extent))
    return ((pred - values) ** 2).mean(1)
