"""Side by side: the marcher's variants on one device (batch sizes, TF32 matmuls, torch.compile, the fused kernels),
for `inr` and `naive`.

    python scripts/render_plans.py --device cuda --sizes 512 1024

Each variant renders the same frames (hydrogen_atom, the bench's camera, light and fits); the table gives the
median seconds per frame, the samples sent to the networks, host syncs per frame, the image's PSNR against the
first variant's, the eager fp32 renderer (the batch must not change the image; TF32 and the fused kernels may, a
little) and, for the fused kernels' whole rays, the share of the kernel's lane trips that were samples. Variants
are interleaved per repeat so drift on a shared machine hits all alike. The fused variant appears where its
kernels run (CUDA with Triton; on the CPU only under TRITON_INTERPRET=1, slowly).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import statistics

import numpy as np
import torch

from diffshadow import render as R
from diffshadow.artifacts import load_scene_file
from diffshadow.bench import BENCH_LIGHT
from diffshadow.bench.profile import op_counts
from diffshadow.data_inr import DataInrConfig, fit_data_inr
from diffshadow.fit import FitConfig, fit_sirens
from diffshadow.metrics import psnr
from diffshadow.render.fused import available as fused_available
from diffshadow.sampling import seeded
from diffshadow.siren import SirenConfig, WeightLayout, init_siren


@dataclasses.dataclass(frozen=True)
class Variant:
    batch: int | None = None  # None: the device's default
    tf32: bool = False  # TF32 matmuls (the eager SIREN)
    kernel: str | None = None  # the scene's kernel (render.Networks.setting(): "fused")


def variants(device: torch.device) -> dict[str, Variant]:
    """The variants by name. On an H200 (2026-11-25), before the plan compacted on every device, a fixed-shape
    plan (finished rays masked for 4 iterations, absent samples evaluated) sent 2.5x the samples and was 1.45x
    slower at 512², 1.2x at 1024² (docs/performance.md)."""
    out = {"default": Variant()}
    for lb in (20, 21, 22) if device.type == "cuda" else (16, 20, 22):
        out[f"batch 2^{lb}"] = Variant(batch=1 << lb)
    out["tf32 matmuls"] = Variant(tf32=True)
    if fused_available(device):
        out["fused"] = Variant(kernel="fused")
    return out


@contextlib.contextmanager
def variant(scene: R.RenderScene, v: Variant):
    old = torch.backends.cuda.matmul.allow_tf32, scene.kernel_used
    torch.backends.cuda.matmul.allow_tf32, scene.kernel_used = v.tf32, v.kernel
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_tf32, scene.kernel_used = old


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    ap.add_argument("--modes", nargs="+", default=["inr", "naive"])
    ap.add_argument("--inr-steps", type=int, default=3000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--profile", action="store_true",
                    help="after the table, torch.profiler's top kernels of one inr frame at the largest size, "
                         "per variant (default and the fused ones)")
    ap.add_argument("--variants", nargs="+", default=None,
                    help="only these variants (names as in the table; 'default' always runs, as the reference)")
    a = ap.parse_args()
    device = torch.device(a.device)
    scene = load_scene_file("config/scenes/hydrogen_atom.yaml", device)
    scene.data_inr = fit_data_inr(scene.volume, scene.tf, DataInrConfig.from_config({"steps": a.inr_steps}),
                                  device=device, log=lambda m: None)
    cfg = SirenConfig(32, 2)
    layout = WeightLayout.for_siren(cfg)
    light = np.asarray(BENCH_LIGHT, float) / np.linalg.norm(BENCH_LIGHT)
    fit = dataclasses.replace(FitConfig.from_config(), steps=300, grid_upsample=1, chunk=4096)
    w = fit_sirens(layout.flatten(init_siren(cfg, seeded(0))), layout, cfg, scene.volume, scene.tf, light[None],
                   fit, device=device, log=lambda m: None)[0]
    kw = {"light": light, "siren": (w, layout, cfg.blocks)}
    plans = variants(device)
    if a.variants:
        unknown = sorted(set(a.variants) - set(plans))
        if unknown:
            raise SystemExit(f"--variants: unknown {unknown}; on {device.type} there are {sorted(plans)}")
        plans = {k: v for k, v in plans.items() if k == "default" or k in a.variants}
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    print(f"device {device}, data INR PSNR {scene.data_inr.psnr:.2f} dB")
    # warm each variant (Triton and torch.compile compile on first use) and drop one that fails, saying why,
    # so that one broken variant leaves the others' table
    small = R.Camera.orbit(scene.volume.extent, azimuth=30.0, elevation=25.0, size=min(a.sizes))
    for name, v in list(plans.items()):
        try:
            with variant(scene, v):
                for mode in a.modes:
                    scene.render(mode, small, batch=v.batch, **kw)
        except Exception as e:  # any failure of one variant: report it and go on
            print(f"variant {name!r} dropped: {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}")
            del plans[name]
    for n in a.sizes:
        cam = R.Camera.orbit(scene.volume.extent, azimuth=30.0, elevation=25.0, size=n)
        for mode in a.modes:
            secs = {k: [] for k in plans}
            imgs, counts = {}, {}
            for _rep in range(a.repeats if mode != "naive" or n <= 256 else 1):
                for name, v in plans.items():
                    with variant(scene, v):
                        sync()
                        img = scene.render(mode, cam, batch=v.batch, **kw)
                        sync()
                    secs[name].append(img.seconds)
                    imgs[name] = img
            for name, v in plans.items():  # naive's count takes minutes past 256²
                with variant(scene, v):
                    counted = mode != "naive" or n <= 256
                    counts[name] = (op_counts(lambda m=mode, c=cam, v=v: scene.render(m, c, batch=v.batch, **kw))
                                    if counted else {"ops": -1, "syncs": -1})
            ref = imgs["default"].rgb
            for name in plans:
                c, img = counts[name], imgs[name]
                p = float(psnr(img.rgb, ref))
                batch = plans[name].batch or R.MarchPlan.for_device(device).batch
                lanes = (f"  lanes {img.counters.primary_samples / img.counters.slots:.1%} useful"
                         if img.counters.slots else "")
                print(f"{n}x{n} {mode:5s} {name:20s} batch {batch:>9,} "
                      f"{statistics.median(secs[name]):8.4f} s "
                      f"({1 / statistics.median(secs[name]):7.2f} fps)  samples {img.counters.primary_samples:>11,} "
                      f"+ {img.counters.secondary_samples:>13,}  ops {c['ops']:>6,} syncs {c['syncs']:>4}  "
                      f"PSNR vs default {p:6.1f} dB{lanes}", flush=True)

    if a.profile:
        cam = R.Camera.orbit(scene.volume.extent, azimuth=30.0, elevation=25.0, size=max(a.sizes))
        for name, v in plans.items():
            if name == "default" or v.kernel:  # the fused kernels and torch.compile
                with variant(scene, v):
                    profile_frame(scene, cam, device, name, batch=v.batch, **kw)


def profile_frame(scene: R.RenderScene, cam: R.Camera, device: torch.device, name: str, **kw) -> None:
    """Where one inr frame's time goes: the top kernels by device time (self CPU time on a CPU), and on a GPU
    how busy the device was over the frame's wall time."""
    from torch.profiler import ProfilerActivity, profile

    cuda = device.type == "cuda"
    scene.render("inr", cam, **kw)  # warm: compiled kernels, caches
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=acts) as prof:
        img = scene.render("inr", cam, **kw)
        if cuda:
            torch.cuda.synchronize()
    key = "self_device_time_total" if cuda else "self_cpu_time_total"
    events = prof.key_averages()
    # the kernels' own rows (device_type CUDA) hold the device time; summing the aten rows too would count it twice
    kernels = [e for e in events if str(getattr(e, "device_type", "")).endswith("CUDA")]
    busy = sum(getattr(e, key, 0.0) for e in kernels) / 1e6
    print(f"\n== profile: {name}, inr {cam.width}x{cam.height}, frame {img.seconds:.4f} s"
          + (f", device busy {busy:.4f} s ({busy / img.seconds:.0%})" if cuda else ""))
    print(events.table(sort_by=key, row_limit=15, max_name_column_width=60), flush=True)


if __name__ == "__main__":
    main()
