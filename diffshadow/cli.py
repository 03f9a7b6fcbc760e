"""The `diffshadow` command: one subcommand per workflow rule, plus `bench` and `install-profiles`."""

from __future__ import annotations

import argparse
import filecmp
import json
import os
import sys
from pathlib import Path

import numpy as np


def _lights(args: argparse.Namespace) -> None:
    from diffshadow.lights import make_light_sets, write_lights

    lights = make_light_sets(args.sphere, args.count, args.center, args.unseen, seed=args.seed)
    write_lights(args.out, lights)
    print(f"wrote {args.out}: {args.count} training and {args.unseen} unseen directions "
          f"(region of a {args.sphere}-point Fibonacci sphere around {lights['center']})")


def _bench_shadow(args: argparse.Namespace) -> None:
    from diffshadow.bench import bench_shadow, default_volumes

    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    volumes = [Path(v) for v in args.volumes] if args.volumes else default_volumes()
    bench_shadow(volumes, Path(args.out), device=args.device)


def _json(text: str) -> dict:
    try:
        value = json.loads(text)
    except json.JSONDecodeError as e:
        raise ValueError(f"--config-json: not valid JSON ({e})") from None
    if not isinstance(value, dict):
        raise ValueError("--config-json: expected a JSON object")
    return value


def _threads(n: int) -> None:
    if n:
        import torch

        torch.set_num_threads(n)


def _prepare_volume(args: argparse.Namespace) -> None:
    from diffshadow.shadow import MACRO_CELL
    from diffshadow.transfer import TransferFunction
    from diffshadow.volume import load_volume, save_prepared

    cfg = _json(args.config_json)
    tf = TransferFunction.from_config(cfg["transfer_function"])
    volume = load_volume(cfg["volume"], **cfg.get("load", {}))
    save_prepared(args.out, volume, tf, cell=MACRO_CELL)
    print(f"wrote {args.out}: {volume.name} {volume.dims}, extent {volume.extent.round(4).tolist()}")


def _stage1_inputs(args):
    from diffshadow.fit import FitConfig
    from diffshadow.lights import read_lights
    from diffshadow.siren import SirenConfig, WeightLayout
    from diffshadow.volume import load_prepared

    cfg = _json(args.config_json)
    volume, tf = load_prepared(args.volume)
    lights = read_lights(args.lights)["train"]
    siren = SirenConfig.from_config(cfg["siren"])
    return cfg, volume, tf, lights, siren, WeightLayout.for_siren(siren), FitConfig.from_config(cfg["fit"])


def _preoptimize(args: argparse.Namespace) -> None:

    from diffshadow.fit import fit_sirens, seeded
    from diffshadow.io import atomic_torch_save
    from diffshadow.siren import init_siren

    _threads(args.threads)
    cfg, volume, tf, lights, siren, layout, fit = _stage1_inputs(args)
    pre = cfg["preoptimize"]
    fit = fit.__class__(**{**fit.__dict__, "steps": int(pre["steps"]), "lr": float(pre["lr"])})
    init = layout.flatten(init_siren(siren, seeded(fit.seed, -1)))
    if pre["steps"] > 0:
        print(f"pre-optimising one SIREN on light 0 for {fit.steps} steps", flush=True)
        init = fit_sirens(init, layout, siren, volume, tf, lights[:1], fit, stream=-1, light_index=[0],
                          device=args.device)[0]
    state = {"weights": init, "layout": layout.to_config(), "siren": siren.to_config()}
    atomic_torch_save(args.out, state)
    print(f"wrote {args.out}")


