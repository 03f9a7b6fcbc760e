"""Every file the stages pass to each other, in one place (docs/design.md §1), each written atomically:

| file | written by | here |
|---|---|---|
| `volume.zarr` | prepare_volume | `volume.save_prepared` / `load_prepared`: grid, box, TF (without torch) |
| `siren_init.pt` | preoptimize | `save_siren_init` / `load_siren_init`: the shared initial SIREN |
| `sirens/subset_N.npz`, `weights.zarr`, `generated.zarr` | fit_siren, collect_weights, sample_shadows | `store` |
| `geometry_points.zarr` | presample | `write_geometry_points` / `read_training_data` |
| `eval_truth.zarr` | eval_truth | `write_eval_truth` / `read_eval_truth`: evaluation points, exact shadows |
| `diffusion_geometry.ckpt`, `diffusion.ckpt` | train_diffusion, finetune_render | `load_checkpoint` |
| `targets.zarr` | render_targets | `write_targets` / `read_targets` |
| `data_inr.pt` | train_data_inr | `save_data_inr` / `load_data_inr`; with a volume: `data_inr_of` |
| `naive_images.zarr` | naive_images | `write_naive_images` / `read_naive_images`: the naive baseline's images |
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import torch
from numpy.typing import ArrayLike

from diffshadow.capacity import Choice
from diffshadow.config import read_scene_file
from diffshadow.data_inr import DataInr
from diffshadow.diffusion.train import TrainingData
from diffshadow.fit import Stage1Layout
from diffshadow.io import VerifiedGroup, atomic_torch_save, did_you_mean, error_line, write_zarr_group
from diffshadow.lights import BLEND_K, POOL_X0_WEIGHTING, PoolLights, blend_weights
from diffshadow.phases import timed
from diffshadow.render import Camera, Image, Networks, RenderScene
from diffshadow.render.bundle import RayBundle, foreground
from diffshadow.siren import Siren, SirenConfig, WeightLayout
from diffshadow.store import WeightStore, open_store
from diffshadow.transfer import TransferFunction
from diffshadow.truth import EvalTruth
from diffshadow.volume import Volume, is_prepared, load_prepared, load_volume, require_visible, scene_volume


class ArtifactError(ValueError):
    """A stage's input file that is missing or is not what that stage writes; the message names it."""


@timed("io")
def _torch_file(path: str | Path, what: str, *, weights_only: bool) -> object:
    """torch.load of `path`, or an ArtifactError naming it and `what` it should be: torch raises many kinds for
    a folder, a truncated or foreign file (a miniz RuntimeError, EOFError, UnpicklingError, IsADirectoryError)."""
    if not Path(path).exists():
        raise ArtifactError(f"{path}: no such file; expected {what}{did_you_mean(path)}")
    if Path(path).is_dir():
        raise ArtifactError(f"{path}: a folder; expected {what}")
    try:
        # mapped, not read: a job reads only the tensors it uses (a sampler: the EMA weights, not the trained ones
        # or the optimizer's moments; at the paper's sizes 0.7 of 2.75 GB, docs/performance.md "The allocator").
        # Every checkpoint is replaced by a rename, never rewritten in place, so the mapping stays valid.
        return torch.load(path, map_location="cpu", weights_only=weights_only, mmap=zipfile.is_zipfile(path))
    except Exception as e:
        raise ArtifactError(f"{path}: unreadable ({error_line(e)}); expected {what}") from None


# ------------------------------------------------------------------------------------- shared initial SIREN


def save_siren_init(path: str | Path, chosen: Stage1Layout) -> None:
    atomic_torch_save(path, {"weights": chosen.init, "layout": chosen.layout.to_config(),
                             "siren": chosen.siren.to_config(), "fit_steps": chosen.steps,
                             "fit_points": chosen.points,
                             "capacity": chosen.choice.to_dict()})


