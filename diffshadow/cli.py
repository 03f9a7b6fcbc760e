"""The `diffshadow` command: one subcommand per workflow rule, plus `bench` and `install-profiles`.

It only parses arguments and dispatches: each rule's work is a function of `diffshadow.stages`, the
device is resolved once by `diffshadow.runtime`, configuration comes from `diffshadow.config`.
"""

from __future__ import annotations

import argparse
import errno
import os
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import TextIO

from diffshadow import __version__
from diffshadow.argparsing import add_networks, at_least, network_flags, seed
from diffshadow.argparsing import add_subcommand as _add
from diffshadow.argparsing import config_of as _cfg
from diffshadow.argparsing import device_of as _device
from diffshadow.config import RESUMABLE, defaults, memory_keys
from diffshadow.lights import LAYOUTS
from diffshadow.stopping import Stopped

# ------------------------------------------------------------------------------------------- stage 1


def _lights(a: argparse.Namespace):
    from diffshadow.stages import stage1

    stage1.lights(Path(a.out), sphere=a.sphere, count=a.count, center=a.center, unseen=a.unseen, seed=a.seed,
                  layout=a.layout)


def _prepare_volume(a: argparse.Namespace):
    from diffshadow.stages import stage1

    stage1.prepare_volume(Path(a.out), _cfg(a))


def _stage1_configs(cfg: dict) -> dict:
    from diffshadow.fit import FitConfig
    from diffshadow.siren import SirenConfig

    return {"siren": SirenConfig.from_config(cfg["siren"]), "fit": FitConfig.from_config(cfg["fit"])}


def _preoptimize(a: argparse.Namespace):
    from diffshadow.stages import stage1

    cfg = _cfg(a)
    stage1.preoptimize(Path(a.volume), Path(a.lights), Path(a.out), **_stage1_configs(cfg),
                       steps=cfg["preoptimize"]["steps"], lr=cfg["preoptimize"]["lr"], device=_device(a))


def _fit_siren(a: argparse.Namespace):
    from diffshadow.runtime import SpareThreads
    from diffshadow.stages import stage1

    cfg = _cfg(a)
    device = _device(a)
    stage1.fit_subset(Path(a.volume), Path(a.lights), Path(a.init), a.subset, Path(a.out), **_stage1_configs(cfg),
                      subset_size=int(cfg["subset_size"]), config=cfg, device=device,
                      spare=SpareThreads.for_run(a.threads, device))


def _collect_weights(a: argparse.Namespace):
    from diffshadow.stages import stage1

    stage1.collect_weights(Path(a.lights), [Path(p) for p in a.subsets], Path(a.out))


# ------------------------------------------------------------------------------------------- stage 2


def _diffusion(a: argparse.Namespace):
    from diffshadow.diffusion.config import DiffusionConfig

    return DiffusionConfig.from_config(_cfg(a)["diffusion"])


def _presample(a: argparse.Namespace):
    from diffshadow.stages import stage2

    stage2.presample(Path(a.volume), Path(a.lights), Path(a.out), cfg=_diffusion(a), device=_device(a))


def _train_diffusion(a: argparse.Namespace):
    from diffshadow.stages import stage2

    stage2.train_diffusion(Path(a.weights), Path(a.points), Path(a.out), cfg=_diffusion(a), device=_device(a))


def _finetune_render(a: argparse.Namespace):
    from diffshadow.diffusion.finetune import FinetuneConfig
    from diffshadow.stages import stage2

    stage2.finetune_render(Path(a.checkpoint), Path(a.weights), Path(a.points), Path(a.targets), Path(a.out),
                           Path(a.metrics), cfg=FinetuneConfig.from_config(_cfg(a)["finetune"]),
                           device=_device(a), threads=a.threads, volume_path=Path(a.volume) if a.volume else None,
                           lights_path=Path(a.lights) if a.lights else None)


def _ddp_processes(a: argparse.Namespace):
    from diffshadow.hpc import ddp_processes, gpu_possible, visible_nvidia_gpus

    gpus = None
    # no torch import where no GPU can be (1.3 of this command's 1.7 s on 2 cores), nor where the driver counts the
    # GPUs (4 s of fine-tuning's 6.6 s launch on an H200 node): each rank resolves its own device
    if gpu_possible(a.device, a.config_device) and not (gpus := visible_nvidia_gpus()):
        import torch

        device = _device(a)
        gpus = torch.cuda.device_count() if device.type == "cuda" else None
    n, why = ddp_processes(a.nproc, gpus)
    print(f"diffshadow: {why}", file=sys.stderr)
    print(n)


def _torchrun(a: argparse.Namespace):
    from diffshadow.hpc import launch_ranks

    if code := launch_ranks(a.torchrun_args):
        raise SystemExit(code)


def _eval_truth(a: argparse.Namespace):
    from diffshadow.stages import stage2

    stage2.eval_truth(Path(a.volume), Path(a.lights), Path(a.out), eval_points=a.eval_points, seed=a.seed,
                      device=_device(a))


def _caches(a: argparse.Namespace):
    from diffshadow.stages import stage2

    stage2.caches(Path(a.weights), Path(a.generated), Path(a.truth), Path(a.lights), Path(a.volume),
                  Path(a.checkpoint) if a.checkpoint else None, Path(a.out), Path(a.figure), blend_k=a.blend_k,
                  weighting=a.blend_weights, device=_device(a), correction_path=a.correction and Path(a.correction))


