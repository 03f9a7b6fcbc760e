"""Where the data INR's training points go: fit one data INR size with each (visible, error) share of points and
score it at every voxel, at random box points, at random points near visible voxels, and in opacity (what the
renderer integrates) at both. One thread per run, so two runs side by side compare fairly.

    python scripts/data_inr_points.py --scene config/scenes/neghip.yaml --width 128 --steps 3000 0.5/0 0.5/0.25
"""

import argparse
import time
from dataclasses import replace

import torch
import yaml

from diffshadow import artifacts
from diffshadow.data_inr import DataInrConfig, fit_data_inr_once
from diffshadow.grid import lookup_grids
from diffshadow.sampling import PointSampler, seeded
from diffshadow.siren import box_to_siren

N_POINTS = 200_000


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", required=True, help="scene file (volume and transfer function)")
    p.add_argument("--width", type=int, default=64)
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("shares", nargs="+", help="VISIBLE/ERROR point shares, e.g. 0.5/0.25 (the rest uniform)")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    volume, tf = artifacts.scene_volume(yaml.safe_load(open(args.scene)))
    base = replace(DataInrConfig.from_config(), width=args.width, steps=args.steps, target_psnr=0.0)
    grid = torch.as_tensor(volume.data)[None]
    extent = torch.as_tensor(volume.extent, dtype=torch.float32)
    sets = {"box": PointSampler(volume, tf, 0.0).sample(1, N_POINTS, seeded(9, 9)),
            "visible": PointSampler(volume, tf, 1.0).sample(1, N_POINTS, seeded(9, 10))}

    def db(mse: torch.Tensor) -> str:
        return f"{float(-10 * torch.log10(mse)):.2f}"

    print("visible/error | voxels dB | box dB | box opacity dB | visible dB | visible opacity dB | s")
    for share in args.shares:
        visible, error = (float(x) for x in share.split("/"))
        cfg = replace(base, visible_fraction=visible, error_fraction=error)
        t0 = time.perf_counter()
        inr = fit_data_inr_once(volume, tf, cfg, log=lambda m: None)
        seconds = time.perf_counter() - t0
        row = [share, f"{inr.psnr:.2f}"]
        for pts in sets.values():
            truth = lookup_grids(grid, pts, extent)[0]
            with torch.no_grad():
                pred = inr.model(box_to_siren(pts[0], extent))
            opacity_err = tf.opacity(pred.clamp(0, 1)) - tf.opacity(truth)
            row += [db(((pred - truth) ** 2).mean()), db((opacity_err ** 2).mean())]
        print(" | ".join(row + [f"{seconds:.0f}"]), flush=True)


if __name__ == "__main__":
    main()