def load_siren_init(path: str | Path, siren: SirenConfig, steps: int | None = None,
                    points: int | None = None) -> Stage1Layout:
    """preoptimize's init, SIREN size, fit steps and points a step; refused when made from other settings than
    `siren`, `steps` and `points` (the configured start of the ladder): the size it chose answers those settings,
    not others."""
    state = _torch_file(path, "preoptimize's siren_init.pt", weights_only=True)
    try:
        chosen = SirenConfig.from_config(state["siren"])
        capacity = state["capacity"]
        choice = Choice.from_dict(capacity)
        start = SirenConfig(int(choice.rungs[0]["width"]), chosen.blocks)
        fit_steps = int(state["fit_steps"])
        fit_points = int(state["fit_points"])
        start_points = int(choice.rungs[0]["points"])
    except (KeyError, IndexError, TypeError, ValueError) as e:
        raise ArtifactError(f"{path}: not a siren_init.pt of this version ({e!r} missing); rerun preoptimize") from None
    if start != siren:
        raise ArtifactError(f"{path}: made for siren {start.to_config()}, the config says {siren.to_config()}; "
                            f"rerun preoptimize")
    if steps is not None and int(choice.rungs[0]["steps"]) != int(steps):
        raise ArtifactError(f"{path}: made for fit.steps = {choice.rungs[0]['steps']}, the config says {steps}; "
                            f"rerun preoptimize")
    if points is not None and start_points != int(points):
        raise ArtifactError(f"{path}: made for fit.points = {start_points}, the config says {points}; "
                            f"rerun preoptimize")
    if state.get("layout") != WeightLayout.for_siren(chosen).to_config():
        raise ArtifactError(f"{path}: its weight layout does not match its SIREN size; rerun preoptimize")
    return Stage1Layout(state["weights"], chosen, fit_steps, fit_points, choice)


def write_geometry_points(path: str | Path, points: torch.Tensor, values: torch.Tensor, lights: np.ndarray,
                          extent: ArrayLike, pool: tuple[np.ndarray, torch.Tensor, torch.Tensor] | None = None,
                          check: tuple[torch.Tensor, torch.Tensor] | None = None) -> None:
    """`presample`'s points (N, M, 3) and true shadow (N, M) per training light, one light per chunk;
    `pool` (lights, points, values) for the lights trained on exact shadows only, when there are any; and
    `check` (points (C, 3), values (R, C) of the lights `geometry.check_rows` picks): held-out points that
    measure the seen-light gap."""

    def fill(root) -> None:
        root.create_array("points", data=points.numpy(), chunks=(1, *points.shape[1:]))
        root.create_array("values", data=values.numpy(), chunks=(1, values.shape[1]))
        root.create_array("lights", data=lights)
        if pool is not None and len(pool[0]):
            root.create_array("pool_lights", data=np.asarray(pool[0]))
            root.create_array("pool_points", data=pool[1].numpy(), chunks=(1, *pool[1].shape[1:]))
            root.create_array("pool_values", data=pool[2].numpy(), chunks=(1, pool[2].shape[1]))
        if check is not None:
            root.create_array("check_points", data=check[0].numpy())
            root.create_array("check_values", data=check[1].numpy(), chunks=(1, check[1].shape[1]))
        root.attrs.update({"extent": np.asarray(extent).tolist()})

    write_zarr_group(path, fill, made_by="presample")


