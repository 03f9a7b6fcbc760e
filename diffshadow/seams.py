"""The seams between stage 1's light subsets: which other subsets' lights a subset fits beside its own (its halo),
and in which round each subset is fitted (`fit.halo`, `fit.rounds`; docs/design.md, "Stage 1"). Free of PyTorch:
the workflow asks it for each fit job's inputs while it parses."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import ArrayLike

from diffshadow.lights import BLEND_K, blend_weights, configured_light_sets, light_subsets, n_subsets, training_pool
from diffshadow.sampling import FIT_BLEND_POOL_SEED


@dataclass(frozen=True)
class SeamSettings:
    """The `fit` settings the seams depend on (a `fit.FitConfig` has them too, and serves as well)."""

    halo: int
    rounds: bool
    blend_weight: float
    blend_per_light: int
    blend_weights: str
    seed: int

    @classmethod
    def of(cls, fit: dict) -> SeamSettings:
        """From a scene's merged `fit` section (`config.scene_config`: every key present)."""
        return cls(**{f.name: fit[f.name] for f in fields(cls)})


_POOL_BLENDS: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}


def pool_blends(train: np.ndarray, center: ArrayLike, k: int,
                cfg: SeamSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every subset's candidate pool lights (`cfg.blend_per_light` per training light in their cap, the same for
    every subset), the training lights each one's blend takes and their weights. Kept for the process's next call
    with the same arguments (the halo's and the pool's, and the fit bench's halo of every subset)."""
    key = hashlib.sha256(np.ascontiguousarray(train, dtype=np.float64).tobytes() + json.dumps(
        [np.asarray(center, np.float64).tolist(), min(BLEND_K, k), cfg.blend_per_light, cfg.seed,
         cfg.blend_weights]).encode()).hexdigest()
    if key not in _POOL_BLENDS:
        lights = training_pool(train, center, cfg.blend_per_light * len(train), seed=cfg.seed + FIT_BLEND_POOL_SEED)
        _POOL_BLENDS.clear()
        _POOL_BLENDS[key] = (lights, *blend_weights(train, lights, min(BLEND_K, k), cfg.blend_weights))
    return _POOL_BLENDS[key]


def halo_size(train: np.ndarray, center: ArrayLike, subset_size: int, cfg: SeamSettings) -> tuple[float, float]:
    """The mean counts of halo lights (`subset_halo`, all rings) a subset of these lights fits beside its own, and
    of those it holds at their stored SIRENs instead (`held_lights`, `fit.rounds`)."""
    subsets = light_subsets(train, subset_size)
    rounds = subset_rounds(train, center, subset_size, cfg)
    halo = [sum(map(len, subset_halo(train, center, s, cfg))) for s in subsets]
    held = [len(held_lights(train, center, subset_size, i, cfg, rounds)) for i in range(len(subsets))]
    return float(np.mean(halo) - np.mean(held)), float(np.mean(held))


def subset_halo(train: np.ndarray, center: ArrayLike, subset: list[int], cfg: SeamSettings) -> list[list[int]]:
    """The rings (`fit.halo` of them) of other subsets' lights that the blends across this subset's border take,
    each sorted: ring 1 those of the blends that take a light of the subset, ring 2 those of the blends that take
    one of ring 1, and so on. Fitted with the subset and discarded (those of earlier rounds held instead,
    `held_lights`), so that the pool lights on its seams are in its blend loss; [] when the halo or the blend loss
    is off or the subset is every light."""
    train = np.asarray(train, dtype=np.float64)
    if not cfg.halo or cfg.blend_weight <= 0 or len(subset) < 2 or len(subset) == len(train):
        return []
    _, idx, _ = pool_blends(train, center, len(subset), cfg)
    inner, rings = set(subset), []
    for _ in range(cfg.halo):
        touching = np.isin(idx, sorted(inner)).any(axis=1)
        rings.append(sorted(set(np.unique(idx[touching]).tolist()) - inner))
        inner |= set(rings[-1])
    return rings


def subset_rounds(train: np.ndarray, center: ArrayLike, subset_size: int, cfg: SeamSettings) -> list[int]:
    """Each subset's round (`fit.rounds`; all 0 without it, or without a halo): the subsets whose lights are in
    one another's halo get different rounds, each subset in index order the first round none of them has."""
    subsets = light_subsets(train, subset_size)
    if not cfg.rounds or not cfg.halo or cfg.blend_weight <= 0 or len(subsets) < 2:
        return [0] * len(subsets)
    owner = np.empty(len(train), dtype=np.int64)
    for s, idx in enumerate(subsets):
        owner[idx] = s
    meets: list[set[int]] = [set() for _ in subsets]
    for s, idx in enumerate(subsets):
        for ring in subset_halo(train, center, idx, cfg):
            for other in set(owner[ring].tolist()):
                meets[s].add(other)
                meets[other].add(s)
    rounds: list[int] = []
    for s in range(len(subsets)):
        taken = {rounds[o] for o in meets[s] if o < s}
        rounds.append(next(r for r in range(len(subsets)) if r not in taken))
    return rounds


def held_subsets(train: np.ndarray, center: ArrayLike, subset_size: int, subset: int, cfg: SeamSettings,
                 rounds: list[int] | None = None) -> list[int]:
    """The subsets of earlier rounds (`subset_rounds`, or `rounds` made by it) with lights in this subset's halo:
    the fit's inputs, their stored SIRENs held where their lights are in its halo (`held_lights`)."""
    rounds = subset_rounds(train, center, subset_size, cfg) if rounds is None else rounds
    subsets = light_subsets(train, subset_size)
    halo = {i for ring in subset_halo(train, center, subsets[subset], cfg) for i in ring}
    return [s for s, idx in enumerate(subsets) if rounds[s] < rounds[subset] and halo.intersection(idx)]


def held_lights(train: np.ndarray, center: ArrayLike, subset_size: int, subset: int, cfg: SeamSettings,
                rounds: list[int] | None = None) -> list[int]:
    """This subset's halo lights that belong to `held_subsets` (`rounds` as there), sorted: held at their stored
    SIRENs."""
    subsets = light_subsets(train, subset_size)
    held = {i for s in held_subsets(train, center, subset_size, subset, cfg, rounds) for i in subsets[s]}
    return sorted(held.intersection(i for ring in subset_halo(train, center, subsets[subset], cfg) for i in ring))


def subset_inputs(cfg: dict) -> tuple[list[int], list[list[int]]]:
    """For a scene's config, each subset's round (`subset_rounds`) and the subsets whose files its fit reads
    (`held_subsets`: earlier rounds' neighbours; none without `fit.rounds`), its lights made as `lights` makes
    them: the workflow's job groups and inputs, Parsl's waves, the paper plan's rounds."""
    size = int(cfg["subset_size"])
    fit = SeamSettings.of(cfg["fit"])
    n = n_subsets(int(cfg["lights"]["count"]), size)
    if not fit.rounds or n < 2:
        return [0] * n, [[] for _ in range(n)]
    sets = configured_light_sets(cfg["lights"])
    train = np.asarray(sets["train"]["cartesian"], dtype=np.float64)
    rounds = subset_rounds(train, sets["center"], size, fit)
    return rounds, [held_subsets(train, sets["center"], size, s, fit, rounds) for s in range(n)]
