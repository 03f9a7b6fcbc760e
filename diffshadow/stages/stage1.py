"""Stage 1 (paper §3.2): light directions, the prepared volume, the shared initial SIREN, one fit per
light subset, the collected weight store.

`lights` and `collect_weights` compute nothing with torch and start without it (a CUDA build's import is seconds
on a GPU node): the modules that need torch are imported by the stages that use them.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from diffshadow.capacity import Choice, size_text
from diffshadow.layout import SirenConfig
from diffshadow.lights import (
    LightRegion,
    index_ranges,
    make_light_sets,
    read_lights,
    subset_indices,
    write_lights,
)
from diffshadow.sampling import SUBSET_HELD_OUT_SEED
from diffshadow.store import collect_subsets, write_store, write_subset
from diffshadow.volume import extinction_id, load_prepared, save_prepared, scene_volume, upsample_factor, volume_source

if TYPE_CHECKING:
    import torch

    from diffshadow.fit import FitConfig
    from diffshadow.runtime import SpareThreads


def heldout_seed(fit: FitConfig, subset: int) -> int:
    """The seed of a subset's held-out evaluation points: apart from every training stream."""
    return fit.seed + SUBSET_HELD_OUT_SEED * (subset + 1)


def lights(out: Path, *, sphere: int, count: int, center: ArrayLike, unseen: int, seed: int,
           layout: str = "rim") -> None:
    sets = make_light_sets(sphere, count, center, unseen, seed=seed, layout=layout)
    write_lights(out, sets)
    edge = f", {sets['on_edge']} of them on its edge" if layout == "rim" else ""
    print(f"wrote {out}: {count} training and {unseen} unseen directions "
          f"(region of a {sphere}-point Fibonacci sphere around {sets['center']}{edge})")


def prepare_volume(out: Path, scene: dict) -> None:
    """The scene's volume normalised to [0, 1] in its box, with its transfer function (without torch)."""
    volume, tf = scene_volume(scene)
    save_prepared(out, volume, tf, source=volume_source(scene))
    print(f"wrote {out}: {volume.name} {volume.dims}, extent {volume.extent.round(4).tolist()}")


def preoptimize(volume_path: Path, lights_path: Path, out: Path, *, siren: SirenConfig, fit: FitConfig,
                steps: int, lr: float, device: torch.device) -> None:
    """One SIREN fitted to light 0 (the initial weights of every other SIREN), and the SIREN size, fit steps and
    points a step of every subset: grown until a probe light reaches `fit.target_psnr`."""
    from diffshadow import artifacts
    from diffshadow.fit import choose_layout

    volume, tf = load_prepared(volume_path)
    train = read_lights(lights_path)["train"]
    chosen = choose_layout(volume, tf, train, siren, fit, preoptimize_steps=steps, preoptimize_lr=lr, device=device,
                           log=lambda m: print(m, flush=True))
    artifacts.save_siren_init(out, chosen)
    print(f"wrote {out}: SIREN width {chosen.siren.width}, {chosen.siren.blocks} blocks "
          f"({chosen.layout.n_params} parameters), {chosen.steps} fit steps of {chosen.points} points per subset")


def fit_subset(volume_path: Path, lights_path: Path, init_path: Path, subset: int, out: Path, *,
               siren: SirenConfig, fit: FitConfig, subset_size: int, config: dict, device: torch.device,
               spare: SpareThreads | None = None) -> None:
    """The SIRENs of one light subset, fitted jointly and checked on held-out points (resumable). Under
    `fit.rounds` it reads the files of the earlier rounds' subsets it holds (`seams.held_subsets`) beside `out`.
    With `spare`, the fit's steps take the cores other jobs leave idle (the same bytes on any threads)."""
    from diffshadow import artifacts
    from diffshadow.fit import (
        FitError,
        blend_pool,
        check_psnr,
        describe_targets,
        evaluate_psnr,
        fit_sirens,
    )
    from diffshadow.runtime import borrowing
    from diffshadow.seams import held_lights, held_subsets, subset_halo, subset_rounds

    volume, tf = load_prepared(volume_path)
    sets = read_lights(lights_path)
    train = sets["train"]
    idx = subset_indices(train, subset_size, subset)
    chosen = artifacts.load_siren_init(init_path, siren, fit.steps, fit.points)
    init, layout, siren = chosen.init, chosen.layout, chosen.siren
    # preoptimize's choice: one layout for every subset
    fit = dataclasses.replace(fit, steps=chosen.steps, points=chosen.points)
    out = Path(out)
    where = f"fit_siren subset {subset} ({volume_path}"
    halo = subset_halo(train, sets["center"], idx, fit)
    rounds = subset_rounds(train, sets["center"], subset_size, fit)
    hold = held_lights(train, sets["center"], subset_size, subset, fit, rounds)
    held = [out.parent / f"subset_{s}.npz"
            for s in held_subsets(train, sets["center"], subset_size, subset, fit, rounds)]
    held_weights = _held_weights(held, hold, subset, layout)
    held_set = set(hold)
    fitted = idx + [i for ring in halo for i in ring if i not in held_set]
    print(f"subset {subset}: fitting {len(idx)} lights jointly ({index_ranges(idx)})", flush=True)
    for r, ring in enumerate(halo, 1):
        print(f"halo ring {r}: {len(ring)} lights of other subsets fitted with them, not kept ({index_ranges(ring)})",
              flush=True)
    if hold:
        print(f"of them held at the stored SIRENs of earlier rounds' subsets (fit.rounds): {len(hold)} "
              f"({index_ranges(hold)})", flush=True)
    print(describe_targets(fit, len(fitted), volume.data.shape, device), flush=True)
    t0 = time.perf_counter()
    pool = blend_pool(volume, tf, train, sets["center"], idx, fit, halo=halo, held=hold, device=device)
    if pool is not None:
        print(f"blend loss: {len(pool.lights)} pool lights with exact shadows at {fit.blend_points} points each "
              f"({time.perf_counter() - t0:.0f} s), weight {fit.blend_weight:g}", flush=True)
    try:
        with borrowing(spare, "fitted") as poll:
            weights = fit_sirens(init, layout, siren, volume, tf, train[fitted], fit, stream=subset,
                                 light_index=fitted, checkpoint=out.with_name(out.name + ".ckpt"), pool=pool,
                                 held=held_weights, device=device, between_steps=poll)[:len(idx)]
    except FitError as e:
        raise FitError(f"{where}, lights {lights_path}): {e}") from None
    box, vis = evaluate_psnr(weights, layout, siren, volume, tf, train[idx], n_points=fit.eval_points,
                             seed=heldout_seed(fit, subset), device=device)
    if fit.min_psnr > 0:
        check_psnr(box, idx, fit.min_psnr, f"{where})")
    if (warning := below_probe_target(chosen.choice, box, subset)) is not None:
        print(warning, flush=True)
    write_subset(out, weights=weights.numpy(), light_index=idx, lights=train[idx], psnr=box, psnr_visible=vis,
                 layout=layout, siren=siren,
                 config={**config, "capacity": chosen.choice.to_dict(),
                         "grid_upsample": upsample_factor(fit.grid_upsample, volume.data.shape)},
                 extinction=extinction_id(volume, tf))
    print(f"wrote {out}: PSNR box median {float(np.median(box)):.2f} dB (min {box.min():.2f}), "
          f"visible median {float(np.median(vis)):.2f} dB")


