"""The light-count sweep (issue 56): the workflow once per light count, each in its own folder, then one JSON,
three figures and a page (`diffshadow.scaling`).

    python scripts/scaling_sweep.py --lights 32 128 512 --out sweep          # every stage, on this machine
    python scripts/scaling_sweep.py --lights 32 128 --out sweep --collect    # only re-read finished runs

Each point is `snakemake --directory OUT/lights_N` with `lights: {count: N, sphere: 4N, unseen: U}` laid over the
run config: the paper's cap fraction (2,000 training lights of 8,000), so the training lights grow denser with N,
and the same number of unseen test lights everywhere. A point that is already finished is not rerun (Snakemake
sees its outputs); one cut short resumes. Writes OUT/scaling.json, OUT/scaling_{costs,quality,storage}.png and
OUT/scaling.html.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

from diffshadow import scaling

ROOT = Path(__file__).resolve().parent.parent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lights", type=int, nargs="+", default=[32, 128, 512])
    ap.add_argument("--out", type=Path, default=Path("sweep"))
    ap.add_argument("--scene", default="nucleon")
    ap.add_argument("--unseen", type=int, default=32)
    ap.add_argument("--profile", default=str(ROOT / "profiles" / "local"))
    ap.add_argument("-j", "--jobs", type=int, default=2)
    ap.add_argument("--configfile", type=Path, help="a further overlay for every point (e.g. config/paper.yaml)")
    ap.add_argument("--collect", action="store_true", help="run nothing: read the finished points under --out")
    a = ap.parse_args()
    out = a.out.resolve()
    runs = []
    for n in sorted(a.lights):
        point = out / f"lights_{n}"
        runs.append(point / "results" / a.scene)
        if a.collect:
            continue
        point.mkdir(parents=True, exist_ok=True)
        overlay = point / "lights.yaml"
        overlay.write_text(f"scenes: [{a.scene}]\nlights: {{count: {n}, sphere: {4 * n}, unseen: {a.unseen}}}\n")
        cmd = ["snakemake", "-s", str(ROOT / "Snakefile"), "--directory", str(point), "--profile", a.profile,
               "-j", str(a.jobs), "--configfile", *([str(a.configfile)] if a.configfile else []), str(overlay)]
        print(f"[sweep] {n} lights: {' '.join(cmd)}", flush=True)
        t0 = time.monotonic()
        with open(point / "snakemake.log", "a") as log:
            rc = subprocess.call(cmd, stdout=log, stderr=subprocess.STDOUT)
        print(f"[sweep] {n} lights: exit {rc} after {time.monotonic() - t0:.0f} s (log {point / 'snakemake.log'})",
              flush=True)
        if rc:
            sys.exit(f"[sweep] the run at {n} lights failed; see {point / 'snakemake.log'}")
    data = scaling.sweep(runs)
    scaling.write_sweep(data, out / "scaling.json")
    print(f"[sweep] wrote {out / 'scaling.json'}, {out / 'scaling.html'} and its three figures")


if __name__ == "__main__":
    main()
