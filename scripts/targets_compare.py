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
from diffshadow.render import RenderScene


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

    def timed_images(scene: RenderScene, w) -> tuple[float, list[torch.Tensor]]:
        t = time.perf_counter()
        scene.gt_shadow(w)  # the grid, cached for the renders below
        seconds = time.perf_counter() - t
        return seconds, [torch.as_tensor(scene.render("gt", cam, light=w, step=cfg.step, min_transmittance=1e-6).rgb)
                         for cam in cams]

    march = RenderScene(volume, tf, gt_method="march")
    timed = [timed_images(march, w) for w in lights]  # rendered once, compared with both refinements
    t_march = sum(seconds for seconds, _ in timed)
    for up in (1, 2):
        sweep = RenderScene(volume, tf, gt_method="sweep", gt_upsample=up)
        values, fg_values, t_sweep = [], [], 0.0
        for w, (_, exact) in zip(lights, timed, strict=True):
            seconds, approx = timed_images(sweep, w)
            t_sweep += seconds
            for a_img, b_img in zip(approx, exact, strict=True):
                values.append(float(psnr(a_img, b_img)))
                fg = (b_img - b_img[0, 0]).abs().sum(-1) > 1e-6  # pixels the volume covers
                fg_values.append(float(psnr(a_img[fg], b_img[fg])))
        n = len(lights)
        print(f"{a.results} sweep at {up}x: image PSNR against the march median {np.median(values):.2f} dB "
              f"(min {np.min(values):.2f}), foreground pixels {np.median(fg_values):.2f} "
              f"(min {np.min(fg_values):.2f}); "
              f"grid s/light: march {t_march / n:.2f}, sweep {t_sweep / n:.3f} ({t_march / t_sweep:.0f}x)", flush=True)


if __name__ == "__main__":
    main()
