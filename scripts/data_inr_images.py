"""Image PSNR of data INRs fitted with other point shares or seeds, on a finished scene's generated SIRENs: each
data INR is fitted, saved to a temporary folder and scored by `evaluate_images` exactly as the workflow does
(the deployed path and `naive`). How far images move between data INRs of the same voxel PSNR.

    python scripts/data_inr_images.py --results results/nucleon 0.5/0/1 0.5/0.25/1   # VISIBLE/ERROR/SEED
"""

import argparse
import contextlib
import io
import json
import tempfile
from dataclasses import replace
from pathlib import Path

import torch

from diffshadow import artifacts
from diffshadow.config import defaults
from diffshadow.data_inr import DataInrConfig, fit_data_inr_once
from diffshadow.stages.images import evaluate_images


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--results", type=Path, required=True, help="a finished scene's results folder")
    p.add_argument("--width", type=int, default=64)
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("specs", nargs="+", help="VISIBLE/ERROR/SEED, e.g. 0.5/0.25/1")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    r = args.results
    volume, tf = artifacts.load_prepared(r / "volume.zarr")
    render_cfg = defaults()["render"]
    base = replace(DataInrConfig.from_config(), width=args.width, steps=args.steps, target_psnr=0.0)
    for spec in args.specs:
        visible, error, seed = spec.split("/")
        cfg = replace(base, visible_fraction=float(visible), error_fraction=float(error), seed=int(seed))
        inr = fit_data_inr_once(volume, tf, cfg, log=lambda m: None)
        with tempfile.TemporaryDirectory() as tmp:
            d = Path(tmp)
            artifacts.save_data_inr(d / "data_inr.pt", inr)
            with contextlib.redirect_stdout(io.StringIO()):
                evaluate_images(r / "volume.zarr", r / "lights.json", d / "data_inr.pt", r / "weights.zarr",
                                r / "generated.zarr", d / "images", d / "m.json", cfg=render_cfg,
                                device=torch.device("cpu"))
            modes = json.loads((d / "m.json").read_text())["modes"]
        print(f"{spec}: voxels {inr.psnr:.2f} dB, deployed {modes['inr_generated_data_inr']['psnr']:.2f} dB, "
              f"naive {modes['naive']['psnr']:.2f} dB", flush=True)


if __name__ == "__main__":
    main()
