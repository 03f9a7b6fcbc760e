"""`caches.json`: every cache a run can serve a light from, as rate (bytes) against distortion (median voxel
PSNR on seen and unseen lights) and the time to answer a new light.

A cache's answer for an unseen light is its own: the diffusion model's sample, the weight blend of the stored
SIRENs (`lights.blend_weights`, as `cache: blend` makes it) decoded from each codec, the mix of the
two that sample_shadows chose (`diffusion.mix`: model and stored SIRENs both kept), the same blend of the dense
shadow grids' values. Seen lights are the stored entries themselves. Every PSNR is at
eval_truth's fixed points against the exact shadow (`truth.EvalTruth`), as in voxel_metrics.json.
"""

from __future__ import annotations

import copy
import hashlib
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from diffshadow.codecs import BasisCodec, codec_named
from diffshadow.evaluate import blend_baseline
from diffshadow.grid import trilinear
from diffshadow.hpc import device_name
from diffshadow.io import atomic_torch_save, resume
from diffshadow.lights import blend_finder, blend_weights, describe_blend, recorded_weighting
from diffshadow.metrics import psnr
from diffshadow.shadow import shadow_grid
from diffshadow.store import blend_rows, corrected_blend
from diffshadow.truth import EvalTruth, median

if TYPE_CHECKING:
    from diffshadow.correction import BlendCorrection
    from diffshadow.layout import SirenConfig, WeightLayout
    from diffshadow.store import WeightStore
    from diffshadow.transfer import TransferFunction
    from diffshadow.volume import Volume

BASIS_K = (4, 8, 16, 32, 64, 128, 256)  # the basis codec's sizes measured (those below the light count)


def encoded(weights: np.ndarray, layout: WeightLayout, name: str) -> tuple[np.ndarray, int]:
    """The stored SIRENs as the cache `name` serves them: (decoded weights (N, P) fp32, the store's bytes)."""
    weights = np.asarray(weights, dtype=np.float32)
    if name == "blend":
        return weights, int(weights.nbytes)
    codec = codec_named(name)
    enc = codec.encode(weights, layout)
    return codec.decode(enc, layout), enc.nbytes


def validation_psnr(weights: np.ndarray, layout: WeightLayout, siren: SirenConfig, train: np.ndarray, val: EvalTruth,
                    k: int, weighting: str) -> float:
    """Median voxel PSNR (box points) at validation lights (`val`: drawn in the training cap like the unseen test
    set, but not from it) of each one's weight blend of the stored SIRENs (`weighting`, `k`): a blend cache's
    answer for lights it never stored, the figure `cache: auto` decides on."""
    idx, mix = blend_weights(train, val.lights, min(k, len(train)), weighting)
    blended = blend_rows(np.asarray(weights, dtype=np.float32), idx, mix)
    return val.median_psnr(blended.astype(np.float32), layout, siren, val.lights)


