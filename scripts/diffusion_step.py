"""Milliseconds per geometry-stage training step (default config, pool lights on) on a finished run's data:
for comparing two versions of the code side by side (docs/tuning.md, "Run time").

    python scripts/diffusion_step.py --threads 2                       # this checkout
    PYTHONPATH=/path/to/other/checkout python scripts/diffusion_step.py --threads 2
"""

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import torch

import diffshadow
from diffshadow import artifacts
from diffshadow.diffusion.train import DiffusionConfig, train_diffusion


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--results", type=Path, default=Path("results/nucleon"))
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--epochs", type=int, default=12)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    data, _ = artifacts.read_training_data(a.results / "weights.zarr", a.results / "geometry_points.zarr")
    cfg = dataclasses.replace(DiffusionConfig.from_config({}), epochs=a.epochs, checkpoint_every=10**9)
    steps = a.epochs * -(-len(data.weights) // cfg.batch_size)
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        train_diffusion(data, cfg, Path(tmp) / "step.ckpt", log=lambda m: None)
        ms = (time.perf_counter() - t) / steps * 1000
    print(f"{Path(diffshadow.__file__).parent.parent}: {ms:.0f} ms per step ({steps} steps, {a.threads} threads)")


if __name__ == "__main__":
    main()
