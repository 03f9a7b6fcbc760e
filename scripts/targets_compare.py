"""Fine-tuning target images with the march's shadow grid against the sweep's, on a finished run's inputs:
image PSNR between them and the grids' time, side by side (docs/tuning.md, "Fine-tuning targets").

    python scripts/targets_compare.py --results results/tooth --lights 2
"""

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from diffshadow import artifacts
from diffshadow.diffusion.finetune import FinetuneConfig, fibonacci_views
from diffshadow.lights import read_lights
from diffshadow.metrics import psnr
from diffshadow.render import GridShadow, RenderScene
from diffshadow.shadow import shadow_grid
from diffshadow.volume import refine


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--results", type=Path, default=Path("results/nucleon"))
    p.add_argument("--lights", type=int, default=4, help="training lights, spread over the set")
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    cfg = FinetuneConfig.from_config()
    volume, tf = artifacts.load_prepared(a.results / "volume.zarr")
    train = read_lights(a.results / "lights.json")["train"]
    lights = train[np.linspace(0, len(train) - 1, a.lights).astype(int)]
    cams = fibonacci_views(volume.extent, cfg.views, size=cfg.image_size, fov=cfg.fov)
    scene = RenderScene(volume, tf)

    for up in (1, 2):
        fine = refine(volume, up)
        values, fg_values, t_march, t_sweep = [], [], 0.0, 0.0
        for w in lights:
            t = time.perf_counter()
            march = shadow_grid(volume, tf, w, method="march")
            t_march += time.perf_counter() - t
            t = time.perf_counter()
            sweep = shadow_grid(fine, tf, w, method="sweep")
            t_sweep += time.perf_counter() - t
            for cam in cams:
                pair = []
                for grid in (march, sweep):
                    scene._cache[scene._gt_key(w)] = GridShadow(grid, volume.extent)  # the gt mode's shadow
                    pair.append(torch.as_tensor(scene.render("gt", cam, light=w, step=cfg.step,
                                                             min_transmittance=1e-6).rgb))
                values.append(float(psnr(pair[1], pair[0])))
                fg = (pair[0] - pair[0][0, 0]).abs().sum(-1) > 1e-6  # pixels the volume covers
                fg_values.append(float(psnr(pair[1][fg], pair[0][fg])))
        n = len(lights)
        print(f"{a.results} sweep at {up}x: image PSNR against the march median {np.median(values):.2f} dB "
              f"(min {np.min(values):.2f}), foreground pixels {np.median(fg_values):.2f} "
              f"(min {np.min(fg_values):.2f}); "
              f"grid s/light: march {t_march / n:.2f}, sweep {t_sweep / n:.3f} ({t_march / t_sweep:.0f}x)", flush=True)


if __name__ == "__main__":
    main()
