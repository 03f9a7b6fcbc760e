"""The primary sample's cost alone, outside the marcher: eager against the fused kernel over tile sizes and warps.

    python scripts/fused_sweep.py --device cuda            # on a GPU (Triton compiles each setting once)
    TRITON_INTERPRET=1 python scripts/fused_sweep.py --n 4096 --blocks 16 --warps 4   # the script itself, on a CPU

A renderer frame is the marcher plus its primary samples. This times the samples alone, on `--n` box points of
hydrogen_atom (the bench's data INR size, a width-32 shadow SIREN): the eager step the renderer runs (data SIREN,
shadow SIREN, TF, opacity, shading) against `FusedSamples` for each precision × points per program × warps,
and prints nanoseconds per sample and the largest difference from the eager opacity and colour. Then one
`--frame`² inr frame, eager and with the fastest fused setting, gives the share of the frame the samples take:
what is left is the marcher's. Last, whole `--frame`² inr frames with the whole-ray kernel (`FusedSamples.march`,
TF32) per points per program × warps × cap on registers per thread (`--registers`; 0: none): ms per frame and
the share of lane trips that were samples.

The data INR has config.yaml's size (width 64, 2 blocks, as the bench's) and is fitted briefly (`--inr-steps`,
without growing) so that the TF sees realistic values; the shadow SIREN is untrained (its cost does not depend on
its weights).
"""

from __future__ import annotations

import argparse
import itertools
import time

import numpy as np
import torch

from diffshadow import render as R
from diffshadow.artifacts import load_scene_file
from diffshadow.bench import BENCH_LIGHT
from diffshadow.data_inr import DataInrConfig, fit_data_inr
from diffshadow.fused import FusedSamples
from diffshadow.sampling import seeded
from diffshadow.siren import SirenConfig, WeightLayout, init_siren


