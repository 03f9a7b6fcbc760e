"""The SIREN weight store (docs/design.md §1): per-subset `.npz` files and the collected Zarr v3 store.

`results/{scene}/weights.zarr`: array `weights` (n_lights, n_params) float32, one light per chunk;
`lights` (n_lights, 3); `psnr` and `psnr_visible` (n_lights,); attrs `layout` ([name, shape] rows),
`siren` (width, blocks) and `config`. Generated SIRENs of later stages use the same layout and reader.
"""

from __future__ import annotations

import io
import json
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike

from diffshadow.io import StoreError, VerifiedGroup, atomic_save, error_line, write_zarr_group
from diffshadow.layout import SirenConfig, WeightLayout
from diffshadow.lights import LightRegion, as_direction, blend_finder, recorded_weighting
from diffshadow.phases import timed
from diffshadow.volume import check_extinction


@dataclass
class WeightStore:
    weights: np.ndarray  # (n_lights, n_params) float32
    lights: np.ndarray  # (n_lights, 3)
    psnr: np.ndarray  # (n_lights,) voxel PSNR over the box
    psnr_visible: np.ndarray  # (n_lights,) over the visible region
    layout: WeightLayout
    siren: SirenConfig
    config: dict
    seen: np.ndarray | None = None  # generated stores: True for training lights, False for unseen ones
    region: dict | None = None  # the light region of the cache (lights.LightRegion.to_dict)
    extinction: str | None = None  # the scene's extinction field the SIRENs shade (volume.extinction_id)

    @property
    def codec(self) -> str:
        """The codec its SIRENs went through (a codec's decoded cache.zarr, or a blend cache's generated store
        records it); fp32 where none did."""
        return (self.config or {}).get("codec", "fp32")

    def light_region(self) -> LightRegion:
        """The light region these SIRENs answer for: as written with the store, else (a store written before
        regions travelled with it) the cap around its training lights' mean direction."""
        return LightRegion.recorded(self.region, self.lights if self.seen is None else self.lights[self.seen])


def blend_rows(weights: np.ndarray, idx: np.ndarray, mix: np.ndarray) -> np.ndarray:
    """Weight blends (Q, P) in float64 of the stored SIRENs `weights[idx]` (Q, k) with weights `mix` (Q, k);
    only the rows blended are converted, not the store."""
    return (np.asarray(weights[idx], dtype=np.float64) * mix[..., None]).sum(1)


class Correction(Protocol):
    """What corrects a blend (`correction.BlendCorrection`, a layer above this module): the change of the blended
    weights (Q, P) of lights (Q, 3) whose blends take corners `idx` with weights `mix`."""

    def delta(self, lights: np.ndarray, idx: np.ndarray, mix: np.ndarray) -> np.ndarray: ...

    def check_weighting(self, weighting: str) -> None: ...


def corrected_blend(weights: np.ndarray, idx: np.ndarray, mix: np.ndarray, lights: np.ndarray,
                    correction: Correction | None) -> np.ndarray:
    """`blend_rows` (float64) of `lights` (Q, 3), with `correction`'s delta added where one is given."""
    rows = blend_rows(weights, idx, mix)
    return rows if correction is None else rows + correction.delta(lights, idx, mix)


class BlendSampler:
    """`cache: blend`: the shadow SIREN of any light as a weight blend of the stored SIRENs (`lights.blend_weights`
    by `weighting`, `k`), the way `blend-shadows` makes generated.zarr's unseen rows (both recorded in that store's
    config). The same interface as the diffusion model's `ShadowSampler`: call it with a direction."""

    def __init__(self, store: WeightStore, k: int, weighting: str, correction: Correction | None = None):
        if weighting == "inverse-angle" and not 1 <= k <= len(store.lights):  # a triangle's corners take no k
            raise ValueError(f"blend k: expected 1 to {len(store.lights)} (the stored SIRENs), got {k}")
        self.store, self.k, self.weighting = store, k, weighting
        self.layout, self.siren = store.layout, store.siren
        self.region, self.extinction = store.light_region(), store.extinction
        self._find = blend_finder(np.asarray(store.lights, dtype=np.float64), k, weighting)
        self.correction = correction  # correction.BlendCorrection, or None: the plain blend
        if correction is not None:
            correction.check_weighting(weighting)

    @classmethod
    def recorded(cls, store: WeightStore, record: dict, correction: Correction | None = None) -> BlendSampler:
        """The blend that a generated store's `record` names (`blend_record`) over `store`'s SIRENs (an old
        record's weighting: `recorded_weighting`)."""
        return cls(store, int(record["blend_k"]), recorded_weighting(record), correction)

    def rows(self, lights: np.ndarray) -> np.ndarray:
        """The blended SIRENs (Q, P) in float64 of `lights` (Q, 3), corrected where a correction is given."""
        lights = np.asarray(lights, dtype=np.float64)
        return corrected_blend(self.store.weights, *self._find(lights), lights, self.correction)

    def many(self, lights: np.ndarray) -> np.ndarray:
        """The blended SIRENs (Q, P) float32 of `lights` (Q, 3)."""
        return self.rows(lights).astype(np.float32)

    def __call__(self, light: ArrayLike) -> np.ndarray:
        return self.many(as_direction(light)[None])[0]


