"""`diffshadow bench render`: frames per second and peak memory of `noshadow`, `inr` and `naive`, side
by side in one process; macro-cell skipping on against off; the renderer's step against error and time.

Peak memory is what a frame's tensors held at once on the device's allocator (`bench.profile.op_counts`, from
the same profiled frame that counts its ops): on CUDA what `max_memory_allocated` says, on a CPU the same
quantity, not the resident set (which glibc's kept blocks make wander by tens of MiB).
"""

from __future__ import annotations

import json
import math
import statistics
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from numpy.typing import ArrayLike

from diffshadow.bench.profile import op_counts, peak_bytes
from diffshadow.io import atomic_path, atomic_write_text, finite_json
from diffshadow.metrics import foreground, image_psnr
from diffshadow.render import DEFAULT_STEP, Camera, RenderScene
from diffshadow.render.scene import KEEP_SAMPLES_BYTES, ShadowSirenSpec

if TYPE_CHECKING:
    from matplotlib.figure import Figure

BENCH_MODES = ("noshadow", "inr", "naive")
REFERENCE_STEP = 0.125


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


SLOW_FRAME_S = 1.0  # a mode this slow per frame is timed once: its run-to-run noise is small beside it


def _light_moved_fps(scene: RenderScene, camera: Camera, kwargs: dict, repeats: int) -> float | None:
    """Frames per second of `inr` with the light moved over a still view, as the viewer draws them: from the view's
    kept samples (the shadow INR evaluated at them alone; the same image). None where the scene keeps nothing for
    `inr` (the fused kernels march whole rays over the data INR). The scene keeps nothing again afterwards."""
    scene.keep_views(KEEP_SAMPLES_BYTES)
    try:
        scene.render("inr", camera, **kwargs)  # marched, its samples kept
        seconds = []
        for _ in range(repeats):
            _sync(scene.device)
            img = scene.render("inr", camera, **kwargs)
            _sync(scene.device)
            if not img.replayed:
                return None
            seconds.append(img.seconds)
    finally:
        scene.keep_views(0)
    return 1.0 / statistics.median(seconds)


def naive_counts(scene: RenderScene, light: ArrayLike, *, size: int, step: float = DEFAULT_STEP,
                 azimuth: float = 30.0, elevation: float = 25.0) -> dict:
    """The naive mode's ops, host syncs, host tensors and peak memory for one frame of `size`², as `bench_render`
    counts them at its smallest size (`bench naive-counts`). The counts do not drift with the machine's load, so
    they need not share the timed frames' cores: profiled, the frame took 3.4x its time (tooth's 64²: 33.5 s, a
    third of the benchmark job), and the workflow takes it beside stage 1 (`bench_render`'s `naive`). The mode
    reads no shadow SIREN, so it needs none."""
    tiny = Camera.orbit(scene.volume.extent, azimuth=azimuth, elevation=elevation, size=8)
    scene.render("naive", tiny, light=light, step=step)  # warmed as bench_render warms it
    cam = Camera.orbit(scene.volume.extent, azimuth=azimuth, elevation=elevation, size=size)
    counts = op_counts(lambda cut: scene.render("naive", cam, light=light, step=step, interrupt=cut),
                       memory=scene.device, pieces=True)
    return {"mode": "naive", "size": size, "step": step, "azimuth": azimuth, "elevation": elevation,
            "light": [float(v) for v in light], "device": str(scene.device), "networks": scene.networks_used(),
            "counts": counts}


def _check_naive(naive: dict, *, size: int, step: float, light: ArrayLike, azimuth: float, elevation: float,
                 kernel: str, device: str) -> None:
    """`naive` (`naive_counts`' record) counted the frame this bench would count, or a ValueError naming the
    difference."""
    want = {"size": size, "step": step, "azimuth": azimuth, "elevation": elevation, "device": device}
    if (naive.get("networks") or {}).get("kernel") != kernel:
        want["networks"] = {"kernel": kernel}
    wrong = [f"{k} {naive.get(k)!r} (this bench: {v!r})" for k, v in want.items() if naive.get(k) != v]
    theirs, ours = np.asarray(naive.get("light", []), float).reshape(-1), np.asarray(light, float).reshape(-1)
    if theirs.shape != ours.shape or not np.allclose(theirs, ours, atol=1e-9):
        wrong.append(f"light {naive.get('light')} (this bench: {ours.tolist()})")
    if wrong:
        raise ValueError(f"--naive-counts: counted another frame than this bench's smallest: {'; '.join(wrong)} "
                         "(expected `bench naive-counts` of the same volume, data INR, first training light, size, "
                         "step and --kernel)")


