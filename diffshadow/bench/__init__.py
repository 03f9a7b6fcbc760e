"""Benchmarks that print and save figures (never asserted in unit tests: machines are noisy).

A leaf: the stage layer and the CLI import it, no concept module does.

- `bench.shadow`: time against error of the ground-truth shadow methods, side by side in one process,
  against `march` at 1/8 voxel.
- `bench.siren`: K SIRENs fitted jointly against one after another; the weight spread of the shared init;
  stored against recomputed PSNR.
- `bench.render`: fps, peak memory and the step curve of the renderer's modes.
- `bench.kernels`: registers, spills and programs per SM of the fused kernels, compiled for a GPU without one.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from diffshadow.volume import bundled_path

T = TypeVar("T")

SHARED_DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
# Opacity 0 below s = 0.1 leaves most of a sparse volume empty (hydrogen_atom: 97 % of voxels).
BENCH_TF = {
    "opacity": [[0.0, 0.0], [0.1, 0.0], [1.0, 1.0]],
    "color": [[0.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0]],
    "density_scale": 40.0,
}
BENCH_LIGHT = (0.3, -0.5, 0.8)  # a generic direction: no axis or diagonal symmetry to flatter the sweep
REFERENCE_STEP = 0.125


def default_volumes() -> list[Path]:
    """The bundled nucleon plus every volume in ../shared/data when present."""
    paths = [bundled_path("nucleon")]
    if SHARED_DATA.is_dir():
        paths += sorted(p for p in SHARED_DATA.glob("*.raw") if not p.name.startswith("nucleon"))
    return paths


def timed(fn: Callable[[], T]) -> tuple[T, float]:
    t = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t