def choose_cache(stage1: WeightStore, truth: EvalTruth, val: EvalTruth, train: np.ndarray, *, blend_k: int,
                 weighting: str, target_psnr: float, candidates: list[str], tolerance: float = float("inf"),
                 log: Callable[[str], None] = print) -> dict:
    """`cache: auto`: the smallest of `candidates` (blend and codecs of the stored SIRENs) whose median voxel PSNR
    reaches `target_psnr` both on the training lights (`truth`: its decoded SIRENs, what it answers for a stored
    light) and on the validation lights `val` (its blend, what it answers for a new one), and whose worse figure
    of the two lies within `tolerance` dB of the best candidate's; `diffusion` (train the model) when none does.
    The target is a floor, the tolerance what auto may give up for bytes: a codec far under the stored SIRENs'
    quality but over the floor does not serve. Every candidate's bytes and figures are kept, so the report can say
    why.

    Validation lights, not each training light left out and blended from its neighbours: leaving one out doubles
    the gap to the nearest stored light, and on nucleon it read 7.7 dB under the unseen lights' figure at 32
    lights, where the validation lights read 1.0 dB under it (docs/performance.md, "cache: auto")."""
    rows, k = [], min(blend_k, len(train))
    for name in candidates:
        codec = None if name == "blend" else codec_named(name)
        if isinstance(codec, BasisCodec) and codec.k >= len(train):
            continue  # k directions need more lights than k
        weights, nbytes = encoded(stage1.weights, stage1.layout, name)
        row = {"cache": name, "bytes": nbytes,
               "seen_psnr": truth.median_psnr(weights, stage1.layout, stage1.siren, train),
               "val_psnr": validation_psnr(weights, stage1.layout, stage1.siren, train, val, k, weighting)}
        row["psnr"] = min(row["seen_psnr"], row["val_psnr"])  # what it promises for a stored and a new light
        rows.append(row)
        log(f"[choose cache] {name}: {nbytes / 2**20:.3f} MiB, median {row['seen_psnr']:.2f} dB on the training "
            f"lights, {row['val_psnr']:.2f} dB on the validation lights")
    top = max(rows, key=lambda r: r["psnr"], default=None)
    floor = max(target_psnr, top["psnr"] - tolerance) if top else target_psnr
    by_size = sorted(rows, key=lambda r: (r["bytes"], -r["psnr"], r["cache"]))
    passing = [r for r in by_size if r["psnr"] >= floor]
    where = f"on the training lights and on {len(val.lights)} validation lights"
    if passing:
        best = passing[0]
        within = (f" and lies within {tolerance:g} dB of the best ({top['cache']}, {top['psnr']:.2f} dB)"
                  if floor > target_psnr else "")
        given_up = [r for r in by_size[:by_size.index(best)] if r["psnr"] >= target_psnr]
        smaller = (f"; smaller and over {target_psnr:g} dB but more than {tolerance:g} dB under the best: "
                   + ", ".join(f"{r['cache']} ({r['psnr']:.2f} dB)" for r in given_up)) if given_up else ""
        why = (f"{best['cache']}: the smallest stored-SIREN cache (a new light: {describe_blend(weighting, k)}) "
               f"that reaches {target_psnr:g} dB {where}{within} ({best['seen_psnr']:.2f} and "
               f"{best['val_psnr']:.2f} dB, {best['bytes'] / 2**20:.3f} MiB){smaller}; no diffusion model trained")
        choice = best["cache"]
    else:
        why = (f"diffusion: no stored-SIREN cache reaches {target_psnr:g} dB {where}"
               + (f" (best {top['cache']}: {top['seen_psnr']:.2f} and {top['val_psnr']:.2f} dB)" if top else "")
               + "; the model is trained")
        choice = "diffusion"
    log(f"[choose cache] {why}")
    return {"choice": choice, "why": why, "target_psnr": target_psnr, "tolerance": tolerance,
            "blend_weights": weighting, "blend_k": k,
            "lights": len(train), "validation_lights": len(val.lights), "candidates": rows}