def _held_weights(paths: list[Path], lights: list[int], subset: int, layout) -> torch.Tensor | None:
    """The stored SIRENs (H, n_params) of `lights`, from the earlier rounds' subset files `paths` (`store.read_subset`:
    checked); a light none of them has, or a file of another layout, is named."""
    import torch

    from diffshadow.store import read_subset

    if not lights:
        return None
    found: dict[int, np.ndarray] = {}
    for path in paths:
        if not path.is_file():
            raise ValueError(f"fit_siren subset {subset}: holds SIRENs of {path} (fit.rounds: a subset of an earlier "
                             f"round beside it), which is missing: fit that subset first")
        stored = read_subset(path)
        if stored["layout"] != layout:
            raise ValueError(f"{path}: SIRENs of another layout ({stored['layout'].n_params} parameters) than this "
                             f"fit's ({layout.n_params}): refit that subset first")
        found.update(zip(stored["light_index"].tolist(), stored["weights"], strict=True))
    missing = [i for i in lights if i not in found]
    if missing:
        raise ValueError(f"fit_siren subset {subset}: holds the stored SIRENs of lights {index_ranges(missing)} "
                         f"(fit.rounds), which none of {', '.join(map(str, paths)) or 'no files'} has: refit "
                         f"the subsets of earlier rounds")
    return torch.as_tensor(np.stack([found[i] for i in lights]), dtype=torch.float32)


def below_probe_target(choice: Choice, box: np.ndarray, subset: int) -> str | None:
    """One line when a subset's held-out median misses the target preoptimize's probe light met: the probe fits
    its light alone, without the blend loss that costs a light ~1 dB in a subset (docs/performance.md, stage 1)."""
    median = float(np.median(box))
    if choice.target <= 0 or not choice.met or median >= choice.target:
        return None
    c = choice.chosen
    return (f"WARNING: subset {subset}: held-out median {median:.2f} dB is below fit.target_psnr {choice.target:g} dB, "
            f"which preoptimize's probe light reached alone ({c['psnr']:.2f} dB at {size_text(c)}); "
            f"raising fit.target_psnr by the gap makes the probe choose a larger size")


def collect_weights(lights_path: Path, subset_paths: list[Path], out: Path) -> None:
    sets = read_lights(lights_path)
    train = sets["train"]
    store = collect_subsets(subset_paths, len(train), train)
    # the cache's light region travels with its SIRENs (and on, with the model trained on them)
    store.region = LightRegion.of(train, sets["unseen"], sets["center"]).to_dict()
    write_store(out, store, made_by="collect_weights")
    median = float(np.median(store.psnr))
    print(f"wrote {out}: {len(train)} SIRENs of {store.layout.n_params} parameters; voxel PSNR median "
          f"{median:.2f} dB, min {store.psnr.min():.2f} dB "
          f"(visible: median {float(np.median(store.psnr_visible)):.2f} dB)")
    if (line := median_below_target(store.config.get("capacity"), median)) is not None:
        print(line, flush=True)


def median_below_target(capacity: dict | None, median: float) -> str | None:
    """One line when the collected SIRENs' held-out median misses the target of preoptimize's size choice
    (`capacity`, `Choice.to_dict`), saying whether the probe light itself met it."""
    if not (capacity or {}).get("target_psnr"):  # a store without a size choice, or one without a target
        return None
    choice = Choice.from_dict(capacity)
    if choice.target <= 0 or median >= choice.target:
        return None
    head = f"WARNING: stage-1 SIRENs reached a median {median:.2f} dB, below fit.target_psnr = {choice.target:g} dB"
    if choice.met:
        return f"{head} that preoptimize's probe light met; raise fit.steps or siren.width, or lower fit.target_psnr"
    return (f"{head}, which preoptimize's probe light missed too ({choice.chosen['psnr']:.2f} dB at "
            f"{size_text(choice.chosen)}; its log says why); lower fit.target_psnr")
