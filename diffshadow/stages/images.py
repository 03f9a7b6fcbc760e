"""The renderer's stages (paper §4.4 and appendix): the data INR, rendering-loss targets, image evaluation
against `gt`, single renders, the renderer benchmark, and the report's figures."""

from __future__ import annotations

import json
import math
from pathlib import Path

import torch
from numpy.typing import ArrayLike

from diffshadow import artifacts
from diffshadow.data_inr import DataInrConfig, fit_data_inr
from diffshadow.diffusion.finetune import FinetuneConfig
from diffshadow.evaluate import REFERENCES, image_evaluation
from diffshadow.evaluate import naive_images as render_naive
from diffshadow.io import atomic_write_text, finite_json, require_png
from diffshadow.lights import as_direction, read_lights
from diffshadow.metrics import lpips_model, ms_ssim_status
from diffshadow.progress import Ticker
from diffshadow.render import Camera, RenderScene, default_views, fibonacci_views, write_png
from diffshadow.render.bundle import build_bundle
from diffshadow.render.bundle import render_targets as targets
from diffshadow.render.scene import KEEP_SAMPLES_BYTES
from diffshadow.report import shading_name
from diffshadow.store import BlendSampler, open_store
from diffshadow.volume import check_extinction, load_prepared, upsample_factor


def train_data_inr(volume_path: Path, out: Path, *, cfg: DataInrConfig, device: torch.device) -> None:
    """The SIREN of the scalar field the renderer queries; resumable from `<out>.ckpt`."""
    volume, tf = load_prepared(volume_path)
    inr = fit_data_inr(volume, tf, cfg, checkpoint=out.with_name(out.name + ".ckpt"), device=device)
    artifacts.save_data_inr(out, inr)
    print(f"wrote {out}: {inr.n_params} parameters, voxel PSNR {inr.psnr:.2f} dB, max error {inr.max_error:.4f}")


def render_targets(volume_path: Path, lights_path: Path, out: Path, *, cfg: FinetuneConfig, upsample: int | str,
                   device: torch.device) -> None:
    """`gt` images per training light × Fibonacci view, and each view's ray samples; a sweep's grid on the
    volume refined as stage 1's targets are (`upsample`: fit.grid_upsample). Resumable from `<out>.ckpt`."""
    volume, tf = load_prepared(volume_path)
    upsample = upsample_factor(upsample, volume.data.shape)
    train = read_lights(lights_path)["train"]
    cams = fibonacci_views(volume.extent, cfg.views, size=cfg.image_size, fov=cfg.fov)
    bundle = build_bundle(volume, tf, cams, step=cfg.step)  # one pass per view: CPU
    print(f"{cfg.views} views of {cfg.image_size}²: {bundle.count.tolist()} foreground pixels, up to "
          f"{bundle.pts.shape[2]} samples each", flush=True)
    images = targets(volume, tf, train, cams, step=cfg.step, method=cfg.targets,
                     upsample=upsample if cfg.targets == "sweep" else 1, device=device,
                     checkpoint=out.with_name(out.name + ".ckpt"))
    artifacts.write_targets(out, images, bundle, cams, train, step=cfg.step, extent=volume.extent)
    print(f"wrote {out}: {len(train)} lights x {cfg.views} views")


