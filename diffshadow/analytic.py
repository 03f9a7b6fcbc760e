"""Analytic test cases: a Gaussian blob whose transmittance has a closed form (erf)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

BLOB_SIGMA = 0.12
BLOB_DENSITY = 10.0
AXIS_AND_DIAGONAL = [(1, 0, 0), (-1, 0, 0), (0, 0, 1), (0, 0, -1), (0, 1, 0), (1, 1, 1), (-1, 1, -1), (1, -1, 1)]


def gaussian_blob(n: int = 65, sigma: float = BLOB_SIGMA) -> np.ndarray:
    """exp(-r²/2σ²) around the centre of the unit box on an n³ vertex-centred grid, (Z, Y, X) float32."""
    ax = np.linspace(0.0, 1.0, n)
    z, y, x = np.meshgrid(ax, ax, ax, indexing="ij")
    return np.exp(-((x - 0.5) ** 2 + (y - 0.5) ** 2 + (z - 0.5) ** 2) / (2 * sigma**2)).astype(np.float32)


def blob_transmittance(p: ArrayLike, w: ArrayLike, *, sigma: float = BLOB_SIGMA,
                       density: float = BLOB_DENSITY) -> float:
    """exp(-∫ density·exp(-|p + tw - c|²/2σ²) dt) from t = 0 to where the ray leaves the unit box.

    With identity opacity μ = density · blob (the blob's minimum, ~5e-12 at the corners, is neglected).
    """
    p = np.asarray(p, dtype=np.float64)
    w = np.asarray(w, dtype=np.float64)
    d = p - 0.5
    s0 = float(d @ w)
    perp2 = float(d @ d) - s0**2
    t_exit = min(((1.0 if wa > 0 else 0.0) - pa) / wa for pa, wa in zip(p, w, strict=True) if wa != 0)
    r = sigma * math.sqrt(2)
    depth = density * math.exp(-perp2 / (2 * sigma**2)) * sigma * math.sqrt(math.pi / 2) * (
        math.erf((t_exit + s0) / r) - math.erf(s0 / r))
    return math.exp(-depth)


def blob_cases(seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """1,000 (direction, points) pairs: 8 axis-aligned/diagonal directions × 45 points, 40 random × 16."""
    rng = np.random.default_rng(seed)
    dirs = [np.asarray(d, float) / np.linalg.norm(d) for d in AXIS_AND_DIAGONAL]
    dirs += [v / np.linalg.norm(v) for v in rng.normal(size=(40, 3))]
    counts = [45] * len(AXIS_AND_DIAGONAL) + [16] * 40
    return [(w, rng.uniform(0, 1, size=(c, 3))) for w, c in zip(dirs, counts, strict=True)]