def timed(fn, device: torch.device, repeats: int) -> float:
    """Median seconds of `fn()` (after one warm call: compiles, caches)."""
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    fn()
    out = []
    for _ in range(repeats):
        sync()
        t = time.perf_counter()
        fn()
        sync()
        out.append(time.perf_counter() - t)
    return float(np.median(out))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--n", type=int, default=1 << 22, help="box points per call (the GPU plan's batch)")
    ap.add_argument("--precisions", nargs="+", default=["tf32", "ieee"])
    ap.add_argument("--blocks", type=int, nargs="+", default=[32, 64, 128], help="points per program")
    ap.add_argument("--warps", type=int, nargs="+", default=[2, 4, 8])
    ap.add_argument("--registers", type=int, nargs="+", default=[0],
                    help="whole rays: at most this many registers per thread (0: the compiler's choice; 168 fits 3 "
                         "programs of 4 warps per SM)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--inr-steps", type=int, default=300)
    ap.add_argument("--frame", type=int, default=1024, help="inr frame size for the share (0: no frame)")
    a = ap.parse_args()
    device = torch.device(a.device)

    scene = load_scene_file("config/scenes/hydrogen_atom.yaml", device)
    inr_cfg = DataInrConfig.from_config({"steps": a.inr_steps, "target_psnr": 0.0})
    scene.data_inr = fit_data_inr(scene.volume, scene.tf, inr_cfg, device=device, log=lambda m: None)
    cfg = SirenConfig(32, 2)
    layout = WeightLayout.for_siren(cfg)
    w = layout.flatten(init_siren(cfg, seeded(0)))
    light = np.asarray(BENCH_LIGHT, float) / np.linalg.norm(BENCH_LIGHT)
    extent = scene.volume.extent
    scalar = R.InrScalar(scene.data_inr.model, extent, device)
    shadow = R.SirenShadow(w, layout, cfg.blocks, extent, device)
    dt = R.DEFAULT_STEP * scene.voxel  # the renderer's step
    g = torch.Generator(device="cpu").manual_seed(0)
    p = (torch.rand(a.n, 3, generator=g) * torch.as_tensor(np.asarray(extent), dtype=torch.float32)).to(device)
    tf = scene.tf

    def eager():
        mu, rgb = tf.optics(scalar.value(p))
        return 1 - torch.exp(-mu * dt), R._shade(rgb, None, shadow(p), None, None, R.Shading())

    with torch.no_grad():
        ref_alpha, ref_rgb = eager()
        t_eager = timed(eager, device, a.repeats)
    print(f"device {device}, {a.n:,} samples, data SIREN width {scene.data_inr.model.cfg.width} "
          f"blocks {scene.data_inr.model.cfg.blocks}, shadow SIREN width {cfg.width} blocks {cfg.blocks}")
    print(f"eager                         {t_eager * 1e9 / a.n:8.2f} ns/sample  {t_eager * 1e3:9.3f} ms")

    best = None
    for precision, block, warps in itertools.product(a.precisions, a.blocks, a.warps):
        try:
            # the renderer's own fused SIRENs for this precision, with this tile and these warps
            fs = R.InrScalar(scene.data_inr.model, extent, device, precision).fast
            fsh = R.SirenShadow(w, layout, cfg.blocks, extent, device, precision).fast
            for f in (fs, fsh):
                f.block, f.warps = block, warps
            fused = FusedSamples(fs, fsh, scalar.extent, tf.optics_knots(device), tf.density_scale, dt)
            alpha, rgb = fused(p)
            t = timed(lambda f=fused: f(p), device, a.repeats)
        except Exception as e:  # a setting Triton cannot compile (shared memory, registers): say so, go on
            print(f"{precision:5s} block {block:4d} warps {warps}  failed: {type(e).__name__}: "
                  f"{str(e).splitlines()[0] if str(e) else ''}")
            continue
        err = max(float((alpha - ref_alpha).abs().max()), float((rgb - ref_rgb).abs().max()))
        print(f"{precision:5s} block {block:4d} warps {warps}  {t * 1e9 / a.n:8.2f} ns/sample  {t * 1e3:9.3f} ms  "
              f"{t_eager / t:6.2f}x eager  max diff {err:.2e}", flush=True)
        if precision == "tf32" and (best is None or t < best[0]):
            best = (t, block, warps)

    if a.frame and best is not None:
        cam = R.Camera.orbit(extent, azimuth=30.0, elevation=25.0, size=a.frame)
        kw = {"light": light, "siren": (w.numpy(), layout, cfg.blocks)}
        scene.render("inr", cam, **kw)
        t_frame = timed(lambda: scene.render("inr", cam, **kw), device, 3)
        n = scene.render("inr", cam, **kw).counters.primary_samples
        print(f"\ninr {a.frame}² eager: {t_frame * 1e3:.1f} ms, {n:,} samples; the samples alone at the eager rate "
              f"{n * t_eager / a.n * 1e3:.1f} ms ({n * t_eager / a.n / t_frame:.0%}), at the best fused rate "
              f"(tf32, block {best[1]}, warps {best[2]}) {n * best[0] / a.n * 1e3:.1f} ms: the marcher's share is "
              f"about {(t_frame - n * t_eager / a.n) * 1e3:.1f} ms")

    if a.frame:
        cam = R.Camera.orbit(extent, azimuth=30.0, elevation=25.0, size=a.frame)
        macro = scene.macro("inr", True)
        print(f"\nwhole rays, inr {a.frame}², tf32:")
        for block, warps, registers in itertools.product(a.blocks, a.warps, a.registers):
            try:
                fs = R.InrScalar(scene.data_inr.model, extent, device, "tf32")
                fsh = R.SirenShadow(w, layout, cfg.blocks, extent, device, "tf32")
                for f in (fs.fast, fsh.fast):
                    f.block, f.warps, f.registers = block, warps, registers or None

                def frame(fs=fs, fsh=fsh):
                    return R.render(cam, fs, tf, extent, scene.voxel, light=light, shadow=fsh, macro=macro,
                                    device=device)

                t = timed(frame, device, a.repeats)
                img = frame()
            except Exception as e:  # a setting Triton cannot compile: say so, go on
                print(f"  block {block:4d} warps {warps} registers {registers or '-':>3}  failed: {type(e).__name__}: "
                      f"{str(e).splitlines()[0] if str(e) else ''}")
                continue
            c = img.counters
            print(f"  block {block:4d} warps {warps} registers {registers or '-':>3}  {t * 1e3:8.2f} ms "
                  f"({1 / t:7.1f} fps)  {c.primary_samples:,} samples, lanes "
                  f"{c.primary_samples / max(c.slots, 1):.1%} useful", flush=True)


if __name__ == "__main__":
    main()