def blend_record(generated: WeightStore) -> dict | None:
    """The record of the weight blend a generated store answers with: its `mix` (sample_shadows mixed the model's
    SIRENs with the blend) or its own config (a blend cache, `blend-shadows`); None where it has none (the model
    alone, or a store written before the record)."""
    config = generated.config or {}
    record = config.get("mix") or config
    return record if "blend_k" in record else None


def write_subset(path: str | Path, *, weights: ArrayLike, light_index: ArrayLike, lights: ArrayLike, psnr: ArrayLike,
                 psnr_visible: ArrayLike, layout: WeightLayout,
                 siren: SirenConfig, config: dict, extinction: str) -> None:
    """One `fit_siren` job's result, written atomically; `extinction`: the scene's `volume.extinction_id`."""
    meta = json.dumps({"layout": layout.to_config(), "siren": siren.to_config(), "config": config,
                       "extinction": extinction})

    arrays = {"weights": np.asarray(weights, np.float32), "light_index": np.asarray(light_index, np.int64),
              "lights": np.asarray(lights, np.float64), "psnr": np.asarray(psnr, np.float64),
              "psnr_visible": np.asarray(psnr_visible, np.float64), "meta": np.array(meta)}
    atomic_save(path, lambda tmp: write_npz(tmp, arrays), suffix=".npz")