def read_training_data(weights_path: str | Path, points_path: str | Path) -> tuple[TrainingData, WeightStore]:
    """The diffusion model's training set: the weight store with the presampled geometry points, and the
    pool lights (exact shadows, x0 the blend of their `BLEND_K` nearest training SIRENs) if presampled."""
    store = open_store(weights_path)
    try:
        geo = VerifiedGroup(points_path, "presample's geometry points")
        geo_lights = geo.read("lights")
        points, values = geo.read("points"), geo.read("values")
        extent = geo.attrs["extent"]
        pool = None
        if "pool_lights" in geo:
            pool_lights = geo.read("pool_lights")
            idx, blend = blend_weights(np.asarray(store.lights, dtype=np.float64), pool_lights, BLEND_K,
                                       POOL_X0_WEIGHTING)
            pool = PoolLights(lights=torch.as_tensor(pool_lights), points=torch.as_tensor(geo.read("pool_points")),
                              values=torch.as_tensor(geo.read("pool_values")), neighbours=torch.as_tensor(idx),
                              blend=torch.as_tensor(blend, dtype=torch.float32))
        check = None
        if "check_points" in geo:
            check = (torch.as_tensor(geo.read("check_points")), torch.as_tensor(geo.read("check_values")))
    except KeyError as e:
        raise ArtifactError(f"{points_path}: not presample's geometry points (missing {e})") from None
    if geo_lights.shape != store.lights.shape or not np.allclose(geo_lights, store.lights):
        raise ArtifactError(f"{points_path}: its lights differ from {weights_path}'s; rerun presample")
    data = TrainingData(weights=torch.as_tensor(store.weights), lights=torch.as_tensor(store.lights),
                        points=torch.as_tensor(points), values=torch.as_tensor(values),
                        extent=torch.as_tensor(extent, dtype=torch.float32), layout=store.layout, siren=store.siren,
                        pool=pool, check=check, region=store.light_region().to_dict(), extinction=store.extinction)
    return data, store


def write_eval_truth(path: str | Path, truth: EvalTruth) -> None:
    """`eval_truth`'s points per set (P, 3) and exact shadow (L, P) of every light, one light per chunk."""

    def fill(root) -> None:
        for name, pts in truth.points.items():
            root.create_array(f"points_{name}", data=pts.numpy())
            root.create_array(f"values_{name}", data=truth.values[name].numpy(),
                              chunks=(1, truth.values[name].shape[1]))
        root.create_array("lights", data=truth.lights)
        root.attrs.update({"sets": list(truth.points), "extent": truth.extent.tolist()})

    write_zarr_group(path, fill, made_by="eval_truth")


def write_naive_images(path: str | Path, images: dict[str, Image], lights: np.ndarray, cameras: list[Camera]) -> None:
    """`naive_images`' renders by tag (`evaluate.naive_tags`): colour and opacity as rendered, the seconds each
    took, and the lights and cameras of the run they were made for (evaluate_images checks them)."""

    def fill(root) -> None:
        for tag, img in images.items():
            root.create_array(f"{tag}_rgb", data=img.rgb.cpu().numpy())
            root.create_array(f"{tag}_alpha", data=img.alpha.cpu().numpy())
        root.create_array("lights", data=np.asarray(lights, dtype=np.float64))
        root.attrs.update({"tags": list(images), "seconds": {t: img.seconds for t, img in images.items()},
                           "cameras": [_camera_row(c) for c in cameras]})

    write_zarr_group(path, fill, made_by="naive_images")


def _camera_row(c: Camera) -> list[float]:
    """A camera as plain numbers (JSON attributes round-trip floats exactly)."""
    return [float(x) for x in (*c.eye, *c.target, *c.up, c.fov, c.width, c.height)]


def read_naive_images(path: str | Path, lights: np.ndarray, cameras: list[Camera]) -> dict[str, Image]:
    """The naive images of `write_naive_images`, refused in one line if they were made for other lights or
    cameras than these (a changed render config or light set: rerun naive_images)."""
    try:
        root = VerifiedGroup(path, "naive_images' renders")
        tags, seconds = list(root.attrs["tags"]), root.attrs["seconds"]
        made_for = (root.read("lights"), root.attrs["cameras"])
        images = {t: Image(rgb=torch.from_numpy(root.read(f"{t}_rgb")), alpha=torch.from_numpy(root.read(f"{t}_alpha")),
                           seconds=float(seconds[t])) for t in tags}
    except KeyError as e:
        raise ArtifactError(f"{path}: not naive_images' renders (missing {e})") from None
    if made_for[1] != [_camera_row(c) for c in cameras] or not np.array_equal(made_for[0], np.asarray(lights)):
        raise ArtifactError(f"{path}: rendered for other lights or cameras than this evaluation's; rerun "
                            f"naive_images")
    return images


