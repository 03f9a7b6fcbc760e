"""Half-precision DDIM sampling against float32 on the main job's checkpoint: the largest weight difference
and how closely the SIRENs' outputs agree (4 training and 4 unseen lights, 5 steps, temperature 0).

    python scripts/half_precision_sampling.py      # after `snakemake --profile local -j2`
"""

import numpy as np
import torch

from diffshadow.diffusion.sample import generate, load_sampler
from diffshadow.lights import read_lights
from diffshadow.metrics import psnr
from diffshadow.siren import BatchedSiren


def main() -> None:
    torch.set_num_threads(1)
    state = torch.load("results/nucleon/diffusion.ckpt", map_location="cpu", weights_only=False)
    model, std, layout, siren = load_sampler(state)
    sets = read_lights("results/nucleon/lights.json")
    lights = np.concatenate([sets["train"][:4], sets["unseen"][:4]])
    full = generate(model, std, lights, steps=5, temperature=0.0, seed=0)
    pts = torch.rand(len(lights), 20000, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    a = BatchedSiren(full, layout, siren.blocks)(pts)
    for dtype in (torch.float16, torch.bfloat16):
        half = generate(model, std, lights, steps=5, temperature=0.0, seed=0, dtype=dtype)
        b = BatchedSiren(half, layout, siren.blocks)(pts)
        print(f"{dtype}: finite {bool(torch.isfinite(half).all())}, max |dw| {float((half - full).abs().max()):.2e}, "
              f"SIREN max diff {float((a - b).abs().max()):.2e}, "
              f"PSNR vs float32 median {float(psnr(b, a, dim=1).median()):.1f} dB")


if __name__ == "__main__":
    main()
