from pathlib import Path

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