def cache_table(stage1: WeightStore, truth: EvalTruth, light_sets: dict, *, blend_k: int, weighting: str,
                volume: Volume | None = None, tf: TransferFunction | None = None, model_state: dict | None = None,
                generated: WeightStore | None = None, log: Callable[[str], None] = print,
                checkpoint: Path | None = None, device: torch.device | str = "cpu",
                correction: BlendCorrection | None = None) -> dict:
    """One row per cache: bytes, seen and unseen median voxel PSNR (box points), seconds to answer a new light.

    The model's fp16 rows sample (and time) its DDIM on `device`; the SIRENs are evaluated where `truth` says
    (`EvalTruth.on`), and every PSNR is taken on the CPU.

    Resumable: with `checkpoint`, each finished group of rows (a codec's; the model's, with its DDIM of every
    light; the grids') is saved there, and a rerun on the same inputs starts at the first group not done. At the
    paper's sizes a group is ~3 min on one thread and the model's ~25, of 52 min (docs/performance.md).

    With `correction` (correction.BlendCorrection, the run's blend's) a row for the stored SIRENs with it, and the
    mix rows' blends corrected as sample_shadows' were, its parameters counted in their bytes (fp32)."""
    train, unseen = light_sets["train"], light_sets["unseen"]
    layout, siren = stage1.layout, stage1.siren
    weights = np.asarray(stage1.weights, dtype=np.float32)
    find = blend_finder(train, blend_k, weighting)  # made once, as the viewer's BlendSampler makes it
    idx, mix = find(unseen) if len(unseen) else (None, None)

    def scored(seen_weights: np.ndarray, unseen_weights: np.ndarray | None) -> dict:
        """Median voxel PSNR at the box points, the set voxel_metrics.json's medians report."""
        out = {"seen_psnr": truth.median_psnr(seen_weights, layout, siren, train)}
        if unseen_weights is not None:
            out["unseen_psnr"] = truth.median_psnr(unseen_weights, layout, siren, unseen)
        return out

    def blend_time(decode_one) -> dict:
        """`answer_s`, the seconds to make one new light's SIREN (the nearest search, the blend, the decoding),
        timed on the unseen lights; none where there are none (`lights.unseen: 0`)."""
        if not len(unseen):
            return {}
        t0 = time.perf_counter()
        for w in unseen:
            decode_one(*find(w[None]))
        return {"answer_s": (time.perf_counter() - t0) / len(unseen)}

    def stored_rows() -> list[dict]:
        plain = blend_rows(weights, idx, mix).astype(np.float32) if len(unseen) else None
        return [{"cache": "stored SIRENs fp32", "kind": "stored", "bytes": int(weights.nbytes),
                 **scored(weights, plain), **blend_time(lambda i, m: blend_rows(weights, i, m))}]

    def codec_rows(codec) -> list[dict]:
        enc = codec.encode(weights, layout)
        decoded = codec.decode(enc, layout)
        if isinstance(codec, BasisCodec):  # a blend of SIRENs is the same blend of their coefficients
            coeff = enc.arrays["coefficients"]
            blended = codec.decode(enc, layout, blend_rows(coeff, idx, mix)) if len(unseen) else None
            answer = blend_time(lambda i, m: codec.decode(enc, layout, blend_rows(coeff, i, m)))
        else:
            blended = blend_rows(decoded, idx, mix).astype(np.float32) if len(unseen) else None
            answer = blend_time(lambda i, m: (codec.decode(enc, rows=i[0]) * m[0][:, None]).sum(0))
        return [{"cache": f"stored SIRENs {codec.name}", "kind": "codec", "bytes": enc.nbytes,
                 **scored(decoded, blended), **answer}]

    def corrected_rows() -> list[dict]:
        fixed = corrected_blend(weights, idx, mix, unseen, correction).astype(np.float32) if len(unseen) else None
        return [{"cache": "stored SIRENs fp32, corrected", "kind": "corrected",
                 "bytes": int(weights.nbytes + correction.nbytes), **scored(weights, fixed),
                 # blend_time hands its lights' corners and weights, not their directions: the first unseen
                 # light's direction stands in (the same work, a correct network input)
                 **blend_time(lambda i, m: corrected_blend(weights, i, m, unseen[:1], correction))}]

    codecs = [codec_named(n) for n in ("fp16", "bf16", *(f"basis-{k}" for k in BASIS_K if k < len(train)))]
    work: list[tuple[str, Callable[[], list[dict]]]] = [("stored SIRENs fp32", stored_rows)]
    if correction is not None:
        work.append(("stored SIRENs fp32, corrected", corrected_rows))
    work += [(f"stored SIRENs {c.name}", lambda c=c: codec_rows(c)) for c in codecs]
    if model_state is not None:
        work.append(("diffusion model", lambda: _model_rows(model_state, generated, train, unseen, scored,
                                                            stored=weights, device=device, correction=correction)))
    if volume is not None:
        work.append(("dense shadow grids", lambda: [_grid_row(volume, tf, truth, train, unseen, idx, mix)]))
    fingerprint = _fingerprint(weights, truth, light_sets, [name for name, _ in work], blend_k=blend_k,
                               weighting=weighting, model_state=model_state, generated=generated, volume=volume,
                               tf=tf, device=device, correction=correction)
    saved = resume(checkpoint, fingerprint, log=log, weights_only=True)
    groups = list(saved["groups"]) if saved else []
    if groups:
        log(f"[caches] resuming from {checkpoint} after {len(groups)} of {len(work)} groups of rows")
    for name, rows_of in work[len(groups):]:
        groups.append((name, rows_of()))
        if checkpoint is not None and len(groups) < len(work):
            atomic_torch_save(checkpoint, {"fingerprint": fingerprint, "groups": groups})
        for row in groups[-1][1]:
            log(f"[caches] {row}")
    if checkpoint is not None:
        Path(checkpoint).unlink(missing_ok=True)
    return {"blend_weights": weighting, "blend_k": blend_k, "lights": {"train": len(train), "unseen": len(unseen)},
            "siren_parameters": layout.n_params, "eval_points": int(len(truth.points["box"])),
            "caches": _mix_answers([row for _, rows in groups for row in rows])}


