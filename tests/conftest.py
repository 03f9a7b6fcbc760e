import contextlib
import os
from pathlib import Path

import pytest
import torch

if not torch.cuda.is_available():
    # Triton reads this when it is first imported (torch may import it before any test does): without a GPU,
    # the fused SIREN's kernel runs through Triton's interpreter in tests/test_fused.py
    os.environ.setdefault("TRITON_INTERPRET", "1")

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


@contextlib.contextmanager
def default_device_meta():
    """Guard for the CUDA path on a machine without CUDA: a tensor made without naming its device lands
    on "meta" and fails as soon as it meets real data, as a CPU tensor fails next to CUDA tensors."""
    torch.set_default_device("meta")
    try:
        yield
    finally:
        torch.set_default_device(None)
