"""Per-light PSNR change from fine-tuning (fine-tuned − geometry-stage model, DDIM) on the test sets of a
finished run and on extra random lights in the training cap: how many lights a median needs (docs/tuning.md,
"How many test lights").

    python scripts/finetune_change.py                       # results/nucleon, 2 draws of 64 random lights
    python scripts/finetune_change.py --random 256 --streams 0 5 9
"""

import argparse
from pathlib import Path

import numpy as np
import torch

from diffshadow import artifacts
from diffshadow.diffusion.sample import generate, load_sampler
from diffshadow.evaluate import EvalTruth, psnr_per_light
from diffshadow.lights import read_lights, validation_lights


def psnr(state: dict, truth: EvalTruth, lights: np.ndarray) -> np.ndarray:
    model, std, layout, siren = load_sampler(state)
    w = generate(model, std, lights, method="ddim", steps=50, seed=0).numpy()
    return psnr_per_light(truth.sirens(w, layout, siren), truth.of(lights))["box"]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--results", type=Path, default=Path("results/nucleon"))
    p.add_argument("--random", type=int, default=64, help="random lights in the cap per stream")
    p.add_argument("--streams", type=int, nargs="+", default=[0, 5])
    p.add_argument("--points", type=int, default=4096)
    p.add_argument("--threads", type=int, default=2)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    states = [torch.load(a.results / name, map_location="cpu", weights_only=False)
              for name in ("diffusion_geometry.ckpt", "diffusion.ckpt")]
    sets = read_lights(a.results / "lights.json")
    truth = artifacts.read_eval_truth(a.results / "eval_truth.zarr")
    volume, tf = artifacts.load_prepared(a.results / "volume.zarr")
    rows = [(name, truth, sets[name]) for name in ("unseen", "train")]
    for stream in a.streams:
        lights = validation_lights(sets["train"], sets["center"], a.random, seed=stream)
        rows.append((f"{a.random} random, stream {stream}", EvalTruth.compute(volume, tf, lights, a.points, 1), lights))
    print("| lights | fine-tuned − geometry stage, median | mean | lights that improved |\n|---|---|---|---|")
    for name, t, lights in rows:
        d = psnr(states[1], t, lights) - psnr(states[0], t, lights)
        print(f"| {name} ({len(lights)}) | {np.median(d):+.2f} dB | {d.mean():+.2f} | {(d > 0).sum()} / {len(d)} |")


if __name__ == "__main__":
    main()
