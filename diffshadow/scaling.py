"""The light-count sweep: what each stage costs, how good the cache is and how much it stores, against the
number of training lights (issue 56). Reads finished runs (`results/<scene>/` of one run per light count: its
`stage_costs.tsv` and `voxel_metrics.json`), fits a power law per stage, writes one JSON, three figures and a
page. It does not run anything: `scripts/scaling_sweep.py` drives the workflow once per point.

Storage per point: the stored SIRENs (fp32 and fp16), the dense shadow grids they replace (fp32, the volume's
grid per light) and the diffusion model's weights (fp32). The model does not grow with the lights, the others
do in proportion, so the model is smaller than the SIRENs it replaces past `crossover` lights.
"""

from __future__ import annotations

import csv
import html
import json
import math
from pathlib import Path

import numpy as np

from diffshadow.io import atomic_path, atomic_write_text, finite_json

# the quality rows of the figure and the JSON: (key in voxel_metrics.json's "unseen" section, label)
UNSEEN = (("generated_psnr_median", "generated (diffusion)"), ("weight_blend_psnr_median", "weight blend, 4 nearest"),
          ("siren_blend_psnr_median", "SIREN blend, 4 nearest"), ("nearest_psnr_median", "nearest stored SIREN"))


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
    stages = {}
    with open(costs_path, newline="") as f:
        for row in csv.DictReader(f, delimiter="\t"):
            if row["stage"].startswith(("total", "elapsed")):
                continue
            stages[row["stage"]] = {"jobs": int(row["jobs"]), "wall_s": float(row["wall_s"]),
                                    "cpu_s": float(row["cpu_s"]), "max_rss_mib": float(row["max_rss_mib"])}
    storage = m["storage_bytes"]
    n = int(m["seen"]["count"])
    return {
        "lights": n, "sphere": lights.get("sphere"), "unseen_count": int(m["unseen"]["count"]),
        "stages": stages,
        "quality": {"seen": {"generated": m["seen"]["generated_psnr_median"],
                             "stage1": m["seen"]["stage1_psnr_median"]},
                    "unseen": {key.removesuffix("_psnr_median"): m["unseen"].get(key) for key, _ in UNSEEN}},
        "storage_bytes": {"model": storage["model"], "sirens_fp32": storage["sirens"],
                          "sirens_fp16": storage["sirens"] // 2, "grids_fp32": storage["grids"]},
        "siren_parameters": m["stage1"]["parameters"], "model_parameters": m["diffusion_model"]["parameters"],
    }


def power_law(ns, ys) -> dict:
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
    stages = sorted({s for p in points for s in p["stages"]})
    fits = {}
    for s in stages:
        have = [p for p in points if s in p["stages"]]
        fits[s] = {metric: power_law([p["lights"] for p in have], [p["stages"][s][metric] for p in have])
                   for metric in ("wall_s", "cpu_s", "max_rss_mib")}
    return {"points": points, "fits": fits,
            "crossover_lights": {"sirens_fp32": crossover(points, "sirens_fp32"),
                                 "sirens_fp16": crossover(points, "sirens_fp16")}}


def write_sweep(data: dict, out: Path) -> None:
    """`out` (JSON), and beside it scaling_costs.png, scaling_quality.png, scaling_storage.png, scaling.html."""
    out = Path(out)
    atomic_write_text(out, json.dumps(finite_json(data), indent=2) + "\n")
    figures = {"costs": cost_figure(data), "quality": quality_figure(data), "storage": storage_figure(data)}
    import matplotlib.pyplot as plt

    for name, fig in figures.items():
        with atomic_path(out.parent / f"scaling_{name}.png", suffix=".png") as tmp:
            fig.savefig(tmp, format="png", dpi=100)
        plt.close(fig)
    atomic_write_text(out.parent / "scaling.html", page(data))


def _axes(ncols: int = 1, width: float = 7.0):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(1, ncols, figsize=(width * ncols, 4.5))


def cost_figure(data: dict):
    """Wall time per stage against lights, log-log, each stage's fitted exponent in its legend."""
    fig, ax = _axes(width=9.0)
    ns = [p["lights"] for p in data["points"]]
    order = sorted(data["fits"], key=lambda s: -max(y for _, y in data["fits"][s]["wall_s"]["points"]))
    for s in order:
        fit = data["fits"][s]["wall_s"]
        x, y = zip(*fit["points"], strict=True)
        b = fit["exponent"]
        ax.plot(x, y, "o-", label=f"{s} (n^{b:.2f})" if b is not None else s)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xticks(ns, [str(n) for n in ns])
    ax.set_xlabel("training lights")
    ax.set_ylabel("wall seconds (Snakemake benchmark)")
    ax.legend(fontsize=7, ncol=2, loc="upper left")
    ax.set_title("cost per stage against lights (fitted exponent in the legend)")
    fig.tight_layout()
    return fig


def quality_figure(data: dict):
    """Median voxel PSNR on unseen lights (generated, blends, nearest) and on seen lights (generated, stage 1)."""
    fig, ax = _axes(2, 6.0)
    ns = [p["lights"] for p in data["points"]]
    for key, label in UNSEEN:
        k = key.removesuffix("_psnr_median")
        ax[0].plot(ns, [p["quality"]["unseen"][k] for p in data["points"]], "o-", label=label)
    for k, label in (("generated", "generated (diffusion)"), ("stage1", "stage 1 (stored SIRENs)")):
        ax[1].plot(ns, [p["quality"]["seen"][k] for p in data["points"]], "o-", label=label)
    for a, title in ((ax[0], "unseen lights"), (ax[1], "training lights")):
        a.set_xscale("log")
        a.set_xticks(ns, [str(n) for n in ns])
        a.set_xlabel("training lights")
        a.set_ylabel("median voxel PSNR (dB)")
        a.set_title(title)
        a.legend(fontsize=8)
    fig.tight_layout()
    return fig


def storage_figure(data: dict):
    """Bytes stored against lights, the measured points and their lines carried to 8,000 lights, the
    crossovers (model = stored SIRENs) marked."""
    fig, ax = _axes(width=8.0)
    pts = data["points"]
    ns = np.array([p["lights"] for p in pts], float)
    far = np.geomspace(ns.min(), max(8000.0, ns.max()), 50)
    for key, label in (("sirens_fp32", "stored SIRENs, fp32"), ("sirens_fp16", "stored SIRENs, fp16"),
                       ("grids_fp32", "dense shadow grids, fp32"), ("model", "diffusion model, fp32")):
        ys = np.array([p["storage_bytes"][key] for p in pts], float)
        line = ax.plot(ns, ys / 2**20, "o", label=label)[0]
        per = float(np.median(ys / ns)) if key != "model" else None
        ax.plot(far, (far * per if per else np.full_like(far, ys[-1])) / 2**20, "--", color=line.get_color(), lw=1)
    for key, style in (("sirens_fp32", ":"), ("sirens_fp16", "-.")):
        n = data["crossover_lights"][key]
        if n:
            ax.axvline(n, color="k", ls=style, lw=1)
            ax.annotate(f"model < SIRENs ({key[-4:]}) past {n:,.0f}", (n, 0.02), xycoords=("data", "axes fraction"),
                        rotation=90, fontsize=8, va="bottom", ha="right")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("training lights (points: measured; dashed: carried at the measured bytes per light)")
    ax.set_ylabel("MiB")
    ax.legend(fontsize=8)
    ax.set_title("storage against lights")
    fig.tight_layout()
    return fig


def page(data: dict) -> str:
    """scaling.html: the three figures, the fitted exponents with their points, the storage crossover."""
    pts = data["points"]
    ns = [p["lights"] for p in pts]
    rows = []
    for s, fit in sorted(data["fits"].items(), key=lambda kv: -kv[1]["wall_s"]["points"][-1][1]):
        w = fit["wall_s"]
        b = "" if w["exponent"] is None else f"{w['exponent']:.2f}"
        rss = fit["max_rss_mib"]
        cells = "".join(f"<td>{y:.1f}</td>" for _, y in w["points"])
        rows.append(f"<tr><td>{html.escape(s)}</td>{cells}<td>{b}</td><td>{rss['points'][-1][1]:.0f}</td></tr>")
    head = "".join(f"<th>{n} lights (s)</th>" for n in ns)
    q = "".join(f"<tr><td>{n}</td>" + "".join(
        f"<td>{(p['quality']['unseen'][k.removesuffix('_psnr_median')] or float('nan')):.2f}</td>" for k, _ in UNSEEN)
        + f"<td>{p['quality']['seen']['generated']:.2f}</td><td>{p['quality']['seen']['stage1']:.2f}</td></tr>"
        for n, p in zip(ns, pts, strict=True))
    qhead = "".join(f"<th>unseen: {html.escape(label)}</th>" for _, label in UNSEEN)
    c = data["crossover_lights"]
    return f"""<!doctype html><html><head><meta charset="utf-8"><title>diffshadow: scaling with the light count</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:2em auto}}td,th{{padding:2px 8px;text-align:right}}
td:first-child{{text-align:left}}table{{border-collapse:collapse}}tr:nth-child(even){{background:#f4f4f4}}</style>
</head><body><h1>Scaling with the number of training lights</h1>
<p>Runs at {", ".join(map(str, ns))} training lights (scripts/scaling_sweep.py). The model is smaller than the
stored SIRENs past {c['sirens_fp32']:,.0f} lights (fp32) or {c['sirens_fp16']:,.0f} (fp16), at these runs' SIREN
and model sizes.</p>
<h2>Cost per stage</h2><img src="scaling_costs.png" width="900">
<table><tr><th>stage</th>{head}<th>exponent</th><th>peak RSS at {ns[-1]} (MiB)</th></tr>{"".join(rows)}</table>
<h2>Quality</h2><img src="scaling_quality.png" width="1000">
<table><tr><th>lights</th>{qhead}<th>seen: generated</th><th>seen: stage 1</th></tr>{q}</table>
<h2>Storage</h2><img src="scaling_storage.png" width="800">
</body></html>
"""
