"""`diffshadow parsl-fit`: every pending `fit_siren` subset in one Parsl run (e.g. one ≥10-node Polaris
`prod` job), writing exactly the files the rule writes, so Snakemake then counts them as done.

The work per subset is the same CLI entry point the rule calls (`diffshadow fit-siren`), in a Parsl
worker; the log goes where the rule's `tee` would put it.
"""

from __future__ import annotations

import json
import runpy
from pathlib import Path


def fit_task(argv: list[str], log_path: str) -> str:
    """Run in a Parsl worker: `diffshadow fit-siren ARGV` with stdout and stderr to `log_path`."""
    import contextlib
    import os
    from pathlib import Path

    from diffshadow.cli import main

    Path(log_path).parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "w") as log, contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
        print(f"parsl worker pid {os.getpid()}, CUDA_VISIBLE_DEVICES={os.environ.get('CUDA_VISIBLE_DEVICES')}")
        main(argv)
    return argv[argv.index("--out") + 1]


def pending(results: Path, scene: str, n_subsets: int) -> list[int]:
    return [i for i in range(n_subsets) if not (results / scene / "sirens" / f"subset_{i}.npz").exists()]


def run(parsl_config: Path, jobs: list[tuple[list[str], str]], log=print) -> list[str]:
    """Submit every (argv, log path) through the Parsl config in `parsl_config`; return the written files."""
    import parsl
    from parsl import python_app

    cfg = runpy.run_path(str(parsl_config)).get("config")
    if cfg is None:
        raise ValueError(f"{parsl_config}: defines no `config` (a parsl.config.Config)")
    app = python_app(fit_task)
    parsl.load(cfg)
    try:
        futures = [(argv, app(argv, log_path)) for argv, log_path in jobs]
        done, failed = [], []
        for argv, fut in futures:
            subset = argv[argv.index("--subset") + 1]
            try:
                done.append(fut.result())
                log(f"[parsl-fit] subset {subset}: wrote {done[-1]}")
            except Exception as e:  # noqa: BLE001 - report every failed subset, then fail once
                failed.append(subset)
                log(f"[parsl-fit] subset {subset}: FAILED ({type(e).__name__}: {e})")
        if failed:
            raise RuntimeError(f"parsl-fit: subsets {failed} failed; rerun `diffshadow parsl-fit` (finished subsets "
                               f"are skipped) or `snakemake -f results/<scene>/sirens/subset_N.npz`")
        return done
    finally:
        parsl.dfk().cleanup()


def fit_args(results: Path, scene: str, subset: int, cfg_json: dict, threads: int) -> tuple[list[str], str]:
    base = results / scene
    argv = ["fit-siren", "--volume", str(base / "volume.zarr"), "--lights", str(base / "lights.json"),
            "--init", str(base / "siren_init.pt"), "--subset", str(subset),
            "--config-json", json.dumps(cfg_json, sort_keys=True), "--threads", str(threads),
            "--out", str(base / "sirens" / f"subset_{subset}.npz")]
    return argv, str(base / "logs" / f"fit_siren_{subset}.log")
