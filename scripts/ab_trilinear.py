"""Side by side: grid_sample trilinear (before issue 8) against the lerp form (`shadow.trilinear`) in the
shadow march and sweep, median of 3 interleaved runs, and how far their results differ.

    python scripts/ab_trilinear.py ../shared/data/hydrogen_atom_128x128x128_uint8.raw   # bench/ab_trilinear_<name>.json
"""

import json
import statistics
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F

import diffshadow.shadow as sh
from diffshadow.transfer import TransferFunction
from diffshadow.volume import load_volume

LIGHT = (0.3, -0.5, 0.8)
TF = {"opacity": [[0, 0], [0.1, 0], [1, 1]], "color": [[0, 1, 1, 1], [1, 1, 1, 1]], "density_scale": 40.0}


def grid_sample_trilinear(grid: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
    """The former implementation: a weighted sum of 8 corners whose weights sum to 1 - 6e-8."""
    c, nz, ny, nx = grid.shape
    g = pos / (torch.tensor([nx, ny, nz], dtype=pos.dtype) - 1) * 2 - 1
    return F.grid_sample(grid[None], g.view(1, 1, 1, -1, 3), mode="bilinear", padding_mode="border",
                         align_corners=True).view(c, -1)


def main(path: str) -> None:
    torch.set_num_threads(2)
    vol, tf = load_volume(path), TransferFunction.from_config(TF)
    lerp = sh.trilinear
    times = {m: {"old": [], "new": []} for m in ("march", "sweep")}
    grids = {}
    try:
        for _rep in range(3):
            for name, fn in (("old", grid_sample_trilinear), ("new", lerp)):
                sh.trilinear = fn
                for method in times:
                    t = time.perf_counter()
                    grids[method, name] = sh.shadow_grid(vol, tf, LIGHT, method=method)
                    times[method][name].append(time.perf_counter() - t)
    finally:
        sh.trilinear = lerp
    summary = {m: {k: statistics.median(v) for k, v in d.items()} for m, d in times.items()}
    for m in times:
        summary[m]["new/old"] = summary[m]["new"] / summary[m]["old"]
        summary[f"max_diff_{m}"] = float((grids[m, "old"] - grids[m, "new"]).abs().max())
    out = Path("bench") / f"ab_trilinear_{vol.name}.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main(sys.argv[1])