def bench_render(scene: RenderScene, siren: ShadowSirenSpec, light: ArrayLike, *, sizes: Sequence[int] = (64, 128),
                 step: float = DEFAULT_STEP, repeats: int = 3, memory_sizes: Sequence[int] | None = None,
                 azimuth: float = 30.0, elevation: float = 25.0, curve_steps: Sequence[float] = (2.0, 1.0, 0.5, 0.25),
                 curve_size: int | None = None, naive: dict | None = None, log: Callable[[str], None] = print) -> dict:
    """All measurements for one scene; `siren` = (weights, layout, blocks) of a shadow INR for `light`.

    `memory_sizes`: larger sides where only the peak memory of noshadow and inr is measured (default 2x and 4x
    the largest of `sizes`). `naive`: the naive frame's counts at the smallest size, taken apart (`naive_counts`),
    checked to be this bench's frame; else counted here.
    """
    device = scene.device
    out: dict = {"device": str(device), "torch_threads": torch.get_num_threads(), "step": step,
                 "repeats": repeats, "light": [float(v) for v in light], "sizes": {}}
    cams = {n: Camera.orbit(scene.volume.extent, azimuth=azimuth, elevation=elevation, size=n) for n in sizes}
    kwargs = {"light": light, "siren": siren, "step": step}
    # every mode once before timing: Triton kernels compile on first use, and a slow mode
    # (naive) is timed once per size; `inr`'s shadow INR is built then, and the timed frames of its light reuse it,
    # as the viewer's frames do (making one is timed apart: evaluate_voxels' seconds_per_inr)
    tiny = Camera.orbit(scene.volume.extent, azimuth=azimuth, elevation=elevation, size=8)
    for mode in BENCH_MODES:
        scene.render(mode, tiny, **kwargs)
    # the networks as configured and as this scene resolved them, after warming: a kernel that failed to compile
    # left it eager
    out["networks"] = scene.networks_used()
    if naive is not None:
        _check_naive(naive, size=min(sizes), step=step, light=light, azimuth=azimuth, elevation=elevation,
                     kernel=out["networks"]["kernel"], device=str(device))
        if naive["networks"] != out["networks"]:  # a fused kernel fell back in one process only: not this frame's
            log(f"[bench render] --naive-counts rendered with {naive['networks']}, this bench with "
                f"{out['networks']}: the naive frame counted here")
            naive = None
    out["naive_counted"] = "here" if naive is None else "apart (bench naive-counts)"
    for n in sizes:
        row: dict = {"seconds": {m: [] for m in BENCH_MODES}, "samples": {}}
        for rep in range(repeats):  # modes interleaved, so drift on a shared machine hits all alike
            for mode in BENCH_MODES:
                if rep and min(row["seconds"][mode]) > SLOW_FRAME_S:
                    continue
                _sync(device)
                img = scene.render(mode, cams[n], **kwargs)
                _sync(device)
                row["seconds"][mode].append(img.seconds)
                # slots: a whole-ray kernel's lane trips (0 for the wavefront loop); primary / slots is its lanes' use
                row["samples"][mode] = {"primary": img.counters.primary_samples,
                                        "secondary": img.counters.secondary_samples, "slots": img.counters.slots}
                log(f"[bench render] {n}x{n} {mode:8s} run {rep + 1}/{repeats}: {img.seconds:.3f} s")
        # recorded a march iteration at a time (the frame's `interrupt`): a naive frame's events at once took GBs
        row["counts"] = {m: op_counts(lambda cut, m=m, n=n: scene.render(m, cams[n], interrupt=cut, **kwargs),
                                      memory=device, pieces=True) for m in ("noshadow", "inr")}
        if n == min(sizes):  # naive's count takes minutes past the smallest size: its secondary rays are the point
            naive = naive or naive_counts(scene, light, size=n, step=step, azimuth=azimuth, elevation=elevation)
            row["counts"]["naive"] = dict(naive["counts"])
        row["peak_mem_bytes"] = {m: c.pop("peak_bytes") for m, c in row["counts"].items()}
        log(f"[bench render] {n}x{n} per frame: " + ", ".join(
            f"{m} {c['ops']:,} ops {c['syncs']} host syncs {c['host_tensors']} host tensors"
            for m, c in row["counts"].items()))
        med = {m: statistics.median(v) for m, v in row["seconds"].items()}
        row["fps"] = {m: 1.0 / t for m, t in med.items()}
        row["fps_light_moved"] = _light_moved_fps(scene, cams[n], kwargs, repeats)
        row["speedup"] = med["naive"] / med["inr"]
        row["overhead"] = med["inr"] / med["noshadow"]
        lanes = {m: c["primary"] / c["slots"] for m, c in row["samples"].items() if c["slots"]}
        moved = row["fps_light_moved"]
        log(f"[bench render] {n}x{n}: fps " + ", ".join(f"{m} {row['fps'][m]:.2f}" for m in BENCH_MODES)
            + (f", inr with the light moved {moved:.2f}" if moved else "")
            + f"; naive/inr {row['speedup']:.1f}x, inr/noshadow {row['overhead']:.2f}x"
            + "".join(f"; {m} lanes {u:.1%} useful" for m, u in lanes.items()))
        out["sizes"][str(n)] = row

    # macro-cell skipping, noshadow at the largest size
    n = max(sizes)
    times = {True: [], False: []}
    images = {}
    for _ in range(repeats):
        for skip in (True, False):
            img = scene.render("noshadow", cams[n], step=step, skip=skip)
            times[skip].append(img.seconds)
            images[skip] = img
    mask = foreground(images[False].alpha)
    macro = scene.macro("inr" if scene.data_inr is not None else "grid", True)
    out["macro_cells"] = {
        "cell": scene.cell, "empty_fraction": macro.empty_fraction, "size": n,
        "seconds_skip": statistics.median(times[True]), "seconds_noskip": statistics.median(times[False]),
        "speedup": statistics.median(times[False]) / statistics.median(times[True]),
        "psnr_skip_vs_noskip": image_psnr(images[True].rgb, images[False].rgb, mask if mask.any() else None),
        "samples_skip": images[True].counters.primary_samples,
        "samples_noskip": images[False].counters.primary_samples,
    }
    same = out["macro_cells"]["psnr_skip_vs_noskip"]
    log(f"[bench render] macro-cells ({out['macro_cells']['empty_fraction']:.0%} empty): "
        f"{out['macro_cells']['speedup']:.2f}x faster, images "
        + (f"equal to {same:.1f} dB" if math.isfinite(same) else "identical"))

    # the renderer's time-versus-error curve: inr mode against itself at a tiny step
    curve_size = curve_size or min(64, max(sizes))
    cam = Camera.orbit(scene.volume.extent, azimuth=azimuth, elevation=elevation, size=curve_size)
    # early termination off (1e-6) throughout, so the curve shows the step's error alone
    ref = scene.render("inr", cam, light=light, siren=siren, step=REFERENCE_STEP, min_transmittance=1e-6)
    mask = foreground(ref.alpha)
    curve = []
    for s in curve_steps:
        t = []
        for _ in range(repeats):
            img = scene.render("inr", cam, light=light, siren=siren, step=s, min_transmittance=1e-6)
            t.append(img.seconds)
        curve.append({"step": s, "seconds": statistics.median(t),
                      "psnr": image_psnr(img.rgb, ref.rgb, mask if mask.any() else None)})
        log(f"[bench render] step {s}: {curve[-1]['seconds']:.3f} s, {curve[-1]['psnr']:.1f} dB vs step "
            f"{REFERENCE_STEP}")
    out["step_curve"] = {"size": curve_size, "reference_step": REFERENCE_STEP, "mode": "inr", "points": curve}

    # peak memory of noshadow and inr past the bench sizes (2x and 4x the largest side by default; naive would
    # take minutes per frame there): does it stay bounded?
    n0 = max(sizes)
    memory_sizes = [2 * n0, 4 * n0] if memory_sizes is None else [n for n in memory_sizes if n not in sizes]
    scaling: dict = {m: {str(n): out["sizes"][str(n)]["peak_mem_bytes"][m] for n in sizes} for m in ("noshadow", "inr")}
    for n in memory_sizes:
        cam = Camera.orbit(scene.volume.extent, azimuth=azimuth, elevation=elevation, size=n)
        for mode, row in scaling.items():
            row[str(n)] = peak_bytes(lambda cut, m=mode, c=cam: scene.render(m, c, interrupt=cut, **kwargs), device,
                                     pieces=True)
    for n in sizes:
        log(f"[bench render] memory {n}²: " + ", ".join(f"{m} +{b / 2**20:.1f} MiB"
                                                      for m, b in out["sizes"][str(n)]["peak_mem_bytes"].items()))
    for mode, row in scaling.items():
        log(f"[bench render] memory {mode}: " + ", ".join(f"{n}² +{b / 2**20:.1f} MiB" for n, b in row.items()))
    out["memory_scaling"] = scaling
    return out