def render_image(scene: RenderScene, out: Path, *, mode: str, camera: Camera, light: ArrayLike | None = None,
                 weights_path: Path | None = None, light_index: int = 0, diffusion: Path | None = None,
                 blend: Path | None = None, blend_k: int, weighting: str = "triangle",
                 model_share: float | None = None, scalar: str | None = None,
                 phong: bool = False, step: float, skip: bool = True, outside_region: bool = False,
                 correction: Path | None = None) -> None:
    """One image (a PNG, `out` named .png) in a shading mode; the shadow INR of mode `inr` is row `light_index` of a
    store, or made for `light` by the diffusion checkpoint `diffusion` or (`cache: blend`) as the weight blend of the
    SIRENs of the store `blend` (`weighting`, `blend_k`: the run's, in generated.zarr's config), or by both mixed,
    `model_share` of the model's (diffusion/mix.py). A light outside the cache's region (`lights.LightRegion`) is
    refused in one line naming the region and the light's angle to it, unless `outside_region` asks for the cache's
    answer anyway (then the line is a warning); one inside it but farther from the training lights than any unseen test
    light was gets a one-line note. A cache made for another volume or opacity than `scene`'s is refused in one line
    (`volume.extinction_id`)."""
    require_png(out, "--out")
    if light is not None:  # checked here, to be named as the flag it came from (the value is used as given)
        as_direction(light, name="--light")
    siren = None
    mixed = model_share is not None
    if mixed and (diffusion is None or blend is None):
        raise ValueError("render: --model-share mixes the model's SIREN with the stored SIRENs' blend; give "
                         "--diffusion and --blend with it")
    if sum(x is not None for x in (weights_path, diffusion, blend)) > 1 and not (mixed and weights_path is None):
        raise ValueError("render: --weights, --diffusion and --blend each give the shadow INR; give one (or "
                         "--diffusion and --blend with --model-share: the two mixed)")
    if diffusion or blend:
        if light is None:
            raise ValueError(f"--{'diffusion' if diffusion else 'blend'}: needs --light, the direction to make the "
                             "shadow SIREN for")
        from diffshadow.diffusion.mix import MixedSampler
        from diffshadow.diffusion.sample import ShadowSampler

        model = ShadowSampler(artifacts.load_checkpoint(diffusion), scene.device) if diffusion else None
        if correction is not None and blend is None:
            raise ValueError("render: --correction corrects the stored SIRENs' blend; give --blend with it")
        if blend:
            from diffshadow.correction import load_correction

            store = open_store(blend)
            fix = load_correction(correction, store.lights, store.weights) if correction else None
            stored = BlendSampler(store, blend_k, weighting, fix)
        else:
            stored = None
        sampler = MixedSampler(model, stored, model_share) if mixed else model or stored
        _same_scene(scene, sampler.extinction, f"--{'diffusion' if diffusion else 'blend'} {diffusion or blend}")
        check = sampler.region.where(light)
        if not check.inside and not outside_region:
            raise ValueError(f"{check.message()} (--mode gt draws the exact shadow; --outside-region draws the "
                             f"cache's answer anyway)")
        if not check.inside or check.far:
            print(f"warning: {check.message()}", flush=True)
        siren = (sampler(light), sampler.layout, sampler.siren.blocks)
    if weights_path:
        store = open_store(weights_path)
        if not 0 <= light_index < len(store.weights):
            raise ValueError(f"--light-index: {weights_path} holds lights 0..{len(store.weights) - 1}, "
                             f"got {light_index}")
        _same_scene(scene, store.extinction, f"--weights {weights_path}")
        siren = (store.weights[light_index], store.layout, store.siren.blocks)
        # the row's SIREN is its own light's shadow, whatever --light says: the image would be labelled wrongly
        if mode == "inr" and light is not None and float(
                as_direction(light) @ (own := as_direction(store.lights[light_index]))) < math.cos(1e-6):
            raise ValueError(f"--light {as_direction(light).round(4).tolist()} is not light {light_index} of "
                             f"{weights_path} ({own.round(4).tolist()}), whose shadow SIREN --mode inr draws; drop "
                             f"--light, or give --diffusion or --blend to make a SIREN for that direction")
        light = light or store.lights[light_index].tolist()
    if mode == "inr" and siren is None:
        raise ValueError("--mode inr needs --weights (a weight store) and --light-index, or --diffusion or --blend "
                         "and --light")
    # a naive or gt frame of a large view can take minutes on a CPU: a line a minute meanwhile
    img = scene.render(mode, camera, light=light, siren=siren, scalar=scalar, phong=phong, step=step, skip=skip,
                       interrupt=Ticker(f"render: {mode} at {camera.width}x{camera.height}"))
    write_png(out, img)
    c = img.counters
    print(f"wrote {out}: {mode}, {camera.width}x{camera.height} in {img.seconds:.3f} s "
          f"({c.primary_samples:,} samples, {c.secondary_samples:,} on shadow rays)")


