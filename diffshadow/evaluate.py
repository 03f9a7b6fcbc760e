"""Stage-2 voxel evaluation: generated SIRENs against the ground truth, beside the stage-1 SIRENs and
baselines for unseen lights, plus storage and time per shadow INR."""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from numpy.typing import ArrayLike

from diffshadow.diffusion.config import DiffusionConfig
from diffshadow.diffusion.mix import mix_weights
from diffshadow.diffusion.sample import generate, load_sampler
from diffshadow.hpc import device_name
from diffshadow.io import atomic_torch_save, resume
from diffshadow.lights import (
    across_subsets,
    blend_weights,
    n_subsets,
    nearest,
    pick,
    recorded_weighting,
    wide_test_lights,
)
from diffshadow.progress import Ticker
from diffshadow.sampling import Stream, seeded
from diffshadow.store import BlendSampler, blend_record, blend_rows
from diffshadow.truth import EvalTruth, median, p10, psnr_per_light

if TYPE_CHECKING:
    from diffshadow.correction import BlendCorrection
    from diffshadow.diffusion.model import WeightTransformer
    from diffshadow.diffusion.standardize import Standardizer
    from diffshadow.render import RenderScene
    from diffshadow.store import WeightStore
    from diffshadow.transfer import TransferFunction
    from diffshadow.volume import Volume


def blend_baseline(train_values: dict, idx: np.ndarray, weights: np.ndarray) -> dict[str, torch.Tensor]:
    """Per set, the rows (L, P) of the k nearest training lights `idx` (Q, k) blended with
    `lights.blend_weights` (Q, k): their true shadows, or their stage-1 SIRENs' values."""
    w = torch.as_tensor(weights, dtype=torch.float32)
    return {key: (vals[torch.as_tensor(idx)] * w[..., None]).sum(dim=1) for key, vals in train_values.items()}


def seconds_per_inr(model: WeightTransformer, std: Standardizer, light: ArrayLike, *, method: str, steps: int,
                    repeats: int = 3, temperature: float = 1.0, device: torch.device | str = "cpu") -> float:
    """Wall time to generate one shadow INR (batch of one) on `device`, best of `repeats` (generate returns the
    weights on the host, so a GPU's queue is drained inside each timing)."""

    best = float("inf")
    for r in range(repeats):
        t = time.perf_counter()
        generate(model, std, light[None], method=method, steps=steps, seed=r, temperature=temperature,
                 device=device)
        best = min(best, time.perf_counter() - t)
    return best


def _interval95(statistic: Callable[[np.ndarray], np.ndarray], n: int, resamples: int) -> list[float]:
    """The 95 % bootstrap interval of `statistic` (of (resamples, n) row picks) over n lights, from a fixed stream
    (the same interval every run)."""
    idx = torch.randint(n, (resamples, n), generator=seeded(Stream.BOOTSTRAP)).numpy()
    return [float(x) for x in np.percentile(statistic(idx), [2.5, 97.5])]