def _mix_answers(rows: list[dict]) -> list[dict]:
    """Each mix row's time to answer a new light, as its sampler answers (`diffusion.mix.MixedSampler`): the model's
    DDIM where the model's share is above 0 and the stored SIRENs' blend in the row's precision where it is below 1.
    At share 0 (the README run's) the answer is the blend's alone, ~0.06 ms, not the model's ~13 ms. In place."""
    blend = {row["cache"].rsplit(" ", 1)[-1]: row.get("answer_s") for row in rows if row["kind"] in ("stored", "codec")}
    # the blend's correction (a mix row that says `corrected`): its time over the plain fp32 blend's, on top
    fixed = next((row.get("answer_s") for row in rows if row["kind"] == "corrected"), None)
    extra = fixed - blend["fp32"] if fixed is not None and blend.get("fp32") is not None else 0.0
    for row in rows:
        blend_s = blend.get(row["cache"].rsplit(" ", 1)[-1])
        if row["kind"] != "mix" or "answer_s" not in row or blend_s is None:
            continue
        if row.get("corrected"):
            blend_s += extra
        row["answer_s"] = (row["answer_s"] if row["share"] > 0 else 0.0) + (blend_s if row["share"] < 1 else 0.0)
    return rows


def _fingerprint(weights: np.ndarray, truth: EvalTruth, light_sets: dict, groups: list[str], *, blend_k: int,
                 weighting: str, model_state: dict | None, generated: WeightStore | None, volume: Volume | None,
                 tf: TransferFunction | None, device: torch.device | str = "cpu", correction=None) -> str:
    """What the table's rows depend on: the stored SIRENs, the truth and its points, the lights, the blend (and its
    correction's network), the groups of rows, the sampler's weights and settings, `generated`'s figures and mix,
    the volume and TF, the threads (a product's sums split by thread: the same bytes need the same count) and the
    kinds of device that sample and evaluate (a GPU computes other bits, and times otherwise). Arrays are hashed in
    place."""
    h = hashlib.sha256(np.ascontiguousarray(weights))
    for name in sorted(truth.values):
        h.update(truth.values[name].contiguous().numpy())
        h.update(truth.points[name].contiguous().numpy())
    for name in ("train", "unseen"):
        h.update(np.ascontiguousarray(light_sets[name], dtype=np.float64))
    meta = [blend_k, weighting, groups, torch.get_num_threads(), torch.device(device).type, truth.device.type]
    if model_state is not None:
        from diffshadow.diffusion.sample import sampler_weights

        for key, tensor in sampler_weights(model_state).items():
            h.update(key.encode())
            h.update(tensor.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy())
        for key in ("mean", "std"):
            h.update(np.ascontiguousarray(np.asarray(model_state["standardizer"][key], dtype=np.float64)))
        meta.append(model_state["config"])
    if generated is not None:
        h.update(np.ascontiguousarray(generated.psnr, dtype=np.float64))
        h.update(np.ascontiguousarray(generated.seen, dtype=bool))
        meta.append(generated.config or {})
    if correction is not None:
        for tensor in correction.net.state_dict().values():
            h.update(tensor.contiguous().reshape(-1).view(torch.uint8).numpy())
    if volume is not None:
        h.update(np.ascontiguousarray(volume.data, dtype=np.float32))
        meta += [np.asarray(volume.extent, np.float64).tolist(), tf.to_config()]
    h.update(json.dumps(meta, sort_keys=True, default=str).encode())
    return h.hexdigest()