def _sample_shadows(a: argparse.Namespace):
    from diffshadow.stages import stage2

    mix = {"model_share": a.model_share, "val_lights": a.val_lights, "val_points": a.val_points, "seed": a.seed}
    device = _device(a)
    stage2.sample_shadows(Path(a.checkpoint), Path(a.truth), Path(a.lights), Path(a.out), device=device, mix=mix,
                          weights_path=a.weights and Path(a.weights), volume_path=a.volume and Path(a.volume),
                          blend_k=a.blend_k, weighting=a.blend_weights,
                          score_device=device if a.score_on == "run" else "cpu",
                          correction_path=a.correction and Path(a.correction))


def _choose_cache(a: argparse.Namespace):
    from diffshadow.stages import stage2

    stage2.choose_cache(Path(a.weights), Path(a.truth), Path(a.volume), Path(a.lights), Path(a.out),
                        blend_k=a.blend_k, weighting=a.blend_weights, target_psnr=a.target_psnr,
                        tolerance=a.tolerance, candidates=a.candidates, val_lights=a.val_lights,
                        val_points=a.val_points, seed=a.seed, device=_device(a))


def _fit_correction(a: argparse.Namespace):
    from diffshadow.correction import CorrectionConfig
    from diffshadow.runtime import SpareThreads
    from diffshadow.stages import stage2

    device = _device(a)
    stage2.fit_correction(Path(a.weights), Path(a.volume), Path(a.lights), Path(a.out),
                          cfg=CorrectionConfig.from_config(_cfg(a).get("correction")), blend_k=a.blend_k,
                          weighting=a.blend_weights, device=device, spare=SpareThreads.for_run(a.threads, device))


def _encode_cache(a: argparse.Namespace):
    from diffshadow.stages import stage2

    stage2.encode_cache(Path(a.weights), Path(a.truth), Path(a.lights), Path(a.out), codec=a.codec,
                        device=_device(a))


def _blend_shadows(a: argparse.Namespace):
    from diffshadow.stages import stage2

    stage2.blend_shadows(Path(a.weights), Path(a.truth), Path(a.lights), Path(a.out), blend_k=a.blend_k,
                         weighting=a.blend_weights, device=_device(a),
                         correction_path=a.correction and Path(a.correction))


def _evaluate_voxels(a: argparse.Namespace):
    from diffshadow.stages import stage2

    checkpoint = Path(a.checkpoint) if a.checkpoint else None
    stage2.evaluate_voxels(checkpoint, Path(a.weights), Path(a.generated), Path(a.truth), Path(a.volume),
                           Path(a.lights), Path(a.out), blend_k=a.blend_k, weighting=a.blend_weights,
                           ddpm_lights=a.ddpm_lights,
                           geometry_checkpoint=Path(a.geometry_checkpoint) if a.geometry_checkpoint else None,
                           device=_device(a), wide_lights=a.wide_lights, wide_points=a.wide_points, wide_seed=a.seed,
                           cache_path=Path(a.cache_weights) if a.cache_weights else None,
                           correction_path=a.correction and Path(a.correction))


# ------------------------------------------------------------------------------------- images, report


def _train_data_inr(a: argparse.Namespace):
    from diffshadow.data_inr import DataInrConfig
    from diffshadow.stages import images

    images.train_data_inr(Path(a.volume), Path(a.out), cfg=DataInrConfig.from_config(_cfg(a)["data_inr"]),
                          device=_device(a))


def _render_targets(a: argparse.Namespace):
    from diffshadow.diffusion.finetune import FinetuneConfig
    from diffshadow.fit import FitConfig
    from diffshadow.stages import images

    cfg = _cfg(a)
    images.render_targets(Path(a.volume), Path(a.lights), Path(a.out), cfg=FinetuneConfig.from_config(cfg["finetune"]),
                          upsample=FitConfig.from_config(cfg.get("fit")).grid_upsample, device=_device(a))


def _evaluate_images(a: argparse.Namespace):
    from diffshadow.stages import images

    images.evaluate_images(Path(a.volume), Path(a.lights), Path(a.data_inr), Path(a.weights),
                           Path(a.generated) if a.generated else None, Path(a.images), Path(a.out),
                           cfg=_cfg(a)["render"], device=_device(a), naive_path=Path(a.naive) if a.naive else None)


def _naive_images(a: argparse.Namespace):
    from diffshadow.stages import images

    images.naive_images(Path(a.volume), Path(a.lights), Path(a.data_inr), Path(a.out), cfg=_cfg(a)["render"],
                        device=_device(a))


