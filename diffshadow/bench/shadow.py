"""Time against error of the ground-truth shadow methods (`diffshadow bench shadow`)."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from numpy.typing import ArrayLike

from diffshadow.bench import BENCH_LIGHT, BENCH_TF, REFERENCE_STEP, timed
from diffshadow.io import atomic_save, atomic_write_text
from diffshadow.shadow import DEFAULT_STEP, DEFAULT_SWEEP_STEP, shadow_grid
from diffshadow.transfer import TransferFunction
from diffshadow.volume import Volume, load_volume


def bench_analytic(steps: Sequence[float] = (2.0, 1.0, 0.5, 0.25)) -> dict:
    """`transmittance` against the closed form on the 65³ Gaussian blob (1,000 points and directions)."""
    import tempfile

    from diffshadow.analytic import BLOB_DENSITY, blob_cases, blob_transmittance, gaussian_blob
    from diffshadow.shadow import ShadowField, transmittance_per_light

    with tempfile.TemporaryDirectory() as tmp:  # through load_volume, as a user's .npy would go
        np.save(Path(tmp) / "blob.npy", gaussian_blob())
        vol = load_volume(Path(tmp) / "blob.npy")
    tf = TransferFunction.from_config({"opacity": [[0, 0], [1, 1]], "color": [[0, 1, 1, 1], [1, 1, 1, 1]],
                                       "density_scale": BLOB_DENSITY})
    field = ShadowField.build(vol, tf)
    # the directions with as many points each marched together (one march per direction was 5.5 of this
    # job's 15 s on the README run's scene); (directions, their points, the closed form there), made once
    by_count: dict[int, list] = {}
    for w, pts in blob_cases():
        by_count.setdefault(len(pts), []).append((w, pts))
    groups = [(np.stack([w for w, _ in cases]), np.stack([pts for _, pts in cases]),
               np.array([[blob_transmittance(p, w) for p in pts] for w, pts in cases])) for cases in by_count.values()]
    out = {}
    for step in steps:
        err = np.concatenate([np.abs(transmittance_per_light(field, tf, dirs, pts, step=step).numpy() - exact).ravel()
                              for dirs, pts, exact in groups])
        out[step] = {"max_err": float(err.max()), "mean_err": float(err.mean()), "points": len(err)}
        print(f"[bench shadow] analytic blob, step {step:g}: max {err.max():.2e}  mean {err.mean():.2e} "
              f"({len(err)} points)", flush=True)
    return out


# Past this many voxels the marches (the 1/8-voxel reference above all) are run on every k-th row of voxels, about
# this many, and their seconds scaled to the whole grid: marching every voxel of a 256³ volume took this job 16
# minutes on a CPU (of 1 G voxels, days). Whole rows, so that neighbouring rays still share the cache as in a whole
# grid's march. The sweeps still run whole; every error is read at the marched voxels. Tooth (1.56 M voxels, one
# thread), every voxel against every 6th row at 2^18: each march's scaled seconds within 6 % of the whole grid's,
# mean errors within 1 %, max errors (a maximum over fewer voxels) up to 21 % lower; the job 117 -> 22 s, which on
# a scene's first run had held train_diffusion back ~2 minutes (docs/performance.md, "The default run").
MARCHED_VOXELS = 1 << 18


def marched_voxels(shape: tuple[int, ...], limit: int | None = None) -> torch.Tensor | None:
    """The voxels the bench marches on a grid of `shape`: None (all) up to `limit` (`MARCHED_VOXELS`), else every
    k-th row along the last axis (k the smallest that keeps them to `limit`), as a bool mask."""
    n, limit = int(np.prod(shape)), MARCHED_VOXELS if limit is None else limit
    if n <= limit:
        return None
    mask = torch.zeros(shape, dtype=torch.bool)
    rows = mask.view(-1, shape[-1])
    k = -(-len(rows) * shape[-1] // limit)
    rows[min(k // 2, len(rows) - 1)::k] = True
    return mask


def bench_shadow(
    volumes: list[Path],
    out_dir: Path,
    *,
    light: ArrayLike = BENCH_LIGHT,
    tf_config: dict | None = None,
    march_steps: Sequence[float] = (2.0, 1.0, 0.5, 0.25),
    sweep_steps: Sequence[float] = (1.0, 0.5, 0.25),
    device: torch.device | str = "cpu",
) -> dict:
    """Time and error of every method and step on each volume; writes JSON and a log-log plot. A scene's
    prepared volume (`results/<scene>/volume.zarr`) is timed with its own transfer function."""
    default_tf = TransferFunction.from_config(tf_config or BENCH_TF)
    loaded = [_load(Path(path), default_tf) for path in volumes]  # a missing volume is said before any timing
    results: dict = {"light": list(light), "tf": default_tf.to_config(), "reference_step": REFERENCE_STEP,
                     "torch_threads": torch.get_num_threads(), "analytic_blob": bench_analytic(), "volumes": {}}
    for vol, tf in loaded:
        mask = marched_voxels(vol.data.shape)
        total = int(np.prod(vol.data.shape))
        marched = total if mask is None else int(mask.sum())
        scale = total / marched  # a march's seconds for the whole grid

        def at(g: torch.Tensor, m=mask) -> torch.Tensor:  # a grid's values at the voxels errors are read at
            return g if m is None else g[m.to(g.device)]

        print(f"[bench shadow] {vol.name} {vol.dims}: reference march at {REFERENCE_STEP} voxel"
              + ("" if mask is None else f" on every k-th row of voxels, {marched:,} of its {total:,} (march "
                                         f"times scaled to the whole grid)") + " ...", flush=True)
        ref, t_ref = timed(lambda v=vol, f=tf, m=mask: shadow_grid(v, f, light, method="march", step=REFERENCE_STEP,
                                                                  device=device, voxels=m))
        ref = at(ref)
        rows = [{"method": "march", "step": REFERENCE_STEP, "seconds": t_ref * scale, "max_err": 0.0,
                 "mean_err": 0.0}]
        cases = [("march", s, True) for s in march_steps] + [("march_noskip", DEFAULT_STEP, False)]
        cases += [("march_auto", DEFAULT_STEP, None)]
        cases += [("sweep", s, None) for s in sweep_steps]
        shadow_grid(vol, tf, light, method="sweep", device=device)  # warm-up
        grids = {}
        for method, step, skip in cases:
            if method == "sweep":
                g, t = timed(lambda v=vol, s=step, f=tf: shadow_grid(v, f, light, method="sweep", step=s,
                                                                device=device))
            else:
                g, t = timed(lambda v=vol, s=step, k=skip, f=tf, m=mask: shadow_grid(
                    v, f, light, method="march", step=s, skip_empty=k, device=device, voxels=m))
                t *= scale
            g = at(g)
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
        results["volumes"][vol.name] = {"dims": list(vol.dims), "tf": tf.to_config(), "rows": rows,
                                        "summary": summary, "marched_voxels": marched, "voxels": total}
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out_dir / "bench_shadow.json", json.dumps(results, indent=1) + "\n")
    _plot(results, out_dir / "bench_shadow.png")
    print(f"[bench shadow] wrote {out_dir / 'bench_shadow.json'} and {out_dir / 'bench_shadow.png'}")
    return results


def _load(path: Path, tf: TransferFunction) -> tuple[Volume, TransferFunction]:
    """A prepared volume with its transfer function; any other volume file with `tf`."""
    from diffshadow.volume import is_prepared, load_prepared

    if is_prepared(path):
        return load_prepared(path)
    return load_volume(path), tf


def _plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from diffshadow.report import decade_labels

    names = list(results["volumes"])
    fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 3.8), squeeze=False, layout="constrained")
    for ax, name in zip(axes[0], names, strict=True):
        rows = [r for r in results["volumes"][name]["rows"] if r["mean_err"] > 0]
        # march_noskip's one point sits on march's at the same step: its label goes below, not on top of march's
        for method, marker, offset in (("march", "o", (3, 3)), ("march_noskip", "x", (3, -9)), ("sweep", "s", (3, 3))):
            pts = sorted((r["seconds"], r["mean_err"], r["step"]) for r in rows if r["method"] == method)
            if not pts:
                continue
            ax.loglog([p[0] for p in pts], [p[1] for p in pts], marker=marker, label=method)
            for t, e, s in pts:
                ax.annotate(f"{s:g}", (t, e), fontsize=7, textcoords="offset points", xytext=offset)
        ax.set_title(f"{name} {results['volumes'][name]['dims']}")
        ax.set_xlabel("wall time [s]")
        ax.set_ylabel("mean |error| vs march @ 1/8 voxel")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
        decade_labels(ax.xaxis)
        decade_labels(ax.yaxis)
    # two lines: one panel (one volume) is narrower than the title on one line
    fig.suptitle("Ground-truth shadow: time vs error\n(point labels: step in voxels)", fontsize=10)
    atomic_save(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png"), suffix=".png")
    plt.close(fig)
