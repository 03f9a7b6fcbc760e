"""`diffshadow parsl-fit`: every pending `fit_siren` subset in one Parsl run (e.g. one ≥10-node Polaris
`prod` job), writing exactly the files the rule writes, so Snakemake then counts them as done.

The work per subset is the stage function the rule's command calls (`stages.stage1.fit_subset`), in a
Parsl worker; the log goes where the rule's `tee` would put it. The caller names every path. Under `fit.rounds`
a subset runs after the pending subsets whose SIRENs it holds (`waves`), as Snakemake orders them.
"""

from __future__ import annotations

import json
import runpy
from collections.abc import Callable
from pathlib import Path


def fit_task(paths: dict[str, str], subset: int, cfg: dict, device: str | None, threads: int, log_path: str) -> str:
    """Run in a Parsl worker: one subset's fit, stdout and stderr to `log_path`; returns the file written."""
    import contextlib
    import os
    import time

    from diffshadow.fit import FitConfig
    from diffshadow.phases import usage
    from diffshadow.runtime import resolve_device, set_threads
    from diffshadow.siren import SirenConfig
    from diffshadow.stages.stage1 import fit_subset

    Path(log_path).parent.mkdir(parents=True, exist_ok=True)
    start, before = time.perf_counter(), usage()
    with open(log_path, "w") as log, contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
        print(f"parsl worker pid {os.getpid()}, CUDA_VISIBLE_DEVICES={os.environ.get('CUDA_VISIBLE_DEVICES')}")
        set_threads(threads)
        fit_subset(Path(paths["volume"]), Path(paths["lights"]), Path(paths["init"]), subset, Path(paths["out"]),
                   siren=SirenConfig.from_config(cfg["siren"]), fit=FitConfig.from_config(cfg["fit"]),
                   subset_size=int(cfg["subset_size"]), config=cfg, device=resolve_device(None, device))
    if paths.get("benchmark"):
        after = usage()
        write_benchmark(Path(paths["benchmark"]), time.perf_counter() - start, after["cpu_s"] - before["cpu_s"],
                        after["max_rss_mib"])
    return paths["out"]


def write_benchmark(path: Path, wall_s: float, cpu_s: float, max_rss_mib: float) -> None:
    """The rule's `benchmark:` file, in Snakemake's columns (those it cannot know here are NA), so the
    stage-cost table counts subsets fitted through Parsl too. max_rss is the worker's peak so far."""
    from diffshadow.io import atomic_write_text

    h, rest = divmod(int(wall_s), 3600)
    atomic_write_text(path, "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"
                      f"{wall_s:.4f}\t{h}:{rest // 60:02d}:{rest % 60:02d}\t{max_rss_mib:.2f}\tNA\tNA\tNA\tNA\tNA\tNA"
                      f"\t{cpu_s:.2f}\n")


def pending(results: Path, scene: str, n_subsets: int) -> list[int]:
    return [i for i in range(n_subsets) if not (results / scene / "sirens" / f"subset_{i}.npz").exists()]


def waves(jobs: list[dict]) -> list[list[dict]]:
    """The jobs in waves: a job whose held subsets (`fit.rounds`, `paths["held"]`) are written by other jobs runs in
    a wave after theirs; the rest in the first."""
    by_out = {job["paths"]["out"]: job for job in jobs}
    wave: dict[str, int] = {}

    def of(job: dict) -> int:
        out = job["paths"]["out"]
        if out not in wave:
            wave[out] = 1 + max((of(by_out[p]) for p in job["paths"].get("held", []) if p in by_out), default=-1)
        return wave[out]

    out = [[] for _ in range(1 + max(map(of, jobs), default=-1))]
    for job in jobs:
        out[of(job)].append(job)
    return out


def run(parsl_config: Path, jobs: list[dict], log: Callable[[str], None] = print) -> list[str]:
    """Submit every job (`fit_task`'s keyword arguments) through the Parsl config file, wave by wave (`waves`);
    return the files."""
    import parsl
    from parsl import python_app

    cfg = runpy.run_path(str(parsl_config)).get("config")
    if cfg is None:
        raise ValueError(f"{parsl_config}: defines no `config` (a parsl.config.Config)")
    app = python_app(fit_task)
    parsl.load(cfg)
    try:
        done, failed = [], []
        for wave in waves(jobs):
            futures = [(job, app(**job)) for job in wave]
            for job, fut in futures:
                subset = job["subset"]
                try:
                    done.append(fut.result())
                    log(f"[parsl-fit] subset {subset}: wrote {done[-1]}")
                except Exception as e:  # noqa: BLE001 - report every failed subset, then fail once
                    failed.append(subset)
                    log(f"[parsl-fit] subset {subset}: FAILED ({type(e).__name__}: {e})")
            if failed:  # a later wave holds some of these subsets' SIRENs
                break
        if failed:
            raise RuntimeError(f"parsl-fit: subsets {failed} failed; rerun `diffshadow parsl-fit` (finished subsets "
                               f"are skipped) or `snakemake -f results/<scene>/sirens/subset_N.npz`")
        return done
    finally:
        parsl.dfk().cleanup()


def fit_pending(parsl_config: Path, configfile: Path, scenes: list[str] | None, results: Path, *,
                threads: int = 1, log: Callable[[str], None] = print) -> None:
    """Every subset of `scenes` (default: the config's) whose file under `results` is missing."""
    from diffshadow.config import load_run, scene_config, stage1_json
    from diffshadow.lights import n_subsets
    from diffshadow.seams import subset_inputs

    if not parsl_config.is_file():  # before any scene is read: with nothing pending it would go unnoticed
        raise ValueError(f"--config {parsl_config}: no such Parsl config file (config/parsl/local.py or polaris.py)")
    run_cfg = load_run(configfile)
    jobs = []
    for scene in scenes or run_cfg["scenes"]:
        cfg = scene_config(run_cfg, scene, scenes_dir=configfile.parent / "scenes")
        base = results / scene
        paths = {"volume": base / "volume.zarr", "lights": base / "lights.json", "init": base / "siren_init.pt"}
        for path in paths.values():
            if not path.exists():
                raise ValueError(f"{path} is missing: run `snakemake --profile local -j2 --until preoptimize` "
                                 f"(or your HPC profile) first")
        n = n_subsets(cfg["lights"]["count"], cfg["subset_size"])
        todo = pending(results, scene, n)
        log(f"[parsl-fit] {scene}: {len(todo)} of {n} subsets pending")
        # the sections as the rule's --config-json gives them (keys sorted, settings at their old behaviour left
        # out): the subset file records them, and should hold the same bytes whichever way it was fitted
        sel = json.loads(stage1_json(cfg, "siren", "fit", "subset_size"))
        _, held = subset_inputs(cfg)
        jobs += [{"paths": {**{k: str(v) for k, v in paths.items()}, "out": str(base / "sirens" / f"subset_{i}.npz"),
                            "benchmark": str(base / "benchmarks" / f"fit_siren_{i}.tsv"),
                            "held": [str(base / "sirens" / f"subset_{s}.npz") for s in held[i]]},
                  "subset": i, "cfg": sel, "device": run_cfg.get("device"), "threads": threads,
                  "log_path": str(base / "logs" / f"fit_siren_{i}.log")} for i in todo]
    if jobs:
        run(parsl_config, jobs, log=log)
    log(f"[parsl-fit] done: {len(jobs)} subsets fitted")