def _render(a: argparse.Namespace):
    from diffshadow.artifacts import load_render_scene, load_scene_file
    from diffshadow.config import parse_json
    from diffshadow.render import Camera
    from diffshadow.stages import images

    if (a.volume is None) == (a.scene_config is None):
        raise ValueError("render: give --volume (a volume.zarr, or a raw file with --tf-json) or --scene-config")
    if a.scene_config and a.data_inr:
        raise ValueError("render: --data-inr needs --volume results/<scene>/volume.zarr, not --scene-config")
    if a.scene_config:
        scene = load_scene_file(Path(a.scene_config), _device(a), network_flags(a))
    else:
        tf = parse_json(a.tf_json, "--tf-json") if a.tf_json else None
        scene = load_render_scene(Path(a.volume), Path(a.data_inr) if a.data_inr else None, _device(a), tf,
                                  network_flags(a))
    if len(a.size) > 2:
        raise ValueError(f"--size: expected one number (square) or two (width height), got {len(a.size)}")
    size = a.size[0] if len(a.size) == 1 else tuple(a.size)
    if (a.eye is None) != (a.target is None):
        raise ValueError("render: give --eye and --target together (or neither, for the orbit camera)")
    if a.up is not None and a.eye is None:
        raise ValueError("render: --up turns the free camera; give --eye and --target with it")
    if a.eye is not None:
        cam = Camera.look_at(a.eye, a.target, up=a.up, fov=a.fov, size=size)
    elif a.distance is not None:
        cam = Camera.orbit(scene.volume.extent, azimuth=a.azimuth, elevation=a.elevation, distance=a.distance,
                           fov=a.fov, size=size)
    else:  # the default view frames what the TF shows
        cam = scene.framed(azimuth=a.azimuth, elevation=a.elevation, fov=a.fov, size=size)
    images.render_image(scene, Path(a.out), mode=a.mode, camera=cam, light=a.light,
                        weights_path=Path(a.weights) if a.weights else None, light_index=a.light_index,
                        diffusion=Path(a.diffusion) if a.diffusion else None,
                        blend=Path(a.blend) if a.blend else None, blend_k=a.blend_k,
                        weighting=a.blend_weights, model_share=a.model_share,
                        correction=Path(a.correction) if a.correction else None,
                        outside_region=a.outside_region,
                        scalar=a.scalar, phong=a.phong, step=a.step, skip=not a.no_skip)


def run_render(a: argparse.Namespace) -> dict:
    """`view`'s render settings: the run's `render` section for the results folder's scene (`--configfile` and
    the scene file, as the workflow merges them), under --kernel; the package defaults where there is no run
    config for it (said in one line)."""
    from diffshadow.config import ConfigError, load_run, scene_config

    render = {}
    if a.configfile is not None and not Path(a.configfile).is_file():  # named, not defaulted: a mistyped path
        raise ConfigError(f"--configfile {a.configfile}: no such file (the run's config, e.g. config/config.yaml)")
    if a.results is not None and (Path(a.results) / "volume.zarr").exists():  # else the viewer's error alone
        scene = Path(a.results).name
        try:
            render = scene_config(load_run(a.configfile or "config/config.yaml"), scene,
                                  scenes_dir=Path(a.scenes_dir))["render"]
        except ConfigError as e:
            print(f"view: no run config for scene {scene!r} ({e}): the package's render defaults", file=sys.stderr)
    return {**render, **network_flags(a)}


def _view(a: argparse.Namespace):
    from diffshadow.viewer import serve

    if (a.results is None) == (a.scene_config is None):
        raise ValueError("view: give a results folder (results/<scene>) or --scene-config, not both")
    render = run_render(a)
    serve(results=Path(a.results) if a.results else None,
          scene_config=Path(a.scene_config) if a.scene_config else None, device=_device(a), host=a.host,
          port=a.port, size=a.size, step=a.step if a.step is not None else render.get("step", 0.5), render=render,
          record=Path(a.record) if a.record else None)


def _report_figures(a: argparse.Namespace):
    from diffshadow.report import scene_figures

    scene_figures(Path(a.weights), Path(a.generated), Path(a.lights), Path(a.images), Path(a.voxel_metrics),
                  Path(a.shadow_bench), _cfg(a), Path(a.out_dir))


def _stage_costs(a: argparse.Namespace):
    from diffshadow.io import require_png
    from diffshadow.report import critical_path, job_spans, mixed_runtimes, stage_costs, timeline_figure

    if a.timeline:  # before the table
        require_png(a.timeline, "--timeline", "figure")
    benchmarks = [Path(b) for b in a.benchmarks]
    jobs, gaps = job_spans(benchmarks)  # read once: the table's critical path, the chain printed, the timeline
    rows = stage_costs(benchmarks, Path(a.out), jobs)
    print(f"critical path, {rows[-1]['critical_s']:.1f} s: "
          + " -> ".join(f"{j['job']} {j['end'] - j['start']:.1f} s" for j in critical_path(jobs)))
    if a.timeline:
        timeline_figure(jobs, gaps, Path(a.timeline), f"{len(jobs)} jobs, {rows[-1]['wall_s']:.0f} s with a job "
                                                      f"running, {rows[-2]['wall_s']:.0f} s summed over them")
    for warning in mixed_runtimes(benchmarks):
        print(warning, file=sys.stderr)


def _summary(a: argparse.Namespace):
    from diffshadow.summary import write_summary

    out = Path(a.out_dir)
    write_summary(Path(a.results), a.scene, out / "summary.html", out / "landing.rst")
    print(f"wrote {out / 'summary.html'} and {out / 'landing.rst'}")


# ------------------------------------------------------------------------------------------- tools


def _parsl_fit(a: argparse.Namespace):
    from diffshadow.parsl_fit import fit_pending

    fit_pending(Path(a.config), Path(a.configfile), a.scenes, Path(a.results), threads=a.threads)


def _pbs_status(a: argparse.Namespace):
    from diffshadow.hpc import pbs_status

    print(pbs_status(a.job))  # Snakemake's cluster-generic status command: always exit 0


def _install_profiles(a: argparse.Namespace):
    from diffshadow.hpc import config_home, install_profiles

    root = Path(a.target) if a.target else config_home() / "snakemake"
    for path in install_profiles(Path(a.source), root, force=a.force):
        print(f"profile {path.name}: {path} -> {path.resolve()}")


