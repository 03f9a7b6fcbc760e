"""The `diffshadow bench ...` and `check-store` subcommands: parse and dispatch."""

from __future__ import annotations

import argparse
from pathlib import Path

from diffshadow.argparsing import add_networks, at_least, network_flags
from diffshadow.argparsing import add_subcommand as _add
from diffshadow.argparsing import device_of as _device


def _out_folder(value: str) -> Path:
    """--out of a bench that writes several files: a folder, checked before the bench runs (minutes of timing
    are not lost to a name that cannot be written)."""
    path = Path(value)
    if path.exists() and not path.is_dir():
        raise ValueError(f"--out {value}: expected a folder for the bench's files, found a file")
    return path


def _out_file(value: str, default_name: str) -> Path:
    """--out of a bench that writes one JSON: the file, or a folder (an existing one, or a name ending in /)
    that receives `default_name`."""
    path = Path(value)
    if path.is_dir() or value.endswith("/"):
        path = path / default_name
    if path.exists() and not path.is_file():
        raise ValueError(f"--out {value}: {path} exists and is not a file")
    from diffshadow.io import file_in_the_way

    blocking = file_in_the_way(path.parent)
    if blocking is not None:
        raise ValueError(f"--out {value}: {blocking} is a file, not a folder")
    return path


def _bench_shadow(a):
    from diffshadow.bench import default_volumes
    from diffshadow.bench.shadow import bench_shadow

    volumes = [Path(v) for v in a.volumes] if a.volumes else default_volumes()
    bench_shadow(volumes, _out_folder(a.out), device=_device(a))


def _bench_siren(a):
    from diffshadow.bench.siren import bench_siren

    bench_siren(_out_folder(a.out), k=a.k, points=a.points, widths=a.widths, device=_device(a))


def _bench_init_spread(a):
    from diffshadow.bench.siren import bench_init_spread

    bench_init_spread(Path(a.results), _out_folder(a.out), n_lights=a.lights)


def _bench_render(a):
    from diffshadow.bench.render import run
    from diffshadow.config import parse_json

    run(_out_file(a.out, "bench_render.json"), scene_config=a.scene_config, volume=a.volume, data_inr=a.data_inr,
        inr_steps=a.inr_steps,
        tf_config=parse_json(a.tf_json, "--tf-json") if a.tf_json else None, weights=a.weights,
        light_index=a.light_index, siren_width=a.siren_width, siren_steps=a.siren_steps, sizes=a.sizes,
        step=a.step, repeats=a.repeats, memory_sizes=a.memory_sizes, render=network_flags(a),
        naive_counts=a.naive_counts, device=_device(a))


def _bench_naive_counts(a):
    from diffshadow.bench.render import run_naive_counts

    run_naive_counts(_out_file(a.out, "bench_naive.json"), volume=Path(a.volume), data_inr=Path(a.data_inr),
                     lights=Path(a.lights), size=a.size, step=a.step, render=network_flags(a), device=_device(a))


def _bench_kernels(a):
    from diffshadow.bench.kernels import KernelCompileError, bench_kernels

    try:
        bench_kernels(_out_file(a.out, "bench_kernels.json"), archs=a.arch)
    except KernelCompileError as e:
        raise SystemExit(f"bench kernels: {e}") from None


def _bench_stages(a):
    from diffshadow.bench.stages import bench_stages
    from diffshadow.config import ConfigError, load_run, scene_config

    out = _out_file(a.out, "bench_stages.json")
    if not Path(a.configfile).is_file():  # the default is relative: outside the repository it is not there
        raise ValueError(f"--configfile {a.configfile}: no such file (a run config; its scenes are read from "
                         f"--scenes-dir {a.scenes_dir}: run it in the repository's folder, or give both)")
    try:
        run = load_run(a.configfile)
        scene = a.scene or run["scenes"][0]
        cfg = scene_config(run, scene, scenes_dir=Path(a.scenes_dir))
    except ConfigError as e:
        raise ValueError(str(e)) from None
    bench_stages(cfg, out, device=_device(a), stages=a.stages, budget_s=a.budget, max_steps=a.max_steps,
                 config_name=f"{a.configfile or 'defaults'} (scene {scene})")


def _check_store(a):
    from diffshadow.io import check_stores, store_folders

    folders = store_folders([Path(p) for p in a.paths])
    for store in check_stores(folders):
        print(store)
    if a.psnr:
        from diffshadow.bench.siren import check_store

        for path, _ in folders:
            if path.suffix != ".zarr":
                result = check_store(path)
                if result["max_abs_diff_db"] > a.tolerance:
                    raise SystemExit(f"check-store: {path}: stored and recomputed PSNR differ by "
                                     f"{result['max_abs_diff_db']:.2f} dB (> {a.tolerance} dB)")


