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
import functools
import html
import json
import math
from pathlib import Path

import numpy as np

from diffshadow.io import atomic_write_text, finite_json
from diffshadow.report import pyplot, save_figure

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
    stages = read_costs(costs_path)
    storage = m["storage_bytes"]
    n = int(m["seen"]["count"])
    note = results.parent.parent / "note.txt"  # lights_N/note.txt: what was unusual about the point, if anything
    return {
        "note": note.read_text().strip() if note.is_file() else "",
        "lights": n, "sphere": lights.get("sphere"), "unseen_count": int(m["unseen"]["count"]),
        "stages": stages,
        "quality": {"seen": {"generated": m["seen"]["generated_psnr_median"],
                             "stage1": m["seen"]["stage1_psnr_median"]},
                    "unseen": {key.removesuffix("_psnr_median"): m["unseen"].get(key) for key, _ in UNSEEN}},
        "storage_bytes": {"model": storage["model"], "sirens_fp32": storage["sirens"],
                          "sirens_fp16": storage["sirens"] // 2, "grids_fp16": storage["grids"]},
        "siren_parameters": m["stage1"]["parameters"],
        "model_parameters": (m.get("diffusion_model") or {}).get("parameters", 0),
        "diffusion_epochs": (m.get("diffusion_model") or {}).get("epochs"),  # past `epochs` by the gap check
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


def write_sweep(data: dict, out: Path) -> None:
    """`out` (JSON), and beside it scaling_costs.png, scaling_quality.png, scaling_storage.png, scaling.html."""
    out = Path(out)
    atomic_write_text(out, json.dumps(finite_json(data), indent=2) + "\n")
    for name, fig in (("costs", cost_figure(data)), ("quality", quality_figure(data)),
                      ("storage", storage_figure(data))):
        save_figure(out.parent / f"scaling_{name}.png", fig)
    atomic_write_text(out.parent / "scaling.html", page(data))


def _axes(ncols: int = 1, width: float = 7.0):
    return pyplot().subplots(1, ncols, figsize=(width * ncols, 4.5))


def _no_ticks():
    from matplotlib.ticker import NullLocator

    return NullLocator()


def cost_figure(data: dict):
    """Wall time per stage against lights, log-log, each stage's fitted exponent in its legend."""
    fig, ax = _axes(width=10.0)
    ns = [p["lights"] for p in data["points"]]
    order = sorted(data["fits"], key=lambda s: -max(y for _, y in data["fits"][s]["wall_s"]["points"]))
    import matplotlib

    colours = matplotlib.colormaps["tab20"]
    for i, s in enumerate(order):
        fit = data["fits"][s]["wall_s"]
        x, y = zip(*fit["points"], strict=True)
        b = fit["exponent"]
        ax.plot(x, y, "o-", color=colours(i % 20), label=f"{s} (n^{b:.2f})" if b is not None else s)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xticks(ns, [str(n) for n in ns])
    ax.xaxis.set_minor_locator(_no_ticks())
    ax.set_xlabel("training lights")
    ax.set_ylabel("wall seconds (Snakemake benchmark)")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
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
        a.xaxis.set_minor_locator(_no_ticks())
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
                       ("grids_fp16", "dense shadow grids, fp16"), ("model", "diffusion model, fp32")):
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


def projection_html(proj: dict | None, points: list[dict]) -> str:
    """The projection's table (stages by node-hours) and the storage at the paper's light counts."""
    if not proj:
        return ""
    epochs = ", ".join(str(p.get("diffusion_epochs")) for p in points)
    def row(s: str, r: dict) -> str:
        benched = r.get("source", CPU_SOURCE) != CPU_SOURCE  # timed by `bench stages` on a GPU: no CPU carry
        carry = ("<td colspan=3>" + html.escape(r["source"]) + "</td>" if benched else
                 f"<td>{r['exponent']:.2f}</td><td>{r['h200_over_cpu']:.1f} ({r['speedup_used']:.1f})</td>"
                 f"<td>{r['work_factor']:,.0f}</td>")
        memory = f"{r['rss_mib'] / 1024:,.1f}" if r.get("rss_mib") else ""
        return (f"<tr><td>{html.escape(s)}</td>{carry}<td>{r['wall_s'] / 3600:,.2f}</td>"
                f"<td>{r['node_hours']:,.1f}</td><td>{memory}</td></tr>")

    rows = "".join(row(s, r) for s, r in sorted(proj["stages"].items(), key=lambda kv: -kv[1]["node_hours"]))
    total = sum(r["node_hours"] for r in proj["stages"].values())
    bench = f" ({html.escape(proj['bench_stages'])})" if proj.get("bench_stages") else ""
    store = "".join(f"<tr><td>{n}</td>" + "".join(f"<td>{v / 2**20:,.0f}</td>" for v in b.values()) + "</tr>"
                    for n, b in proj["storage_bytes"].items())
    return f"""<h2>Projection: the paper's scale on Polaris</h2>
<p>{proj['lights']:,} training lights at config/paper.yaml, each stage from this sweep's exponent, the H200's
measured speed over this machine's per stage, the paper config's work per light over this run's, and an A100 taking
{proj['a100_per_h200']}x an H200's time (an assumption); a stage timed by `bench stages` at the paper's sizes on a
GPU{bench} instead takes that measurement's steps (the same A100 factor). Stage 1: subsets of 50, four to a node,
10 nodes. Upper bounds where a small run leaves a GPU idle. train_diffusion's exponent is its cost per epoch,
carried at the configured epochs (its gap check chose the epochs each point trained: {epochs}). Host memory: the
peak RSS carried to this light count plus the paper model's parameters in host memory (weights, gradients, Adam's
moments, EMA: scaling.MODEL_COPIES).</p>
<table><tr><th>stage</th><th>exponent</th><th>H200 / this CPU (used)</th><th>work factor</th><th>wall (h)</th>
<th>node-hours</th><th>host memory per job (GiB)</th></tr>{rows}<tr><td>total</td><td></td><td></td><td></td><td></td>
<td>{total:,.1f}</td><td></td></tr></table>
<table><tr><th>lights</th><th>SIRENs fp32 (MiB)</th><th>SIRENs fp16 (MiB)</th><th>model fp32 (MiB)</th></tr>
{store}</table>
"""


def page(data: dict) -> str:
    """scaling.html: the three figures, the fitted exponents with their points, the storage crossover."""
    pts = data["points"]
    ns = [p["lights"] for p in pts]
    rows = []
    for s, fit in sorted(data["fits"].items(), key=lambda kv: -kv[1]["wall_s"]["points"][-1][1]):
        w = fit["wall_s"]
        b = "" if w["exponent"] is None else f"{w['exponent']:.2f}"
        at = {int(n): y for n, y in w["points"]}
        rss = {int(n): y for n, y in fit["max_rss_mib"]["points"]}
        cells = "".join(f"<td>{at[n]:.1f}</td>" if n in at else "<td></td>" for n in ns)
        rows.append(f"<tr><td>{html.escape(s)}</td>{cells}<td>{b}</td><td>{max(rss.values()):.0f}</td></tr>")
    head = "".join(f"<th>{n} lights (s)</th>" for n in ns)
    notes = "".join(f"<li>{n} lights: {html.escape(p['note'])}</li>" for n, p in zip(ns, pts, strict=True)
                    if p.get("note"))
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
{f"<ul>{notes}</ul>" if notes else ""}
<h2>Cost per stage</h2><img src="scaling_costs.png" width="900">
<table><tr><th>stage</th>{head}<th>exponent</th><th>peak RSS (MiB)</th></tr>{"".join(rows)}</table>
<h2>Quality</h2><img src="scaling_quality.png" width="1000">
<table><tr><th>lights</th>{qhead}<th>seen: generated</th><th>seen: stage 1</th></tr>{q}</table>
<h2>Storage</h2><img src="scaling_storage.png" width="800">
{projection_html(data.get("projection"), pts)}
</body></html>
"""


# --------------------------------------------------------------------------------------------- the projection

# An assumption, not a measurement: an A100 takes this many times an H200's time for this project's work. The
# HBM bandwidth ratio (4.8 / 2.0 TB/s); fp32 peaks differ by 3.4x, launch-bound small kernels by ~1x.
A100_PER_H200 = 2.4
GPUS_PER_NODE = 4  # Polaris


def model_size(cfg: dict) -> tuple[int, int]:
    """(parameters, tokens) of the diffusion model a run config builds."""
    return _model_size(json.dumps(cfg["siren"], sort_keys=True), json.dumps(cfg["diffusion"], sort_keys=True))


@functools.lru_cache(maxsize=8)
def _model_size(siren_json: str, diffusion_json: str) -> tuple[int, int]:
    # built once per config: the paper's model has 172 million parameters
    from diffshadow.diffusion.config import DiffusionConfig, build_model
    from diffshadow.siren import SirenConfig, WeightLayout

    siren = SirenConfig.from_config(json.loads(siren_json))
    diffusion = DiffusionConfig.from_config(json.loads(diffusion_json)).for_siren(siren.width)
    model = build_model(WeightLayout.for_siren(siren), diffusion)
    return model.n_params(), len(model.sizes) + 2


def model_cost(cfg: dict) -> float:
    """Parameters x tokens of the diffusion model a run config builds: its forward cost up to a constant."""
    params, tokens = model_size(cfg)
    return float(params * tokens)


def work_factors(run: dict, paper: dict) -> dict[str, float]:
    """Per stage, the paper config's work per light (or per job) over the run config's, from what each stage
    computes (the light count is the sweep's exponent's business): fitting costs steps x points x width² per
    light; the diffusion stages cost their model's parameters x tokens per sample, times epochs (and views and
    sampled pixels, over GPUs, for fine-tuning); evaluating and rendering SIRENs costs width². Other stages: 1.
    Upper bounds on a GPU: small networks leave it idle, large ones use it better."""
    fit = {k: paper["fit"][k] / run["fit"][k] for k in ("steps", "points")}
    width2 = (paper["siren"]["width"] / run["siren"]["width"]) ** 2
    model = model_cost(paper) / model_cost(run)
    epochs = paper["diffusion"]["epochs"] / run["diffusion"]["epochs"]
    ft = paper["finetune"]
    # a step samples `pixels` per view per light (the target images' size changes only render_targets)
    finetune = (ft["epochs"] / run["finetune"]["epochs"]) * (ft["views"] / run["finetune"]["views"]) * (
        ft["pixels"] / run["finetune"]["pixels"]) * model / (ft["nproc"] / run["finetune"]["nproc"])
    fitting = fit["steps"] * fit["points"] * width2
    return {"fit_siren": fitting, "preoptimize": fitting, "train_diffusion": epochs * model,
            "finetune_render": finetune, "sample_shadows": model, "evaluate_voxels": width2,
            "evaluate_images": width2, "render_targets": width2, "benchmark": width2}


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


# Copies of the diffusion model's parameters a stage's process holds in host memory: training holds weights,
# gradients, Adam's two moments and the EMA (5); a loaded checkpoint holds weights, Adam's two and the EMA (4)
# and the model built from it one more. Fine-tuning loads the geometry checkpoint and trains, per rank;
# evaluate_voxels loads both checkpoints. The sweep's small model makes this term invisible in its RSS.
MODEL_COPIES = {"train_diffusion": 5, "finetune_render": 4 + 5, "sample_shadows": 5, "evaluate_voxels": 2 * 5}


def model_state_mib(stage: str, run: dict, paper: dict) -> float:
    """Host memory (MiB) the paper's diffusion model adds over the run config's to one job of `stage`."""
    copies = MODEL_COPIES.get(stage, 0)
    if stage == "finetune_render":
        copies *= paper["finetune"]["nproc"]  # one process per GPU on the node
    if not copies:
        return 0.0
    return (model_size(paper)[0] - model_size(run)[0]) * 4 * copies / 2**20


QUEUE_MAX_H = 72.0  # Polaris' preemptable queue's longest walltime (ALCF's documentation; check `qstat -Qf`)
MARGIN = 1.5  # requests are the projection times this
# A stage timed by `bench stages` asks at least this: the bench times steps, not a job's start-up, its
# checkpoints, its periodic checks or its outputs (at the README's sizes on the H200 those were 14 of
# fit_siren's 19 s, stage_costs.tsv against 1,000 steps of 5.6 ms)
BENCH_FLOOR_H = 0.5


def project(data: dict, run: dict, paper: dict, gpu_costs: dict[str, dict], *, lights: int | None = None,
            subset: int | None = None, stage1_nodes: int = 10) -> dict:
    """Each stage's wall time, node-hours and peak memory for `paper` at `lights` (default: the paper config's
    count, in subsets of its subset_size) on Polaris: the sweep's CPU
    power law carried to `lights` at the run's config, divided by the H200's speed over this CPU measured on
    the same run config at the sweep's smallest point (`gpu_costs`: stage_costs of a GPU run), times the
    paper's work per light (`work_factors`), times A100_PER_H200.

    Upper bounds: the small run's GPU jobs are mostly start-up, so where the H200 measured slower than the CPU
    it is taken as fast as the CPU (1x); preoptimize, one fit, takes fit_siren's speed-up. Stage 1 runs
    lights / subset jobs four to a node on `stage1_nodes` nodes; fine-tuning on one node of four GPUs; every
    other stage on one node. Requests: MARGIN x the projection, at most QUEUE_MAX_H; a stage that needs more
    resumes from its checkpoint in further jobs (`resubmits`)."""
    lights = lights or paper["lights"]["count"]
    subset = subset or paper["subset_size"]
    n0 = data["points"][0]["lights"]
    factors = work_factors(run, paper)

    def measured_ratio(stage):
        cpu_n0 = dict((int(n), y) for n, y in data["fits"][stage]["wall_s"]["points"]).get(n0)
        gpu = gpu_costs.get(stage)
        return cpu_n0 / gpu["wall_s"] if cpu_n0 and gpu else None

    rows = {}
    for stage, fit in data["fits"].items():
        cpu_total = predict(fit["wall_s"], lights)
        exponent = fit["wall_s"]["exponent"]
        if "wall_s_per_epoch" in fit and cpu_total is not None:  # at the run config's epochs, as work_factors counts
            cpu_total = predict(fit["wall_s_per_epoch"], lights) * run["diffusion"]["epochs"]
            exponent = fit["wall_s_per_epoch"]["exponent"]
        ratio = measured_ratio("fit_siren" if stage == "preoptimize" else stage)
        if cpu_total is None or ratio is None:
            continue
        used = max(ratio, 1.0)
        a100_total = cpu_total / used * factors.get(stage, 1.0) * A100_PER_H200  # all jobs of the stage
        rss = predict(fit["max_rss_mib"], lights) or fit["max_rss_mib"]["points"][-1][1]
        model_mib = model_state_mib(stage, run, paper)
        rows[stage] = {"exponent": exponent, "cpu_s_run_config": cpu_total,
                       "h200_over_cpu": ratio, "speedup_used": used, "work_factor": factors.get(stage, 1.0),
                       **_schedule(stage, a100_total, -(-lights // subset), stage1_nodes),
                       "rss_mib_run_config": rss, "model_state_mib": model_mib, "rss_mib": rss + max(model_mib, 0.0)}
    return {"lights": lights, "a100_per_h200": A100_PER_H200, "margin": MARGIN, "queue_max_h": QUEUE_MAX_H,
            "stages": rows, "storage_bytes": storage_at(paper, [lights, paper["lights"]["sphere"]])}


CPU_SOURCE = "CPU sweep x the tiny run's H200 speed-up (upper bound)"


def measured_projection(proj: dict, bench: dict, *, stage1_nodes: int = 10) -> dict:
    """`proj` (`project`) with each stage that `bench stages` measured at the paper config on a GPU (`bench`, its
    JSON) timed from that measurement instead: its seconds per step times the paper's steps, times A100_PER_H200
    (the same stated assumption) for Polaris' A100s, asking at least BENCH_FLOOR_H. Host memory stays the
    sweep's (the bench measures the GPU's).
    Every row names its `source`; stages the bench did not time keep the CPU-based upper bound."""
    if bench.get("device_type") != "cuda":
        raise ValueError(f"bench stages JSON measured on {bench.get('device')!r}: the paper-scale plan needs one "
                         f"measured on a GPU (docs/measurements/<card>_bench_stages_paper.json)")
    out = {**proj, "stages": {k: {**v, "source": CPU_SOURCE} for k, v in proj["stages"].items()},
           "bench": {k: bench.get(k) for k in ("device", "torch", "cuda", "config")}}
    for stage, row in bench["stages"].items():
        jobs = -(-proj["lights"] // int(row["units"]))  # fit_siren: the bench times one job of `units` SIRENs
        total = row["projected_s"] * A100_PER_H200 * (jobs if stage == "fit_siren" else 1)
        plan = _schedule(stage, total, jobs, stage1_nodes)
        plan["walltime_request_h"] = min(max(plan["walltime_request_h"], BENCH_FLOOR_H), QUEUE_MAX_H)
        out["stages"].setdefault(stage, {"rss_mib": None, "model_state_mib": 0.0}).update(
            **plan, source=f"bench stages on {bench.get('device')} x "
                                                                 f"{A100_PER_H200}")
    return out


def _schedule(stage: str, a100_total: float, jobs: int, stage1_nodes: int) -> dict:
    """A stage's A100 seconds (all its jobs) as Polaris runs them: fit_siren's `jobs` four to a node on
    `stage1_nodes` nodes, any other stage one job on one node; its wall time, node-hours, and a job's walltime
    request (MARGIN x its time, at most QUEUE_MAX_H, `resubmits` more jobs resuming from the checkpoint)."""
    if stage == "fit_siren":
        per_job = a100_total / jobs
        wall = a100_total / jobs * -(-jobs // (stage1_nodes * GPUS_PER_NODE))
        node_hours = a100_total / GPUS_PER_NODE / 3600
    else:
        wall = per_job = a100_total
        node_hours = a100_total / 3600
    request_h = per_job * MARGIN / 3600
    return {"a100_s_total": a100_total, "wall_s": wall, "node_hours": node_hours,
            "walltime_request_h": min(request_h, QUEUE_MAX_H),
            "resubmits": max(0, math.ceil(request_h / QUEUE_MAX_H) - 1)}


def walltime(hours: float) -> str:
    """PBS's HH:MM:SS, rounded up to whole minutes."""
    minutes = max(1, math.ceil(hours * 60))
    return f"{minutes // 60:02d}:{minutes % 60:02d}:00"