# ------------------------------------------------------------------------------------------- parser


def _blend_args(p: argparse.ArgumentParser, evaluate: dict, *, used: str = "") -> None:
    p.add_argument("--blend-weights", choices=["triangle", "inverse-angle"], default=evaluate["blend_weights"],
                   help=f"{used}how a light's stored SIRENs are blended: the corners of its Delaunay triangle, or the "
                   "--blend-k nearest (evaluate.blend_weights)")
    p.add_argument("--blend-k", type=at_least(1), default=evaluate["blend_k"],
                   help="with --blend-weights inverse-angle: stored SIRENs blended per light (evaluate.blend_k)")


def _correction_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--correction", help="fit-correction's correction.pt: the blend is corrected by it (none: the "
                   "plain blend)")


# the commands that only score SIRENs: --device is where (evaluate.device)
SCORED = ("the SIRENs evaluated for their PSNR on --device (the workflow passes --device cpu unless evaluate.device "
          "is run)")


def build_parser() -> argparse.ArgumentParser:
    from diffshadow.bench.cli import add_bench_parsers

    parser = argparse.ArgumentParser(prog="diffshadow", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"diffshadow {__version__}")
    parser.add_argument("--phases", metavar="FILE", help="write where this process's time went (import, device, "
                        "compile, io, compute seconds) as JSON to FILE; the workflow puts it beside each job's "
                        "benchmark file")
    sub = parser.add_subparsers(dest="command", required=True)
    evaluate = defaults()["evaluate"]  # the evaluation's package defaults (the workflow passes the run's)

    p = _add(sub, "lights", _lights, "training and unseen light directions as JSON", device=False)
    p.add_argument("--sphere", type=int, required=True, help="points on the Fibonacci sphere (paper: 8000)")
    p.add_argument("--count", type=int, required=True, help="training directions kept (paper: 2000)")
    p.add_argument("--center", type=float, nargs=3, required=True, metavar=("X", "Y", "Z"))
    p.add_argument("--unseen", type=int, required=True, help="held-out directions (paper: 500)")
    p.add_argument("--seed", type=seed, default=0)
    p.add_argument("--layout", choices=LAYOUTS, default=LAYOUTS[0], help="cap: the region of the Fibonacci "
                   "sphere (the paper's); rim: its outer shell moved onto the region's edge (lights.layout)")
    _add(sub, "prepare-volume", _prepare_volume, "normalised grid + TF as Zarr", device=False,
         config='{"volume": PATH, "load": {...}, "transfer_function": {...}}')
    _add(sub, "preoptimize", _preoptimize, "fit the shared initial SIREN on light 0", "volume", "lights",
         config='{"siren": ..., "fit": ..., "preoptimize": ...}')
    p = _add(sub, "fit-siren", _fit_siren, "fit one subset of SIRENs jointly", "volume", "lights", "init",
             config='{"siren": ..., "fit": ..., "subset_size": N}')
    p.add_argument("--subset", type=int, required=True)
    p = _add(sub, "collect-weights", _collect_weights, "merge subset files into the Zarr weight store", "lights",
             device=False)
    p.add_argument("--subsets", nargs="+", required=True)
    _add(sub, "presample", _presample, "points and true shadow per training light (geometry loss)",
         "volume", "lights", config='{"diffusion": {...}}')
    _add(sub, "train-diffusion", _train_diffusion, "train the weight-space diffusion model (geometry loss)",
         "weights", "points", config='{"diffusion": {...}}')
    p = _add(sub, "finetune-render", _finetune_render, "rendering-loss fine-tuning (under torchrun for DDP)",
             "checkpoint", "weights", "points", "targets", "metrics", config='{"finetune": {...}}')
    p.add_argument("--volume", help="the prepared volume: validation lights choose the model kept")
    p.add_argument("--lights", help="the light sets (with --volume): validation lights are drawn in their cap")
    p = _add(sub, "ddp-processes", _ddp_processes, "how many DDP processes to launch here (prints a number)",
             out=False)
    p.add_argument("--nproc", type=at_least(1), required=True, help="processes asked for (finetune.nproc)")
    # torchrun's own options pass through untouched ("-" is not this parser's prefix)
    p = sub.add_parser("torchrun", prefix_chars="+", add_help=False,
                       help="torchrun with its own arguments, ending in one line where a rank fails (the workflow's "
                       "DDP launcher; `diffshadow torchrun --help` is torchrun's)")
    p.add_argument("torchrun_args", nargs=argparse.REMAINDER)
    p.set_defaults(func=_torchrun)
    p = _add(sub, "eval-truth", _eval_truth, "evaluation points and the exact shadow of every light at them "
             "(the workflow passes --device cpu unless evaluate.device is run)", "volume", "lights")
    p.add_argument("--eval-points", type=at_least(1), default=evaluate["points"], help="points per set (box, visible; "
                   "evaluate.points)")
    p.add_argument("--seed", type=seed, default=evaluate["seed"], help="their random draw (evaluate.seed)")
    mix = defaults()["mix"]
    p = _add(sub, "sample-shadows", _sample_shadows, "generate SIRENs for every training and unseen light, mixed "
             "with the stored SIRENs' weight blend (mix.model_share)", "checkpoint", "truth", "lights")
    p.add_argument("--weights", help="stage 1's stored SIRENs (weights.zarr): the blend a model share under 1 mixes in")
    p.add_argument("--volume", help="the prepared volume: the validation lights' exact shadows (--model-share auto)")
    _correction_arg(p)
    p.add_argument("--model-share", default="1",
                   help="auto (chosen on validation lights, with --weights and --volume) or 0..1 (with --weights); "
                   "default 1: the model alone, as before the mix (the workflow passes mix.model_share)")
    _blend_args(p, evaluate)
    p.add_argument("--val-lights", type=at_least(1), default=mix["val_lights"], help="mix.val_lights")
    p.add_argument("--val-points", type=at_least(1), default=mix["val_points"], help="mix.val_points")
    p.add_argument("--seed", type=seed, default=mix["seed"], help="their random draw (mix.seed)")
    p.add_argument("--score-on", choices=("cpu", "run"), default="cpu",
                   help="where the SIRENs are evaluated for their PSNR: cpu (default), or run: --device (the workflow "
                   "passes run under evaluate.device: run)")
    auto = defaults()["cache_auto"]
    p = _add(sub, "choose-cache", _choose_cache, "cache: auto: the smallest stored-SIREN cache whose blend reaches "
             "the target on validation lights, else diffusion (cache_choice.json); " + SCORED, "weights", "truth",
             "volume", "lights")
    _blend_args(p, evaluate)
    p.add_argument("--target-psnr", type=float, default=auto["target_psnr"],
                   help="dB, median voxel PSNR on the validation lights (cache_auto.target_psnr)")
    p.add_argument("--tolerance", type=at_least(0, float), default=auto["tolerance"],
                   help="dB a cache may lie under the best candidate (cache_auto.tolerance)")
    p.add_argument("--val-lights", type=at_least(1), default=auto["val_lights"], help="cache_auto.val_lights")
    p.add_argument("--val-points", type=at_least(1), default=auto["val_points"], help="cache_auto.val_points")
    p.add_argument("--seed", type=seed, default=auto["seed"], help="their random draw (cache_auto.seed)")
    p.add_argument("--candidates", nargs="+", default=auto["candidates"],
                   help="blend, fp16, bf16, basis-<k> (cache_auto.candidates)")
    p = _add(sub, "fit-correction", _fit_correction, "the blend's correction: an MLP of the light direction that "
             "corrects the stored SIRENs' blend between the training lights (correction.pt)", "weights", "volume",
             "lights", config='{"correction": {...}}')
    _blend_args(p, evaluate)
    p = _add(sub, "encode-cache", _encode_cache, "a codec's cache: the stored SIRENs through fp16, bf16 or "
             "basis-<k>, written decoded as a weight store; " + SCORED, "weights", "truth", "lights", "codec")
    p = _add(sub, "blend-shadows", _blend_shadows, "cache: blend: every training light's stored SIREN and every "
             "unseen light's weight blend of the nearest, as sample-shadows' store; " + SCORED, "weights", "truth",
             "lights")
    _blend_args(p, evaluate)
    _correction_arg(p)
    p = _add(sub, "evaluate-voxels", _evaluate_voxels, "voxel PSNR of generated SIRENs, baselines, storage, the "
             "samplers' timing; the samplers and the SIRENs' evaluation on --device (the workflow passes --device cpu "
             "unless evaluate.device is run), the PSNRs on the CPU",
             "weights", "generated", "truth", "volume", "lights")
    p.add_argument("--checkpoint", help="the diffusion checkpoint that sampled --generated (none: cache: blend)")
    _blend_args(p, evaluate)
    p.add_argument("--ddpm-lights", type=at_least(0), default=evaluate["ddpm_lights"],
                   help="training lights sampled with 500-step DDPM too (evaluate.ddpm_lights)")
    p.add_argument("--geometry-checkpoint", help="the model before fine-tuning: unseen lights before and after")
    p.add_argument("--wide-lights", type=at_least(0), default=evaluate["wide_lights"],
                   help="further test lights the cache's answer, the weight blend and the model alone are compared on "
                   "(evaluate.wide_lights; 0: none)")
    p.add_argument("--wide-points", type=at_least(1), default=evaluate["wide_points"],
                   help="box points per further test light (evaluate.wide_points)")
    p.add_argument("--seed", type=seed, default=evaluate["seed"], help="the further test lights' draw (evaluate.seed)")
    p.add_argument("--cache-weights", help="a codec's decoded store (encode-cache's cache.zarr) that --generated "
                   "blended: the further test lights' answer blends it (none: --weights)")
    _correction_arg(p)
    p = _add(sub, "caches", _caches, "caches.json: every cache (stored SIRENs and their codecs, the model, dense "
             "grids) as bytes against seen and unseen voxel PSNR; the model's fp16 DDIM (timed) and the SIRENs' "
             "evaluation on --device (the workflow passes --device cpu unless evaluate.device is run), the PSNRs on "
             "the CPU",
             "weights", "generated", "truth", "lights", "volume", "figure")
    p.add_argument("--checkpoint", help="the diffusion checkpoint (none: cache: blend, no model rows)")
    _blend_args(p, evaluate)
    _correction_arg(p)
    _add(sub, "train-data-inr", _train_data_inr, "fit the data INR (a SIREN of the scalar field)", "volume",
         config='{"data_inr": {...}}')
    _add(sub, "render-targets", _render_targets, "ground-truth images per training light and view", "volume",
         "lights", config='{"finetune": {...}}')
    p = _add(sub, "evaluate-images", _evaluate_images, "images and image metrics of every mode against gt",
             "volume", "lights", "data-inr", "weights", "images", config='{"render": {...}}')
    p.add_argument("--generated", help="stage 2's generated.zarr (optional)")
    p.add_argument("--naive", help="naive-images' naive_images.zarr (optional: else the naive images are rendered "
                   "here)")
    _add(sub, "naive-images", _naive_images, "the naive baseline's images for evaluate-images (naive_images.zarr)",
         "volume", "lights", "data-inr", config='{"render": {...}}')
    p = _add(sub, "render", _render, "render one image (PNG) in a shading mode")
    p.add_argument("--volume", help="results/<scene>/volume.zarr, or a raw volume file with --tf-json")
    p.add_argument("--scene-config", help="a scene file (config/scenes/<scene>.yaml): preview its volume and "
                   "transfer function before a run")
    p.add_argument("--tf-json", help="transfer function, as JSON or a JSON file: needed with a raw --volume file; "
                   "with a volume.zarr, in place of its own (a cache of the run still shades it where the opacity "
                   "is the same)")
    p.add_argument("--mode", choices=["noshadow", "gt", "inr", "naive"], default="gt")
    p.add_argument("--scalar", choices=["grid", "inr"], default=None, help="default: inr when --data-inr")
    for name, helptext in (("data-inr", "data_inr.pt (needed for --scalar inr and mode naive)"),
                           ("weights", "weight store for mode inr (weights.zarr or generated.zarr)")):
        p.add_argument(f"--{name}", help=helptext)
    p.add_argument("--light-index", type=int, default=0, help="row of --weights (its light is used)")
    p.add_argument("--diffusion", help="mode inr: a diffusion checkpoint (results/<scene>/diffusion.ckpt) that "
                   "generates the shadow SIREN of --light now, as the viewer does for a new direction")
    p.add_argument("--blend", help="mode inr, cache: blend: a weight store (results/<scene>/weights.zarr) whose "
                   "nearest SIRENs to --light are blended, as the viewer does for a new direction")
    _blend_args(p, evaluate, used="with --blend (the run's, in generated.zarr's config): ")
    p.add_argument("--correction", help="with --blend: fit-correction's correction.pt, as the run corrected its blend "
                   "(generated.zarr's config, correction)")
    p.add_argument("--model-share", type=float, help="with --diffusion and --blend: the model's share of the SIREN "
                   "beside the blend's, as the run mixed them (generated.zarr's config, mix.model_share)")
    p.add_argument("--light", type=float, nargs=3, metavar=("X", "Y", "Z"), help="toward the light")
    p.add_argument("--outside-region", action="store_true", help="with --diffusion or --blend: draw the cache's "
                   "answer for a light outside the region it was trained for (refused otherwise, exit code 2)")
    p.add_argument("--phong", action="store_true", help="Blinn-Phong lighting from the field's gradient")
    for name, value in (("azimuth", 30.0), ("elevation", 25.0), ("fov", 60.0), ("step", 0.5)):
        p.add_argument(f"--{name}", type=float, default=value)
    p.add_argument("--distance", type=float, help="the orbit camera's distance from the box centre in box "
                   "half-diagonals (default: the view that frames the visible part of the volume)")
    for name in ("eye", "target"):
        p.add_argument(f"--{name}", type=float, nargs=3, metavar=("X", "Y", "Z"),
                       help="a free camera in box coordinates (instead of --azimuth/--elevation/--distance)")
    p.add_argument("--up", type=float, nargs=3, metavar=("X", "Y", "Z"),
                   help="the free camera's up direction (default: +z; +y looking along z)")
    p.add_argument("--size", type=int, nargs="+", default=[128], help="image size: N (square) or W H")
    p.add_argument("--no-skip", action="store_true", help="turn macro-cell skipping off")
    add_networks(p)
    p = _add(sub, "view", _view, "an interactive viewer in the browser: move the light, see the cached shadow",
             out=False)
    p.add_argument("results", nargs="?", help="a finished scene's results folder (results/<scene>)")
    p.add_argument("--scene-config", help="a scene file, before any run: modes noshadow and gt only")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1: this machine "
                   "only; on ALCF forward it with ssh -L, see the README)")
    p.add_argument("--port", type=int, default=8080)
    p.add_argument("--size", type=int, default=0, help="image height in pixels when still (default 0: the "
                   "canvas's own, sharp at any window size; a panel control)")
    p.add_argument("--step", type=float, help="marching step in voxels (a panel control; default: the run's "
                   "render.step)")
    p.add_argument("--configfile", help="the run's config, whose render section "
                   "(the kernel, the step) the viewer uses for a results folder (default: config/config.yaml)")
    p.add_argument("--scenes-dir", default="config/scenes")
    p.add_argument("--record", help="a folder where every still frame is written (PNG, and JSON with its render "
                   "command) and every frame's cost is logged (frames.jsonl)")
    add_networks(p)
    p = _add(sub, "report-figures", _report_figures, "the report's figures for one finished scene", "weights",
             "generated", "lights", "images", "voxel-metrics", "shadow-bench", "out-dir",
             out=False, device=False, config="the scene's merged configuration")

    p = sub.add_parser("stage-costs", help="a table of every rule's cost from Snakemake's benchmark files")
    p.add_argument("--benchmarks", nargs="+", required=True, help="results/<scene>/benchmarks/*.tsv")
    p.add_argument("--out", required=True)
    p.add_argument("--timeline", help="also draw every job over the run's time as this PNG")
    p.set_defaults(func=_stage_costs)
    p = _add(sub, "summary", _summary, "one finished scene's headline numbers and tables (the report's front page)",
             "results", "scene", "out-dir", out=False, device=False)
    add_bench_parsers(sub)
    p = sub.add_parser("parsl-fit", help="fit every pending fit_siren subset through Parsl (one big allocation)")
    for name, default, helptext in (("config", "config/parsl/local.py", "Parsl config file (config/parsl/*.py)"),
                                    ("configfile", "config/config.yaml", "the workflow's config file"),
                                    ("results", "results", None)):
        p.add_argument(f"--{name}", default=default, help=helptext)
    p.add_argument("--scenes", nargs="*", help="default: the config's scenes")
    p.add_argument("--threads", type=at_least(1), default=1, help="torch threads per worker")
    p.set_defaults(func=_parsl_fit)
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
            "fit-correction", "evaluate-voxels", "caches", "render-targets", "evaluate-images", "render"}


