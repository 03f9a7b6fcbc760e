"""Stage-1 benchmarks: joint against one-by-one SIREN fitting, init spread, stored against recomputed PSNR."""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from diffshadow.adam import Adam
from diffshadow.io import atomic_write_text


def _sequential_step(cfg, x, y):
    """One training step of K separate SIRENs, each with its own Adam, one after another."""
    from diffshadow.siren import Siren

    models = [Siren(cfg).to(x.device) for _ in range(len(x))]
    opts = [Adam(m.parameters(), lr=1e-4) for m in models]

    def step():
        for i, (m, o) in enumerate(zip(models, opts, strict=True)):
            o.zero_grad(set_to_none=True)
            ((m(x[i]) - y[i]) ** 2).mean().backward()
            o.step()
    return step


def _joint_step(cfg, x, y, chunk):
    """One training step of K SIRENs as one BatchedSiren, points in chunks with gradient accumulation."""
    from diffshadow.siren import BatchedSiren, WeightLayout, init_siren

    layout = WeightLayout.for_siren(cfg)
    k, points = y.shape
    w = layout.flatten(init_siren(cfg)).expand(k, -1).clone().to(x.device).requires_grad_(True)
    opt = Adam([w], lr=1e-4)
    c = chunk or points

    def step():
        opt.zero_grad(set_to_none=True)
        for c0 in range(0, points, c):
            pred = BatchedSiren(w, layout, cfg.blocks)(x[:, c0:c0 + c])
            (((pred - y[:, c0:c0 + c]) ** 2).sum(dim=1) / points).sum().backward()
        opt.step()
    return step


def bench_siren(out_dir: Path, *, k: int = 16, points: int = 4096, widths: Sequence[int] = (32, 64, 128),
                blocks: int = 2, chunks: Sequence[int] = (0, 1024, 512, 256), steps: int = 20,
                device: torch.device | str = "cpu") -> dict:
    """Training throughput (points/s, forward + backward + Adam) of K SIRENs fitted jointly with
    `BatchedSiren` (optionally in point chunks with gradient accumulation) vs K `Siren`s one after another."""
    from diffshadow.fit import FitConfig, points_per_pass
    from diffshadow.siren import SirenConfig

    for flag, values in (("--k", [k]), ("--points", [points]), ("--widths", list(widths))):
        if not values or min(values) < 1:  # none would divide the throughput by zero
            raise ValueError(f"bench siren: {flag}: expected positive integers, got {' '.join(map(str, values))}")
    device = torch.device(device)
    default_chunk = points_per_pass(FitConfig.from_config().chunk, points, device)
    gen = torch.Generator().manual_seed(0)
    results: dict = {"k": k, "points": points, "blocks": blocks, "device": str(device),
                     "torch_threads": torch.get_num_threads(), "widths": {}}

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize()

    for width in widths:
        cfg = SirenConfig(width, blocks)
        x = (torch.rand(k, points, 3, generator=gen, device=gen.device) * 2 - 1).to(device)
        y = torch.rand(k, points, generator=gen, device=gen.device).to(device)
        variants = {"sequential": _sequential_step(cfg, x, y)}
        # the default (config.yaml's fit.chunk for this device) first; the other sizes for comparison
        variants[f"joint_default_chunk{default_chunk}"] = _joint_step(cfg, x, y, default_chunk)
        variants |= {f"joint_chunk{c or points}": _joint_step(cfg, x, y, c) for c in chunks
                     if (c or points) != default_chunk}
        rates: dict[str, list[float]] = {}
        for _round in range(2):  # interleaved rounds: drift on a shared machine hits every variant alike
            for name, step in variants.items():
                step()
                sync()
                t = time.perf_counter()
                for _ in range(steps):
                    step()
                sync()
                rates.setdefault(name, []).append(k * points * steps / (time.perf_counter() - t))
        best = {name: max(r) for name, r in rates.items()}
        ratios = {name: best[name] / best["sequential"] for name in best if name != "sequential"}
        results["widths"][width] = {"points_per_s": best, "ratio_vs_sequential": ratios}
        print(f"[bench siren] width {width}: sequential {best['sequential']:,.0f} pts/s; "
              + ", ".join(f"{n} {r:.2f}x" for n, r in ratios.items()), flush=True)
    out_dir.mkdir(parents=True, exist_ok=True)
    name = f"bench_siren_{device.type}.json"
    atomic_write_text(out_dir / name, json.dumps(results, indent=1) + "\n")
    print(f"[bench siren] wrote {out_dir / name}")
    return results


def _scene_inputs(results: Path):
    from diffshadow.fit import FitConfig
    from diffshadow.lights import read_lights
    from diffshadow.store import open_store
    from diffshadow.volume import load_prepared

    volume, tf = load_prepared(results / "volume.zarr")
    store = open_store(results / "weights.zarr")
    lights = read_lights(results / "lights.json")["train"]
    return volume, tf, store, lights, FitConfig.from_config(store.config["fit"])