def read_eval_truth(path: str | Path) -> EvalTruth:
    try:
        root = VerifiedGroup(path, "eval_truth's evaluation points")
        sets = list(root.attrs["sets"])
        points = {k: torch.from_numpy(root.read(f"points_{k}")) for k in sets}
        values = {k: torch.from_numpy(root.read(f"values_{k}")) for k in sets}
        lights, extent = root.read("lights"), root.attrs["extent"]
    except KeyError as e:
        raise ArtifactError(f"{path}: not eval_truth's evaluation points (missing {e})") from None
    return EvalTruth(points=points, lights=lights, values=values,
                     extent=torch.as_tensor(extent, dtype=torch.float32))


# -------------------------------------------------------------------------------------------- checkpoints


def load_checkpoint(path: str | Path) -> dict:
    """A diffusion checkpoint (train_diffusion's or finetune_render's), on the CPU."""
    what = "a diffusion checkpoint (train_diffusion's or finetune_render's)"
    state = _torch_file(path, what, weights_only=False)
    if not isinstance(state, dict) or not {"model", "standardizer", "layout", "config"} <= set(state):
        raise ArtifactError(f"{path}: not {what}")
    return state


# ---------------------------------------------------------------------------------------- rendering targets


def write_targets(path: str | Path, images: torch.Tensor, bundle: RayBundle, cameras: list[Camera], lights: np.ndarray,
                  *, step: float, extent: ArrayLike) -> None:
    """`render_targets`' gt images per light × view, and each view's light-independent ray samples."""

    def fill(root) -> None:
        root.create_array("images", data=images.numpy(), chunks=(1, *images.shape[1:]))
        for name in ("pix", "pts", "wc", "base", "count"):
            root.create_array(f"bundle_{name}", data=getattr(bundle, name).numpy())
        root.create_array("lights", data=np.asarray(lights))
        root.attrs.update({"step": step, "extent": np.asarray(extent).tolist(),
                           "cameras": [{"eye": c.eye, "target": c.target, "up": c.up, "fov": c.fov,
                                        "width": c.width, "height": c.height} for c in cameras]})

    write_zarr_group(path, fill, made_by="render_targets")


def read_targets(path: str | Path) -> tuple[torch.Tensor, RayBundle, np.ndarray]:
    """(targets (L, V, F, 3), bundle, lights) from `render_targets`' targets.zarr: the target images at each view's
    foreground pixels, in the bundle's row order (`bundle.foreground`), read a few lights at a time, so that the
    whole images (2.6 GiB at the paper's sizes, of which fine-tuning reads about one pixel in eight) are never
    held."""
    try:
        root = VerifiedGroup(path, "a targets store from render_targets")
        bundle = RayBundle(*(torch.as_tensor(root.read(f"bundle_{k}")) for k in ("pix", "pts", "wc", "base", "count")))

        def keep(slab: np.ndarray) -> np.ndarray:
            return foreground(torch.as_tensor(slab).reshape(slab.shape[0], slab.shape[1], -1, 3), bundle).numpy()

        targets = torch.as_tensor(root.read_rows("images", keep))
        lights = root.read("lights")
    except KeyError as e:
        raise ArtifactError(f"{path}: not a targets store from render_targets (missing {e})") from None
    return targets, bundle, lights


def save_data_inr(path: str | Path, inr: DataInr) -> None:
    state = {"weights": inr.model.flat().detach().cpu(), "layout": inr.model.layout.to_config(),
             "siren": inr.model.cfg.to_config(), "extent": np.asarray(inr.extent).tolist(), "psnr": inr.psnr,
             "max_error": inr.max_error, "config": inr.config,
             "cell_lo": torch.as_tensor(inr.cell_lo), "cell_hi": torch.as_tensor(inr.cell_hi), "volume": inr.volume}
    atomic_torch_save(path, state)