def subset_indices(n_lights: int, subset_size: int, subset: int) -> list[int]:
    """Lights of subset `subset` (0..S-1, S = ceil(n / size))."""
    n_subsets = -(-n_lights // subset_size)
    if not 0 <= subset < n_subsets:
        raise ValueError(f"subset {subset} does not exist: {n_lights} lights in subsets of {subset_size} "
                         f"give subsets 0..{n_subsets - 1}")
    return list(range(subset * subset_size, min(n_lights, (subset + 1) * subset_size)))


def _fit_siren(args: argparse.Namespace) -> None:
    import torch

    from diffshadow.fit import FitError, check_psnr, evaluate_psnr, fit_sirens
    from diffshadow.store import write_subset

    _threads(args.threads)
    cfg, volume, tf, lights, siren, layout, fit = _stage1_inputs(args)
    idx = subset_indices(len(lights), int(cfg["subset_size"]), args.subset)
    init_state = torch.load(args.init, map_location="cpu", weights_only=True)
    if init_state["layout"] != layout.to_config():
        raise ValueError(f"{args.init}: SIREN layout differs from the config's siren settings; rerun preoptimize")
    out = Path(args.out)
    print(f"subset {args.subset}: fitting lights {idx[0]}..{idx[-1]} jointly", flush=True)
    try:
        weights = fit_sirens(init_state["weights"], layout, siren, volume, tf, lights[idx], fit, stream=args.subset,
                             light_index=idx, checkpoint=out.with_name(out.name + ".ckpt"), device=args.device)
    except FitError as e:
        raise FitError(f"fit_siren subset {args.subset} ({args.volume}, lights {args.lights}): {e}") from None
    box, vis = evaluate_psnr(weights, layout, siren, volume, tf, lights[idx], n_points=fit.eval_points,
                             seed=fit.seed + 7919 * (args.subset + 1), device=args.device)
    if fit.min_psnr > 0:
        check_psnr(box, idx, fit.min_psnr, f"fit_siren subset {args.subset} ({args.volume})")
    write_subset(out, weights=weights.numpy(), light_index=idx, lights=lights[idx], psnr=box, psnr_visible=vis,
                 layout=layout, siren=siren, config=cfg)
    print(f"wrote {out}: PSNR box median {float(np.median(box)):.2f} dB (min {box.min():.2f}), "
          f"visible median {float(np.median(vis)):.2f} dB")


def _collect_weights(args: argparse.Namespace) -> None:
    from diffshadow.lights import read_lights
    from diffshadow.store import collect_subsets, write_store

    lights = read_lights(args.lights)["train"]
    store = collect_subsets(args.subsets, len(lights), lights)
    write_store(args.out, store)
    print(f"wrote {args.out}: {len(lights)} SIRENs of {store.layout.n_params} parameters; voxel PSNR median "
          f"{float(np.median(store.psnr)):.2f} dB, min {store.psnr.min():.2f} dB "
          f"(visible: median {float(np.median(store.psnr_visible)):.2f} dB)")


def _bench_siren(args: argparse.Namespace) -> None:
    from diffshadow.bench import bench_siren

    _threads(args.threads)
    bench_siren(Path(args.out), k=args.k, points=args.points, widths=args.widths, device=args.device)


def _bench_init_spread(args: argparse.Namespace) -> None:
    from diffshadow.bench import bench_init_spread

    _threads(args.threads)
    bench_init_spread(Path(args.results), Path(args.out), n_lights=args.lights)


def _check_store(args: argparse.Namespace) -> None:
    from diffshadow.bench import check_store

    _threads(args.threads)
    result = check_store(Path(args.results))
    if result["max_abs_diff_db"] > args.tolerance:
        raise SystemExit(f"check-store: stored and recomputed PSNR differ by {result['max_abs_diff_db']:.2f} dB "
                         f"(> {args.tolerance} dB)")


def _presample(args: argparse.Namespace) -> None:
    import zarr

    from diffshadow.diffusion.train import DiffusionConfig
    from diffshadow.evaluate import presample
    from diffshadow.lights import read_lights
    from diffshadow.store import write_zarr_group
    from diffshadow.volume import load_prepared

    _threads(args.threads)
    cfg = DiffusionConfig.from_config(_json(args.config_json)["diffusion"])
    volume, tf = load_prepared(args.volume)
    lights = read_lights(args.lights)["train"]
    print(f"presampling {cfg.presample_points} points for each of {len(lights)} lights", flush=True)
    pts, values = presample(volume, tf, lights, cfg.presample_points, seed=cfg.seed)

    def fill(root: zarr.Group) -> None:
        root.create_array("points", data=pts.numpy(), chunks=(1, *pts.shape[1:]))
        root.create_array("values", data=values.numpy(), chunks=(1, values.shape[1]))
        root.create_array("lights", data=lights)
        root.attrs.update({"extent": volume.extent.tolist()})

    write_zarr_group(args.out, fill)
    print(f"wrote {args.out}")


def _load_training_data(weights_path: str, points_path: str):
    import torch
    import zarr

    from diffshadow.diffusion.train import TrainingData
    from diffshadow.store import open_store

    store = open_store(weights_path)
    geo = zarr.open_group(points_path, mode="r")
    if not np.allclose(np.asarray(geo["lights"][...]), store.lights):
        raise ValueError(f"{points_path}: its lights differ from {weights_path}'s; rerun presample")
    return TrainingData(weights=torch.as_tensor(store.weights), lights=torch.as_tensor(store.lights),
                        points=torch.as_tensor(np.asarray(geo["points"][...])),
                        values=torch.as_tensor(np.asarray(geo["values"][...])),
                        extent=torch.as_tensor(geo.attrs["extent"], dtype=torch.float32),
                        layout=store.layout, siren=store.siren), store


def _train_diffusion(args: argparse.Namespace) -> None:
    from diffshadow.diffusion.train import DiffusionConfig, DiffusionError, train_diffusion

    _threads(args.threads)
    cfg = DiffusionConfig.from_config(_json(args.config_json)["diffusion"])
    data, _ = _load_training_data(args.weights, args.points)
    out = Path(args.out)
    try:
        train_diffusion(data, cfg, out.with_name(out.name + ".part"), device=args.device)
    except DiffusionError as e:
        raise DiffusionError(f"train_diffusion ({args.weights}): {e}") from None
    os.replace(out.with_name(out.name + ".part"), out)
    print(f"wrote {out}")


def _sample_shadows(args: argparse.Namespace) -> None:
    import torch

    from diffshadow.diffusion.train import generate, load_sampler
    from diffshadow.evaluate import TruthPoints, psnr_per_light
    from diffshadow.lights import read_lights
    from diffshadow.store import WeightStore, write_store
    from diffshadow.volume import load_prepared

    _threads(args.threads)
    state = torch.load(args.checkpoint, map_location="cpu", weights_only=False)
    model, std, layout, siren = load_sampler(state, args.device)
    cfg = state["config"]
    light_sets = read_lights(args.lights)
    lights = np.concatenate([light_sets["train"], light_sets["unseen"]])
    seen = np.arange(len(lights)) < len(light_sets["train"])
    print(f"sampling {len(lights)} shadow SIRENs ({seen.sum()} seen, {(~seen).sum()} unseen) with "
          f"DDIM {cfg['ddim_steps']} steps", flush=True)
    weights = generate(model, std, lights, method="ddim", steps=cfg["ddim_steps"], seed=cfg["seed"],
                       temperature=cfg["temperature"], device=args.device).numpy()
    volume, tf = load_prepared(args.volume)
    points = TruthPoints(volume, tf, args.eval_points, seed=cfg["seed"] + 1)
    scores = psnr_per_light(points.sirens(weights, layout, siren), points.truth(lights))
    store = WeightStore(weights=weights, lights=lights, psnr=scores["box"],
                        psnr_visible=scores.get("visible", scores["box"]), layout=layout, siren=siren,
                        config={"diffusion": cfg, "checkpoint": str(args.checkpoint)}, seen=seen)
    write_store(args.out, store)
    print(f"wrote {args.out}: PSNR median seen {np.median(store.psnr[seen]):.2f} dB, "
          f"unseen {np.median(store.psnr[~seen]) if (~seen).any() else float('nan'):.2f} dB")


def _evaluate_voxels(args: argparse.Namespace) -> None:
    import torch

    from diffshadow.evaluate import voxel_metrics
    from diffshadow.io import atomic_write_text
    from diffshadow.lights import read_lights
    from diffshadow.store import open_store
    from diffshadow.volume import load_prepared

    _threads(args.threads)
    volume, tf = load_prepared(args.volume)
    state = torch.load(args.checkpoint, map_location="cpu", weights_only=False)
    result = voxel_metrics(state, open_store(args.weights), open_store(args.generated), volume, tf,
                           read_lights(args.lights), eval_points=args.eval_points, blend_k=args.blend_k)
    atomic_write_text(args.out, json.dumps(result, indent=1) + "\n")
    print(json.dumps(result, indent=1))


def config_home() -> Path:
    return Path(os.environ.get("XDG_CONFIG_HOME") or Path.home() / ".config")


def _train_data_inr(args: argparse.Namespace) -> None:
    from diffshadow.data_inr import DataInrConfig, fit_data_inr, save_data_inr
    from diffshadow.volume import load_prepared

    _threads(args.threads)
    cfg = DataInrConfig.from_config(_json(args.config_json)["data_inr"])
    volume, tf = load_prepared(args.volume)
    out = Path(args.out)
    inr = fit_data_inr(volume, tf, cfg, checkpoint=out.with_name(out.name + ".ckpt"), device=args.device)
    save_data_inr(out, inr)
    print(f"wrote {out}: {inr.n_params} parameters, voxel PSNR {inr.psnr:.2f} dB, max error {inr.max_error:.4f}")


def _render_targets(args: argparse.Namespace) -> None:
    from diffshadow.finetune import FinetuneConfig, build_bundle, fibonacci_views, render_targets, write_targets
    from diffshadow.lights import read_lights
    from diffshadow.volume import load_prepared

    _threads(args.threads)
    cfg = FinetuneConfig.from_config(_json(args.config_json)["finetune"])
    volume, tf = load_prepared(args.volume)
    lights = read_lights(args.lights)["train"]
    cams = fibonacci_views(volume.extent, cfg.views, size=cfg.image_size, fov=cfg.fov)
    bundle = build_bundle(volume, tf, cams, step=cfg.step)
    print(f"{cfg.views} views of {cfg.image_size}²: {bundle.count.tolist()} foreground pixels, up to "
          f"{bundle.pts.shape[2]} samples each", flush=True)
    images = render_targets(volume, tf, lights, cams, step=cfg.step)
    write_targets(args.out, images, bundle, cams, lights, step=cfg.step, extent=volume.extent)
    print(f"wrote {args.out}: {len(lights)} lights x {cfg.views} views")


def _finetune_render(args: argparse.Namespace) -> None:
    import json as _json_mod

    import torch

    from diffshadow.finetune import (
        FinetuneConfig,
        FinetuneData,
        finetune,
        image_psnr_of_model,
        init_distributed,
        read_targets,
    )
    from diffshadow.io import atomic_write_text

    cfg = FinetuneConfig.from_config(_json(args.config_json)["finetune"])
    rank, world, device = init_distributed(cfg, args.device)
    _threads(args.threads)
    log = print if rank == 0 else (lambda m: print(m) if m.startswith(f"rank {rank}") else None)
    geometry = torch.load(args.checkpoint, map_location="cpu", weights_only=False)
    train, _ = _load_training_data(args.weights, args.points)
    images, bundle, lights = read_targets(args.targets)
    if not np.allclose(lights, train.lights.numpy()):
        raise ValueError(f"{args.targets}: its lights differ from {args.weights}'s; rerun render_targets")
    data = FinetuneData(train, bundle, images)
    out = Path(args.out)
    part = out.with_name(out.name + ".part")
    import time as _time

    t0 = _time.perf_counter()
    state = finetune(geometry, data, cfg, part, rank=rank, world=world, device=device, log=log)
    seconds = _time.perf_counter() - t0
    if rank == 0:
        before = image_psnr_of_model(geometry, data)
        after = image_psnr_of_model(state, data)
        metrics = {"image_psnr_geometry_only": {"mean": float(before.mean()), "median": float(np.median(before)),
                                                "min": float(before.min())},
                   "image_psnr_finetuned": {"mean": float(after.mean()), "median": float(np.median(after)),
                                            "min": float(after.min())},
                   "lights": len(before), "views": int(len(bundle.count)), "processes": world,
                   "ranks": state.get("finetune_ranks"),
                   "seconds": seconds, "config": cfg.__dict__}
        print(f"image PSNR of generated shadows on training lights (foreground, {len(bundle.count)} views): "
              f"geometry only {before.mean():.2f} dB (min {before.min():.2f}), fine-tuned {after.mean():.2f} dB "
              f"(min {after.min():.2f}); {seconds:.0f} s on {world} process(es)")
        for r in state.get("finetune_ranks") or []:
            step_s = f"{r['median_step_s']:.3f} s" if r["median_step_s"] is not None else "n/a"
            print(f"rank {r['rank']}: median step {step_s}, peak memory {r['peak_mem_bytes'] / 2**20:.0f} MiB")
        atomic_write_text(args.metrics, _json_mod.dumps(metrics, indent=2) + "\n")
        os.replace(part, out)
        print(f"wrote {out} and {args.metrics}")
    if world > 1:
        import torch.distributed as dist

        dist.barrier()
        dist.destroy_process_group()


def _scene_config(configfile: Path, scene: str) -> dict:
    """config/scenes/<scene>.yaml over the run's defaults (as the workflow merges them)."""
    import yaml

    with open(configfile) as f:
        cfg = yaml.safe_load(f) or {}
    path = configfile.parent / "scenes" / f"{scene}.yaml"
    if not path.exists():
        raise ValueError(f"scene {scene!r}: no file {path}")
    with open(path) as f:
        own = yaml.safe_load(f) or {}
    merged = dict(cfg)
    for key, value in own.items():
        merged[key] = {**merged[key], **value} if isinstance(merged.get(key), dict) else value
    return merged


def _parsl_fit(args: argparse.Namespace) -> None:
    import yaml

    from diffshadow.parsl_fit import fit_args, pending, run

    configfile = Path(args.configfile)
    scenes = args.scenes or (yaml.safe_load(configfile.read_text()) or {}).get("scenes", [])
    results = Path(args.results)
    jobs = []
    for scene in scenes:
        cfg = _scene_config(configfile, scene)
        for need in ("volume.zarr", "lights.json", "siren_init.pt"):
            if not (results / scene / need).exists():
                raise ValueError(f"{results / scene / need} is missing: run `snakemake --profile local -j2 "
                                 f"--until preoptimize` (or your HPC profile) first")
        n = -(-cfg["lights"]["count"] // cfg["subset_size"])
        todo = pending(results, scene, n)
        print(f"[parsl-fit] {scene}: {len(todo)} of {n} subsets pending")
        sel = {k: cfg[k] for k in ("siren", "fit", "subset_size")}
        jobs += [fit_args(results, scene, i, sel, args.threads) for i in todo]
    if jobs:
        run(Path(args.config), jobs)
    print(f"[parsl-fit] done: {len(jobs)} subsets fitted")


def _report_figures(args: argparse.Namespace) -> None:
    import json as _json_mod

    import torch

    from diffshadow import report
    from diffshadow.bench import bench_shadow
    from diffshadow.io import atomic_write_text
    from diffshadow.lights import read_lights
    from diffshadow.store import open_store
    from diffshadow.volume import load_prepared

    _threads(args.threads)
    res, out = Path(args.results), Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cfg = _json(args.config_json)
    report.write_config(out / "config.yaml", cfg)
    stage1, generated = open_store(res / "weights.zarr"), open_store(res / "generated.zarr")
    report.siren_psnr_figure(stage1, out / "siren_psnr.png")
    report.generated_figure(stage1, generated, out / "generated_psnr.png", out / "generated_psnr.csv")
    report.image_grid_figure(res / "images", out / "image_grid.png")
    report.storage_figure(_json_mod.loads((res / "voxel_metrics.json").read_text()), out / "storage.png")
    volume, tf = load_prepared(res / "volume.zarr")
    ckpt = res / ("diffusion.ckpt" if (res / "diffusion.ckpt").exists() else "diffusion_geometry.ckpt")
    state = torch.load(ckpt, map_location="cpu", weights_only=False)
    ddim = report.ddim_curve_figure(state, volume, tf, read_lights(res / "lights.json")["train"],
                                    out / "ddim_curve.png")
    atomic_write_text(out / "ddim_curve.json", _json_mod.dumps(ddim, indent=2) + "\n")
    shadow = bench_shadow([Path(cfg["volume"])], out, tf_config=cfg["transfer_function"])
    report.shadow_curve_figure(shadow, out / "shadow_curve.png")
    print(f"wrote the report figures in {out}")


def _pbs_status(args: argparse.Namespace) -> None:
    """Snakemake's cluster-generic status command: running | success | failed, always exit 0."""
    import subprocess

    from diffshadow.hpc import pbs_state

    try:
        out = subprocess.run(["qstat", "-fx", args.job], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        print("running")  # the server did not answer: ask again at the next check
        return
    print(pbs_state(out.stdout) if out.returncode == 0 else "failed")


def _render_scene(volume_path: str, data_inr: str | None, device, tf_json: str | None = None):
    """A RenderScene from a prepared volume.zarr, or from a raw volume file with a TF (JSON)."""
    from diffshadow.data_inr import load_data_inr
    from diffshadow.render import RenderScene
    from diffshadow.transfer import TransferFunction
    from diffshadow.volume import load_prepared, load_volume

    if Path(volume_path).suffix == ".zarr" and (Path(volume_path) / "zarr.json").exists() and not tf_json:
        volume, tf = load_prepared(volume_path)
    else:
        from diffshadow.bench import BENCH_TF

        volume = load_volume(volume_path)
        tf = TransferFunction.from_config(_json(tf_json) if tf_json else BENCH_TF)
    inr = load_data_inr(data_inr) if data_inr else None
    if inr is not None and not np.allclose(inr.extent, volume.extent):
        raise ValueError(f"{data_inr}: fitted to a box of {inr.extent.tolist()}, the volume's is "
                         f"{volume.extent.tolist()}")
    return RenderScene(volume, tf, inr, device=device)


def _render(args: argparse.Namespace) -> None:
    from diffshadow.render import Camera, write_png
    from diffshadow.store import open_store

    _threads(args.threads)
    scene = _render_scene(args.volume, args.data_inr, args.device)
    siren = None
    light = args.light
    if args.weights:
        store = open_store(args.weights)
        if not 0 <= args.light_index < len(store.weights):
            raise ValueError(f"--light-index: {args.weights} holds lights 0..{len(store.weights) - 1}, "
                             f"got {args.light_index}")
        siren = (store.weights[args.light_index], store.layout, store.siren.blocks)
        light = light or store.lights[args.light_index].tolist()
    if args.mode == "inr" and siren is None:
        raise ValueError("--mode inr needs --weights (a weight store) and --light-index")
    cam = Camera.orbit(scene.volume.extent, azimuth=args.azimuth, elevation=args.elevation,
                       distance=args.distance, fov=args.fov, size=args.size)
    img = scene.render(args.mode, cam, light=light, siren=siren, scalar=args.scalar, phong=args.phong,
                       step=args.step, skip=not args.no_skip)
    write_png(args.out, img)
    c = img.counters
    print(f"wrote {args.out}: {args.mode}, {args.size}x{args.size} in {img.seconds:.3f} s "
          f"({c.primary_samples:,} samples, {c.secondary_samples:,} on shadow rays)")


def _bench_render(args: argparse.Namespace) -> None:
    import yaml

    from diffshadow.bench import BENCH_LIGHT
    from diffshadow.bench_render import bench_render, write_bench
    from diffshadow.data_inr import DataInrConfig, fit_data_inr
    from diffshadow.fit import FitConfig, fit_sirens, seeded
    from diffshadow.render import RenderScene
    from diffshadow.siren import SirenConfig, WeightLayout, init_siren
    from diffshadow.store import open_store
    from diffshadow.transfer import TransferFunction
    from diffshadow.volume import load_volume

    _threads(args.threads)
    if args.scene_config:
        with open(args.scene_config) as f:
            sc = yaml.safe_load(f) or {}
        for key in ("volume", "transfer_function"):
            if key not in sc:
                raise ValueError(f"{args.scene_config}: missing key {key!r}")
        volume = load_volume(sc["volume"], **sc.get("load", {}))
        scene = RenderScene(volume, TransferFunction.from_config(sc["transfer_function"]), device=args.device)
        name = Path(args.scene_config).stem
    elif args.volume:
        scene = _render_scene(args.volume, None, args.device, args.tf_json)
        name = scene.volume.name
    else:
        raise ValueError("bench render: give --scene-config FILE or --volume PATH")
    if args.data_inr:
        from diffshadow.data_inr import load_data_inr

        scene.data_inr = load_data_inr(args.data_inr)
    else:
        print(f"[bench render] fitting a data INR ({args.inr_steps} steps; pass --data-inr to reuse one) ...")
        scene.data_inr = fit_data_inr(scene.volume, scene.tf, DataInrConfig(steps=args.inr_steps),
                                      device=args.device, log=lambda m: None)
    if args.weights:
        store = open_store(args.weights)
        siren = (store.weights[args.light_index], store.layout, store.siren.blocks)
        light = store.lights[args.light_index]
    else:
        cfg = SirenConfig(args.siren_width, 2)
        layout = WeightLayout.for_siren(cfg)
        light = np.asarray(BENCH_LIGHT, float) / np.linalg.norm(BENCH_LIGHT)
        print(f"[bench render] fitting a shadow INR ({args.siren_steps} steps; pass --weights to reuse one) ...")
        w = fit_sirens(layout.flatten(init_siren(cfg, seeded(0))), layout, cfg, scene.volume, scene.tf,
                       light[None], FitConfig(steps=args.siren_steps, grid_upsample=1, chunk=4096),
                       device=args.device, log=lambda m: None)[0]
        siren = (w, layout, cfg.blocks)
    results = bench_render(scene, siren, light, sizes=args.sizes, step=args.step, repeats=args.repeats)
    results.update({"scene": name, "dims": list(scene.volume.dims),
                    "data_inr": {"params": scene.data_inr.n_params, "psnr": scene.data_inr.psnr},
                    "shadow_inr": {"params": int(siren[1].n_params)}})
    write_bench(Path(args.out), results)
    print(f"wrote {args.out} and {Path(args.out).with_suffix('.png')}")


def _evaluate_images(args: argparse.Namespace) -> None:
    import json as _json_mod

    from diffshadow.bench_render import finite_json
    from diffshadow.evaluate import image_evaluation
    from diffshadow.io import atomic_write_text
    from diffshadow.lights import read_lights
    from diffshadow.metrics import lpips_model
    from diffshadow.render import default_views
    from diffshadow.store import open_store

    _threads(args.threads)
    cfg = _json(args.config_json)["render"]
    scene = _render_scene(args.volume, args.data_inr, args.device)
    light_sets = read_lights(args.lights)
    stage1 = open_store(args.weights)
    generated = open_store(args.generated) if args.generated else None
    views = default_views(scene.volume.extent, cfg["views"], size=cfg["image_size"], fov=cfg["fov"])
    lpips, reason = lpips_model()
    result = image_evaluation(scene, light_sets, stage1, generated, views, step=cfg["step"],
                              out_dir=Path(args.images), lights_per_set=cfg["lights_per_set"],
                              naive_views=cfg.get("naive_views"), lpips=lpips)
    result.update({"lpips": "available (VGG)" if lpips is not None else f"unavailable: {reason}",
                   "image_size": cfg["image_size"], "views": cfg["views"], "step": cfg["step"],
                   "reference": "gt: raw scalar field and shadow_grid (march), same step",
                   "data_inr_psnr": scene.data_inr.psnr if scene.data_inr is not None else None})
    atomic_write_text(args.out, _json_mod.dumps(finite_json(result), indent=2) + "\n")
    for name, m in sorted(result["modes"].items()):
        print(f"{name:24s} PSNR {m['psnr']:.2f} dB  SSIM {m['ssim']:.4f}  over {m['count']} images")
    print(f"wrote {args.out}")


def _same_profile(a: Path, b: Path) -> bool:
    if a.resolve() == b.resolve():
        return True
    if not (a.is_dir() and b.is_dir()):
        return False
    cmp = filecmp.dircmp(a, b)
    return not (cmp.left_only or cmp.right_only or cmp.diff_files or cmp.funny_files)


def install_profiles(source: Path, target_root: Path, *, force: bool = False) -> list[Path]:
    """Link each profile folder of `source` into `target_root` (Snakemake's search path).

    An existing profile of the same name is left alone when it is this one (or identical) and
    refused otherwise, unless `force`.
    """
    if not source.is_dir():
        raise SystemExit(f"install-profiles: no profiles folder at {source} (run from the repository root "
                         f"or pass --source)")
    target_root.mkdir(parents=True, exist_ok=True)
    installed = []
    for profile in sorted(p for p in source.iterdir() if p.is_dir()):
        target = target_root / profile.name
        if target.exists() or target.is_symlink():
            if _same_profile(profile, target):
                installed.append(target)
                continue
            if not force:
                raise SystemExit(f"install-profiles: {target} exists and differs from {profile}; "
                                 f"remove it or pass --force")
            if target.is_symlink() or target.is_file():
                target.unlink()
            else:
                raise SystemExit(f"install-profiles: {target} is a real folder; remove it by hand")
        target.symlink_to(profile.resolve(), target_is_directory=True)
        installed.append(target)
    return installed


def _install_profiles(args: argparse.Namespace) -> None:
    root = Path(args.target) if args.target else config_home() / "snakemake"
    for path in install_profiles(Path(args.source), root, force=args.force):
        print(f"profile {path.name}: {path} -> {path.resolve()}")


def _run_options(p: argparse.ArgumentParser, *, device: bool = True) -> None:
    """--out, --device, --threads: shared by the rule subcommands."""
    p.add_argument("--out", required=True)
    if device:
        p.add_argument("--device", default=None, help="torch device (default: cpu)")
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="diffshadow", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("lights", help="training and unseen light directions as JSON")
    p.add_argument("--sphere", type=int, default=8000, help="points on the Fibonacci sphere (paper: 8000)")
    p.add_argument("--count", type=int, default=2000, help="training directions kept (paper: 2000)")
    p.add_argument("--center", type=float, nargs=3, default=(0.0, 0.0, 1.0), metavar=("X", "Y", "Z"))
    p.add_argument("--unseen", type=int, default=500, help="held-out directions (paper: 500)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True)
    p.set_defaults(func=_lights)

    bench = sub.add_parser("bench", help="benchmarks that print and save figures")
    bench_sub = bench.add_subparsers(dest="bench", required=True)
    p = bench_sub.add_parser("shadow", help="time vs error of the ground-truth shadow methods")
    p.add_argument("--volumes", nargs="*", help="volume files (default: bundled nucleon + ../shared/data)")
    p.add_argument("--out", default="bench", help="folder for bench_shadow.json and bench_shadow.png")
    p.add_argument("--device", default=None)
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    p.set_defaults(func=_bench_shadow)

    p = bench_sub.add_parser("siren", help="throughput of K SIRENs fitted jointly vs one after another")
    p.add_argument("--k", type=int, default=16)
    p.add_argument("--points", type=int, default=4096, help="points per SIREN per step")
    p.add_argument("--widths", type=int, nargs="+", default=[32, 64, 128])
    p.add_argument("--out", default="bench")
    p.add_argument("--device", default=None)
    p.add_argument("--threads", type=int, default=0)
    p.set_defaults(func=_bench_siren)

    p = bench_sub.add_parser("init-spread", help="weight spread across lights: shared init vs random inits")
    p.add_argument("--results", default="results/nucleon", help="a finished scene's results folder")
    p.add_argument("--lights", type=int, default=8, help="lights to refit from random inits")
    p.add_argument("--out", default="bench")
    p.add_argument("--threads", type=int, default=0)
    p.set_defaults(func=_bench_init_spread)

    p = bench_sub.add_parser("render", help="fps and peak memory of noshadow / inr / naive; skipping; step curve")
    p.add_argument("--scene-config", help="a scene YAML (volume, transfer_function), e.g. config/scenes/neghip.yaml")
    p.add_argument("--volume", help="or a volume: prepare_volume's volume.zarr, or a raw file (with --tf-json)")
    p.add_argument("--tf-json", help="transfer function for a raw --volume (default: the bench TF)")
    p.add_argument("--data-inr", help="train_data_inr's data_inr.pt (default: fit one)")
    p.add_argument("--inr-steps", type=int, default=600, help="steps when fitting the data INR here")
    p.add_argument("--weights", help="a weight store whose SIREN --light-index is the shadow INR (default: fit one)")
    p.add_argument("--light-index", type=int, default=0)
    p.add_argument("--siren-width", type=int, default=32)
    p.add_argument("--siren-steps", type=int, default=300)
    p.add_argument("--sizes", type=int, nargs="+", default=[64, 128])
    p.add_argument("--step", type=float, default=0.5, help="voxels")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", default="bench/bench_render.json")
    p.add_argument("--device", default=None)
    p.add_argument("--threads", type=int, default=0)
    p.set_defaults(func=_bench_render)

    p = sub.add_parser("check-store", help="re-evaluate every stored SIREN independently against the store's PSNR")
    p.add_argument("--results", default="results/nucleon")
    p.add_argument("--tolerance", type=float, default=0.5, help="dB")
    p.add_argument("--threads", type=int, default=0)
    p.set_defaults(func=_check_store)

    p = sub.add_parser("prepare-volume", help="normalised grid + TF + macro-cells as Zarr")
    p.add_argument("--config-json", required=True, help='{"volume": PATH, "transfer_function": {...}}')
    p.add_argument("--out", required=True)
    p.set_defaults(func=_prepare_volume)

    for name, func, helptext in (("preoptimize", _preoptimize, "fit the shared initial SIREN on light 0"),
                                 ("fit-siren", _fit_siren, "fit one subset of SIRENs jointly")):
        p = sub.add_parser(name, help=helptext)
        p.add_argument("--volume", required=True, help="prepare_volume's volume.zarr")
        p.add_argument("--lights", required=True, help="lights.json")
        p.add_argument("--config-json", required=True, help='{"siren": ..., "fit": ..., ...}')
        _run_options(p)
        if name == "fit-siren":
            p.add_argument("--init", required=True, help="preoptimize's siren_init.pt")
            p.add_argument("--subset", type=int, required=True)
        p.set_defaults(func=func)

    p = sub.add_parser("collect-weights", help="merge subset files into the Zarr weight store")
    p.add_argument("--lights", required=True)
    p.add_argument("--subsets", nargs="+", required=True)
    p.add_argument("--out", required=True)
    p.set_defaults(func=_collect_weights)

    p = sub.add_parser("presample", help="points and true shadow per training light (geometry loss)")
    p.add_argument("--volume", required=True)
    p.add_argument("--lights", required=True)
    p.add_argument("--config-json", required=True, help='{"diffusion": {...}}')
    _run_options(p, device=False)
    p.set_defaults(func=_presample)

    p = sub.add_parser("train-diffusion", help="train the weight-space diffusion model (geometry loss)")
    p.add_argument("--weights", required=True, help="weights.zarr")
    p.add_argument("--points", required=True, help="geometry_points.zarr")
    p.add_argument("--config-json", required=True, help='{"diffusion": {...}}')
    _run_options(p)
    p.set_defaults(func=_train_diffusion)

    p = sub.add_parser("sample-shadows", help="generate SIRENs for every training and unseen light")
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--volume", required=True)
    p.add_argument("--lights", required=True)
    p.add_argument("--eval-points", type=int, default=32768)
    _run_options(p)
    p.set_defaults(func=_sample_shadows)

    p = sub.add_parser("evaluate-voxels", help="voxel PSNR of generated SIRENs, baselines, storage, timing")
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--weights", required=True)
    p.add_argument("--generated", required=True)
    p.add_argument("--volume", required=True)
    p.add_argument("--lights", required=True)
    p.add_argument("--eval-points", type=int, default=32768)
    p.add_argument("--blend-k", type=int, default=4)
    _run_options(p, device=False)
    p.set_defaults(func=_evaluate_voxels)

    p = sub.add_parser("train-data-inr", help="fit the data INR (a SIREN of the scalar field)")
    p.add_argument("--volume", required=True, help="prepare_volume's volume.zarr")
    p.add_argument("--config-json", required=True, help='{"data_inr": {...}}')
    _run_options(p)
    p.set_defaults(func=_train_data_inr)

    p = sub.add_parser("render", help="render one image (PNG) in a shading mode")
    p.add_argument("--volume", required=True, help="volume.zarr (or a raw volume file)")
    p.add_argument("--mode", choices=["noshadow", "gt", "inr", "naive"], default="gt")
    p.add_argument("--data-inr", help="data_inr.pt (needed for --scalar inr and mode naive)")
    p.add_argument("--weights", help="weight store for mode inr (weights.zarr or generated.zarr)")
    p.add_argument("--light-index", type=int, default=0, help="row of --weights (its light is used)")
    p.add_argument("--light", type=float, nargs=3, metavar=("X", "Y", "Z"), help="toward the light")
    p.add_argument("--scalar", choices=["grid", "inr"], default=None, help="default: inr when --data-inr")
    p.add_argument("--phong", action="store_true", help="Blinn-Phong lighting from the field's gradient")
    p.add_argument("--azimuth", type=float, default=30.0)
    p.add_argument("--elevation", type=float, default=25.0)
    p.add_argument("--distance", type=float, default=2.2, help="in box half-diagonals")
    p.add_argument("--fov", type=float, default=60.0)
    p.add_argument("--size", type=int, default=128)
    p.add_argument("--step", type=float, default=0.5, help="voxels")
    p.add_argument("--no-skip", action="store_true", help="turn macro-cell skipping off")
    _run_options(p)
    p.set_defaults(func=_render)

    p = sub.add_parser("evaluate-images", help="images and image metrics of every mode against gt")
    p.add_argument("--volume", required=True)
    p.add_argument("--lights", required=True)
    p.add_argument("--data-inr", required=True)
    p.add_argument("--weights", required=True, help="stage 1's weights.zarr")
    p.add_argument("--generated", help="stage 2's generated.zarr (optional)")
    p.add_argument("--config-json", required=True, help='{"render": {...}}')
    p.add_argument("--images", required=True, help="folder for the PNGs")
    _run_options(p)
    p.set_defaults(func=_evaluate_images)

    p = sub.add_parser("render-targets", help="ground-truth images per training light and view (rendering loss)")
    p.add_argument("--volume", required=True)
    p.add_argument("--lights", required=True)
    p.add_argument("--config-json", required=True, help='{"finetune": {...}}')
    _run_options(p, device=False)
    p.set_defaults(func=_render_targets)

    p = sub.add_parser("finetune-render", help="rendering-loss fine-tuning (run under torchrun for DDP)")
    p.add_argument("--checkpoint", required=True, help="diffusion_geometry.ckpt")
    p.add_argument("--weights", required=True)
    p.add_argument("--points", required=True)
    p.add_argument("--targets", required=True)
    p.add_argument("--config-json", required=True, help='{"finetune": {...}}')
    p.add_argument("--metrics", required=True, help="JSON: image PSNR before and after, wall time")
    _run_options(p)
    p.set_defaults(func=_finetune_render)

    p = sub.add_parser("parsl-fit", help="fit every pending fit_siren subset through Parsl (one big allocation)")
    p.add_argument("--config", default="config/parsl/local.py", help="Parsl config file (config/parsl/*.py)")
    p.add_argument("--configfile", default="config/config.yaml", help="the workflow's config file")
    p.add_argument("--scenes", nargs="*", help="default: the config's scenes")
    p.add_argument("--results", default="results")
    p.add_argument("--threads", type=int, default=1, help="torch threads per worker")
    p.set_defaults(func=_parsl_fit)

    p = sub.add_parser("report-figures", help="the figures of the Snakemake report for one finished scene")
    p.add_argument("--results", required=True, help="results/<scene>")
    p.add_argument("--config-json", required=True, help="the scene's merged configuration")
    p.add_argument("--out-dir", required=True)
    p.add_argument("--threads", type=int, default=0)
    p.set_defaults(func=_report_figures)

    p = sub.add_parser("pbs-status", help="PBS job state for Snakemake's cluster-generic executor")
    p.add_argument("job", help="PBS job id")
    p.set_defaults(func=_pbs_status)

    p = sub.add_parser("install-profiles", help="make the repo's Snakemake profiles usable by bare name")
    p.add_argument("--source", default="profiles", help="folder of profiles (default: ./profiles)")
    p.add_argument("--target", default=None, help="default: ${XDG_CONFIG_HOME:-~/.config}/snakemake")
    p.add_argument("--force", action="store_true", help="replace a different profile that is a symlink")
    p.set_defaults(func=_install_profiles)
    return parser


# subcommands that use one GPU: on a node shared by several jobs each claims its own (DIFFSHADOW_GPU_LOCK)
_ONE_GPU = {"preoptimize", "fit-siren", "train-data-inr", "presample", "train-diffusion", "sample-shadows",
            "evaluate-voxels", "render-targets", "evaluate-images", "render"}


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    if hasattr(args, "device") and args.device is None:
        args.device = os.environ.get("DIFFSHADOW_DEVICE") or None  # the profile's jobscript sets it on GPU nodes
    gpus = os.environ.get("DIFFSHADOW_GPU_LOCK")
    if gpus and args.command in _ONE_GPU:
        from diffshadow.hpc import claim_gpu

        gpu = claim_gpu(int(gpus))
        print(f"diffshadow {args.command}: claimed GPU {gpu} of {gpus} (CUDA_VISIBLE_DEVICES={gpu})", flush=True)
    try:
        args.func(args)
    except ValueError as e:  # the library's input errors: one line, no traceback
        print(f"diffshadow {args.command}: error: {e}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
