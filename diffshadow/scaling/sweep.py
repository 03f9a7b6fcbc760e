"""The sweep's points: each finished run's costs, quality and storage, and a power law per stage."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from diffshadow.lights import layout_of

# the quality rows of the figure and the JSON: (key in voxel_metrics.json's "unseen" section, label)
# (the model alone only where the cache mixed it with the stored SIRENs' blend: diffusion/mix.py)
UNSEEN = (("generated_psnr_median", "generated (the cache's answer)"),
          ("model_alone_psnr_median", "the model alone (the paper)"),
          ("weight_blend_psnr_median", "weight blend"),
          ("siren_blend_psnr_median", "SIREN values' blend"), ("nearest_psnr_median", "nearest stored SIREN"))
# and of its "seen" section; the model alone is scored only where the run mixed
SEEN = (("generated_psnr_median", "generated (the cache's answer)"),
        ("model_alone_psnr_median", "the model alone (the paper)"), ("stage1_psnr_median", "stage 1 (stored SIRENs)"))


class SweepError(ValueError):
    pass


def read_point(results: Path) -> dict:
    """One finished run (`results/<scene>`): light count, per-stage costs, quality and storage."""
    metrics_path, costs_path = results / "voxel_metrics.json", results / "stage_costs.tsv"
    for path in (metrics_path, costs_path):
        if not path.is_file():
            raise SweepError(f"{path}: missing; the sweep reads finished runs (run the workflow for this point first)")
    m = json.loads(metrics_path.read_text())
    lights = json.loads((results / "lights.json").read_text())
    stages = read_costs(costs_path)
    storage = m["storage_bytes"]
    n = int(m["seen"]["count"])
    note = results.parent.parent / "note.txt"  # lights_N/note.txt: what was unusual about the point, if anything
    return {
        "note": note.read_text().strip() if note.is_file() else "",
        "lights": n, "sphere": lights.get("sphere"), "unseen_count": int(m["unseen"]["count"]),
        "layout": layout_of(lights),
        "stages": stages,
        "quality": {"seen": {key.removesuffix("_psnr_median"): m["seen"].get(key) for key, _ in SEEN},
                    "unseen": {key.removesuffix("_psnr_median"): m["unseen"].get(key) for key, _ in UNSEEN}},
        "storage_bytes": {"model": storage["model"], "sirens_fp32": storage["sirens"],
                          "sirens_fp16": storage["sirens"] // 2, "grids_fp16": storage["grids"]},
        "siren_parameters": m["stage1"]["parameters"],
        "model_parameters": (m.get("diffusion_model") or {}).get("parameters", 0),
        "diffusion_epochs": (m.get("diffusion_model") or {}).get("epochs"),  # past `epochs` by the gap check
    }


def power_law(ns: ArrayLike, ys: ArrayLike) -> dict:
    """y = a · n^b by least squares in log-log: the exponent b, the factor a and the points it came from."""
    ns, ys = np.asarray(ns, float), np.asarray(ys, float)
    keep = ys > 0
    if keep.sum() < 2:
        return {"exponent": None, "factor": None, "points": [[float(n), float(y)] for n, y in zip(ns, ys, strict=True)]}
    b, log_a = np.polyfit(np.log(ns[keep]), np.log(ys[keep]), 1)
    return {"exponent": float(b), "factor": float(math.exp(log_a)),
            "points": [[float(n), float(y)] for n, y in zip(ns, ys, strict=True)]}


def predict(fit: dict, n: float) -> float | None:
    return None if fit["exponent"] is None else fit["factor"] * n ** fit["exponent"]


def crossover(points: list[dict], key: str = "sirens_fp32") -> float | None:
    """The light count above which the model is smaller than the stored SIRENs (`key`), from bytes per SIREN."""
    per_light = [p["storage_bytes"][key] / p["lights"] for p in points]
    model = points[-1]["storage_bytes"]["model"]
    return model / float(np.median(per_light)) if per_light else None


def sweep(runs: list[Path]) -> dict:
    """The sweep's JSON from its finished runs (any order; at least two light counts)."""
    points = sorted((read_point(Path(r)) for r in runs), key=lambda p: p["lights"])
    ns = [p["lights"] for p in points]
    if len(set(ns)) < 2:
        raise SweepError(f"a sweep needs runs at two light counts at least, got {ns}")
    layouts = {p["lights"]: layout_of(p) for p in points}
    if len(set(layouts.values())) > 1:  # the quality curve would mix two regions' blends
        raise SweepError(f"a sweep's runs must share one lights.layout, got {layouts} by light count: rerun "
                         "the points of the other layout")
    stages = sorted({s for p in points for s in p["stages"]})
    fits = {}
    for s in stages:
        have = [p for p in points if s in p["stages"]]
        fits[s] = {metric: power_law([p["lights"] for p in have], [p["stages"][s][metric] for p in have])
                   for metric in ("wall_s", "cpu_s", "max_rss_mib")}
    # train_diffusion trains past `epochs` as long as its gap check asks, so points differ in epochs: its cost
    # per epoch is what grows with the lights, and what the projection carries
    have = [p for p in points if "train_diffusion" in p["stages"] and p.get("diffusion_epochs")]
    if len(have) == len(points) and "train_diffusion" in fits:
        fits["train_diffusion"]["wall_s_per_epoch"] = power_law(
            [p["lights"] for p in have], [p["stages"]["train_diffusion"]["wall_s"] / p["diffusion_epochs"]
                                          for p in have])
    return {"points": points, "fits": fits,
            "crossover_lights": {"sirens_fp32": crossover(points, "sirens_fp32"),
                                 "sirens_fp16": crossover(points, "sirens_fp16")}}

def read_costs(path: Path) -> dict[str, dict]:
    """A `stage_costs.tsv` (`report.stage_costs`) as stage -> {jobs, wall_s, cpu_s, max_rss_mib}, without its
    total and elapsed rows."""
    out = {}
    with open(path, newline="") as f:
        for row in csv.DictReader(f, delimiter="\t"):
            if not row["stage"].startswith(("total", "elapsed")):
                out[row["stage"]] = {"jobs": int(row["jobs"]), "wall_s": float(row["wall_s"]),
                                     "cpu_s": float(row["cpu_s"]), "max_rss_mib": float(row["max_rss_mib"])}
    return out
