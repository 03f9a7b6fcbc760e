"""How well a trained diffusion model fits the pool lights it was trained on (issue 18).

    python scripts/pool_fit.py --results results/nucleon [--checkpoint diffusion_geometry.ckpt]

The pool lights (`diffusion.pool_lights`) have exact shadows at `pool_points` points and the model is trained
on them with the geometry loss, so their PSNR says whether unseen lights are limited by what the model can
fit (pool lights about as poor as unseen ones) or by interpolation (pool lights near the seen ones). Prints the
median voxel PSNR at those points of: the stage-1 SIRENs and the generated ones on the training lights, the
generated SIRENs and the weight blend of the 4 nearest training SIRENs on the pool lights. `--timesteps`
adds the model's x0 on the pool lights from their training input (the blend noised to t): equal to the
generated figure when sampling is not what limits them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from diffshadow import artifacts
from diffshadow.diffusion.sample import generate, load_sampler
from diffshadow.diffusion.schedule import Schedule
from diffshadow.metrics import psnr
from diffshadow.siren import BatchedSiren, box_to_siren


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", type=Path, default=Path("results/nucleon"))
    parser.add_argument("--checkpoint", default="diffusion_geometry.ckpt", help="file under --results")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--timesteps", type=int, nargs="*", default=[], help="score the x0 from the blend noised to t")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    r = args.results
    data, _ = artifacts.read_training_data(r / "weights.zarr", r / "geometry_points.zarr")
    if data.pool is None:
        raise SystemExit(f"{r / 'geometry_points.zarr'}: no pool lights (diffusion.pool_lights is 0)")
    state = artifacts.load_checkpoint(r / args.checkpoint)
    model, std, layout, siren = load_sampler(state)
    steps, temperature = state["config"]["ddim_steps"], state["config"]["temperature"]

    def median_psnr(weights: torch.Tensor, points: torch.Tensor, values: torch.Tensor) -> float:
        with torch.no_grad():
            pred = BatchedSiren(weights, layout, siren.blocks)(box_to_siren(points, data.extent))
        return float(np.median(psnr(pred, values, dim=1).numpy()))

    generated = generate(model, std, data.lights.numpy(), steps=steps, temperature=temperature)
    print(f"training lights ({len(data.lights)}): stage 1 {median_psnr(data.weights, data.points, data.values):.2f} dB,"
          f" generated {median_psnr(generated, data.points, data.values):.2f} dB")
    pool = data.pool
    generated = generate(model, std, pool.lights.numpy(), steps=steps, temperature=temperature)
    # the pool lights' x0 prior in training: the blend of their nearest training SIRENs' weights
    z_blend = pool.x0(std.standardize(data.weights).float(), torch.arange(len(pool.lights)))
    blend = std.destandardize(z_blend.double()).float()
    print(f"pool lights ({len(pool.lights)}): generated {median_psnr(generated, pool.points, pool.values):.2f} dB,"
          f" weight blend of the 4 nearest {median_psnr(blend, pool.points, pool.values):.2f} dB")
    schedule = Schedule()
    noise = torch.randn(z_blend.shape, generator=torch.Generator().manual_seed(0))
    for t in args.timesteps:
        tt = torch.full((len(z_blend),), t, dtype=torch.long)
        with torch.no_grad():
            x0 = model(schedule.q_sample(z_blend, tt, noise), tt, pool.lights.float())
        print(f"x0 from the blend noised to t = {t}: "
              f"{median_psnr(std.destandardize(x0.double()).float(), pool.points, pool.values):.2f} dB")


if __name__ == "__main__":
    main()