def median_gap_interval(a: np.ndarray, b: np.ndarray, *, resamples: int = 2000) -> list[float]:
    """The 95 % bootstrap interval of median(a) - median(b) over the lights, resampled with their two figures
    paired: how far the gap would move with other test lights."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return _interval95(lambda i: np.median(a[i], axis=1) - np.median(b[i], axis=1), len(a), resamples)


def mean_gap_interval(gaps: np.ndarray, *, resamples: int = 2000) -> list[float]:
    """The 95 % bootstrap interval of the mean of `gaps`, one a light (its images' mean: a light's views are not
    independent images, so lights are what is resampled)."""
    gaps = np.asarray(gaps, dtype=np.float64)
    return _interval95(lambda i: gaps[i].mean(axis=1), len(gaps), resamples)


def wide_comparison(state: dict | None, stage1: WeightStore, light_sets: dict, volume: Volume, tf: TransferFunction, *,
                    share: float, lights: int, points: int, seed: int, blend_k: int, weighting: str,
                    device: torch.device | str = "cpu", cache: WeightStore | None = None,
                    correction: BlendCorrection | None = None) -> dict:
    """The cache's answer (`share` x the model's SIREN + the rest x the weight blend of the stored SIRENs,
    `lights.blend_weights` by `weighting` and `blend_k`; share 1: the model alone), the weight blend and the model
    alone on `lights` further test lights (`lights.wide_test_lights`), exact shadows at `points` box points each:
    the test lights' comparison, with an interval many times tighter. 32 test lights cannot tell a few tenths of a
    dB (nucleon, 512 training lights: the mix over the blend +0.36 dB, interval +0.04 to +0.78, on its 32 test
    lights; +0.77, +0.73 to +0.84, on 4,096 of these). The model samples, and the SIRENs are evaluated at the
    points, on `device`; the truth (marched on the CPU) and the PSNRs stay on the CPU.

    Without a model (`state` None: `cache: blend` or a codec) the cache's answer is the weight blend of `cache`'s
    SIRENs (a codec's decoded store of stage 1's lights in their order, set beside stage 1's fp32 blend: what the
    codec costs), or, `cache` None, the
    weight blend itself; `share` is not read. Either way the lights are those a diffusion run draws at `seed`, so
    the two runs' medians stand side by side. With `correction` (correction.BlendCorrection) the answer's blend
    is the corrected one; `weight_blend` stays the plain blend, so the two say what the correction gained."""
    if lights < 1 or points < 1:  # the schema holds the workflow's values; these are the command's own
        raise ValueError(f"--wide-lights and --wide-points (evaluate.wide_lights, evaluate.wide_points): expected at "
                         f"least 1 light and 1 point, got {lights} and {points} (wide_lights 0 skips the comparison)")
    train = light_sets["train"]
    wide = wide_test_lights(train, light_sets["center"], lights, seed=seed)
    truth = EvalTruth.compute(volume, tf, wide, points, seed, sets=("box",)).on(device)
    rows = truth.of(wide)
    idx, w = blend_weights(train, wide, blend_k, weighting)
    plain = blend_rows(stage1.weights, idx, w)
    blend = plain.astype(np.float32)
    corrected = None if correction is None else (plain + correction.delta(wide, idx, w)).astype(np.float32)
    out = {"lights": lights, "points": points, "seed": seed, **({"corrected": True} if correction is not None else {})}
    if state is None:
        layout, siren = stage1.layout, stage1.siren
        sides = {"weight_blend": blend}
        if cache is not None:
            sides["answer"] = blend_rows(cache.weights, idx, w).astype(np.float32)
            out["codec"] = cache.codec
        elif corrected is not None:
            sides["answer"] = corrected
    else:
        cfg = state["config"]
        model, std, layout, siren = load_sampler(state, device)
        sampled = generate(model, std, wide, method="ddim", steps=int(cfg["ddim_steps"]), seed=int(cfg["seed"]),
                           temperature=cfg["temperature"], device=device).numpy()
        sides = {"answer": mix_weights(sampled, blend if corrected is None else corrected, share),
                 "weight_blend": blend, "model_alone": sampled}
        out["model_share"] = share
    score = {name: psnr_per_light(truth.sirens(x, layout, siren), rows)["box"].astype(np.float64)
             for name, x in sides.items()}
    a, b = score.get("answer", score["weight_blend"]), score["weight_blend"]
    m = score.get("model_alone")
    out.update(blend_weights=weighting, blend_k=blend_k, generated_psnr_median=median(a),
               weight_blend_psnr_median=median(b), **({} if m is None else {"model_alone_psnr_median": median(m)}))
    # the lower tail, which a median does not see: lights the training lights' hull does not hold (lights.layout)
    out.update(generated_psnr_p10=p10(a), weight_blend_psnr_p10=p10(b),
               **({} if m is None else {"model_alone_psnr_p10": p10(m)}))
    if "answer" in score:
        out.update(weight_blend_gap_interval95_db=median_gap_interval(a, b),
                   better_than_weight_blend=int((a > b).sum()))
    if m is not None:
        out.update(model_alone_gap_interval95_db=median_gap_interval(a, m), better_than_model_alone=int((a > m).sum()))
    if seams := seam_split(a, train, idx, w, stage1.config):
        out["seams"] = seams
    return out


def seam_split(score: np.ndarray, train: np.ndarray, idx: np.ndarray, mix: np.ndarray, config: dict | None) -> dict:
    """The cache's answer on the further lights whose blend spans two fit_siren subsets (`lights.across_subsets`)
    against those inside one: stage 1's seams, which its median hides (128 lights in subsets of 50 without a halo:
    47 of 256 lights, median 38.69 against 48.14 dB; with a halo fitted in rounds 48.88 against 48.08;
    docs/performance.md). {} with one subset, or for a store that
    does not record its subset size."""
    size = (config or {}).get("subset_size")
    if not size or n_subsets(len(train), int(size)) < 2:
        return {}
    across = across_subsets(train, idx, mix, int(size))
    fit = config.get("fit") or {}
    halo = int(fit.get("halo", 0))
    return {"subset_size": int(size), "halo": halo, "rounds": bool(halo and fit.get("rounds", False)),
            "lights": int(across.sum()),
            "answer_median_across": median(score[across]) if across.any() else None,
            "answer_median_within": median(score[~across]) if (~across).any() else None}


def voxel_metrics(state: dict | None, stage1: WeightStore, generated: WeightStore, truth: EvalTruth, light_sets: dict,
                  *, blend_k: int, weighting: str, grid_voxels: int, ddpm_lights: int = 8,
                  geometry_state: dict | None = None, device: torch.device | str = "cpu",
                  curve_checkpoint: Path | None = None, log: Callable[[str], None] = print) -> dict:
    """`voxel_metrics.json`: generated SIRENs (seen and unseen) against the ground truth, beside the stage-1
    SIRENs, the nearest and blend baselines, DDIM vs DDPM on `ddpm_lights` training lights, and storage.
    With `geometry_state` (the model before rendering-loss fine-tuning), the unseen lights are also sampled
    from it: what fine-tuning did to lights it never saw. `state` None (`cache: blend`): `generated` holds the
    stored and blended SIRENs; no sampler to time, no model to store. Where sample_shadows mixed the model's SIRENs
    with the stored ones' blend (its config's `mix`), the model's own, as sample_shadows scored them before the mix,
    are reported beside them (`model_alone_psnr_median`); fine-tuning's change and the sampler curve are the
    model's own. The samplers run,
    and are timed, on `device`, where `truth` (`EvalTruth.on`) evaluates the SIRENs it scores; the truth and the
    PSNRs stay on the CPU.

    Resumable: the sampler curve (its 500-step DDPM the longest row) saves its rows to `curve_checkpoint` as
    each is done, and a rerun for the same model, lights, truth and device kind starts at the first row not done
    (each row samples from a fixed seed, so the PSNRs are the same; the timings are those measured then). The
    checkpoint is removed at the end."""

    train, unseen = light_sets["train"], light_sets["unseen"]
    seen = generated.seen
    if state is None:
        model, layout, siren = None, stage1.layout, stage1.siren
    else:
        cfg = state["config"]
        model, std, layout, siren = load_sampler(state, device)
    truth_train = truth.of(train)
    truth_unseen = truth.of(unseen) if len(unseen) else {}
    gen_seen = psnr_per_light(truth.sirens(generated.weights[seen], layout, siren), truth_train)
    mixed = (generated.config or {}).get("mix") if model is not None else None
    # the model's own SIRENs' box PSNR per light: generated.zarr's, or, where sample_shadows mixed them with the
    # stored SIRENs' blend, as it scored them before the mix
    alone = np.asarray(mixed["model_alone_psnr"]) if mixed else None
    alone_seen = alone[seen] if mixed else gen_seen["box"]
    stage1_values = truth.sirens(stage1.weights, layout, siren)
    stage1_seen = psnr_per_light(stage1_values, truth_train)
    result = {"seen": {"count": int(seen.sum()),
                       "generated_psnr_median": median(gen_seen["box"]),
                       "generated_psnr_min": float(gen_seen["box"].min()),
                       "stage1_psnr_median": median(stage1_seen["box"]),
                       "generated_minus_stage1_median_db": median(gen_seen["box"] - stage1_seen["box"])},
              "eval_points": int(len(truth.points["box"]))}
    if "visible" in gen_seen:
        result["seen"]["generated_psnr_visible_median"] = median(gen_seen["visible"])
        result["seen"]["stage1_psnr_visible_median"] = median(stage1_seen["visible"])
    # the blend's correction (diffshadow/correction.py) where the answer's blend was corrected: the mix's, or a
    # blend cache's; the "weight blend" baselines below stay plain, so the two side by side say what it adds
    if (mixed or generated.config or {}).get("correction"):
        result["corrected"] = True
    if mixed:
        result["mix"] = {k: mixed[k] for k in ("model_share", "chosen", "blend_k")}
        result["mix"]["blend_weights"] = recorded_weighting(mixed)
        result["seen"]["model_alone_psnr_median"] = median(alone_seen)
    if len(unseen):
        idx, mix = blend_weights(train, unseen, blend_k, weighting)
        near_idx, angles = nearest(train, unseen, 1)
        gen_unseen = psnr_per_light(truth.sirens(generated.weights[~seen], layout, siren), truth_unseen)
        alone_unseen = alone[~seen] if mixed else gen_unseen["box"]
        near = psnr_per_light(truth.sirens(stage1.weights[near_idx[:, 0]], layout, siren), truth_unseen)
        blend = psnr_per_light(blend_baseline(truth_train, idx, mix), truth_unseen)
        # the same blend of the stage-1 SIRENs' weights: one SIREN per unseen light, as the model gives
        weight_blend = blend_rows(stage1.weights, idx, mix)
        wblend = psnr_per_light(truth.sirens(weight_blend, layout, siren), truth_unseen)
        # the blend of their values: a cache of the fitted SIRENs read k times per sample. Unlike the true
        # shadows' blend it carries stage 1's fit error, which caps what any generated SIREN can reach.
        sblend = psnr_per_light(blend_baseline(stage1_values, idx, mix), truth_unseen)
        result["unseen"] = {"count": len(unseen),
                            "generated_psnr_median": median(gen_unseen["box"]),
                            "nearest_psnr_median": median(near["box"]),
                            "blend_psnr_median": median(blend["box"]),
                            "weight_blend_psnr_median": median(wblend["box"]),
                            # is the model's gap to the blend more than the test lights' draw? (the summary's verdict)
                            "weight_blend_gap_interval95_db": median_gap_interval(gen_unseen["box"], wblend["box"]),
                            "better_than_weight_blend": int((gen_unseen["box"] > wblend["box"]).sum()),
                            "siren_blend_psnr_median": median(sblend["box"]),
                            "blend_weights": weighting, "blend_k": blend_k,
                            "nearest_angle_median_deg": float(np.degrees(np.median(angles[:, 0])))}
        if mixed:
            result["unseen"]["model_alone_psnr_median"] = median(alone_unseen)
        pool = np.asarray((state or {}).get("pool_lights") or np.zeros((0, 3)), dtype=np.float64).reshape(-1, 3)
        if len(pool):  # lights trained on exact shadows only: how close the test lights came to any of them
            _, a_any = nearest(np.concatenate([train, pool]), unseen, 1)
            result["unseen"]["pool_lights"] = len(pool)
            result["unseen"]["nearest_trained_angle_median_deg"] = float(np.degrees(np.median(a_any[:, 0])))
        if geometry_state is not None:
            g_model, g_std, _, _ = load_sampler(geometry_state, device)
            before = generate(g_model, g_std, unseen, method="ddim", steps=int(cfg["ddim_steps"]),
                              seed=int(cfg["seed"]), temperature=cfg["temperature"], device=device).numpy()
            before_psnr = psnr_per_light(truth.sirens(before, layout, siren), truth_unseen)["box"]
            result["unseen"]["geometry_only_psnr_median"] = median(before_psnr)
            result["unseen"]["finetune_change_median_db"] = median(alone_unseen - before_psnr)
    result["stage1"] = {"width": siren.width, "blocks": siren.blocks, "parameters": layout.n_params,
                        "capacity": (stage1.config or {}).get("capacity")}
    result["cache"] = "diffusion" if model is not None else "blend"
    stored = {"sirens": int(len(train) * layout.n_params * 4), "grids": int(len(train) * grid_voxels * 2)}
    if model is None:
        result["storage_bytes"] = {"model": 0, **stored}
        codec = generated.codec
        if codec != "fp32":  # cache: fp16, bf16, basis-<k>: the stored SIRENs' blend, stored in that codec
            result["codec"] = codec
            result["storage_bytes"]["cache"] = int(generated.config["encoded_bytes"])
        return result
    # DDIM at several step counts and 500-step DDPM on a spread of training lights: quality on the same lights,
    # time per INR alone; the report's DDIM curve plots these rows (one measurement, not two)
    ddim_steps = int(cfg["ddim_steps"])
    sel = pick(len(train), ddpm_lights)
    if not sel:  # evaluate.ddpm_lights: 0, no curve: the run's own sampler is timed alone
        log("[evaluate voxels] no sampler curve (evaluate.ddpm_lights: 0): DDIM's time per INR alone")
        t_ddim = seconds_per_inr(model, std, train[0], method="ddim", steps=ddim_steps, repeats=3,
                                 temperature=cfg["temperature"], device=device)
        result["sampling"] = {"ddim_steps": ddim_steps, "lights": 0, "device": device_name(device),
                              "threads": torch.get_num_threads()}
        result["seconds_per_inr"] = {"ddim": t_ddim}
        return _with_model(result, model, std, cfg, siren, stored, geometry_state or state)
    truth_sel = {k: v[sel] for k, v in truth_train.items()}
    t0 = time.perf_counter()
    steps = sorted({5, 10, 20, 50, ddim_steps})
    log(f"[evaluate voxels] DDIM {', '.join(map(str, steps))} steps and 500-step DDPM for "
        f"{len(sel)} of the {len(train)} training lights, and one INR of each timed ...")
    rows = [*(("ddim", s) for s in steps), ("ddpm", 500)]
    fingerprint = _curve_fingerprint(model, std, train[sel], truth_sel, cfg, rows, device)
    saved = resume(curve_checkpoint, fingerprint, log=log, weights_only=True)
    curve = list(saved["curve"]) if saved else []
    if curve:
        log(f"[evaluate voxels] resuming from {curve_checkpoint} after {len(curve)} of {len(rows)} sampler rows")
    for method, k in rows[len(curve):]:
        if method == "ddim" and k == ddim_steps:  # the run's own sampler: these lights are already scored
            box = alone_seen[sel]
        else:
            w = generate(model, std, train[sel], method=method, steps=k, seed=int(cfg["seed"]),
                         temperature=cfg["temperature"], device=device).numpy()
            box = psnr_per_light(truth.sirens(w, layout, siren), truth_sel)["box"]
        seconds = seconds_per_inr(model, std, train[0], method=method, steps=k, repeats=3 if method == "ddim" else 1,
                                  temperature=cfg["temperature"], device=device)
        curve.append({"method": method, "steps": k, "seconds_per_inr": seconds, "psnr_median": median(box)})
        if curve_checkpoint is not None and len(curve) < len(rows):
            atomic_torch_save(curve_checkpoint, {"fingerprint": fingerprint, "curve": curve})
        log(f"[evaluate voxels] {method} {k} steps: {curve[-1]['psnr_median']:.2f} dB, {seconds:.3g} s an INR "
            f"({len(curve)}/{len(rows)})")
    log(f"[evaluate voxels] samplers done ({time.perf_counter() - t0:.0f} s)")
    if curve_checkpoint is not None:
        Path(curve_checkpoint).unlink(missing_ok=True)
    ddim_row = next(r for r in curve if r["method"] == "ddim" and r["steps"] == ddim_steps)
    t_ddim, t_ddpm = ddim_row["seconds_per_inr"], curve[-1]["seconds_per_inr"]
    result["sampling"] = {"ddim_steps": ddim_steps, "lights": len(sel), "device": device_name(device),
                          "threads": torch.get_num_threads(),
                          "ddim_psnr_median": ddim_row["psnr_median"],
                          "ddpm_psnr_median": curve[-1]["psnr_median"], "speedup": t_ddpm / t_ddim, "curve": curve}
    result["seconds_per_inr"] = {"ddim": t_ddim, "ddpm": t_ddpm}
    return _with_model(result, model, std, cfg, siren, stored, geometry_state or state)


def _with_model(result: dict, model: WeightTransformer, std: Standardizer, cfg: dict, siren, stored: dict,
                state: dict) -> dict:
    """`result` with the diffusion model's size, how long its geometry stage trained, and the cache's bytes."""
    mc = model.cfg
    # the training forward's precision as it ran (`diffusion.precision: auto` resolves per machine)
    result["diffusion_model"] = {"preset": cfg["preset"], "layers": mc.n_layer, "width": mc.n_embd,
                                 "parameters": model.n_params(), "siren_width": siren.width,
                                 "precision": DiffusionConfig.of_checkpoint(state).precision}
    growth = state.get("growth")
    if growth:  # how long the geometry stage trained and why it stopped (diffusion.target_gap)
        result["diffusion_model"].update(epochs=growth.get("epochs"), stopped=growth.get("reason"),
                                         kept_epoch=growth.get("kept_epoch", growth.get("epochs")),
                                         gap_checks=growth.get("checks", []))
    # the model's weights plus its standardiser (float64 mean and std, per token or per parameter)
    result["storage_bytes"] = {"model": int(sum(p.numel() * p.element_size() for p in model.parameters())
                                            + 2 * 8 * len(std.mean)), **stored}
    return result


def _curve_fingerprint(model: WeightTransformer, std: Standardizer, lights: np.ndarray, truth: dict, cfg: dict,
                       rows: list, device) -> str:
    """What the sampler curve's rows depend on: the model's weights and standardiser, the lights and their truth,
    the sampler settings and rows, and the kind of device (a GPU samples other bits, and times otherwise)."""
    h = hashlib.sha256(np.ascontiguousarray(lights, dtype=np.float64).tobytes())
    for t in [*model.state_dict().values(), std.mean, std.std, *(truth[k] for k in sorted(truth))]:
        h.update(torch.as_tensor(t).detach().cpu().contiguous().numpy().tobytes())
    h.update(json.dumps([int(cfg["seed"]), cfg["temperature"], rows, torch.device(device).type]).encode())
    return h.hexdigest()


# ------------------------------------------------------------------------------------------- images


def naive_tags(light_sets: dict, views: list, *, lights_per_set: int = 2, naive_views: int | None = None,
               naive_lights: int | None = None) -> list[tuple[str, int, int]]:
    """(tag, light row, view) of every image the slow naive baseline is rendered for: a few views and lights of
    the training set only (it learns nothing from the training lights, so the unseen set would only repeat its
    measurement; its comparison needs a few images, not all)."""
    return [(f"train{i}_view{v}", int(i), v)
            for j, i in enumerate(pick(len(light_sets["train"]), lights_per_set))
            if naive_lights is None or j < naive_lights
            for v in range(len(views)) if naive_views is None or v < naive_views]


def naive_images(scene: RenderScene, light_sets: dict, views: list, *, step: float, lights_per_set: int = 2,
                 naive_views: int | None = None, naive_lights: int | None = None, phong: bool = False,
                 log: Callable[[str], None] = print) -> dict:
    """The naive baseline's images (secondary rays through the data INR) by tag, for `image_evaluation`. They
    need only the volume, the data INR and the lights, so the workflow renders them in a job of their own
    (`naive_images`) while stage 1 and 2 run, not after them."""
    out = {}
    tags = naive_tags(light_sets, views, lights_per_set=lights_per_set, naive_views=naive_views,
                      naive_lights=naive_lights)
    for n, (tag, i, v) in enumerate(tags, 1):
        out[tag] = scene.render("naive", views[v], light=light_sets["train"][i], scalar="inr", phong=phong,
                                step=step, interrupt=Ticker(f"[naive images] {tag} ({n}/{len(tags)})", log=log))
        log(f"[naive images] {tag} {out[tag].seconds:.2f} s")
    return out


# `render.reference`: what image_evaluation scores every mode against (the renderer's mode drawing it on the raw
# scalar field; image_metrics.json's description)
REFERENCES = {
    "exact": ("naive", "gt: raw scalar field, the shadow marched from every sample through the raw volume (the naive "
                       "method on the voxels), same step"),
    "grid": ("gt", "gt: raw scalar field and shadow_grid (march at the voxels), same step"),
}


def image_evaluation(scene: RenderScene, light_sets: dict, stage1: WeightStore, generated: WeightStore, views: list, *,
                     step: float, out_dir: Path, lights_per_set: int = 2, naive_views: int | None = None,
                     naive_lights: int | None = None, lpips: torch.nn.Module | None = None, phong: bool = False,
                     naive: dict | None = None, reference: str = "exact", log: Callable[[str], None] = print) -> dict:
    """`image_metrics.json`: every mode against `gt` over a few training and unseen lights and views.

    `gt` (`reference`, REFERENCES): "exact", the shadow marched from every sample through the raw volume, or "grid",
    the `gt` mode's shadow grid marched at the voxels, whose trilinear lookups missed the exact shadow by as much as
    the shadow INRs it scored (nucleon: 51-53 dB; docs/performance.md, "The renderer").

    Modes: `inr_stage1` / `inr_generated` (shadow INR on the raw scalar field, so only the shadow's error
    shows), `inr_generated_data_inr` (the deployed path: data INR + generated shadow INR), `naive`
    (secondary rays through the data INR: it carries the data INR's error; training lights only, since it
    does not depend on which lights the model saw) and `noshadow` (the same shading
    without the shadow term, so its error is what the shadow adds). `phong` lights every mode, gt included.
    `naive`: the naive images by tag (`naive_images`), rendered here when not given. `inr_weight_blend` (unseen
    lights, where `generated` records the blend it answers with: `store.blend_record`): stage 1's plain weight blend
    on the raw scalar field, the baseline the voxel evaluation sets beside the answer; `weight_blend_images` compares
    the two image by image (the images' word on the correction and the model's share: neghip's voxels gained 0.25 dB
    where its images did not).
    """
    from pathlib import Path

    from diffshadow.metrics import image_metrics
    from diffshadow.render import write_png

    if reference not in REFERENCES:
        raise ValueError(f"render.reference: expected one of {', '.join(REFERENCES)}, got {reference!r}")
    out_dir = Path(out_dir)
    layout, blocks = stage1.layout, stage1.siren.blocks
    have_inr = scene.data_inr is not None
    if naive is None:
        naive = naive_images(scene, light_sets, views, step=step, lights_per_set=lights_per_set,
                             naive_views=naive_views, naive_lights=naive_lights, phong=phong,
                             log=log) if have_inr else {}
    gen_rows, plain = {}, None
    if generated is not None:
        seen = generated.seen
        gen_rows = {"train": np.flatnonzero(seen), "unseen": np.flatnonzero(~seen)}
        plain = BlendSampler.recorded(stage1, record) if (record := blend_record(generated)) else None
    per_image, sums = [], {}
    for set_name in ("train", "unseen"):
        for i in pick(len(light_sets[set_name]), lights_per_set):
            light = light_sets[set_name][i]
            # an unseen light's plain blend, where it is not the answer: once a light, for every view
            blend = plain(light) if set_name == "unseen" and plain is not None else None
            if blend is not None and np.array_equal(blend, generated.weights[gen_rows[set_name][i]]):
                blend = None
            for v, cam in enumerate(views):
                tag = f"{set_name}{i}_view{v}"
                gt = scene.render(REFERENCES[reference][0], cam, light=light, scalar="grid", phong=phong, step=step)
                write_png(out_dir / f"{tag}_gt.png", gt)
                modes = {}
                if set_name == "train":
                    modes["inr_stage1"] = {"mode": "inr", "scalar": "grid",
                                           "siren": (stage1.weights[i], layout, blocks)}
                if gen_rows:
                    w = generated.weights[gen_rows[set_name][i]]
                    modes["inr_generated"] = {"mode": "inr", "scalar": "grid", "siren": (w, layout, blocks)}
                    if have_inr:
                        modes["inr_generated_data_inr"] = {"mode": "inr", "scalar": "inr",
                                                           "siren": (w, layout, blocks)}
                    if blend is not None:
                        modes["inr_weight_blend"] = {"mode": "inr", "scalar": "grid",
                                                     "siren": (blend, layout, blocks)}
                if tag in naive:
                    modes["naive"] = {"image": naive[tag]}
                modes["noshadow"] = {"mode": "noshadow", "scalar": "grid"}
                for name, spec in modes.items():
                    img = spec.get("image") or scene.render(spec["mode"], cam, light=light, siren=spec.get("siren"),
                                                            scalar=spec["scalar"], phong=phong, step=step)
                    write_png(out_dir / f"{tag}_{name}.png", img)
                    m = image_metrics(img.rgb, gt.rgb, gt.alpha, lpips)
                    per_image.append({"set": set_name, "light": i, "view": v, "mode": name, **m,
                                      "seconds": img.seconds, "replayed": img.replayed})
                    sums.setdefault((set_name, name), []).append(m)
                    log(f"[evaluate images] {tag} {name:24s} PSNR {m['psnr']:6.2f} dB  SSIM {m['ssim']:.4f}  "
                        f"{img.seconds:.2f} s{' (kept samples)' if img.replayed else ''}")
    by_set: dict = {}
    overall: dict = {}
    for (set_name, name), rows in sums.items():
        by_set.setdefault(set_name, {})[name] = _mean_metrics(rows)
    for name in dict.fromkeys(n for _, n in sums):  # first-seen order: a set's order changes run to run
        overall[name] = _mean_metrics([r for (s, n), rows in sums.items() if n == name for r in rows])
    out = {"modes": overall, "by_set": by_set, "images": per_image}
    if pairs := _paired(per_image, "inr_generated", "inr_weight_blend"):
        out["weight_blend_images"] = pairs
    return out


PAIRED_INTERVAL_LIGHTS = 8  # the fewest lights whose images' gap gets a bootstrap interval (the default run has 2)


def _paired(rows: list[dict], a: str, b: str) -> dict | None:
    """Mode `a` against mode `b` over the images both were scored on: mean PSNRs, in how many `a` is better, and
    from PAIRED_INTERVAL_LIGHTS lights the mean gap's 95 % interval over the lights (`mean_gap_interval`)."""
    by = {(r["set"], r["light"], r["view"], r["mode"]): r["psnr"] for r in rows}
    keys = sorted(k[:3] for k in by if k[3] == a and (*k[:3], b) in by)
    if not keys:
        return None
    x, y = (np.array([by[(*k, m)] for k in keys], dtype=np.float64) for m in (a, b))
    out = {"images": len(keys), f"{a}_psnr_mean": float(x.mean()), f"{b}_psnr_mean": float(y.mean()),
           "better": int((x > y).sum())}
    by_light: dict[tuple, list[float]] = {}
    for k, gap in zip(keys, x - y, strict=True):
        by_light.setdefault(k[:2], []).append(gap)
    if len(by_light) >= PAIRED_INTERVAL_LIGHTS:
        per_light = np.array([np.mean(gaps) for gaps in by_light.values()])  # keys sorted: lights in order
        out.update(lights=len(by_light), gap_interval95_db=mean_gap_interval(per_light))
    return out


def _mean_metrics(rows: list[dict]) -> dict:
    out = {"count": len(rows)}
    for key in ("psnr", "ssim", "ms_ssim", "lpips"):
        vals = [r[key] for r in rows if r.get(key) is not None]
        out[key] = float(np.mean(vals)) if vals and len(vals) == len(rows) else None
    return out
