"""The light-count sweep: the workflow once per light count, each in its own folder, then one JSON,
three figures and a page (`diffshadow.scaling`).

    python scripts/scaling_sweep.py --lights 32 128 512 --out sweep          # every stage, on this machine
    python scripts/scaling_sweep.py --lights 32 128 --out sweep --collect    # only re-read finished runs
    python scripts/scaling_sweep.py --from-json docs/scaling/rim/scaling.json --out docs/scaling/rim \
        --bench-stages docs/measurements/h200_bench_stages_paper.json --profile-out profiles/paper/config.yaml
                                               # the projection and profiles/paper again from a committed sweep

Each point is `snakemake --directory OUT/lights_N` with `lights: {count: N, sphere: 4N, unseen: U}` laid over the
run config: the paper's cap fraction (2,000 training lights of 8,000), so the training lights grow denser with N,
and the same number of unseen test lights everywhere; `--sphere 8000` instead fixes the spacing at the paper's, so
the training region grows with N. A point that is already finished is not rerun (Snakemake
sees its outputs); one cut short resumes. Writes OUT/scaling.json, OUT/scaling_{costs,quality,storage}.png and
OUT/scaling.html, with the projection of every stage to the paper's scale on Polaris (`scaling.project`: this
sweep's exponents, the H200's speed over this machine's from `--gpu-costs`, the paper config's work per light over
the run config's). scaling.json records that run config (`run_config`: config/config.yaml and any --configfile
when the points are collected), and `--from-json` counts against the record, not against config/config.yaml as it
has become.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from diffshadow import config, scaling

ROOT = Path(__file__).resolve().parent.parent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lights", type=int, nargs="+", default=[32, 128, 512])
    ap.add_argument("--out", type=Path, default=Path("sweep"))
    ap.add_argument("--scene", default="nucleon")
    ap.add_argument("--unseen", type=int, default=32)
    ap.add_argument("--sphere", type=int, help="a fixed sphere (a fixed light spacing: 8000 is the paper's) "
                    "instead of 4N, the paper's cap fraction")
    ap.add_argument("--profile", default=str(ROOT / "profiles" / "local"))
    ap.add_argument("-j", "--jobs", type=int, default=2)
    ap.add_argument("--configfile", type=Path, help="a further overlay for every point (e.g. config/paper.yaml)")
    ap.add_argument("--caches", action="store_true", help="stage 1 and the caches table only (`cache: blend`, target "
                    "caches.json): every codec's rate and distortion per light count, beside the model's figures "
                    "from --model-json; writes OUT/caches.json and OUT/scaling_caches.png")
    ap.add_argument("--model-json", type=Path, default=ROOT / "docs" / "scaling" / "rim" / "scaling.json",
                    help="with --caches: the sweep whose diffusion model the codecs are set beside")
    ap.add_argument("--collect", action="store_true", help="run nothing: read the finished points under --out")
    ap.add_argument("--from-json", type=Path, help="run nothing: the points of an earlier sweep's scaling.json "
                    "(e.g. docs/scaling/rim/scaling.json), projected again")
    ap.add_argument("--paper", type=Path, default=ROOT / "config" / "paper.yaml",
                    help="the config overlay to project to (over config/config.yaml)")
    ap.add_argument("--gpu-costs", type=Path,
                    default=ROOT / "docs" / "measurements" / "h200_readme_run_stage_costs.tsv",
                    help="stage_costs.tsv of the default run on a GPU: each stage's speed there over this machine's")
    ap.add_argument("--bench-stages", type=Path, help="`diffshadow bench stages --configfile config/paper.yaml` "
                    "run on a GPU (docs/measurements/<card>_bench_stages_paper.json): the stages it timed are "
                    "projected from it instead of the CPU sweep")
    ap.add_argument("--profile-out", type=Path,
                    help="also write the per-rule walltimes as a workflow profile (profiles/paper/config.yaml)")
    a = ap.parse_args()
    out = a.out.resolve()
    runs = []
    for n in [] if a.from_json else sorted(a.lights):
        point = out / f"lights_{n}"
        runs.append(point / "results" / a.scene)
        if a.collect:
            continue
        point.mkdir(parents=True, exist_ok=True)
        overlay = point / "lights.yaml"
        sphere = a.sphere or 4 * n
        # the gap check on at every count, as the package has it: config/config.yaml turns it off for the README
        # run's 32 lights, where it bought nothing, while at 512 and 1,024 it grew training to 800 epochs
        gap = config.defaults()["diffusion"]["target_gap"]
        overlay.write_text(f"scenes: [{a.scene}]\nlights: {{count: {n}, sphere: {sphere}, unseen: {a.unseen}}}\n"
                           f"diffusion: {{target_gap: {gap}}}\n" + ("cache: blend\n" if a.caches else ""))
        # the target first: --configfile takes every word after it
        cmd = ["snakemake", *([f"results/{a.scene}/caches.json"] if a.caches else []), "-s", str(ROOT / "Snakefile"),
               "--directory", str(point), "--profile", a.profile, "-j", str(a.jobs), "--configfile",
               *([str(a.configfile)] if a.configfile else []), str(overlay)]
        print(f"[sweep] {n} lights: {' '.join(cmd)}", flush=True)
        t0 = time.monotonic()
        with open(point / "snakemake.log", "a") as log:
            rc = subprocess.call(cmd, stdout=log, stderr=subprocess.STDOUT)
        print(f"[sweep] {n} lights: exit {rc} after {time.monotonic() - t0:.0f} s (log {point / 'snakemake.log'})",
              flush=True)
        if rc:
            sys.exit(f"[sweep] the run at {n} lights failed; see {point / 'snakemake.log'}")
    if a.caches:  # the codecs beside the full sweep's model, per light count
        from diffshadow.scaling import rate_distortion

        source = _shown(a.model_json)
        try:
            table = rate_distortion.collect(runs, json.loads(a.model_json.read_text())["points"], source)
        except FileNotFoundError as e:
            sys.exit(f"[sweep] {e}")
        table["model_json"] = source
        rate_distortion.write(table, out / "caches.json")
        print(rate_distortion.markdown(table))
        print(f"[sweep] wrote {out / 'caches.json'} and {out / 'scaling_caches.png'}")
        return
    # what the points ran with: config/config.yaml and the --configfile overlay (the sweep's own lights and gap
    # check change no work per light)
    own = config.read_yaml(ROOT / "config" / "config.yaml")
    run_cfg = config.run_config(config.merge(own, config.read_yaml(a.configfile)) if a.configfile else own,
                                str(a.configfile or "config/config.yaml"))
    if a.from_json:
        data = {k: v for k, v in json.loads(a.from_json.read_text()).items() if k != "projection"}
        if "run_config" in data:  # the work per light is counted against the config the points ran at
            run_cfg = {**run_cfg, **data["run_config"]}
        else:
            print(f"[sweep] {a.from_json} does not record the config its points ran at: counting the paper's work "
                  f"per light against config/config.yaml as it is now", flush=True)
    else:
        try:
            data = scaling.sweep(runs)
        except scaling.SweepError as e:  # e.g. one new point run alone: its results stand; collect with the others
            sys.exit(f"[sweep] {e}; collect finished points together (--collect --lights N1 N2 ...)")
    data["run_config"] = {k: run_cfg[k] for k in scaling.RUN_CONFIG_SECTIONS}
    paper = config.run_config(config.merge(config.read_yaml(ROOT / "config" / "config.yaml"),
                                           config.read_yaml(a.paper)), str(a.paper))
    data["projection"] = scaling.project(data, run_cfg, paper, scaling.read_costs(a.gpu_costs))
    data["projection"]["gpu_costs"] = _shown(a.gpu_costs)
    if a.bench_stages:  # stages timed at the paper's sizes on a GPU replace their CPU-based upper bounds
        data["projection"] = scaling.measured_projection(data["projection"], json.loads(a.bench_stages.read_text()))
        data["projection"]["bench_stages"] = _shown(a.bench_stages)
    if a.profile_out:
        from diffshadow.io import atomic_write_text

        a.profile_out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(a.profile_out, scaling.polaris_profile(data["projection"]))
        print(f"[sweep] wrote {a.profile_out} (per-rule walltimes for the paper config on Polaris)")
    scaling.write_sweep(data, out / "scaling.json")
    print(f"[sweep] wrote {out / 'scaling.json'}, {out / 'scaling.html'} and its three figures")


def _shown(path: Path) -> str:
    """`path` relative to the repository where it lies inside it (a committed JSON names no machine's folders)."""
    try:
        return str(path.resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


if __name__ == "__main__":
    main()