def polaris_profile(proj: dict) -> str:
    """A Snakemake workflow profile (`--workflow-profile`) whose per-rule walltimes are the projection's
    requests; laid over `--profile polaris`, it replaces the profile's guesses. `mem_mb`: the peak RSS carried to
    the light count plus the paper model's state in host memory (`model_state_mib`), x margin (Polaris nodes
    are whole: 512 GB; Snakemake checks it, qsub is not sent it)."""
    lines = ["# Made by scripts/scaling_sweep.py from the light-count sweep (diffshadow.scaling.project): each",
             f"# rule's projected A100 time at {proj['lights']:,} lights x {proj['margin']}, at most "
             f"{proj['queue_max_h']:.0f} h",
             "# (a longer stage resumes from its checkpoint in a further job); mem_mb: the peak RSS carried to that",
             "# light count, plus the paper model's parameters held in host memory (scaling.MODEL_COPIES), x the",
             "# margin (a Polaris node has 512 GB). Use:",
             "#   snakemake --profile polaris --workflow-profile profiles/paper --configfile config/paper.yaml",
             "set-resources:"]
    for stage, r in sorted(proj["stages"].items()):
        lines.append(f"  {stage}:  # {r.get('source', CPU_SOURCE)}")
        lines.append(f"    walltime: \"{walltime(r['walltime_request_h'])}\"")
        if r.get("rss_mib"):
            lines.append(f"    mem_mb: {math.ceil(r['rss_mib'] * proj['margin'] * 1.048576 / 100) * 100}")
    return "\n".join(lines) + "\n"


def storage_at(cfg: dict, counts: list[int]) -> dict:
    """Stored SIRENs (fp32, fp16) and the model (fp32) for a config, at each light count."""
    from diffshadow.siren import SirenConfig, WeightLayout

    per = WeightLayout.for_siren(SirenConfig.from_config(cfg["siren"])).n_params * 4
    model = model_size(cfg)[0] * 4
    return {str(n): {"sirens_fp32": per * n, "sirens_fp16": per * n // 2, "model": model} for n in counts}
