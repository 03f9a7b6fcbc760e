"""The sweep's three figures and its page (scaling.html), the projection's table included."""

from __future__ import annotations

import html
import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from diffshadow.io import atomic_write_text, finite_json
from diffshadow.lights import layout_of
from diffshadow.report import pyplot, save_figure
from diffshadow.scaling.projection import CPU_SOURCE
from diffshadow.scaling.sweep import SEEN, UNSEEN

if TYPE_CHECKING:  # matplotlib is imported where a figure is drawn
    from matplotlib.figure import Figure


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


def cost_figure(data: dict) -> Figure:
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


def _quality(point: dict, section: str, key: str) -> float | None:
    """A point's figure for the voxel_metrics `key` of `section` ("seen" or "unseen"); None where not measured."""
    return point["quality"][section].get(key.removesuffix("_psnr_median"))


def quality_figure(data: dict) -> Figure:
    """Median voxel PSNR on unseen lights (generated, the model alone, blends, nearest) and on seen lights
    (generated, the model alone, stage 1); a row no point measured is left out."""
    fig, ax = _axes(2, 6.0)
    ns = [p["lights"] for p in data["points"]]
    for a, section, rows in ((ax[0], "unseen", UNSEEN), (ax[1], "seen", SEEN)):
        for key, label in rows:
            ys = [_quality(p, section, key) for p in data["points"]]
            if any(y is not None for y in ys):  # a row the points measured (the model alone: only where mixed)
                a.plot(ns, [np.nan if y is None else y for y in ys], "o-", label=label)
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


def storage_figure(data: dict) -> Figure:
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

    # the CPU rules timed at the paper's sizes beside the carried and benched ones; the total counts those that a
    # run of the paper config has
    measured = {s: {**r, "source": r["source"] + (f" (only under {r['only_with']}; not in the total)"
                                                   if r["only_with"] else "")}
                for s, r in proj.get("measured", {}).items()}
    stages = {**proj["stages"], **measured}
    rows = "".join(row(s, r) for s, r in sorted(stages.items(), key=lambda kv: -kv[1]["node_hours"]))
    total = sum(r["node_hours"] for r in stages.values() if not r.get("only_with"))
    bench = f" ({html.escape(proj['bench_stages'])})" if proj.get("bench_stages") else ""
    fits = proj.get("fit_rounds") or []
    rounds = (f"{sum(fits)} subsets in {len(fits)} rounds of {', '.join(map(str, fits))} (<code>fit.rounds</code>: "
              f"a subset waits for the earlier-round neighbours whose SIRENs it holds)" if len(fits) > 1
              else f"{sum(fits)} subsets in one round" if fits else "subsets of 50")
    store = "".join(f"<tr><td>{n}</td>" + "".join(f"<td>{v / 2**20:,.0f}</td>" for v in b.values()) + "</tr>"
                    for n, b in proj["storage_bytes"].items())
    return f"""<h2>Projection: the paper's scale on Polaris</h2>
<p>{proj['lights']:,} training lights at config/paper.yaml, each stage from this sweep's exponent, the H200's
measured speed over this machine's per stage, the paper config's work per light over this run's, and an A100 taking
{proj['a100_per_h200']}x an H200's time (an assumption); a stage timed by `bench stages` at the paper's sizes on a
GPU{bench} instead takes that measurement's steps (the same A100 factor), and a CPU rule timed at the paper's sizes on
one thread of this machine takes that time, on one node. Stage 1: {rounds}, four to a
node job, {proj.get('stage1_nodes', 10)} nodes. Upper bounds where a small run leaves a GPU idle. train_diffusion's
exponent is its cost per epoch, carried at the configured epochs (its gap check chose the epochs each point
trained: {epochs}). The work per light is counted against the config the sweep's points ran at. Host memory: the
largest of the peak RSS carried to this light count, the same job's RSS on the H200 (CUDA's host context) and, where
measured, its peak on a CPU at the paper's sizes (scaling.PAPER_CPU_RSS_MIB: an upper bound for a GPU job, whose
model lives on the device; fine-tuning's per process, x its processes).</p>
<table><tr><th>stage</th><th>exponent</th><th>H200 / this CPU (used)</th><th>work factor</th><th>wall (h)</th>
<th>node-hours</th><th>host memory per job (GiB)</th></tr>{rows}<tr><td>total</td><td></td><td></td><td></td><td></td>
<td>{total:,.1f}</td><td></td></tr></table>
<table><tr><th>lights</th><th>SIRENs fp32 (MiB)</th><th>SIRENs fp16 (MiB)</th><th>model fp32 (MiB)</th></tr>
{store}</table>
"""


def ran_at(data: dict) -> str:
    """The run config's sizes that the sweep's points ran at (scaling.json's `run_config`), as the page says them."""
    run = data.get("run_config")
    if not run:
        return ""
    fit, diffusion = run["fit"], run["diffusion"]
    return html.escape(f", stage 1 at {fit['steps']:,} steps of {fit['points']:,} points, SIREN width "
                       f"{run['siren']['width']}; the diffusion model's preset {diffusion['preset']}, "
                       f"{diffusion['epochs']:,} epochs")


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
    cols = [("unseen", k) for k, _ in UNSEEN] + [("seen", k) for k, _ in SEEN]
    q = "".join(f"<tr><td>{n}</td>" + "".join(f"<td>{(_quality(p, *c) or float('nan')):.2f}</td>" for c in cols)
                + "</tr>" for n, p in zip(ns, pts, strict=True))
    qhead = "".join(f"<th>unseen: {html.escape(label)}</th>" for _, label in UNSEEN)
    qhead += "".join(f"<th>seen: {html.escape(label)}</th>" for _, label in SEEN)
    c = data["crossover_lights"]
    layout = html.escape(", ".join(sorted({layout_of(p) for p in pts})))
    return f"""<!doctype html><html><head><meta charset="utf-8"><title>diffshadow: scaling with the light count</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:2em auto}}td,th{{padding:2px 8px;text-align:right}}
td:first-child{{text-align:left}}table{{border-collapse:collapse}}tr:nth-child(even){{background:#f4f4f4}}</style>
</head><body><h1>Scaling with the number of training lights</h1>
<p>Runs at {", ".join(map(str, ns))} training lights (scripts/scaling_sweep.py), light layout <code>{layout}</code>
(<code>lights.layout</code>){ran_at(data)}. The model is smaller than the stored
SIRENs past {c['sirens_fp32']:,.0f} lights (fp32) or {c['sirens_fp16']:,.0f} (fp16), at these runs' SIREN and model
sizes.</p>
{f"<ul>{notes}</ul>" if notes else ""}
<h2>Cost per stage</h2><img src="scaling_costs.png" width="900">
<table><tr><th>stage</th>{head}<th>exponent</th><th>peak RSS (MiB)</th></tr>{"".join(rows)}</table>
<h2>Quality</h2><img src="scaling_quality.png" width="1000">
<table><tr><th>lights</th>{qhead}</tr>{q}</table>
<h2>Storage</h2><img src="scaling_storage.png" width="800">
{projection_html(data.get("projection"), pts)}
</body></html>
"""


