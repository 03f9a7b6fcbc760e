"""Several trained diffusion models' generated SIRENs per light, alone and averaged (docs/tuning.md).

Scores, as medians of voxel PSNR on eval_truth's points, the SIRENs each checkpoint generates for the seen and
the unseen lights (DDIM at the checkpoint's settings), and the per-light mean of their weights: is the spread
between training seeds independent error that averaging removes?

    python scripts/seed_ensemble.py --results results/tooth /tmp/tooth_s0.ckpt /tmp/tooth_s1.ckpt /tmp/tooth_s2.ckpt

(checkpoints from `python scripts/diffusion_precision.py --results results/tooth --state CKPT '{"seed": S}'`)
"""

import argparse
from pathlib import Path

import torch

from diffshadow import artifacts
from diffshadow.diffusion.sample import generate, load_sampler
from diffshadow.diffusion.train import DiffusionConfig
from diffshadow.lights import read_lights


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoints", nargs="+", type=Path)
    p.add_argument("--results", type=Path, default=Path("results/tooth"))
    p.add_argument("--threads", type=int, default=2)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    truth = artifacts.read_eval_truth(a.results / "eval_truth.zarr")
    light_sets = read_lights(a.results / "lights.json")
    gens: dict[str, list[torch.Tensor]] = {"train": [], "unseen": []}
    for path in a.checkpoints:
        state = torch.load(path, map_location="cpu", weights_only=False)
        model, std, layout, siren = load_sampler(state)
        cfg = DiffusionConfig.of_checkpoint(state)
        for name, out in gens.items():
            out.append(generate(model, std, light_sets[name], steps=cfg.ddim_steps, seed=cfg.seed,
                                temperature=cfg.temperature))

    def median(w: torch.Tensor, name: str) -> float:
        return truth.median_psnr(w.numpy(), layout, siren, light_sets[name])

    for name, out in gens.items():
        alone = ", ".join(f"{median(w, name):.2f}" for w in out)
        print(f"{name}: each model {alone} dB; weights averaged over the {len(out)} models "
              f"{median(torch.stack(out).mean(0), name):.2f} dB")


if __name__ == "__main__":
    main()