def _model_rows(state: dict, generated: WeightStore, train, unseen, scored, *, stored: np.ndarray,
                device: torch.device | str = "cpu", correction=None) -> list[dict]:
    """The diffusion model with its parameters stored in fp32 (its samples: sample_shadows' `generated` store, or,
    where that store mixed them with the stored SIRENs, their PSNRs as it scored them before the mix) and in fp16
    (rounded, then sampled in fp32 with the same DDIM steps and seed: what storing them in 16 bits costs). The time
    to answer: one DDIM sample per light, in batches as sample_shadows draws them. Where sample_shadows mixed, also
    the mix at its share: the model and the stored SIRENs, both in fp32 (`generated`'s own SIRENs), and both in
    fp16."""
    from diffshadow.diffusion.mix import mix_weights
    from diffshadow.diffusion.sample import generate, load_sampler

    model, std, layout, _ = load_sampler(state, device)
    cfg = state["config"]
    half = copy.deepcopy(model)
    with torch.no_grad():
        for p in half.parameters():
            p.copy_(p.half().float())
    lights = np.concatenate([train, unseen])
    t0 = time.perf_counter()
    with torch.no_grad():
        w16 = generate(half, std, lights, method="ddim", steps=int(cfg["ddim_steps"]), seed=int(cfg["seed"]),
                       temperature=cfg["temperature"], device=device).numpy()
    answer = (time.perf_counter() - t0) / len(lights)  # the copy back to the host waited for the device
    mixed = (generated.config or {}).get("mix")
    seen = np.asarray(generated.seen)

    def medians(per_light) -> dict:
        """The seen and unseen medians of box PSNRs per light in `generated`'s order (its own, scored at the same
        points by sample_shadows)."""
        per_light = np.asarray(per_light)
        return {"seen_psnr": median(per_light[seen]),
                **({"unseen_psnr": median(per_light[~seen])} if len(unseen) else {})}

    n_params = sum(p.numel() for p in model.parameters())
    n = len(train)
    # the model's own SIRENs: `generated`'s, or as sample_shadows scored them before it mixed them
    fp32 = medians(mixed["model_alone_psnr"] if mixed else generated.psnr)
    rows = []
    for name, psnrs, bits in (("fp32", fp32, 32), ("fp16", scored(w16[:n], w16[n:] if len(unseen) else None), 16)):
        rows.append({"cache": f"diffusion model {name}", "kind": "model", "bytes": int(n_params * bits // 8),
                     **psnrs, "answer_s": answer, "device": device_name(device)})
    if mixed:
        share, k = float(mixed["model_share"]), min(int(mixed["blend_k"]), n)
        weighting = recorded_weighting(mixed)
        fp16 = codec_named("fp16")
        enc = fp16.encode(stored, layout)
        stored16 = fp16.decode(enc, layout)
        idx, w = blend_weights(train, unseen, k, weighting)
        blended16 = corrected_blend(stored16, idx, w, unseen, correction).astype(np.float32)
        extra = 0 if correction is None else correction.nbytes
        blend16 = np.concatenate([stored16, blended16])
        w16_mix = mix_weights(w16, blend16, share)
        for name, psnrs, nbytes in (("fp32", medians(generated.psnr), 4 * n_params + stored.nbytes + extra),
                                    ("fp16", scored(w16_mix[:n], w16_mix[n:] if len(unseen) else None),
                                     2 * n_params + enc.nbytes + extra)):
            rows.append({"cache": f"model {share:g} + stored SIRENs {1 - share:g}, both {name}", "kind": "mix",
                         "share": share, **({"corrected": True} if correction is not None else {}),
                         "bytes": int(nbytes), **psnrs, "answer_s": answer, "device": device_name(device)})
    return rows


def _grid_row(volume: Volume, tf: TransferFunction, truth: EvalTruth, train, unseen, idx, mix) -> dict:
    """Dense shadow grids at the volume's resolution (fp16, as voxel_metrics' storage counts them), read
    trilinearly at the evaluation points; an unseen light's answer is the blend of its nearest lights' grids."""
    points = truth.points["box"]
    voxel = torch.as_tensor(volume.voxel_size, dtype=torch.float32)

    def values(w) -> torch.Tensor:
        g = shadow_grid(volume, tf, w)
        g.copy_(g.half())  # rounded in place: a second float32 grid was 0.5 GiB more at 512³
        return trilinear(g[None], points / voxel)[0]

    seen_vals = torch.stack([values(w) for w in train])
    row = {"cache": "dense shadow grids fp16", "kind": "grids", "bytes": int(len(train) * volume.data.size * 2),
           "seen_psnr": median(psnr(seen_vals, truth.of(train)["box"], dim=1).numpy())}
    if len(unseen):
        blended = blend_baseline({"box": seen_vals}, idx, mix)["box"]
        row["unseen_psnr"] = median(psnr(blended, truth.of(unseen)["box"], dim=1).numpy())
        # an answer reads its nearest grids and sums them into one: timed on stand-ins for as many grids, not on a
        # whole stack of len(train) (256³ at the paper's 1,024 lights: 64 GiB) whose other grids it never reads,
        # and summed in place, so the time is the reads and not the allocator's (a gathered copy per answer timed
        # 37 to 200 ms on one 256³ volume, as the process's heap stood)
        k = max(len(i) for i in idx)
        stand_ins = torch.randn(k, *volume.data.shape, generator=torch.Generator().manual_seed(0))
        answer = torch.empty(volume.data.shape)
        t0 = time.perf_counter()
        for m in mix:
            torch.mul(stand_ins[0], float(m[0]), out=answer)
            for j in range(1, len(m)):
                answer.add_(stand_ins[j], alpha=float(m[j]))
        row["answer_s"] = (time.perf_counter() - t0) / len(unseen)
    return row