def load_data_inr(path: str | Path) -> DataInr:
    path, what = Path(path), "a data INR file (train_data_inr's data_inr.pt)"
    state = _torch_file(path, what, weights_only=True)
    try:
        layout = WeightLayout.from_config(state["layout"])
        model = Siren.from_flat(state["weights"], layout, SirenConfig.from_config(state["siren"]))
        return DataInr(model, np.asarray(state["extent"]), float(state["psnr"]), float(state["max_error"]),
                       dict(state["config"]), state["cell_lo"].numpy(), state["cell_hi"].numpy(), state.get("volume"))
    except KeyError as e:
        raise ArtifactError(f"{path}: not {what}: no key {e}") from None
    except (AttributeError, RuntimeError, TypeError, ValueError) as e:
        raise ArtifactError(f"{path}: not {what}: {e}") from None


# ------------------------------------------------------------------------------------------ render scene


def data_inr_of(path: Path, volume: Volume, source: str) -> DataInr:
    """The data INR in `path`, refused in one line where it was fitted to another box or grid than `volume`'s
    (`source` names the volume): it would draw another scene's scalar field."""
    inr = load_data_inr(path)
    if not np.allclose(inr.extent, volume.extent):
        raise ValueError(f"{path}: fitted to a box of {inr.extent.tolist()}, the volume's is {volume.extent.tolist()}")
    if inr.volume is not None and inr.volume != volume.checksum:  # None: a file from before the checksum was kept
        raise ValueError(f"{path}: fitted to another volume than {source} (its grid's checksum differs); give the "
                         f"data INR of this volume's run (train_data_inr)")
    return inr


def load_scene_file(scene_file: Path, device: torch.device, render: dict | None = None) -> RenderScene:
    """A RenderScene straight from a scene file: what prepare_volume would make of it, for previews and
    benchmarks. Its networks: `render` over the file's `render` section over the defaults'."""
    own = read_scene_file(scene_file)
    networks = Networks.from_config({**own.get("render", {}), **(render or {})})
    return RenderScene(*scene_volume(own), device=device, networks=networks)


def load_render_scene(volume_path: Path, data_inr: Path | None, device: torch.device,
                      tf_config: dict | None = None, render: dict | None = None) -> RenderScene:
    """A RenderScene from a prepared volume.zarr (under its own transfer function, or `tf_config`), or from a raw
    volume file with its transfer function."""
    if not Path(volume_path).exists():  # not "needs a transfer function": a mistyped path is the likelier mistake
        raise ValueError(f"{volume_path}: no such file; expected a prepared volume.zarr (results/<scene>/) or "
                         f"a raw volume with --tf-json{did_you_mean(volume_path)}")
    if is_prepared(volume_path):
        # the prepared grid and box as they are: read as a raw volume, a grid normalised from a value_range or a box
        # from a spacing were normalised again and lost its spacing
        volume, tf = load_prepared(volume_path)
        tf = tf if tf_config is None else TransferFunction.from_config(tf_config)
    else:
        if tf_config is None:
            raise ValueError(f"{volume_path}: not a prepared volume.zarr, so it needs a transfer function "
                             f"(--tf-json '{{\"opacity\": [[s, a], ...], \"color\": [[s, r, g, b], ...], "
                             f"\"density_scale\": K}}')")
        volume = load_volume(volume_path)
        tf = TransferFunction.from_config(tf_config)
    if tf_config is not None:  # a TF given here was checked nowhere: an image of nothing is refused as a scene is
        require_visible(volume, tf, str(volume_path))
    inr = data_inr_of(data_inr, volume, str(volume_path)) if data_inr else None
    networks = Networks.from_config(render or {})
    return RenderScene(volume, tf, inr, device=device, networks=networks)