# subcommands that never touch torch: importing it (~1 s on a CPU, seconds with a CUDA build) would be most of
# their run; lights, prepare-volume and collect-weights are workflow jobs, stage-costs, summary and report-figures
# sit on every run's last stretch, pbs-status in the scheduler's polling loop, ddp-processes before
# finetune_render (it imports torch only where a GPU may be); tests/test_cli.py and tests/test_hpc.py check they
# start without torch
_NO_TORCH = {"lights", "prepare-volume", "collect-weights", "stage-costs", "summary", "pbs-status",
             "install-profiles", "ddp-processes", "report-figures"}


def _warning_line(command: str) -> Callable[..., None]:
    """`warnings.showwarning` for a command: one line, `diffshadow <command>: warning: <message>`, like its errors
    (Python's own format adds the source line that warned, which reads as a fragment of a traceback). A warning
    from outside the package keeps its category and origin, for whoever reports it."""
    package = Path(__file__).resolve().parent

    def show(message: Warning | str, category: type[Warning], filename: str, lineno: int,
             file: TextIO | None = None, line: str | None = None) -> None:
        origin = "" if Path(filename).resolve().is_relative_to(package) else \
            f" ({category.__name__} at {filename}:{lineno})"
        print(f"diffshadow {command}: warning: {message}{origin}", file=file or sys.stderr)

    return show


