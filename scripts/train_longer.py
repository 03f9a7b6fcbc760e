"""Does a longer geometry stage help unseen lights? Continue a finished run's geometry stage (issue 18).

Copies `<results>/diffusion_geometry.ckpt`, reopens its growth (at the lr reached, as growth trains), trains on
to `--to` epochs with settings given as JSON over the checkpoint's own (e.g. '{"pool_x0_weight": 0}'), and
prints the median voxel PSNR of the generated seen and unseen lights (DDIM as the run samples, eval_truth's
points) at the start and every `--every` epochs. Each step's checkpoint is kept beside `--out` (`.e<epoch>`).

    python scripts/train_longer.py --results results/neghip --out /tmp/neghip_longer.ckpt --to 1000
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import time
from pathlib import Path

import torch

from diffshadow import artifacts
from diffshadow.diffusion import train as training
from diffshadow.diffusion.sample import generate, load_sampler
from diffshadow.diffusion.train import DiffusionConfig, train_diffusion
from diffshadow.lights import read_lights


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("spec", nargs="?", default="{}", help="JSON settings over the checkpoint's diffusion config")
    p.add_argument("--results", type=Path, required=True)
    p.add_argument("--out", type=Path, required=True, help="the continued checkpoint (written)")
    p.add_argument("--to", type=int, required=True, help="last epoch")
    p.add_argument("--every", type=int, default=100, help="epochs between scores")
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    data, _ = artifacts.read_training_data(a.results / "weights.zarr", a.results / "geometry_points.zarr")
    truth = artifacts.read_eval_truth(a.results / "eval_truth.zarr")
    light_sets = read_lights(a.results / "lights.json")
    src = artifacts.load_checkpoint(a.results / "diffusion_geometry.ckpt")
    # growth never ends early: no target reached (a tiny positive gap) and no plateau stop
    training.PLATEAU_CHECKS = 10**6
    cfg = dataclasses.replace(DiffusionConfig.of_checkpoint(src), target_gap=1e-3, max_epochs=a.to,
                              **json.loads(a.spec))
    state = {**src, "growth": {**src["growth"], "finished": False}, "config": dataclasses.asdict(cfg),
             "fingerprint": training._fingerprint(data, cfg)}
    torch.save(state, a.out)

    def score(st: dict) -> dict:
        model, std, layout, siren = load_sampler(st)
        out = {}
        for name in ("train", "unseen"):
            w = generate(model, std, light_sets[name], steps=cfg.ddim_steps, seed=cfg.seed, temperature=cfg.temperature)
            out[name] = round(truth.median_psnr(w.numpy(), layout, siren, light_sets[name]), 2)
        return out

    print(json.dumps({"epoch": int(src["epoch"]), **score(src)}), flush=True)
    t0 = time.perf_counter()
    for epoch in range(int(src["epoch"]) + a.every, a.to + 1, a.every):
        st = train_diffusion(data, cfg, a.out, log=lambda m: None, stop_after_epoch=epoch)
        shutil.copy(a.out, a.out.with_suffix(f".e{epoch}"))
        print(json.dumps({"epoch": epoch, **score(st), "s": round(time.perf_counter() - t0)}), flush=True)


if __name__ == "__main__":
    main()
