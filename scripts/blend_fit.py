"""Stage 1 refitted with the blend loss on a finished run's inputs, scored (issue 18, docs/tuning.md).

Fits a scene's training lights subset by subset from its `siren_init.pt`, as `fit_siren` does, with `fit`
settings given as JSON over config.yaml's (e.g. `{"blend_weight": 0.1}`), and prints the median voxel PSNR on
eval_truth's points of the stage-1 SIRENs on the training lights and of the weight blend of their 4 nearest at
the unseen test lights, beside the scene's own stage-1 weights. With `--out`, writes the weights as a
`weights.zarr` (the scene's store with these weights) for a diffusion run (`scripts/tuning.py diffusion`).

    python scripts/blend_fit.py --results results/tooth '{"blend_weight": 0.1}' --out /tmp/tooth_blend.zarr
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import torch

from diffshadow import artifacts
from diffshadow.config import defaults
from diffshadow.diffusion.train import BLEND_K
from diffshadow.fit import FitConfig, blend_pool, fit_sirens
from diffshadow.lights import blend_weights, light_subsets, read_lights
from diffshadow.siren import SirenConfig
from diffshadow.store import open_store, write_store


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("spec", nargs="?", default="{}", help="JSON settings over config.yaml's fit section")
    p.add_argument("--results", type=Path, default=Path("results/tooth"))
    p.add_argument("--subset-size", type=int, default=0, help="0: config.yaml's subset_size")
    p.add_argument("--contiguous", action="store_true",
                   help="subsets as runs of consecutive light indices (rings around the centre; before light_subsets)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--out", type=Path, default=None)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    r = a.results
    volume, tf = artifacts.load_prepared(r / "volume.zarr")
    sets = read_lights(r / "lights.json")
    train = sets["train"]
    store = open_store(r / "weights.zarr")
    chosen = artifacts.load_siren_init(r / "siren_init.pt", SirenConfig.from_config(defaults()["siren"]))
    siren, layout = chosen.siren, chosen.layout
    cfg = dataclasses.replace(FitConfig.from_config(json.loads(a.spec)), steps=chosen.steps)
    size = a.subset_size or int(defaults()["subset_size"])
    t0 = time.perf_counter()
    w = np.zeros((len(train), layout.n_params), dtype=np.float32)
    subsets = ([list(range(i, min(len(train), i + size))) for i in range(0, len(train), size)] if a.contiguous
               else light_subsets(train, size))
    for s, idx in enumerate(subsets):
        pool = blend_pool(volume, tf, train, sets["center"], idx, cfg)
        print(f"subset {s}: {len(idx)} lights, {0 if pool is None else len(pool.lights)} pool lights", flush=True)
        w[idx] = fit_sirens(chosen.init, layout, siren, volume, tf, train[idx], cfg, stream=s,
                            light_index=idx, pool=pool, log=lambda m: None).numpy()  # a subset is a patch, not a run

    def scores(w: np.ndarray) -> tuple[float, float]:
        idx, mix = blend_weights(train, sets["unseen"], BLEND_K)
        blend = (w.astype(np.float64)[idx] * mix[..., None]).sum(1)
        return (truth.median_psnr(w, layout, siren, train),
                truth.median_psnr(blend, layout, siren, sets["unseen"]))

    truth = artifacts.read_eval_truth(r / "eval_truth.zarr")
    print(f"fit {a.spec}: {time.perf_counter() - t0:.0f} s; stage 1 on the training lights / weight blend at the "
          f"unseen lights (median dB): {'{:.2f} / {:.2f}'.format(*scores(w))}; the scene's stage 1: "
          f"{'{:.2f} / {:.2f}'.format(*scores(np.asarray(store.weights)))}", flush=True)
    if a.out is not None:
        write_store(a.out, dataclasses.replace(store, weights=w.astype(np.float32)))
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