def _unchecked(e: BaseException) -> str:
    """"" where `e` was raised in this package's own code (an input checked and named there); else where in this
    package the library that raised it was called, for a report: numpy's "kth(=3) out of bounds (3)" once reached
    the user as if it were their error, with nothing to say where it came from."""
    package = Path(__file__).resolve().parent
    ours, tb = None, e.__traceback__
    while tb is not None:
        if Path(tb.tb_frame.f_code.co_filename).resolve().is_relative_to(package):
            ours = tb
        last, tb = tb, tb.tb_next
    if ours is None or ours is last:
        return ""
    where = Path(ours.tb_frame.f_code.co_filename).resolve().relative_to(package.parent)
    return (f" (raised inside {last.tb_frame.f_globals.get('__name__', '?').split('.')[0]}, called at "
            f"{where.as_posix()}:{ours.tb_lineno}: an input diffshadow does not check yet; please report it)")


def _lost_a_peer(e: RuntimeError) -> bool:
    """Whether `e` is a DDP collective's failure: a torch.distributed error, or (gloo's "Connection closed by peer"
    is a plain RuntimeError) one raised inside torch.distributed."""
    import traceback

    dist = sys.modules.get("torch.distributed")
    if dist is None or int(os.environ.get("WORLD_SIZE", "1")) < 2:  # no peer to lose
        return False
    if isinstance(e, dist.DistError):
        return True
    frames = traceback.extract_tb(e.__traceback__)
    return bool(frames) and f"{os.sep}torch{os.sep}distributed{os.sep}" in frames[-1].filename