def _same_scene(scene: RenderScene, made_for: str | None, cache: str) -> None:
    """A shadow cache made for another scene shades this one wrongly, with nothing to see in the image: refused."""
    check_extinction(made_for, scene.extinction, cache=cache, scene="the volume rendered",
                     remedy="its shadows would be wrong here; give the cache of this volume's run, or --mode gt for "
                            "the exact shadow")


def _views(scene: RenderScene, cfg: dict) -> list[Camera]:
    return default_views(scene.visible_sphere(), cfg["views"], size=cfg["image_size"], fov=cfg["fov"])


def _naive_settings(cfg: dict) -> dict:
    return {"step": cfg["step"], "lights_per_set": cfg["lights_per_set"], "naive_views": cfg.get("naive_views"),
            "naive_lights": cfg.get("naive_lights"), "phong": bool(cfg.get("phong", False))}


def naive_images(volume_path: Path, lights_path: Path, data_inr: Path, out: Path, *, cfg: dict,
                 device: torch.device) -> None:
    """`naive_images.zarr`: the naive baseline's images for `evaluate_images` (the slowest of its renders, and
    they need no SIREN of stage 1 or 2, so they are made while those train)."""
    scene = artifacts.load_render_scene(volume_path, data_inr, device, render=cfg)
    light_sets, views = read_lights(lights_path), _views(scene, cfg)
    images = render_naive(scene, light_sets, views, **_naive_settings(cfg))
    artifacts.write_naive_images(out, images, light_sets["train"], views)
    print(f"wrote {out}: {len(images)} naive images")


def evaluate_images(volume_path: Path, lights_path: Path, data_inr: Path, weights_path: Path,
                    generated_path: Path | None, images_dir: Path, out: Path, *, cfg: dict,
                    device: torch.device, naive_path: Path | None = None) -> None:
    """`image_metrics.json` and the PNGs: every shading mode against `gt`; the naive images from `naive_path`
    (`naive_images`) where given, else rendered here."""
    scene = artifacts.load_render_scene(volume_path, data_inr, device, render=cfg)
    scene.keep_views(KEEP_SAMPLES_BYTES)  # a view's samples serve every light and shadow INR drawn of it
    light_sets = read_lights(lights_path)
    stage1 = open_store(weights_path)
    generated = open_store(generated_path) if generated_path else None
    views = _views(scene, cfg)
    naive = artifacts.read_naive_images(naive_path, light_sets["train"], views) if naive_path else None
    lpips, reason = lpips_model()
    result = image_evaluation(scene, light_sets, stage1, generated, views, out_dir=images_dir, lpips=lpips,
                              naive=naive, reference=cfg["reference"], **_naive_settings(cfg))
    result.update({"lpips": "available (VGG)" if lpips is not None else f"unavailable: {reason}",
                   "image_size": cfg["image_size"], "views": cfg["views"], "step": cfg["step"],
                   "shading": shading_name(bool(cfg.get("phong"))), "ms_ssim": ms_ssim_status(cfg["image_size"]),
                   "reference": REFERENCES[cfg["reference"]][1],
                   "data_inr_psnr": scene.data_inr.psnr if scene.data_inr is not None else None,
                   "data_inr": _data_inr_size(scene.data_inr), "networks": scene.networks_used()})
    atomic_write_text(out, json.dumps(finite_json(result), indent=2) + "\n")
    for name, m in sorted(result["modes"].items()):
        print(f"{name:24s} PSNR {m['psnr']:.2f} dB  SSIM {m['ssim']:.4f}  over {m['count']} images")
    print(f"wrote {out}")


def _data_inr_size(inr) -> dict | None:
    if inr is None:
        return None
    return {"width": inr.model.cfg.width, "blocks": inr.model.cfg.blocks, "parameters": inr.n_params,
            "psnr": inr.psnr, "capacity": inr.config.get("capacity")}
