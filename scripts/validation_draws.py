"""Diffusion checkpoints scored on random lights in the training cap, drawn like fine-tuning's validation set
(lights.validation_lights) with any count and seed: how far a median over a few lights moves between draws.

    python scripts/validation_draws.py --results results/nucleon --lights 64 --seed 0 \
        results/nucleon/diffusion_geometry.ckpt
"""

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from diffshadow import artifacts
from diffshadow.diffusion.sample import generate, load_sampler
from diffshadow.evaluate import EvalTruth, psnr_per_light
from diffshadow.lights import read_lights, validation_lights


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoints", nargs="+", type=Path)
    p.add_argument("--results", type=Path, default=Path("results/nucleon"))
    p.add_argument("--lights", type=int, default=64)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--points", type=int, default=4096)
    p.add_argument("--steps", type=int, nargs="+", default=[10])
    p.add_argument("--threads", type=int, default=2)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    volume, tf = artifacts.load_prepared(a.results / "volume.zarr")
    sets = read_lights(a.results / "lights.json")
    lights = validation_lights(sets["train"], sets["center"], a.lights, seed=a.seed)
    t = time.perf_counter()
    truth = EvalTruth.compute(volume, tf, lights, a.points, a.seed + 1)
    print(f"{a.lights} lights (seed {a.seed}), exact shadows at {a.points} points each: "
          f"{time.perf_counter() - t:.0f} s")
    for path in a.checkpoints:
        model, std, layout, siren = load_sampler(artifacts.load_checkpoint(path))
        for steps in a.steps:
            w = generate(model, std, lights, method="ddim", steps=steps, seed=0, temperature=0.0).numpy()
            psnr = psnr_per_light(truth.sirens(w, layout, siren), truth.of(lights))["box"]
            print(f"{path} DDIM {steps}: median {np.median(psnr):.2f} dB, mean {psnr.mean():.2f}, "
                  f"25th percentile {np.percentile(psnr, 25):.2f}")


if __name__ == "__main__":
    main()