def add_bench_parsers(sub: argparse._SubParsersAction) -> None:
    bench = sub.add_parser("bench", help="benchmarks that print and save figures").add_subparsers(
        dest="bench", required=True)
    p = _add(bench, "shadow", _bench_shadow, "time vs error of the ground-truth shadow methods", out=False)
    p.add_argument("--volumes", nargs="*", help="volume files (default: bundled nucleon + ../shared/data)")
    p.add_argument("--out", default="bench", help="a folder for its JSON and figures")
    p = _add(bench, "siren", _bench_siren, "K SIRENs fitted jointly vs one after another", out=False)
    p.add_argument("--k", type=int, default=16)
    p.add_argument("--points", type=int, default=4096, help="points per SIREN per step")
    p.add_argument("--widths", type=int, nargs="+", default=[32, 64, 128])
    p.add_argument("--out", default="bench", help="a folder for its JSON and figures")
    p = _add(bench, "init-spread", _bench_init_spread, "weight spread: shared init vs random inits", out=False,
             device=False)
    p.add_argument("--results", default="results/nucleon", help="a finished scene's results folder")
    p.add_argument("--lights", type=int, default=8, help="lights to refit from random inits")
    p.add_argument("--out", default="bench", help="a folder for its JSON and figures")
    p = _add(bench, "render", _bench_render, "fps and memory of noshadow / inr / naive; skipping; step curve",
             out=False)
    for name, kind, default, helptext in (
            ("scene-config", str, None, "a scene YAML (volume, transfer_function)"),
            ("volume", str, None, "or prepare_volume's volume.zarr, or a raw file (--tf-json, else the bench TF)"),
            ("tf-json", str, None, "transfer function for a raw --volume, as JSON or a JSON file"),
            ("data-inr", str, None, "train_data_inr's data_inr.pt (default: fit one)"),
            ("inr-steps", at_least(1), None, "steps when fitting the data INR here (default: config's data_inr.steps)"),
            ("weights", str, None, "a weight store whose SIREN --light-index is the shadow INR (default: fit one)"),
            ("light-index", at_least(0), 0, None), ("siren-width", at_least(1), 32, None),
            ("siren-steps", at_least(1), 300, None),
            ("step", float, 0.5, "voxels"), ("repeats", int, 3, None), ("out", str, "bench/bench_render.json",
                                                     "a JSON file, or a folder for bench_render.json")):
        p.add_argument(f"--{name}", type=kind, default=default, help=helptext)
    p.add_argument("--sizes", type=at_least(1), nargs="+", default=[64, 128])  # refused before any fit or frame
    p.add_argument("--memory-sizes", type=at_least(1), nargs="*", default=None,
                   help="larger sides measured for peak memory only (default: 2x and 4x the largest size)")
    p.add_argument("--naive-counts", help="`bench naive-counts`' file: the naive frame's counts at the smallest "
                   "size, taken apart (default: counted here)")
    add_networks(p)
    p = _add(bench, "naive-counts", _bench_naive_counts, "ops, host syncs and peak memory of the naive frame that "
             "`bench render` counts at its smallest size, under the first training light (for --naive-counts)",
             out=False)
    p.add_argument("--volume", required=True, help="prepare_volume's volume.zarr")
    p.add_argument("--data-inr", required=True, help="train_data_inr's data_inr.pt")
    p.add_argument("--lights", required=True, help="lights.json")
    p.add_argument("--size", type=at_least(1), default=64, help="the frame's side (bench render's smallest size)")
    p.add_argument("--step", type=float, default=0.5, help="voxels")
    p.add_argument("--out", default="bench/bench_naive.json", help="a JSON file, or a folder for bench_naive.json")
    add_networks(p)
    p = _add(bench, "stages", _bench_stages, "per-step cost (time, ops, host syncs, memory) of every heavy stage at "
             "a config's sizes on synthetic inputs, projected to the config's steps, epochs and lights", out=False)
    p.add_argument("--configfile", default="config/config.yaml",
                   help="a run config over the defaults (e.g. config/paper.yaml; default: config/config.yaml)")
    p.add_argument("--scene", help="the scene whose file and volume to use (default: the config's first)")
    p.add_argument("--scenes-dir", default="config/scenes")
    p.add_argument("--stages", nargs="+", help="default: all (fit_siren preoptimize train_data_inr train_diffusion "
                   "fit_correction finetune_render sample_shadows eval_truth)")
    p.add_argument("--budget", type=at_least(0, float), default=2.0,
                   help="seconds of timed steps per stage (at least 2 steps)")
    p.add_argument("--max-steps", type=int, default=50, help="timed steps per stage at most")
    p.add_argument("--out", default="bench/bench_stages.json", help="a JSON file, or a folder for bench_stages.json")
    p = _add(bench, "kernels", _bench_kernels, "registers, spills, programs per SM and machine-code counts of the "
             "fused kernels, compiled for a GPU without one", out=False, device=False)
    p.add_argument("--arch", type=at_least(75), nargs="+", default=[80, 90],
                   help="CUDA compute capabilities, 75 and up (80: A100, 90: H100)")
    p.add_argument("--out", default="bench/bench_kernels.json", help="a JSON file, or a folder for bench_kernels.json")

    p = _add(sub, "check-store", _check_store, "verify Zarr stores against their checksums (a store, every "
             "store of a results folder, or of every scene in results/); --psnr also re-evaluates every stored SIREN",
             out=False, device=False)
    p.add_argument("paths", nargs="+", help="a .zarr store, a results folder (results/<scene>) or "
                   "results/ (every scene)")
    p.add_argument("--psnr", action="store_true", help="results folders: re-evaluate weights.zarr's SIRENs against "
                   "their stored PSNR")
    p.add_argument("--tolerance", type=at_least(0, float), default=0.5, help="dB")
