import contextlib
import os
import shutil
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

if not torch.cuda.is_available():
    # Triton reads this when it is first imported (torch may import it before any test does): without a GPU,
    # the fused SIREN's kernel runs through Triton's interpreter in tests/test_fused.py
    os.environ.setdefault("TRITON_INTERPRET", "1")

from diffshadow.hpc import JOB_ENVIRONMENT
from diffshadow.siren import Siren, SirenConfig
from diffshadow.transfer import TransferFunction

for _key, _value in JOB_ENVIRONMENT.items():  # the workflow's job environment: the stages' matrix products
    os.environ.setdefault(_key, _value)

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def _fused_adamw_on_cpu() -> bool:
    from diffshadow.adam import fused_supported

    return fused_supported([torch.ones(1)])  # torch 2.3: CUDA only


needs_cpu_fused_adamw = pytest.mark.skipif(not _fused_adamw_on_cpu(),
                                           reason="this torch has no fused AdamW on the CPU (2.4 and later do)")


def identity_tf(density_scale: float = 10.0) -> TransferFunction:
    return TransferFunction.from_config({
        "opacity": [[0.0, 0.0], [1.0, 1.0]],
        "color": [[0.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0]],
        "density_scale": density_scale,
    })


def data_inr_stub(width: int, blocks: int, seed: int = 3) -> SimpleNamespace:
    """What RenderScene reads of a data INR: its SIREN, and no cell ranges (the renderer finds its own)."""
    return SimpleNamespace(model=Siren(SirenConfig(width, blocks), torch.Generator().manual_seed(seed)),
                           cell_lo=None, cell_hi=None)


def installed(name: str) -> Path:
    """This environment's console script `name`: beside the interpreter in a virtual environment, else on PATH
    (the lent GPU machine puts the checkout on PYTHONPATH and its commands in a folder of their own)."""
    found = shutil.which(name, path=str(Path(sys.executable).parent)) or shutil.which(name)
    if found is None:
        pytest.fail(f"no {name!r} beside {sys.executable} or on PATH: run `pip install -e .` first")
    return Path(found)


def imported_modules(importtime_stderr: str) -> list[str]:
    """The modules a process imported, from its `python -X importtime` report (its stderr)."""
    return [line.rsplit("|", 1)[-1].strip() for line in importtime_stderr.splitlines() if "import time:" in line]


@pytest.fixture
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is absent")
    return SHARED_DATA


class Asker:
    """An `interrupt` that counts the times it is asked and says stop from the `stop_at`-th on (0: never)."""

    def __init__(self, stop_at: int = 0):
        self.asked, self.stop_at = 0, stop_at

    def __call__(self) -> bool:
        self.asked += 1
        return 0 < self.stop_at <= self.asked


class Killed(Exception):
    """A run killed by `stop_at`'s log function."""


def stop_at(prefix: str):
    """A log function that kills the run (raises Killed) at the first line starting with `prefix`: a job killed
    at a known step, its checkpoints as they were."""
    def log(message: str) -> None:
        if message.startswith(prefix):
            raise Killed(message)
    return log


@contextlib.contextmanager
def default_device_meta():
    """Guard for the CUDA path on a machine without CUDA: a tensor made without naming its device lands
    on "meta" and fails as soon as it meets real data, as a CPU tensor fails next to CUDA tensors.
    (diffshadow.adam names the host for Adam's step count, which PyTorch's own Adam kept there by design.)"""
    torch.set_default_device("meta")
    try:
        yield
    finally:
        torch.set_default_device(None)


def cores() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def pytest_configure(config) -> None:
    """pytest-xdist (the `-n` in pyproject.toml) runs test files in parallel processes. PyTorch's OpenMP threads spin
    while they wait for each other, so two processes of 2 threads each on 2 cores can stall each other: a loop of
    small products took 9-76 s a process against 2.5-3.9 s alone (docs/performance.md, "The test suite"). Each
    worker, and every process it starts, gets its share of the cores, unless the user set OMP_NUM_THREADS."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1 and "OMP_NUM_THREADS" not in os.environ:
        share = max(1, cores() // workers)
        os.environ["OMP_NUM_THREADS"] = str(share)
        torch.set_num_threads(share)


def pytest_xdist_auto_num_workers(config) -> int:
    """What `-n auto` means: a worker per core, at most 4. The longest test file (tests/test_workflow.py, its
    Snakemake runs one after another) bounds the suite's time whatever the number of workers."""
    return max(1, min(4, cores()))
