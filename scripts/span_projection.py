"""How much of the generated SIRENs' error lies outside the span of the training SIRENs (issue 18).

Loads a trained checkpoint, generates SIRENs for the training and the unseen lights (DDIM, the config's
steps), and scores them as generated and projected (in standardised weight space) onto the affine span of the
first k principal components of the training weights; also splits the seen lights' weight error into its
in-span and out-of-span parts, and scores each tensor's share of it. Medians of voxel PSNR on eval_truth's box points.

    python scripts/span_projection.py --results results/tooth results/tooth/diffusion_geometry.ckpt
"""

import argparse
from pathlib import Path

import numpy as np
import torch

from diffshadow import artifacts
from diffshadow.diffusion.sample import generate, load_sampler
from diffshadow.diffusion.train import DiffusionConfig
from diffshadow.evaluate import psnr_per_light
from diffshadow.lights import read_lights


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("checkpoint", type=Path)
    p.add_argument("--results", type=Path, default=Path("results/nucleon"))
    p.add_argument("--threads", type=int, default=2)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    data, _ = artifacts.read_training_data(a.results / "weights.zarr", a.results / "geometry_points.zarr")
    truth = artifacts.read_eval_truth(a.results / "eval_truth.zarr")
    light_sets = read_lights(a.results / "lights.json")
    state = torch.load(a.checkpoint, map_location="cpu", weights_only=False)
    cfg = DiffusionConfig.of_checkpoint(state)
    model, std, layout, siren = load_sampler(state)

    def median(z: torch.Tensor, name: str) -> float:
        w = std.destandardize(z.double()).float().numpy()
        return float(np.median(psnr_per_light(truth.sirens(w, layout, siren), truth.of(light_sets[name]))["box"]))

    z_train = std.standardize(data.weights).double()
    mean = z_train.mean(0)
    _, s, vt = torch.linalg.svd(z_train - mean, full_matrices=False)
    print(f"training weights: {len(z_train)} lights, {z_train.shape[1]} parameters; singular values "
          f"{', '.join(f'{v:.1f}' for v in s[:8].tolist())}, ... {s[-2]:.2e}, {s[-1]:.2e}")
    gen = {n: std.standardize(generate(model, std, light_sets[n], steps=cfg.ddim_steps, seed=cfg.seed,
                                       temperature=cfg.temperature)).double() for n in ("train", "unseen")}
    err = gen["train"] - z_train
    inside = (err @ vt.T) @ vt
    print(f"seen-light weight error (standardised MSE): {float((err ** 2).mean()):.3e}, in the training span "
          f"{float((inside ** 2).mean()):.3e}, outside {float(((err - inside) ** 2).mean()):.3e}")
    print(f"stage 1: seen {median(z_train, 'train'):.2f} dB")
    full = len(s) - 1  # the last singular value is 0: N lights span N - 1 dimensions around their mean
    rows = [("generated", full, 1.0)] + [(f"projected on {k} components", k, 0.0) for k in (4, 8, 16, full)]
    rows += [(f"out-of-span part x {alpha}", full, alpha) for alpha in (0.25, 0.5, 0.75)]
    for name, k, alpha in rows:
        out = []
        for n in ("train", "unseen"):
            basis = vt[:k]
            inside = mean + ((gen[n] - mean) @ basis.T) @ basis
            out.append(median((inside + alpha * (gen[n] - inside)).float(), n))
        print(f"{name}: seen {out[0]:.2f} dB, unseen {out[1]:.2f} dB")
    # which tensors' errors cost the seen lights most: the generated weights with one tensor set to stage 1's
    offsets = np.cumsum([0] + layout.sizes)
    for (tensor, _), lo, hi in zip(layout.entries, offsets[:-1], offsets[1:], strict=True):
        z = gen["train"].clone()
        z[:, lo:hi] = z_train[:, lo:hi]
        share = float((err[:, lo:hi] ** 2).sum() / (err ** 2).sum())
        print(f"seen lights with {tensor} from stage 1: {median(z.float(), 'train'):.2f} dB "
              f"({share:.1%} of the standardised error)")


if __name__ == "__main__":
    main()
