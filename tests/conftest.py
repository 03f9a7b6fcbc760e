from pathlib import Path

import numpy as np
import pytest

from diffshadow.transfer import TransferFunction

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def identity_tf(density_scale: float = 10.0) -> TransferFunction:
    return TransferFunction.from_config({
        "opacity": [[0.0, 0.0], [1.0, 1.0]],
        "color": [[0.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0]],
        "density_scale": density_scale,
    })


@pytest.fixture
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is absent")
    return SHARED_DATA


def gaussian_blob(n: int = 65, sigma: float = 0.12) -> np.ndarray:
    """exp(-r²/2σ²) around the box centre on an n³ vertex-centred grid, (Z, Y, X)."""
    ax = np.linspace(0.0, 1.0, n)
    z, y, x = np.meshgrid(ax, ax, ax, indexing="ij")
    return np.exp(-((x - 0.5) ** 2 + (y - 0.5) ** 2 + (z - 0.5) ** 2) / (2 * sigma**2)).astype(np.float32)