def write_bench(path: Path, results: dict) -> None:
    atomic_write_text(path, json.dumps(finite_json(results), indent=2) + "\n")
    _plot(results, path.with_suffix(".png"))


def _plot(results: dict, path: Path) -> None:
    fig = figure(results)  # first: it picks matplotlib's Agg backend before pyplot is imported
    import matplotlib.pyplot as plt

    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)


def figure(results: dict) -> Figure:
    """bench.png's figure: fps, peak memory (every size rendered), the step curve, ops and syncs per frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from diffshadow.summary import peak_memory

    fig, ax = plt.subplots(1, 4, figsize=(18, 4))
    sizes = list(results["sizes"])
    x = np.arange(len(sizes))
    # memory at every size rendered, the memory-only ones too: the panel answers "does it stay bounded?"
    every, peaks = peak_memory(results)
    for i, mode in enumerate(BENCH_MODES):
        ax[0].bar(x + (i - 1) * 0.25, [results["sizes"][s]["fps"][mode] for s in sizes], 0.25, label=mode)
        peak = [peaks.get(mode, {}).get(s, np.nan) / 2**20 for s in every]
        ax[1].bar(np.arange(len(every)) + (i - 1) * 0.25, peak, 0.25, label=mode)
    for a, label, ticks in ((ax[0], "frames per second", sizes), (ax[1], "peak memory added (MiB)", every)):
        a.set_xticks(np.arange(len(ticks)), [f"{s}²" for s in ticks])
        a.set_ylabel(label)
    ax[0].set_yscale("log")
    for i, mode in enumerate(BENCH_MODES):  # per-frame counts: device-independent, so they do not drift
        xs = [j for j, s in enumerate(sizes) if mode in results["sizes"][s].get("counts", {})]
        ops = [results["sizes"][sizes[j]]["counts"][mode]["ops"] for j in xs]
        bars = ax[3].bar(np.array(xs) + (i - 1) * 0.25, ops, 0.25, label=mode)
        for bar, j in zip(bars, xs, strict=True):
            ax[3].annotate(f"{results['sizes'][sizes[j]]['counts'][mode]['syncs']}", (bar.get_x() + 0.125,
                           bar.get_height()), ha="center", va="bottom", fontsize=8)
    ax[3].set_xticks(x, [f"{s}²" for s in sizes])
    ax[3].set_ylabel("ops per frame (bar label: host syncs)")
    ax[3].set_yscale("log")
    pts = results["step_curve"]["points"]
    ax[2].plot([p["seconds"] for p in pts], [p["psnr"] for p in pts], "o-")
    for p in pts:
        ax[2].annotate(f"step {p['step']}", (p["seconds"], p["psnr"]))
    ax[2].set_xlabel("seconds per frame")
    ax[2].set_ylabel(f"PSNR vs step {results['step_curve']['reference_step']} (dB)")
    ax[2].set_xscale("log")
    from diffshadow.report import decade_labels

    for axis in (ax[0].yaxis, ax[3].yaxis, ax[2].xaxis):
        decade_labels(axis)
    handles, labels = ax[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper right", ncol=len(labels))  # one legend, clear of the bars
    fig.suptitle(f"{results.get('scene', '')} on {results['device']}")
    fig.tight_layout()
    return fig


def run(out: Path, *, scene_config: Path | None = None, volume: Path | None = None, tf_config: dict | None = None,
        data_inr: Path | None = None, inr_steps: int | None = None, weights: Path | None = None, light_index: int = 0,
        siren_width: int = 32, siren_steps: int = 300, sizes: Sequence[int] = (64, 128), step: float = 0.5,
        repeats: int = 3, memory_sizes: Sequence[int] | None = None, render: dict | None = None,
        naive_counts: Path | None = None, device: torch.device | str = "cpu") -> dict:
    """`diffshadow bench render`: a scene (scene file, prepared volume, or raw file with the bench TF), its data
    INR and one shadow INR (given, or fitted here), then `bench_render`; writes JSON and a plot. `naive_counts`:
    `run_naive_counts`' file, the naive frame's counts taken apart."""
    import dataclasses

    from diffshadow.artifacts import data_inr_of, load_render_scene, load_scene_file
    from diffshadow.bench import BENCH_LIGHT, BENCH_TF
    from diffshadow.data_inr import DataInrConfig, fit_data_inr
    from diffshadow.fit import FitConfig, fit_sirens
    from diffshadow.sampling import seeded
    from diffshadow.siren import SirenConfig, WeightLayout, init_siren
    from diffshadow.store import open_store
    from diffshadow.volume import check_extinction, is_prepared

    if repeats < 1:  # before any fit: with no timed frame there is no median to report
        raise ValueError(f"bench render: --repeats: expected at least 1 timed frame per mode, got {repeats}")
    naive = _read_naive(Path(naive_counts)) if naive_counts else None
    if scene_config:
        scene = load_scene_file(Path(scene_config), device, render)
        name = Path(scene_config).stem
    elif volume:
        tf = tf_config if tf_config is not None or is_prepared(volume) else BENCH_TF
        scene = load_render_scene(volume, None, device, tf, render)
        name = scene.volume.name
    else:
        raise ValueError("bench render: give --scene-config FILE or --volume PATH")
    if data_inr:
        scene.data_inr = data_inr_of(data_inr, scene.volume, str(scene_config or volume))
    else:
        inr_cfg = DataInrConfig.from_config({} if inr_steps is None else {"steps": inr_steps})
        print(f"[bench render] fitting a data INR ({inr_cfg.steps} steps; pass --data-inr to reuse one) ...")
        scene.data_inr = fit_data_inr(scene.volume, scene.tf, inr_cfg, device=device, log=lambda m: None)
    if weights:
        store = open_store(weights)
        check_extinction(store.extinction, scene.extinction, cache=str(weights),
                         scene=str(scene_config or volume), remedy="the bench would time and score another scene's "
                         "shadow; give the weights of this scene's run")
        siren = (store.weights[light_index], store.layout, store.siren.blocks)
        light = store.lights[light_index]
    else:
        cfg = SirenConfig(siren_width, 2)
        layout = WeightLayout.for_siren(cfg)
        light = np.asarray(BENCH_LIGHT, float) / np.linalg.norm(BENCH_LIGHT)
        print(f"[bench render] fitting a shadow INR ({siren_steps} steps; pass --weights to reuse one) ...")
        fit = dataclasses.replace(FitConfig.from_config(), steps=siren_steps, grid_upsample=1, chunk=4096)
        w = fit_sirens(layout.flatten(init_siren(cfg, seeded(0))), layout, cfg, scene.volume, scene.tf,
                       light[None], fit, device=device, log=lambda m: None)[0]
        siren = (w, layout, cfg.blocks)
    results = bench_render(scene, siren, light, sizes=sizes, step=step, repeats=repeats, memory_sizes=memory_sizes,
                           naive=naive)
    results.update({"scene": name, "dims": list(scene.volume.dims),
                    "data_inr": {"params": scene.data_inr.n_params, "psnr": scene.data_inr.psnr},
                    "shadow_inr": {"params": int(siren[1].n_params)}})
    write_bench(Path(out), results)
    print(f"wrote {out} and {Path(out).with_suffix('.png')}")
    return results


def run_naive_counts(out: Path, *, volume: Path, data_inr: Path, lights: Path, size: int, step: float = 0.5,
                     render: dict | None = None, device: torch.device | str = "cpu") -> dict:
    """`diffshadow bench naive-counts`: `naive_counts` under the first training light of `lights` (the light
    `bench render --weights` takes at --light-index 0) of a prepared volume and its data INR, for `bench render
    --naive-counts`."""
    from diffshadow.artifacts import data_inr_of, load_render_scene
    from diffshadow.lights import read_lights

    if size < 1:
        raise ValueError(f"bench naive-counts: --size: expected a side of at least 1 pixel, got {size}")
    scene = load_render_scene(volume, None, device, None, render)
    scene.data_inr = data_inr_of(data_inr, scene.volume, str(volume))
    result = naive_counts(scene, read_lights(lights)["train"][0], size=size, step=step)
    atomic_write_text(out, json.dumps(finite_json(result), indent=1) + "\n")
    c = result["counts"]
    print(f"[bench naive-counts] {size}x{size} naive: {c['ops']:,} ops, {c['syncs']} host syncs, {c['host_tensors']} "
          f"host tensors, +{c['peak_bytes'] / 2**20:.1f} MiB; wrote {out}")
    return result


def _read_naive(path: Path) -> dict:
    """`run_naive_counts`' file, or a one-line error naming it."""
    try:
        naive = json.loads(path.read_text())
        counts = naive["counts"]
        if not all(isinstance(counts.get(k), int) for k in ("ops", "syncs", "host_tensors", "peak_bytes")):
            raise KeyError("counts")
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
        raise ValueError(f"--naive-counts {path}: expected the JSON of `diffshadow bench naive-counts` (its "
                         f"counts: ops, syncs, host_tensors, peak_bytes), could not read it: {e}") from None
    return naive