def write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """An .npz that `np.load` reads, its bytes those of the arrays alone: each member stored whole with a fixed date
    and no zip64 field. `np.savez` streams its members with zip64 headers that CPython's zipfile writes differently
    from one patch release to the next (3.11.2 and 3.11.7: the same arrays, other file bytes)."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as z:
        for name, array in arrays.items():
            member = io.BytesIO()
            np.lib.format.write_array(member, array, allow_pickle=False)
            z.writestr(zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0)), member.getvalue())


@timed("io")
def read_subset(path: str | Path) -> dict:
    """One `fit_siren` job's subset file, its arrays' shapes checked against each other and its SIREN layout, and
    its weights finite: a file of another version or edited by hand is named here, not met in a broadcast error
    or a NaN downstream."""
    path = Path(path)
    again = "rerun the fit_siren job that writes it"
    try:
        with np.load(path, allow_pickle=False) as z:
            out = {k: z[k] for k in ("weights", "light_index", "lights", "psnr", "psnr_visible")}
            meta = json.loads(str(z["meta"]))
        out["layout"] = WeightLayout.from_config(meta["layout"])
        out["siren"] = SirenConfig.from_config(meta["siren"])
        out["config"] = meta["config"]
    except Exception as e:  # a truncated copy is zipfile's BadZipFile or an EOFError, neither OSError nor ValueError
        raise StoreError(f"{path}: not a readable subset file ({error_line(e)}); {again}") from None
    out["extinction"] = meta.get("extinction")
    if out["light_index"].ndim != 1:
        raise StoreError(f"{path}: light_index has shape {out['light_index'].shape}, expected one index a light; "
                         f"{again}")
    n = len(out["light_index"])
    expected = {"weights": (n, out["layout"].n_params), "lights": (n, 3), "psnr": (n,), "psnr_visible": (n,)}
    for key, shape in expected.items():
        if out[key].shape != shape:
            raise StoreError(f"{path}: {key} has shape {out[key].shape}, expected {shape} (its {n} light indices; "
                             f"its SIREN layout's {out['layout'].n_params} parameters); {again}")
    bad = ~np.isfinite(out["weights"]).all(axis=1)
    if bad.any():
        raise StoreError(f"{path}: the weights of light(s) {out['light_index'][bad][:10].tolist()} are not finite; "
                         f"{again}")
    return out


def write_store(path: str | Path, store: WeightStore, *, made_by: str) -> None:
    """Write a weight store (Zarr v3) atomically; `made_by`: the step that writes it (named if it is damaged)."""

    def fill(root) -> None:
        n, p = store.weights.shape
        root.create_array("weights", data=np.asarray(store.weights, np.float32), chunks=(1, p))
        root.create_array("lights", data=np.asarray(store.lights, np.float64))
        root.create_array("psnr", data=np.asarray(store.psnr, np.float64))
        root.create_array("psnr_visible", data=np.asarray(store.psnr_visible, np.float64))
        if store.seen is not None:
            root.create_array("seen", data=np.asarray(store.seen, bool))
        root.attrs.update({"layout": store.layout.to_config(), "siren": store.siren.to_config(),
                           "config": store.config, "n_lights": n, "n_params": p})
        if store.region is not None:
            root.attrs["region"] = store.region
        if store.extinction is not None:
            root.attrs["extinction"] = store.extinction

    write_zarr_group(path, fill, made_by=made_by)


def open_store(path: str | Path) -> WeightStore:
    """Read a weight store (stage 1's `weights.zarr` or a generated one), its arrays checked against their
    checksums."""
    group = VerifiedGroup(path, "a weight store")
    try:
        attrs = group.attrs
        return WeightStore(
            weights=group.read("weights"),
            lights=group.read("lights"),
            psnr=group.read("psnr"),
            psnr_visible=group.read("psnr_visible"),
            layout=WeightLayout.from_config(attrs["layout"]),
            siren=SirenConfig.from_config(attrs["siren"]),
            config=attrs.get("config", {}),
            seen=group.read("seen") if "seen" in group else None,
            region=attrs.get("region"),
            extinction=attrs.get("extinction"),
        )
    except KeyError as e:
        raise StoreError(f"{path}: not a weight store (missing {e})") from None


def collect_subsets(subset_paths: list, n_lights: int, lights: np.ndarray) -> WeightStore:
    """Merge subset files; every light must appear exactly once and every layout must agree."""
    parts = [(Path(p), read_subset(p)) for p in subset_paths]
    if not parts:
        raise StoreError("collect_weights: no subset files given")
    layout, siren = parts[0][1]["layout"], parts[0][1]["siren"]
    weights = np.full((n_lights, layout.n_params), np.nan, np.float32)
    psnr = np.full(n_lights, np.nan)
    psnr_vis = np.full(n_lights, np.nan)
    owner: dict[int, Path] = {}
    for path, part in parts:
        if part["layout"] != layout:
            raise StoreError(f"{path}: its SIREN layout differs from {parts[0][0]}'s")
        check_extinction(part["extinction"], parts[0][1]["extinction"], cache=str(path), scene=str(parts[0][0]),
                         remedy="rerun fit_siren for every subset of this scene", error=StoreError)
        for row, idx in enumerate(part["light_index"].tolist()):
            if not 0 <= idx < n_lights:
                raise StoreError(f"{path}: light index {idx} outside 0..{n_lights - 1}")
            if idx in owner:
                raise StoreError(f"{path}: light {idx} is also in {owner[idx]}")
            if not np.allclose(part["lights"][row], lights[idx], atol=1e-9):
                raise StoreError(f"{path}: light {idx} has direction {part['lights'][row].tolist()}, "
                                 f"lights.json says {lights[idx].tolist()}")
            owner[idx] = path
            weights[idx] = part["weights"][row]
            psnr[idx] = part["psnr"][row]
            psnr_vis[idx] = part["psnr_visible"][row]
    missing = sorted(set(range(n_lights)) - set(owner))
    if missing:
        raise StoreError(f"collect_weights: lights {missing[:10]}{'...' if len(missing) > 10 else ''} are in "
                         f"no subset file; given: {[str(p) for p, _ in parts]}")
    return WeightStore(weights=weights, lights=np.asarray(lights), psnr=psnr, psnr_visible=psnr_vis,
                       layout=layout, siren=siren, config=parts[0][1]["config"], extinction=parts[0][1]["extinction"])