_NO_ROOM = (errno.ENOSPC, errno.EDQUOT)  # a full disk, a full quota (an ALCF project's on /eagle)

def _out_of_memory(e: BaseException) -> str | None:
    """torch's or numpy's message where `e` is an allocation that failed (a GPU's, the CPU allocator's, a numpy
    array's), cut before CUDA's advice on its allocator's settings; else None."""
    if isinstance(e, MemoryError):
        return str(e) or "MemoryError"
    text = str(e).strip()  # torch's OutOfMemoryError (CUDA, HIP, MPS) says "out of memory", its CPU allocator this
    if "can't allocate memory" not in text and "out of memory" not in text.lower():
        return None
    text = text.splitlines()[0]
    text = text.split("] err == 0. ")[-1]  # the CPU allocator's "[enforce fail at alloc_cpu.cpp:N]" prefix
    for advice in (" Including non-PyTorch memory", " Of the allocated memory", " If reserved"):
        text = text.split(advice)[0]
    return text.strip()


def main(argv: list[str] | None = None) -> None:
    from diffshadow import phases

    args = build_parser().parse_args(argv)
    # a rule pipes the output through `tee`: without line buffering its progress would arrive at the end
    if hasattr(sys.stdout, "reconfigure"):
        sys.stdout.reconfigure(line_buffering=True)
    warnings.showwarning = _warning_line(args.command)
    try:
        if args.command not in _NO_TORCH and args.command != "torchrun":  # the ranks set up their own
            import torch  # noqa: F401  (here, so that its import is timed as such, not as the stage's compute)

            from diffshadow.runtime import claim_gpu_lock, keep_freed_memory, set_threads, vector_unit_warning

            keep_freed_memory()
            if warning := vector_unit_warning():
                print(warning, file=sys.stderr)
            if args.command in _ONE_GPU:
                claim_gpu_lock(args.command)
            if args.command not in ("finetune-render", "parsl-fit"):  # threads per rank and per worker: set there
                set_threads(getattr(args, "threads", 0))
        phases.mark_imports_done()
        args.func(args)
    except ValueError as e:  # the library's input errors: one line, no traceback
        print(f"diffshadow {args.command}: error: {e}{_unchecked(e)}", file=sys.stderr)
        raise SystemExit(2) from None
    except (MemoryError, RuntimeError) as e:
        if (reason := _out_of_memory(e)) is not None:  # a size too large for the machine: which keys set it
            lower = memory_keys(args.command)
            print(f"diffshadow {args.command}: error: out of memory ({reason}); lower {lower}, or run it where "
                  f"there is more memory (a profile's mem_mb, a larger GPU); no earlier output was replaced",
                  file=sys.stderr)
            raise SystemExit(1) from None
        # a process of a DDP job whose peer stopped: one line, not a traceback from the collective it waited in
        # (each of a node's four ranks printed ~25 lines around the one line of the process that failed first)
        if not _lost_a_peer(e):
            raise
        reason = (str(e).strip().splitlines() or [type(e).__name__])[0]
        print(f"diffshadow {args.command}: rank {os.environ.get('RANK', '0')}: error: the job's processes lost "
              f"touch ({reason}); a process that stopped first says why", file=sys.stderr)
        raise SystemExit(1) from None
    except Stopped as e:  # a loop's signal (a PBS walltime or preemption, Ctrl-C) answered with its checkpoint
        if os.environ.get("RANK", "0") == "0":  # a DDP job's ranks stop together: one line for them all
            _say(f"diffshadow {args.command}: {e}")
        raise SystemExit(128 + e.signum) from None
    except KeyboardInterrupt:  # Ctrl-C outside a training loop (a rule's `tee` ignores it: the line reaches its log)
        again = ("resumes from its last checkpoint" if args.command in RESUMABLE else
                 "starts from the beginning (it keeps no checkpoint)")
        print(f"diffshadow {args.command}: interrupted; no earlier output was replaced, and run again it {again}",
              file=sys.stderr)
        raise SystemExit(130) from None
    except OSError as e:  # a path given that cannot be read or written: the path and why, in one line
        if e.filename is None:
            raise
        where, why = e.filename, e.strerror
        if isinstance(e, (FileExistsError, NotADirectoryError)):  # an output's folder, or a path through, is a file
            from diffshadow.io import file_in_the_way

            blocking = file_in_the_way(e.filename)
            if blocking is not None:
                where, why = blocking, "a file, where a folder is needed"
        if e.errno in _NO_ROOM:  # written beside its output and renamed over it only once whole (io.atomic_path)
            why += ": free space (or quota) there and run it again; no earlier output was replaced"
        print(f"diffshadow {args.command}: error: {where}: {why}", file=sys.stderr)
        raise SystemExit(2) from None
    if args.phases and os.environ.get("RANK", "0") == "0":  # under torchrun: rank 0's clock
        import json

        from diffshadow.io import atomic_write_text

        atomic_write_text(args.phases, json.dumps(phases.record(args.command), indent=1) + "\n")


