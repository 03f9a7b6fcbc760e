"""Run the pipeline on several scenes at a reduced light count and print one quality table.

    python scripts/quality_table.py --scenes nucleon neghip tooth hydrogen_atom --lights 32 --unseen 8

Each scene runs with `snakemake --profile profiles/local -j2 --config scenes=[<scene>] ...` up to its
summary (the benchmark and report figures are left out: this is about quality), then the table is read
from the results: the sizes chosen (data INR, stage-1 SIRENs), the PSNRs, and the wall time per stage from
Snakemake's benchmark files. `--table-only` prints the table from results already there.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import torch

from diffshadow.report import ELAPSED_ROW, stage_costs

REPO = Path(__file__).resolve().parent.parent


def run(scene: str, lights: int, unseen: int) -> float:
    targets = [f"results/{scene}/{f}" for f in ("voxel_metrics.json", "image_metrics.json")]
    # a config file, not --config: Snakemake passes nested --config values as strings
    overlay = REPO / "results" / f"quality_{scene}.yaml"
    overlay.parent.mkdir(exist_ok=True)
    overlay.write_text(f"scenes: [{scene}]\nlights: {{count: {lights}, unseen: {unseen}}}\n")
    cmd = ["snakemake", "--profile", "profiles/local", "-j2", "--configfile", "config/config.yaml", str(overlay),
           "--", *targets]
    t0 = time.perf_counter()
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, cwd=REPO, check=True)
    return time.perf_counter() - t0


def row(scene: str, wall: float | None) -> dict:
    res = REPO / "results" / scene
    voxel = json.loads((res / "voxel_metrics.json").read_text())
    images = json.loads((res / "image_metrics.json").read_text())
    stage1 = voxel.get("stage1") or {}
    inr = images.get("data_inr") or {}
    init = torch.load(res / "siren_init.pt", map_location="cpu", weights_only=True)
    rows = stage_costs(sorted((res / "benchmarks").glob("*.tsv")), REPO / "results" / f"quality_{scene}_costs.tsv")
    costs = {r["stage"]: r["wall_s"] for r in rows if not r["stage"].startswith("total") and r["stage"] != ELAPSED_ROW}
    if wall is None:  # --table-only: the run's elapsed time from its benchmark files
        wall = next(r["wall_s"] for r in rows if r["stage"] == ELAPSED_ROW)
    unseen = voxel.get("unseen", {})
    dm = voxel.get("diffusion_model") or {}
    kept = dm.get("kept_epoch") if dm.get("kept_epoch") != dm.get("epochs") else None
    deployed = images["modes"].get("inr_generated_data_inr", {})
    return {"scene": scene, "lights": voxel["seen"]["count"],
            "data INR": f"w{inr.get('width')} x{(inr.get('capacity') or {}).get('steps')}",
            "data INR dB": inr.get("psnr"),
            "SIREN": f"w{stage1.get('width')} x{init.get('fit_steps')}",
            "probe dB": (stage1.get("capacity") or {}).get("psnr"),
            "stage 1 dB": voxel["seen"]["stage1_psnr_median"],
            "diffusion": f"{dm.get('preset')} x{dm.get('epochs')} ep" + (f" (kept {kept})" if kept else ""),
            "seen dB": voxel["seen"]["generated_psnr_median"],
            "unseen dB": unseen.get("generated_psnr_median"),
            "share": (voxel.get("mix") or {}).get("model_share"),  # the model's in the mix (none: the model alone)
            "model alone dB": unseen.get("model_alone_psnr_median"),
            "before FT": unseen.get("geometry_only_psnr_median"),
            "blend dB": unseen.get("blend_psnr_median"),
            "weight blend dB": unseen.get("weight_blend_psnr_median"),
            "SIREN blend dB": unseen.get("siren_blend_psnr_median"),
            "image dB": deployed.get("psnr"),
            "wall min": None if wall is None else wall / 60,
            "stage s": ", ".join(f"{k} {v:.0f}" for k, v in sorted(costs.items(), key=lambda kv: -kv[1])[:6])}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="+", default=["nucleon", "neghip", "tooth", "hydrogen_atom"])
    p.add_argument("--lights", type=int, default=32)
    p.add_argument("--unseen", type=int, default=8)
    p.add_argument("--table-only", action="store_true")
    a = p.parse_args()
    rows = []
    for scene in a.scenes:
        wall = None if a.table_only else run(scene, a.lights, a.unseen)
        rows.append(row(scene, wall))
    keys = list(rows[0])
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for r in rows:
        print("| " + " | ".join(f"{v:.2f}" if isinstance(v, float) else str(v) for v in r.values()) + " |")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
