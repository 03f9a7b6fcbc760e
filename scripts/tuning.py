"""The runs behind the tiny scene's defaults (docs/performance.md): one stage refitted with settings given as JSON
over the package defaults (diffshadow/defaults.yaml, not config/config.yaml), on a finished run's inputs, timed on
`--threads` threads (default one), scored on held-out points.

    python scripts/tuning.py fit '{}' '{"points": 4096}' '{"points": 1024, "lr": 2e-3}'   # 4 lights, like a subset
    python scripts/tuning.py data-inr '{}' '{"steps": 1500, "points": 16384}'
    python scripts/tuning.py diffusion '{}' '{"epochs": 400}' '{"preset": "tiny"}'     # seen/unseen DDIM PSNR
    python scripts/tuning.py diffusion '{"pool_lights": 0}' '{"pool_lights": 128, "pool_x0_weight": 1.0}'

`--results DIR` (default results/nucleon) must hold volume.zarr, lights.json, siren_init.pt; the diffusion
runs also need weights.zarr, geometry_points.zarr and eval_truth.zarr.
"""

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import torch

from diffshadow import artifacts
from diffshadow.lights import read_lights
from diffshadow.volume import load_prepared

FIT_LIGHTS = [5, 21, 38, 60]  # spread over 64 training lights; scaled to a run with another count (none is light 0,
# the pre-optimised one)


def fit(results: Path, spec: dict) -> str:
    from diffshadow.fit import FitConfig, evaluate_psnr, fit_sirens
    from diffshadow.siren import SirenConfig, WeightLayout

    volume, tf = load_prepared(results / "volume.zarr")
    train = read_lights(results / "lights.json")["train"]
    lights = train[[i * len(train) // 64 for i in FIT_LIGHTS]]
    chosen = artifacts.load_siren_init(results / "siren_init.pt", SirenConfig(32, 2))
    siren, init = chosen.siren, chosen.init
    layout = WeightLayout.for_siren(siren)
    cfg = FitConfig.from_config({"steps": chosen.steps, "points": chosen.points, **spec})
    t = time.perf_counter()
    w = fit_sirens(init, layout, siren, volume, tf, lights, cfg, stream=0, log=lambda m: None)
    seconds = time.perf_counter() - t
    box, vis = evaluate_psnr(w, layout, siren, volume, tf, lights, n_points=16384, seed=99)
    return f"{seconds:6.1f} s  box median {np.median(box):.2f} dB (min {box.min():.2f}), visible {np.median(vis):.2f}"


def data_inr(results: Path, spec: dict) -> str:
    from diffshadow.data_inr import DataInrConfig, fit_data_inr

    volume, tf = load_prepared(results / "volume.zarr")
    t = time.perf_counter()
    inr = fit_data_inr(volume, tf, DataInrConfig.from_config(spec), log=lambda m: None)
    return f"{time.perf_counter() - t:6.1f} s  voxel PSNR {inr.psnr:.2f} dB, max error {inr.max_error:.4f}"


def _pool(results: Path, light_sets: dict, cfg):
    from diffshadow.lights import BLEND_K, POOL_X0_WEIGHTING, PoolLights, blend_weights, training_pool
    from diffshadow.sampling import Stream
    from diffshadow.truth import presample

    volume, tf = load_prepared(results / "volume.zarr")
    lights = training_pool(light_sets["train"], light_sets["center"], cfg.pool_lights, seed=cfg.seed)
    pts, values = presample(volume, tf, lights, cfg.pool_points, seed=cfg.seed, stream=Stream.POOL_POINTS)
    idx, blend = blend_weights(light_sets["train"], lights, BLEND_K, POOL_X0_WEIGHTING)
    return PoolLights(torch.as_tensor(lights), pts, values, torch.as_tensor(idx),
                      torch.as_tensor(blend, dtype=torch.float32))


def diffusion(results: Path, spec: dict) -> str:
    from diffshadow.diffusion.sample import generate, load_sampler
    from diffshadow.diffusion.train import DiffusionConfig, train_diffusion

    data, _ = artifacts.read_training_data(results / "weights.zarr", results / "geometry_points.zarr")
    truth = artifacts.read_eval_truth(results / "eval_truth.zarr")
    light_sets = read_lights(results / "lights.json")
    cfg = DiffusionConfig.from_config(spec)
    if not cfg.target_gap:  # no checkpoints to write; with a target gap they are where it is checked
        cfg = dataclasses.replace(cfg, checkpoint_every=10**9)
    if cfg.pool_lights and (data.pool is None or len(data.pool.lights) != cfg.pool_lights):
        data.pool = _pool(results, light_sets, cfg)  # another count than presample's: drawn here the same way
    part = Path(f"/tmp/tuning_diffusion_{abs(hash(json.dumps(spec, sort_keys=True)))}.part")
    part.unlink(missing_ok=True)
    t = time.perf_counter()
    state = train_diffusion(data, cfg, part, log=lambda m: None)
    seconds = time.perf_counter() - t
    part.unlink(missing_ok=True)
    model, std, layout, siren = load_sampler(state)
    scores = []
    for name in ("train", "unseen"):
        w = generate(model, std, light_sets[name], method="ddim", steps=cfg.ddim_steps, seed=cfg.seed,
                     temperature=cfg.temperature).numpy()
        scores.append(truth.median_psnr(w, layout, siren, light_sets[name]))
    return (f"{seconds:6.1f} s, {int(state['epoch'])} epochs  generated median seen {scores[0]:.2f} dB, unseen "
            f"{scores[1]:.2f} dB (geometry stage)")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("stage", choices=["fit", "data-inr", "diffusion"])
    p.add_argument("specs", nargs="+", help="JSON settings over the package defaults' section, one run each")
    p.add_argument("--results", type=Path, default=Path("results/nucleon"))
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    run = {"fit": fit, "data-inr": data_inr, "diffusion": diffusion}[a.stage]
    for spec in a.specs:
        print(f"{a.stage} {spec:48s} {run(a.results, json.loads(spec))}", flush=True)


if __name__ == "__main__":
    main()
