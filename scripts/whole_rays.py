"""Counts of the whole-ray kernel that need no GPU: how busy its lanes are per ray order, and its ops and host
syncs per frame at the GPU plan.

    python scripts/whole_rays.py --sizes 64 512 1024

1. Lane use. A program of `FusedSamples.march` takes `block` rays and runs until its last ray stops, so its
   lanes do (trips x block) sample slots for the samples its rays take. On hydrogen_atom no ray stops early
   (checked at 64² in Triton's interpreter: the same samples as without early termination), so a ray's samples
   are its occupied samples (`Runs.total`) and the slots of any ray order follow from those: in image order (rows
   of pixels), in 8x8 pixel tiles, rays without samples dropped, and most samples first (what the kernel does).
2. Ops and host syncs per frame (bench.profile's count) of `inr` and `noshadow` at batch 2^22 (an 80 GB GPU's
   plan), whole rays against the per-sample kernel in the wavefront loop. The kernel launch is replaced by a stub
   that still counts as one op, so the count needs no interpreter and is exact for the rest.

The data INR is fitted here (`--inr-steps`); the shadow SIREN is untrained (neither count depends on it).
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("TRITON_INTERPRET", "1")  # the fused setting resolves on a CPU; the launch is stubbed below
os.environ["DIFFSHADOW_FUSED_SIREN"] = "tf32"

import numpy as np  # noqa: E402
import torch  # noqa: E402
from torch.profiler import record_function  # noqa: E402

from diffshadow import fused  # noqa: E402
from diffshadow import render as R  # noqa: E402
from diffshadow.artifacts import load_scene_file  # noqa: E402
from diffshadow.bench import BENCH_LIGHT  # noqa: E402
from diffshadow.bench.profile import op_counts  # noqa: E402
from diffshadow.data_inr import DataInrConfig, fit_data_inr  # noqa: E402
from diffshadow.grid import ray_span  # noqa: E402
from diffshadow.sampling import seeded  # noqa: E402
from diffshadow.siren import SirenConfig, WeightLayout, init_siren  # noqa: E402


def slots(samples: torch.Tensor, block: int) -> int:
    """Lane slots of programs taking `block` consecutive rays of this order."""
    padded = torch.cat([samples, samples.new_zeros((-len(samples)) % block)])
    return int(padded.view(-1, block).max(1).values.sum()) * block


def lane_use(scene: R.RenderScene, size: int, block: int) -> None:
    cam = R.Camera.orbit(scene.volume.extent, azimuth=30.0, elevation=25.0, size=size)
    o, d = cam.rays()
    t0, t1 = ray_span(o, d, torch.as_tensor(scene.volume.extent, dtype=torch.float32))
    macro, tile = scene.macro("inr", True), 1 << 16
    total = torch.cat([R.Runs.build(o[a:a + tile], d[a:a + tile], t0[a:a + tile], t1[a:a + tile],
                                    R.DEFAULT_STEP * scene.voxel, macro).total.long() for a in range(0, len(o), tile)])
    image = total.view(size, size)
    tiles = image.view(size // 8, 8, size // 8, 8).permute(0, 2, 1, 3).reshape(-1)
    n = int(total.sum())
    orders = {"image order (rows)": total, "8x8 pixel tiles": tiles, "rows, empty rays dropped": total[total > 0],
              "most samples first (the kernel)": total.sort(descending=True).values}
    print(f"{size}²: {n:,} samples, {float((total > 0).float().mean()):.0%} of rays have any; {block} rays/program")
    for name, order in orders.items():
        print(f"  {name:32s} lanes {n / slots(order, block):6.1%} useful")


def counts(scene: R.RenderScene, size: int, kw: dict) -> None:
    cam = R.Camera.orbit(scene.volume.extent, azimuth=30.0, elevation=25.0, size=size)
    for mode in ("noshadow", "inr"):
        for whole in (True, False):
            c = op_counts(lambda m=mode, w=whole: scene.render(m, cam, whole_rays=w, batch=1 << 22, **kw))
            print(f"  {size}² {mode:8s} {'whole rays' if whole else 'wavefront steps':16s} "
                  f"{c['ops']:5d} ops {c['syncs']:3d} host syncs")


def stub(name, n, block, warps, *args, **constants):
    """The launch, counted as one op, without running the kernel: its outputs stay as allocated (trips zeroed)."""
    with record_function(fused.LAUNCH):
        for a in args:
            if isinstance(a, torch.Tensor) and a.dtype == torch.int32 and a.dim() == 1 and len(a) == -(-n // block):
                a.zero_()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 512, 1024])
    ap.add_argument("--inr-steps", type=int, default=3000)
    a = ap.parse_args()
    torch.manual_seed(0)
    scene = load_scene_file("config/scenes/hydrogen_atom.yaml", "cpu")
    scene.data_inr = fit_data_inr(scene.volume, scene.tf, DataInrConfig.from_config({"steps": a.inr_steps}),
                                  device="cpu", log=lambda m: None)
    cfg = SirenConfig(32, 2)
    layout = WeightLayout.for_siren(cfg)
    kw = {"light": np.asarray(BENCH_LIGHT) / np.linalg.norm(BENCH_LIGHT),
          "siren": (layout.flatten(init_siren(cfg, seeded(0))).numpy(), layout, cfg.blocks)}
    block = min(fused.block_points(scene.data_inr.model.cfg.width), fused.block_points(cfg.width))
    print("lane use of the whole-ray kernel, hydrogen_atom inr:")
    for n in a.sizes:
        lane_use(scene, n, block)
    fused._launch = stub
    tiny = R.Camera.orbit(scene.volume.extent, azimuth=30.0, elevation=25.0, size=8)
    for mode in ("noshadow", "inr"):  # once before counting: the scene caches its macro grid and data INR
        scene.render(mode, tiny, **kw)
    print("ops and host syncs per frame at batch 2^22 (the launch stubbed):")
    for n in a.sizes:
        counts(scene, n, kw)


if __name__ == "__main__":
    main()
