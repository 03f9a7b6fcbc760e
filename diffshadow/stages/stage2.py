"""Stage 2 (paper §3.3): presampled geometry points, diffusion training (geometry loss), rendering-loss
fine-tuning under DDP, sampling every seen and unseen light, the voxel evaluation."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import torch

from diffshadow import artifacts
from diffshadow.correction import CorrectionConfig
from diffshadow.diffusion.config import DiffusionConfig, DiffusionError
from diffshadow.diffusion.finetune import (
    FinetuneConfig,
    FinetuneData,
    finetune,
    image_psnr_of_model,
    keep_if_images_improve,
    same_sampler,
)
from diffshadow.diffusion.model import PRESETS
from diffshadow.diffusion.sample import checkpoint_region, generate, load_sampler
from diffshadow.diffusion.train import train_diffusion as train
from diffshadow.evaluate import voxel_metrics, wide_comparison
from diffshadow.hpc import device_name
from diffshadow.io import atomic_torch_save, atomic_write_text, finite_json
from diffshadow.lights import blend_label, describe_blend, read_lights, training_pool, validation_lights
from diffshadow.runtime import SpareThreads, borrowing, distributed, set_threads
from diffshadow.sampling import VALIDATION_POINTS_SEED, Stream
from diffshadow.store import BlendSampler, WeightStore, open_store, write_store
from diffshadow.truth import EvalTruth, check_points, psnr_per_light
from diffshadow.truth import presample as presample_points
from diffshadow.volume import check_extinction, extinction_id, load_prepared, prepared_voxels

# test lights further than this from a training light are helped by a denser sphere (tooth, docs/performance.md)
SPARSE_LIGHTS_DEG = 2.0


def presample(volume_path: Path, lights_path: Path, out: Path, *, cfg: DiffusionConfig,
              device: torch.device) -> None:
    """Points and their true shadow per training light, for the geometry loss."""
    volume, tf = load_prepared(volume_path)
    sets = read_lights(lights_path)
    train_lights = sets["train"]
    print(f"presampling {cfg.presample_points} points for each of {len(train_lights)} lights", flush=True)
    pts, values = presample_points(volume, tf, train_lights, cfg.presample_points, seed=cfg.seed, device=device)
    pool = None
    if cfg.pool_lights > 0:
        t0 = time.perf_counter()
        pool_lights = training_pool(train_lights, sets["center"], cfg.pool_lights, seed=cfg.seed)
        pool = (pool_lights, *presample_points(volume, tf, pool_lights, cfg.pool_points, seed=cfg.seed,
                                                stream=Stream.POOL_POINTS, device=device))
        print(f"pool: {cfg.pool_points} points and exact shadows for each of {cfg.pool_lights} lights without a "
              f"fitted SIREN ({time.perf_counter() - t0:.1f} s)", flush=True)
    check = check_points(volume, tf, train_lights, seed=cfg.seed, device=device)
    artifacts.write_geometry_points(out, pts, values, train_lights, volume.extent, pool, check)
    print(f"wrote {out}")


def train_diffusion(weights_path: Path, points_path: Path, out: Path, *, cfg: DiffusionConfig,
                    device: torch.device) -> None:
    """The geometry-stage model; resumable from `<out>.part`, renamed to `out` when complete."""
    data, _ = artifacts.read_training_data(weights_path, points_path)
    part = out.with_name(out.name + ".part")
    try:
        train(data, cfg, part, device=device)
    except DiffusionError as e:
        raise DiffusionError(f"train_diffusion ({weights_path}): {e}") from None
    os.replace(part, out)
    print(f"wrote {out}")


def _summary(psnr: np.ndarray) -> dict:
    return {"mean": float(psnr.mean()), "median": float(np.median(psnr)), "min": float(psnr.min())}


def finetune_render(checkpoint: Path, weights_path: Path, points_path: Path, targets_path: Path, out: Path,
                    metrics_path: Path, *, cfg: FinetuneConfig, device: torch.device, threads: int = 0,
                    volume_path: Path | None = None, lights_path: Path | None = None) -> None:
    """Rendering-loss fine-tuning from the geometry-stage checkpoint, one DDP rank per process; with the
    volume and the light sets, the model kept is chosen on validation lights (lights.validation_lights)."""
    with distributed(device, timeout_s=cfg.timeout_s) as ddp:
        set_threads(threads)
        rank, world = ddp.rank, ddp.world
        log = print if rank == 0 else (lambda m: print(m) if m.startswith(f"rank {rank}") else None)
        geometry = artifacts.load_checkpoint(checkpoint)
        train_data, _ = artifacts.read_training_data(weights_path, points_path)
        targets, bundle, target_lights = artifacts.read_targets(targets_path)
        if not np.allclose(target_lights, train_data.lights.numpy()):
            raise ValueError(f"{targets_path}: its lights differ from {weights_path}'s; rerun render_targets")
        val = None
        if volume_path is not None and cfg.val_lights > 0 and rank == 0:
            volume, tf = load_prepared(volume_path)
            if lights_path is None:
                raise ValueError("finetune_render: validation lights need the light sets (--lights) with the volume")
            lights = validation_lights(train_data.lights.numpy(), read_lights(lights_path)["center"], cfg.val_lights,
                                       seed=cfg.seed)
            val = EvalTruth.compute(volume, tf, lights, cfg.val_points, cfg.seed + VALIDATION_POINTS_SEED)
        data = FinetuneData(train_data, bundle, targets, val)
        part = out.with_name(out.name + ".part")
        t0 = time.perf_counter()
        state = finetune(geometry, data, cfg, part, rank=rank, world=world, device=ddp.device, log=log)
        seconds = time.perf_counter() - t0
        if rank != 0:
            return
        before = image_psnr_of_model(geometry, data)
        after = before.copy() if same_sampler(geometry, state) else image_psnr_of_model(state, data)
        final, kept = keep_if_images_improve(geometry, state, before, after)
        if final is not state:
            state = final  # written without the per-rank timings, like finetune's own checkpoint (same bytes)
            atomic_torch_save(part, {k: v for k, v in state.items() if k != "finetune_ranks"})
            print(f"fine-tuning rendered the training lights worse ({after.mean():.2f} dB against the geometry "
                  f"stage's {before.mean():.2f}): keeping the geometry stage's model")
        metrics = {"kept": kept, "image_psnr_geometry_only": _summary(before), "image_psnr_finetuned": _summary(after),
                   "lights": len(before), "views": int(len(bundle.count)), "processes": world,
                   "ranks": state.get("finetune_ranks"), "seconds": seconds, "config": cfg.__dict__,
                   "validation": state.get("selection")}
        print(f"image PSNR of generated shadows on training lights (foreground, {len(bundle.count)} views): "
              f"geometry only {before.mean():.2f} dB (min {before.min():.2f}), fine-tuned {after.mean():.2f} dB "
              f"(min {after.min():.2f}); {seconds:.0f} s on {world} process(es)")
        for r in state.get("finetune_ranks") or []:
            step_s = f"{r['median_step_s']:.3f} s" if r["median_step_s"] is not None else "n/a"
            print(f"rank {r['rank']}: median step {step_s}, peak memory {r['peak_mem_bytes'] / 2**20:.0f} MiB")
        atomic_write_text(metrics_path, json.dumps(metrics, indent=2) + "\n")
        os.replace(part, out)
        print(f"wrote {out} and {metrics_path}")


def eval_truth(volume_path: Path, lights_path: Path, out: Path, *, eval_points: int, seed: int,
               device: torch.device | str = "cpu") -> None:
    """Evaluation points and the exact shadow of every training and unseen light at them (the march),
    once per scene: it needs only the volume, so it runs beside stage 1, not after sampling."""
    volume, tf = load_prepared(volume_path)
    light_sets = read_lights(lights_path)
    lights = np.concatenate([light_sets["train"], light_sets["unseen"]])
    print(f"exact shadows of {len(lights)} lights at {eval_points} points per set", flush=True)
    truth = EvalTruth.compute(volume, tf, lights, eval_points, seed, device=device,
                              log=lambda m: print(f"[eval truth] {m}", flush=True))
    artifacts.write_eval_truth(out, truth)
    print(f"wrote {out}: sets {', '.join(truth.points)}")


def sample_shadows(checkpoint: Path, truth_path: Path, lights_path: Path, out: Path, *, device: torch.device,
                   mix: dict | None = None, weights_path: Path | None = None, volume_path: Path | None = None,
                   blend_k: int = 4, weighting: str = "triangle", score_device: torch.device | str = "cpu",
                   correction_path: Path | None = None) -> None:
    """SIRENs generated (on `device`) for every training and unseen light, with their voxel PSNR (the SIRENs
    evaluated on `score_device`: evaluate.device, the CPU by default). With `mix` (the config's section)
    and a model share under 1, each is mixed with the weight blend of the stored SIRENs of `weights_path`
    (`lights.blend_weights` by `weighting`, `blend_k`; a training light's blend is its own stored SIREN); share `auto`
    is chosen on validation lights with exact shadows from `volume_path` (diffusion/mix.py). With `correction_path`
    (fit_correction's correction.pt) the blend is the corrected one (diffshadow/correction.py). The share, its curve
    and the correction are recorded in the store's config, where the viewer reads them."""
    from diffshadow.diffusion.mix import mix_weights

    state = artifacts.load_checkpoint(checkpoint)
    model, std, layout, siren = load_sampler(state, device)
    cfg = state["config"]
    light_sets = read_lights(lights_path)
    train, unseen = light_sets["train"], light_sets["unseen"]
    all_lights = np.concatenate([train, unseen])
    seen = np.arange(len(all_lights)) < len(train)
    region = checkpoint_region(state)
    _check_region(region, unseen, checkpoint)
    share = "1" if mix is None else str(mix["model_share"])
    stage1 = _mix_inputs(share, weights_path, volume_path, layout, state.get("extinction"))
    blend_k = min(blend_k, len(train))
    correction = _correction(correction_path, stage1, weighting) if stage1 is not None else None
    blend = BlendSampler(stage1, blend_k, weighting, correction) if stage1 is not None else None
    print(f"sampling {len(all_lights)} shadow SIRENs ({seen.sum()} seen, {(~seen).sum()} unseen) with "
          f"DDIM {cfg['ddim_steps']} steps", flush=True)

    def sample(lights: np.ndarray) -> np.ndarray:
        return generate(model, std, lights, method="ddim", steps=cfg["ddim_steps"], seed=cfg["seed"],
                        temperature=cfg["temperature"], device=device).numpy()

    weights = sample(all_lights)
    truth = artifacts.read_eval_truth(truth_path).on(score_device)
    truth_rows = truth.of(all_lights, str(truth_path))
    config = {"diffusion": cfg, "checkpoint": str(checkpoint)}
    config.update(scored_on(score_device))
    if stage1 is not None:
        record = {"blend_weights": weighting, "blend_k": blend_k, "weights": str(weights_path),
                  **_correction_record(correction, correction_path)}
        if share == "auto":
            record.update(_choose_share(sample, blend, volume_path, light_sets, mix, score_device))
            record["chosen"] = "validation lights"
        else:
            record.update(model_share=float(share), chosen="config")
        # the model's own SIRENs scored before the mix (box points, per light): evaluate_voxels and caches report
        # the model alone from these instead of sampling every light again
        alone = psnr_per_light(truth.sirens(weights, layout, siren, sets=("box",)), {"box": truth_rows["box"]})["box"]
        record["model_alone_psnr"] = [float(x) for x in alone]
        # a training light's blend is its own stored SIREN, an unseen light's a float64 blend (blend_rows): mixed
        # apart, so that the stored SIRENs are not widened to float64 beside them (1.3 GB at the paper's sizes)
        n, unseen_blend = len(train), blend.rows(unseen)
        weights = np.concatenate([mix_weights(weights[:n], stage1.weights, record["model_share"]),
                                  mix_weights(weights[n:], unseen_blend, record["model_share"])])
        config["mix"] = record
        corrected = ", corrected" if correction is not None else ""
        print(f"the cache's answer: {record['model_share']:g} x the model's SIREN + {1 - record['model_share']:g} x "
              f"{describe_blend(weighting, blend_k)}{corrected} ({record['chosen']})", flush=True)
    scores = psnr_per_light(truth.sirens(weights, layout, siren), truth_rows)
    store = WeightStore(weights=weights, lights=all_lights, psnr=scores["box"],
                        psnr_visible=scores.get("visible", scores["box"]), layout=layout, siren=siren,
                        config=config, seen=seen, region=region.to_dict(), extinction=state.get("extinction"))
    write_store(out, store, made_by="sample_shadows")
    print(f"wrote {out}: PSNR median {_seen_unseen(store.psnr, seen)}")


def _correction(path: Path | None, stage1: WeightStore, weighting: str):
    """fit_correction's correction of the blend, checked to be for these stored SIRENs and blends; None without a
    path, or where its fit's held-out check declined it."""
    from diffshadow.correction import load_correction

    if path is None:
        return None
    correction = load_correction(path, stage1.lights, stage1.weights)
    if correction is not None:
        correction.check_weighting(weighting)
    return correction


def _correction_record(correction, path: Path | None) -> dict:
    """What a store's config says of the blend's correction: its file and settings (the viewer reads the file)."""
    if correction is None:
        return {}
    return {"correction": {"path": str(path), "config": correction.record.get("config")}}


def _seen_unseen(psnr: np.ndarray, seen: np.ndarray) -> str:
    """"seen X dB, unseen Y dB" for a log line; "no unseen lights" where the run holds none out (`lights.unseen: 0`)."""
    unseen = f"unseen {np.median(psnr[~seen]):.2f} dB" if (~seen).any() else "no unseen lights"
    return f"seen {np.median(psnr[seen]):.2f} dB, {unseen}"


def scored_on(device: torch.device | str) -> dict:
    """Where a store's or a choice's PSNRs were scored, for its record, where that is not the CPU (evaluate.device:
    run); nothing on the CPU, so that a store written before the key reads as the CPU's."""
    return {} if torch.device(device).type == "cpu" else {"scored_on": device_name(device)}


def _mix_inputs(share: str, weights_path: Path | None, volume_path: Path | None, layout,
                extinction: str | None) -> WeightStore | None:
    """The stored SIRENs a model share under 1 mixes in (None for share 1: the model alone), checked against the
    model's SIREN layout and extinction field; one ValueError naming what is missing or wrong."""
    from diffshadow.diffusion.mix import model_alone

    if model_alone(share):
        return None
    if weights_path is None or (share == "auto" and volume_path is None):
        need = "--weights (stage 1's weights.zarr)" + (" and --volume" if share == "auto" else "")
        raise ValueError(f"mix.model_share {share}: the model is mixed with the stored SIRENs' blend; give {need}, "
                         f"or model share 1 for the model alone")
    stage1 = open_store(weights_path)
    if stage1.layout.n_params != layout.n_params:
        raise ValueError(f"{weights_path}: SIRENs of {stage1.layout.n_params} parameters, but the model makes "
                         f"{layout.n_params}; rerun stage 2 on these SIRENs")
    check_extinction(stage1.extinction, extinction, cache=str(weights_path), scene="the model's",
                     remedy="rerun stage 2 on these SIRENs")
    return stage1


def _choose_share(sample, blend: BlendSampler, volume_path: Path, light_sets: dict, mix: dict,
                  score_device: torch.device | str = "cpu") -> dict:
    """`mix.model_share: auto`: the share chosen on `mix.val_lights` validation lights (exact shadows at
    `mix.val_points` box points each, marched on the CPU as eval_truth's are; the SIRENs evaluated on
    `score_device`) between the model's SIRENs and `blend`'s, with its curve."""
    from diffshadow.diffusion.mix import choose_share

    t0 = time.perf_counter()
    train = light_sets["train"]
    lights = validation_lights(train, light_sets["center"], int(mix["val_lights"]), seed=int(mix["seed"]))
    volume, tf = load_prepared(volume_path)
    # the box points alone: the set the medians are reported on (the visible set would double the march and scoring)
    val = EvalTruth.compute(volume, tf, lights, int(mix["val_points"]), int(mix["seed"]) + VALIDATION_POINTS_SEED,
                            sets=("box",)).on(score_device)
    truth = val.of(lights)
    share, curve = choose_share(sample(lights), blend.rows(lights),
                                lambda w: psnr_per_light(val.sirens(w, blend.layout, blend.siren), truth)["box"])
    print("model share on the validation lights (mean / median voxel PSNR, dB): "
          + ", ".join(f"{r['share']:g}: {r['psnr_mean']:.2f} / {r['psnr_median']:.2f}" for r in curve)
          + f"; chose {share:g} ({time.perf_counter() - t0:.1f} s)", flush=True)
    return {"model_share": share, "curve": curve,
            "validation": {"lights": len(lights), "points": int(mix["val_points"]), "seed": int(mix["seed"])}}


def _check_region(region, unseen: np.ndarray, source: Path) -> None:
    """The cache is asked for its unseen test lights: each must lie in its region (they are drawn in its cap)."""
    outside = [i for i, w in enumerate(unseen) if not region.contains(w)]
    if outside:
        raise ValueError(f"{source}: unseen light {outside[0]} ({len(outside)} in all) lies outside the cache's region "
                         f"({region.describe()}); rerun the lights rule and everything after it")
    far = (f"the unseen test lights lie up to {region.far_deg:.1f}° from the nearest training light" if len(unseen)
           else f"no unseen test lights: a light {region.far_deg:.1f}° (the spacing) past the nearest is flagged")
    print(f"light region of the cache: {region.describe()}; {far}", flush=True)


def choose_cache(weights_path: Path, truth_path: Path, volume_path: Path, lights_path: Path, out: Path, *,
                 blend_k: int, weighting: str, target_psnr: float, tolerance: float, candidates: list[str],
                 val_lights: int, val_points: int, seed: int, device: torch.device | str = "cpu") -> None:
    """`cache: auto`, right after stage 1: `cache_choice.json`, the cache that serves this scene (the smallest
    stored-SIREN cache whose blend reaches `target_psnr` on `val_lights` validation lights, exact shadows at
    `val_points` points each, within `tolerance` dB of the best candidate, else diffusion) with every candidate's
    bytes and figures; the workflow runs stage 2 only when it says diffusion."""
    from diffshadow.caches import choose_cache as choose

    stage1 = open_store(weights_path)
    light_sets = read_lights(lights_path)
    train = light_sets["train"]
    volume, tf = load_prepared(volume_path)
    lights = validation_lights(train, light_sets["center"], val_lights, seed=seed)
    # the box points alone, as the mix's choice: the medians are taken there, and the visible set doubled the march
    val = EvalTruth.compute(volume, tf, lights, val_points, seed + VALIDATION_POINTS_SEED, sets=("box",)).on(device)
    result = choose(stage1, artifacts.read_eval_truth(truth_path).on(device), val, train, blend_k=blend_k,
                    weighting=weighting, target_psnr=target_psnr, tolerance=tolerance, candidates=candidates)
    result["validation"] = {"lights": val_lights, "points": val_points, "seed": seed}
    result.update(scored_on(device))
    atomic_write_text(out, json.dumps(finite_json(result), indent=1) + "\n")
    print(f"wrote {out}: cache {result['choice']}")


def fit_correction(weights_path: Path, volume_path: Path, lights_path: Path, out: Path, *, cfg: CorrectionConfig,
                   blend_k: int, weighting: str, device: torch.device | str = "cpu",
                   spare: SpareThreads | None = None) -> None:
    """`correction.pt`: the blend's correction of stage 1's stored SIRENs (diffshadow/correction.py), fitted on
    exact-shadow lights of the training cap for blends by `weighting` (`blend_k`); resumable from `<out>.ckpt`.
    With `spare`, its march and steps take the cores other jobs leave idle (the same bytes on any threads)."""
    from diffshadow.correction import fit_correction as fit
    from diffshadow.correction import save_correction

    stage1 = open_store(weights_path)
    light_sets = read_lights(lights_path)
    train = light_sets["train"]
    volume, tf = load_prepared(volume_path)
    check_extinction(stage1.extinction, extinction_id(volume, tf), cache=str(weights_path), scene=str(volume_path),
                     remedy="rerun stage 1 on this volume")
    k = min(blend_k, len(train))
    with borrowing(spare, "fitted") as poll:
        correction = fit(stage1, volume, tf, train, light_sets["center"], cfg, k=k, weighting=weighting,
                         device=device, log=lambda m: print(m, flush=True), between_steps=poll,
                         checkpoint=out.with_name(out.name + ".ckpt"))
    save_correction(out, correction)
    print(f"wrote {out}", flush=True)


def encode_cache(weights_path: Path, truth_path: Path, lights_path: Path, out: Path, *, codec: str,
                 device: torch.device | str = "cpu") -> None:
    """A codec's cache (`cache: fp16 | bf16 | basis-<k>`): the stored SIRENs through the codec, written decoded
    (ordinary SIREN weights, which the renderer and the viewer read as any weight store) with the encoded
    store's bytes and each decoded SIREN's voxel PSNR at eval_truth's points."""
    from diffshadow.caches import encoded

    stage1 = open_store(weights_path)
    train = read_lights(lights_path)["train"]
    weights, nbytes = encoded(stage1.weights, stage1.layout, codec)
    truth = artifacts.read_eval_truth(truth_path).on(device)
    scores = psnr_per_light(truth.sirens(weights, stage1.layout, stage1.siren), truth.of(train, str(truth_path)))
    store = WeightStore(weights=weights, lights=stage1.lights, psnr=scores["box"],
                        psnr_visible=scores.get("visible", scores["box"]), layout=stage1.layout, siren=stage1.siren,
                        config={**(stage1.config or {}), "codec": codec, "encoded_bytes": nbytes,
                                "source": str(weights_path), **scored_on(device)}, region=stage1.region,
                        extinction=stage1.extinction)
    write_store(out, store, made_by="encode_cache")
    print(f"wrote {out}: {len(weights)} SIRENs through {codec}, {nbytes / 2**20:.3f} MiB encoded "
          f"(fp32 {stage1.weights.nbytes / 2**20:.3f} MiB), voxel PSNR median {np.median(store.psnr):.2f} dB")


def blend_shadows(weights_path: Path, truth_path: Path, lights_path: Path, out: Path, *, blend_k: int,
                  weighting: str, device: torch.device | str = "cpu", correction_path: Path | None = None) -> None:
    """`cache: blend`: the SIRENs of every training and unseen light without a model: a training light's own
    stored SIREN, an unseen light's weight blend of the stored ones (`lights.blend_weights` by `weighting`,
    `blend_k`: the baseline evaluate_voxels scores; with `correction_path`, corrected), with their voxel PSNR; the
    same store as `sample_shadows` writes."""
    stage1 = open_store(weights_path)
    light_sets = read_lights(lights_path)
    train, unseen = light_sets["train"], light_sets["unseen"]
    correction = _correction(correction_path, stage1, weighting)
    # what the viewer and `render --blend` make of a new direction
    blend = BlendSampler(stage1, blend_k, weighting, correction)
    weights = np.concatenate([np.asarray(stage1.weights, dtype=np.float32), blend.many(unseen)])
    all_lights = np.concatenate([train, unseen])
    seen = np.arange(len(all_lights)) < len(train)
    _check_region(blend.region, unseen, weights_path)
    codec = stage1.codec  # cache: blend reads stage 1's own fp32 store
    corrected = ", corrected" if correction is not None else ""
    print(f"blending {(~seen).sum()} unseen shadow SIRENs, each {describe_blend(weighting, blend_k)}{corrected} "
          f"({len(train)} stored, {codec})", flush=True)
    truth = artifacts.read_eval_truth(truth_path).on(device)
    scores = psnr_per_light(truth.sirens(weights, stage1.layout, stage1.siren), truth.of(all_lights, str(truth_path)))
    store = WeightStore(weights=weights, lights=all_lights, psnr=scores["box"],
                        psnr_visible=scores.get("visible", scores["box"]), layout=stage1.layout, siren=stage1.siren,
                        config={"cache": "blend", "codec": codec, "blend_weights": weighting, "blend_k": blend_k,
                                "weights": str(weights_path), **_correction_record(correction, correction_path),
                                **({"encoded_bytes": stage1.config["encoded_bytes"]} if codec != "fp32" else {}),
                                **scored_on(device)},
                        seen=seen, region=blend.region.to_dict(), extinction=stage1.extinction)
    write_store(out, store, made_by="sample_shadows")
    print(f"wrote {out}: PSNR median {_seen_unseen(store.psnr, seen)}")


def evaluate_voxels(checkpoint: Path | None, weights_path: Path, generated_path: Path, truth_path: Path,
                    volume_path: Path, lights_path: Path, out: Path, *, blend_k: int, weighting: str,
                    ddpm_lights: int,
                    geometry_checkpoint: Path | None = None, device: torch.device | str = "cpu",
                    wide_lights: int = 0, wide_points: int = 1024, wide_seed: int = 0,
                    cache_path: Path | None = None, correction_path: Path | None = None) -> None:
    """`voxel_metrics.json`: generated against stage 1 and the baselines, storage, time per INR (the samplers
    run and are timed on `device`, and the SIRENs are evaluated there); with the geometry-stage checkpoint, unseen
    lights before and after fine-tuning. Without `checkpoint` (`cache: blend` or a codec) the generated SIRENs are
    the blended ones and there is no model to time. The sampler curve resumes from `<out>.ckpt`. With
    `wide_lights`, the cache's answer, the weight blend and (with a model) the model alone on that many further test
    lights too (`evaluate.wide_comparison`); a codec's answer blends its decoded store, `cache_path`, and the answer
    of the blend or the mix is corrected by `correction_path` (fit_correction's correction.pt), as sample_shadows'
    was."""
    geometry = artifacts.load_checkpoint(geometry_checkpoint) if geometry_checkpoint else None
    state = artifacts.load_checkpoint(checkpoint) if checkpoint else None
    stage1, light_sets = open_store(weights_path), read_lights(lights_path)  # read (and verified) once for both
    cache = open_store(cache_path) if cache_path else None
    correction = _correction(correction_path, stage1, weighting)
    if cache is not None and not np.array_equal(cache.lights, stage1.lights):  # before the work, not after
        raise ValueError(f"--cache-weights {cache_path}: {len(cache.lights)} lights, not the {len(stage1.lights)} of "
                         f"--weights {weights_path} in their order (expected encode-cache's decoded copy of it)")
    truth = artifacts.read_eval_truth(truth_path).on(device)
    # read (and its checksum checked) before the sampler curve, not after: a damaged volume fails the job at once
    volume, tf = load_prepared(volume_path) if wide_lights != 0 else (None, None)
    result = voxel_metrics(state, stage1, open_store(generated_path), truth, light_sets, blend_k=blend_k,
                           weighting=weighting,
                           grid_voxels=prepared_voxels(volume_path), ddpm_lights=ddpm_lights,
                           geometry_state=geometry, device=device,
                           curve_checkpoint=out.with_name(out.name + ".ckpt"))
    if correction is not None:  # the cache keeps it beside the stored SIRENs (fp32)
        result["storage_bytes"]["correction"] = correction.nbytes
    if correction_path is not None:  # its fit's held-out check, whether it kept the correction or declined it
        from diffshadow.correction import fit_check

        if (check := fit_check(correction_path)) is not None:
            result["correction_check"] = check
    if wide_lights != 0:  # negative: wide_comparison says what it expects
        t0 = time.perf_counter()
        share = float((result.get("mix") or {}).get("model_share", 1.0))
        result["wide"] = w = wide_comparison(state, stage1, light_sets, volume, tf, share=share, lights=wide_lights,
                                             points=wide_points, seed=wide_seed, blend_k=blend_k, weighting=weighting,
                                             device=device, cache=cache, correction=correction)
        said = [f"the cache's answer {w['generated_psnr_median']:.2f} dB", f"weight blend "
                f"{w['weight_blend_psnr_median']:.2f}"]
        if "model_alone_psnr_median" in w:
            said.append(f"model alone {w['model_alone_psnr_median']:.2f}")
        lo, hi = w.get("weight_blend_gap_interval95_db") or (None, None)  # none where the answer is the blend
        gap = "" if lo is None else f"over the blend: interval {lo:+.2f} to {hi:+.2f} dB; "
        print(f"[evaluate voxels] {wide_lights} further test lights: {', '.join(said)} "
              f"({gap}{time.perf_counter() - t0:.1f} s)", flush=True)
    atomic_write_text(out, json.dumps(result, indent=1) + "\n")
    print(json.dumps(result, indent=1))
    for line in quality_warnings(result):
        print(line)


def caches(weights_path: Path, generated_path: Path, truth_path: Path, lights_path: Path, volume_path: Path,
           checkpoint: Path | None, out: Path, figure: Path, *, blend_k: int, weighting: str,
           device: torch.device | str = "cpu", correction_path: Path | None = None) -> None:
    """`caches.json` and its figure: every cache of this run as bytes against seen and unseen voxel PSNR
    (`diffshadow.caches`); the model's rows where the run trained one (`checkpoint`), its DDIM and every SIREN's
    evaluation on `device`."""
    from diffshadow.caches import cache_table
    from diffshadow.report import caches_figure

    volume, tf = load_prepared(volume_path)
    stage1 = open_store(weights_path)
    table = cache_table(stage1, artifacts.read_eval_truth(truth_path).on(device), read_lights(lights_path),
                        blend_k=blend_k, weighting=weighting, volume=volume, tf=tf,
                        model_state=artifacts.load_checkpoint(checkpoint) if checkpoint else None,
                        generated=open_store(generated_path), checkpoint=out.with_name(out.name + ".ckpt"),
                        device=device, correction=_correction(correction_path, stage1, weighting))
    atomic_write_text(out, json.dumps(finite_json(table), indent=1) + "\n")
    caches_figure(table, figure)
    for row in table["caches"]:
        unseen = f"{row['unseen_psnr']:6.2f} dB" if "unseen_psnr" in row else "     - dB"
        answer = f"{row['answer_s'] * 1e3:8.2f} ms" if "answer_s" in row else "       - ms"
        print(f"{row['cache']:28s} {row['bytes'] / 2**20:9.3f} MiB  seen {row['seen_psnr']:6.2f} dB  unseen {unseen}  "
              f"{answer}")
    print(f"wrote {out} and {figure}")


def _wider_presets(model: dict) -> list[str]:
    width = PRESETS.get(model.get("preset"), PRESETS["small"]).n_embd  # metrics written before the key: the default
    return [name for name, c in sorted(PRESETS.items(), key=lambda kv: kv[1].n_embd) if c.n_embd > width]


def quality_warnings(result: dict, *, max_gap_db: float = 1.5) -> list[str]:
    """One line per quality goal that `voxel_metrics.json` shows missed: generated seen lights more than
    `max_gap_db` under stage 1, unseen lights under the blend baseline, fine-tuning that lowered unseen lights."""
    out = []
    model = result.get("diffusion_model") or {}
    ran, wider = model.get("preset"), _wider_presets(model)
    gap = result["seen"]["generated_minus_stage1_median_db"]
    if gap < -max_gap_db:
        options = []
        if (model.get("stopped") or "").startswith("reached"):
            options.append("raise diffusion.max_epochs (this run stopped at it)")
        if wider:
            than = f" than this run's {ran}" if ran else ""
            options.append(f"set a wider diffusion.preset ({', '.join(wider)}){than}")
        advice = " or ".join(options) or f"this run's {ran} is the widest preset, and the gap stopped closing"
        out.append(f"WARNING: generated SIRENs on seen lights are {-gap:.2f} dB under stage 1 (goal: within "
                   f"{max_gap_db:g} dB); {advice}")
    unseen = result.get("unseen")
    if unseen and unseen["generated_psnr_median"] < unseen["blend_psnr_median"]:
        angle = unseen.get("nearest_angle_median_deg")
        where = f"; the test lights lie a median {angle:.1f} deg from the nearest training light" if angle else ""
        # tooth: 4.2 -> 2.1 deg raised unseen lights 3 dB, 2.1 -> 0.9 deg did not (docs/performance.md)
        closer = ("raise lights.sphere (spacing ~200/sqrt(sphere) deg; lights.count in proportion keeps the "
                  "region) or " if angle is None or angle > SPARSE_LIGHTS_DEG else "")
        bigger = f"set a wider diffusion.preset ({', '.join(wider)})" if wider else "raise diffusion.max_epochs"
        out.append(f"WARNING: generated SIRENs on unseen lights ({unseen['generated_psnr_median']:.2f} dB) are under "
                   f"the {blend_label(unseen)} true shadows ({unseen['blend_psnr_median']:.2f} dB)"
                   f"{where}: {closer}{bigger} (docs/performance.md)")
    if unseen and unseen.get("finetune_change_median_db", 0.0) < -0.1:
        out.append(f"WARNING: rendering-loss fine-tuning lowered unseen lights by "
                   f"{-unseen['finetune_change_median_db']:.2f} dB; lower finetune.lr or finetune.epochs")
    return out