def run() -> None:
    """The `diffshadow` command (and `python -m diffshadow.cli`, as under torchrun): `main`, then the process's end.
    After a command that imported PyTorch has succeeded, the process ends at once instead of through Python's
    teardown: every output is written, flushed and renamed into place by then, and the teardown (a last garbage
    collection over PyTorch's objects, its thread pools, CUDA's context) took 0.5-0.7 s a job on a 2-core machine,
    in a run of 16 such jobs (b27925d; docs/performance.md, "The default run": the run's launch 19.3 → 5.4 s). A
    command that failed with its one line (`main`'s handlers, argparse's usage) ends there too: the teardown would
    print the leftovers of what it was doing (zarr's chunk reads still pending after one failed, ~35 lines of
    asyncio warnings and a traceback). An unexpected error
    keeps its traceback, and a run under coverage, which writes its data at exit, exits the normal way. Tests call
    `main`, which returns."""
    fast = "coverage" not in sys.modules
    try:
        main()
    except SystemExit as e:
        if not fast:
            raise
        code = e.code
        if code is not None and not isinstance(code, int):  # sys.exit("why"): Python would print it, then exit 1
            print(code, file=sys.stderr)
            code = 1
        _end(code or 0)
    if "torch" in sys.modules and fast:
        _end(0)


def _say(line: str) -> None:
    """`line` on stderr, where it may no longer go: a pipe's reader (a `tee` of one's own; the rules' ignores the
    signal, hpc.JOB_LOG) that the same signal ended."""
    try:
        print(line, file=sys.stderr, flush=True)
    except OSError:
        pass


def _end(code: int) -> None:
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except OSError:  # a reader gone (`tee` ended by the signal that stopped this command)
            pass
    os._exit(code)


if __name__ == "__main__":
    run()