def weight_spread(weights: torch.Tensor) -> dict:
    """Spread of flattened weights across lights: per-parameter std, averaged; and relative to their RMS."""
    std = weights.double().std(dim=0).mean().item()
    return {"mean_param_std": std, "relative": std / weights.double().pow(2).mean().sqrt().item()}


def bench_init_spread(results: Path, out_dir: Path, *, n_lights: int = 8) -> dict:
    """Weight spread across lights with the shared pre-optimised init (the store) vs each light fitted from
    its own random init with the same settings (paper §3.2: the shared init makes the weight space coherent)."""
    from diffshadow.fit import evaluate_psnr, fit_sirens
    from diffshadow.sampling import Stream, seeded
    from diffshadow.siren import init_siren

    if n_lights < 2:  # before reading the results: a spread needs two lights
        raise ValueError(f"bench init-spread: --lights: expected at least 2 (a spread across lights), got {n_lights}")
    volume, tf, store, lights, fit = _scene_inputs(results)
    idx = np.linspace(0, len(lights) - 1, n_lights).round().astype(int)
    shared = torch.as_tensor(store.weights[idx])
    own = []
    for i in idx:
        init = store.layout.flatten(init_siren(store.siren, seeded(fit.seed, Stream.FIT_SHARED_POINTS, int(i))))
        own.append(fit_sirens(init, store.layout, store.siren, volume, tf, lights[i:i + 1], fit, stream=int(i),
                              log=lambda *a: None)[0])
        print(f"[bench init-spread] fitted light {i} from its own random init", flush=True)
    own = torch.stack(own)
    psnr_own, _ = evaluate_psnr(own, store.layout, store.siren, volume, tf, lights[idx],
                                n_points=fit.eval_points, seed=fit.seed)
    result = {
        "lights": idx.tolist(),
        "shared_init": {**weight_spread(shared), "psnr_median": float(np.median(store.psnr[idx]))},
        "own_random_init": {**weight_spread(own), "psnr_median": float(np.median(psnr_own))},
        "all_lights_shared_init": weight_spread(torch.as_tensor(store.weights)),
    }
    ratio = result["own_random_init"]["mean_param_std"] / result["shared_init"]["mean_param_std"]
    result["spread_ratio_random_over_shared"] = ratio
    print(f"[bench init-spread] std across lights: shared init {result['shared_init']['mean_param_std']:.4f}, "
          f"own random inits {result['own_random_init']['mean_param_std']:.4f} ({ratio:.1f}x); PSNR median "
          f"{result['shared_init']['psnr_median']:.2f} vs {result['own_random_init']['psnr_median']:.2f} dB")
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out_dir / "bench_init_spread.json", json.dumps(result, indent=1) + "\n")
    return result


def check_store(results: Path, *, n_points: int = 65536, seed: int = 12345) -> dict:
    """Re-evaluate every stored SIREN independently (`Siren.from_flat`, fresh points, `transmittance`)
    and compare with the PSNR recorded in the store."""
    from diffshadow.metrics import psnr
    from diffshadow.sampling import PointSampler, seeded
    from diffshadow.shadow import ShadowField, transmittance
    from diffshadow.siren import Siren, box_to_siren

    volume, tf, store, lights, _ = _scene_inputs(results)
    field = ShadowField.build(volume, tf)
    extent = torch.as_tensor(volume.extent, dtype=torch.float32)
    sampler = PointSampler(volume, tf, 1.0)
    box, vis = [], []
    with torch.no_grad():
        for i, w in enumerate(lights):
            gen = seeded(seed, i)
            model = Siren.from_flat(store.weights[i], store.layout, store.siren)
            for pts, out in ((torch.rand(n_points, 3, generator=gen, device=gen.device) * extent, box),
                             (sampler.sample(1, n_points, gen)[0], vis)):
                out.append(float(psnr(model(box_to_siren(pts, extent)), transmittance(field, tf, w, pts))))
    box, vis = np.asarray(box), np.asarray(vis)
    result = {"recomputed_median": float(np.median(box)), "stored_median": float(np.median(store.psnr)),
              "recomputed_min": float(box.min()), "stored_min": float(store.psnr.min()),
              "max_abs_diff_db": float(np.abs(box - store.psnr).max()),
              "visible_max_abs_diff_db": float(np.abs(vis - store.psnr_visible).max())}
    print(f"[check-store] {results}: recomputed PSNR median {result['recomputed_median']:.2f} dB "
          f"(stored {result['stored_median']:.2f}), min {result['recomputed_min']:.2f} "
          f"(stored {result['stored_min']:.2f}); largest per-light difference {result['max_abs_diff_db']:.2f} dB "
          f"(visible {result['visible_max_abs_diff_db']:.2f} dB)")
    return result
