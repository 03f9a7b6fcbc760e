"""Benchmarks that print and save figures (never asserted in unit tests: machines are noisy).

`bench_shadow`: time against error of the ground-truth shadow methods, measured side by side in one
process, against `march` at 1/8 voxel.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from diffshadow.io import atomic_save, atomic_write_text
from diffshadow.shadow import DEFAULT_STEP, DEFAULT_SWEEP_STEP, shadow_grid
from diffshadow.transfer import TransferFunction
from diffshadow.volume import bundled_path, load_volume

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

# Opacity 0 below s = 0.1 leaves most of a sparse volume empty (hydrogen_atom: 97 % of voxels).
BENCH_TF = {
    "opacity": [[0.0, 0.0], [0.1, 0.0], [1.0, 1.0]],
    "color": [[0.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0]],
    "density_scale": 40.0,
}
BENCH_LIGHT = (0.3, -0.5, 0.8)  # a generic direction: no axis or diagonal symmetry to flatter the sweep
REFERENCE_STEP = 0.125


def default_volumes() -> list[Path]:
    """The bundled nucleon plus every volume in ../shared/data when present."""
    paths = [bundled_path("nucleon")]
    if SHARED_DATA.is_dir():
        paths += sorted(p for p in SHARED_DATA.glob("*.raw") if not p.name.startswith("nucleon"))
    return paths


def _timed(fn):
    t = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t


def bench_analytic(steps=(2.0, 1.0, 0.5, 0.25)) -> dict:
    """`transmittance` against the closed form on the 65³ Gaussian blob (1,000 points and directions)."""
    import tempfile

    from diffshadow.analytic import BLOB_DENSITY, blob_cases, blob_transmittance, gaussian_blob
    from diffshadow.shadow import ShadowField, transmittance

    with tempfile.TemporaryDirectory() as tmp:  # through load_volume, as a user's .npy would go
        np.save(Path(tmp) / "blob.npy", gaussian_blob())
        vol = load_volume(Path(tmp) / "blob.npy")
    tf = TransferFunction.from_config({"opacity": [[0, 0], [1, 1]], "color": [[0, 1, 1, 1], [1, 1, 1, 1]],
                                       "density_scale": BLOB_DENSITY})
    field = ShadowField.build(vol, tf)
    out = {}
    for step in steps:
        err = np.concatenate([np.abs(transmittance(field, tf, w, pts, step=step).numpy()
                                     - np.array([blob_transmittance(p, w) for p in pts])) for w, pts in blob_cases()])
        out[step] = {"max_err": float(err.max()), "mean_err": float(err.mean()), "points": len(err)}
        print(f"[bench shadow] analytic blob, step {step:g}: max {err.max():.2e}  mean {err.mean():.2e} "
              f"({len(err)} points)", flush=True)
    return out


def bench_shadow(
    volumes: list[Path],
    out_dir: Path,
    *,
    light=BENCH_LIGHT,
    tf_config: dict | None = None,
    march_steps=(2.0, 1.0, 0.5, 0.25),
    sweep_steps=(1.0, 0.5, 0.25),
    device=None,
) -> dict:
    """Time and error of every method and step on each volume; writes JSON and a log-log plot."""
    tf = TransferFunction.from_config(tf_config or BENCH_TF)
    results: dict = {"light": list(light), "tf": tf.to_config(), "reference_step": REFERENCE_STEP,
                     "torch_threads": torch.get_num_threads(), "analytic_blob": bench_analytic(), "volumes": {}}
    for path in volumes:
        vol = load_volume(path)
        print(f"[bench shadow] {vol.name} {vol.dims}: reference march at {REFERENCE_STEP} voxel ...", flush=True)
        ref, t_ref = _timed(lambda v=vol: shadow_grid(v, tf, light, method="march", step=REFERENCE_STEP,
                                                      device=device))
        rows = [{"method": "march", "step": REFERENCE_STEP, "seconds": t_ref, "max_err": 0.0, "mean_err": 0.0}]
        cases = [("march", s, True) for s in march_steps] + [("march_noskip", DEFAULT_STEP, False)]
        cases += [("march_auto", DEFAULT_STEP, None)]
        cases += [("sweep", s, None) for s in sweep_steps]
        shadow_grid(vol, tf, light, method="sweep", device=device)  # warm-up
        grids = {}
        for method, step, skip in cases:
            if method == "sweep":
                g, t = _timed(lambda v=vol, s=step: shadow_grid(v, tf, light, method="sweep", step=s,
                                                                device=device))
            else:
                g, t = _timed(lambda v=vol, s=step, k=skip: shadow_grid(v, tf, light, method="march", step=s,
                                                                        skip_empty=k, device=device))
            err = (g - ref).abs()
            row = {"method": method, "step": step, "seconds": t, "max_err": float(err.max()),
                   "mean_err": float(err.mean())}
            rows.append(row)
            grids[(method, step)] = g
            print(f"  {method:13s} step {step:<6g} {t:8.3f} s  max {row['max_err']:.2e}  "
                  f"mean {row['mean_err']:.2e}", flush=True)
        t_of = {(r["method"], r["step"]): r["seconds"] for r in rows}
        summary = {
            "sweep_speedup": t_of[("march", DEFAULT_STEP)] / t_of[("sweep", DEFAULT_SWEEP_STEP)],
            "skip_speedup": t_of[("march_noskip", DEFAULT_STEP)] / t_of[("march", DEFAULT_STEP)],
            "skip_max_diff": float((grids[("march", DEFAULT_STEP)]
                                    - grids[("march_noskip", DEFAULT_STEP)]).abs().max()),
            "min_transmittance": float(ref.min()),
        }
        print(f"  sweep {summary['sweep_speedup']:.1f}x faster than march at default steps; "
              f"skipping {summary['skip_speedup']:.2f}x (max diff {summary['skip_max_diff']:.1e})", flush=True)
        results["volumes"][vol.name] = {"dims": list(vol.dims), "rows": rows, "summary": summary}
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out_dir / "bench_shadow.json", json.dumps(results, indent=1) + "\n")
    _plot(results, out_dir / "bench_shadow.png")
    print(f"[bench shadow] wrote {out_dir / 'bench_shadow.json'} and {out_dir / 'bench_shadow.png'}")
    return results


def _plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(results["volumes"])
    fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 3.8), squeeze=False)
    for ax, name in zip(axes[0], names, strict=True):
        rows = [r for r in results["volumes"][name]["rows"] if r["mean_err"] > 0]
        for method, marker in (("march", "o"), ("march_noskip", "x"), ("sweep", "s")):
            pts = sorted((r["seconds"], r["mean_err"], r["step"]) for r in rows if r["method"] == method)
            if not pts:
                continue
            ax.loglog([p[0] for p in pts], [p[1] for p in pts], marker=marker, label=method)
            for t, e, s in pts:
                ax.annotate(f"{s:g}", (t, e), fontsize=7, textcoords="offset points", xytext=(3, 3))
        ax.set_title(f"{name} {results['volumes'][name]['dims']}")
        ax.set_xlabel("wall time [s]")
        ax.set_ylabel("mean |error| vs march @ 1/8 voxel")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("Ground-truth shadow: time vs error (labels: step in voxels)")
    fig.tight_layout()
    atomic_save(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png"), suffix=".png")
    plt.close(fig)


def _sequential_step(cfg, x, y):
    """One training step of K separate SIRENs, each with its own Adam, one after another."""
    from diffshadow.siren import Siren

    models = [Siren(cfg).to(x.device) for _ in range(len(x))]
    opts = [torch.optim.Adam(m.parameters(), lr=1e-4) for m in models]

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
    opt = torch.optim.Adam([w], lr=1e-4)
    c = chunk or points

    def step():
        opt.zero_grad(set_to_none=True)
        for c0 in range(0, points, c):
            pred = BatchedSiren(w, layout, cfg.blocks)(x[:, c0:c0 + c])
            (((pred - y[:, c0:c0 + c]) ** 2).sum(dim=1) / points).sum().backward()
        opt.step()
    return step


def bench_siren(out_dir: Path, *, k: int = 16, points: int = 4096, widths=(32, 64, 128), blocks: int = 2,
                chunks=(0, 1024, 512, 256), steps: int = 20, device=None) -> dict:
    """Training throughput (points/s, forward + backward + Adam) of K SIRENs fitted jointly with
    `BatchedSiren` (optionally in point chunks with gradient accumulation) vs K `Siren`s one after another."""
    from diffshadow.siren import SirenConfig

    device = torch.device(device or "cpu")
    gen = torch.Generator().manual_seed(0)
    results: dict = {"k": k, "points": points, "blocks": blocks, "device": str(device),
                     "torch_threads": torch.get_num_threads(), "widths": {}}

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize()

    for width in widths:
        cfg = SirenConfig(width, blocks)
        x = (torch.rand(k, points, 3, generator=gen) * 2 - 1).to(device)
        y = torch.rand(k, points, generator=gen).to(device)
        variants = {"sequential": _sequential_step(cfg, x, y)}
        variants |= {f"joint_chunk{c or points}": _joint_step(cfg, x, y, c) for c in chunks}
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
    from diffshadow.fit import evaluate_psnr, fit_sirens, seeded
    from diffshadow.siren import init_siren

    volume, tf, store, lights, fit = _scene_inputs(results)
    idx = np.linspace(0, len(lights) - 1, n_lights).round().astype(int)
    shared = torch.as_tensor(store.weights[idx])
    own = []
    for i in idx:
        init = store.layout.flatten(init_siren(store.siren, seeded(fit.seed, -2, int(i))))
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
    from diffshadow.fit import PointSampler, seeded
    from diffshadow.metrics import psnr
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
            for pts, out in ((torch.rand(n_points, 3, generator=gen) * extent, box),
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
