"""The caches' rate and distortion across the sweep's light counts: each point's `caches.json` (the stored
SIRENs, their codecs, the dense grids; a stage-1-only run, `cache: blend`) beside the diffusion model's figures
at the same point from the full sweep's scaling.json (its bytes in fp32 and fp16, its seen and unseen medians).

At each light count: where every cache sits on the bytes-PSNR plane, and the model against the best stored-SIREN
cache no larger than it (`equal_bytes`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from diffshadow.io import atomic_write_text, finite_json
from diffshadow.lights import layout_of
from diffshadow.report import label_points, pyplot, save_figure

if TYPE_CHECKING:  # matplotlib is imported where a figure is drawn
    from matplotlib.figure import Figure


def collect(runs: list[Path], model_points: list[dict], model_source: str = "the sweep's scaling.json") -> dict:
    """One entry per run (results/<scene>/ with caches.json): its rows. A full run's table holds the model's own
    rows (and the mix's), measured on the same points; a stage-1-only run's (`cache: blend`) gets the model's
    rows from the sweep point of the same light count and light layout (`model_points`, read from `model_source`;
    none where the sweep has no such point)."""
    models = {p["lights"]: p for p in model_points}
    points = []
    for results in runs:
        path = Path(results) / "caches.json"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: missing (run the point with scripts/scaling_sweep.py --caches)")
        table = json.loads(path.read_text())
        n = table["lights"]["train"]
        rows = list(table["caches"])
        choice = _read(Path(results) / "cache_choice.json")  # where `cache: auto` was asked too
        if choice:
            val = {("fp32" if c["cache"] == "blend" else c["cache"]): c["val_psnr"] for c in choice["candidates"]}
            for r in rows:
                name = r["cache"].removeprefix("stored SIRENs ")
                if r["kind"] in ("stored", "codec") and name in val:
                    r["val_psnr"] = val[name]
        m = models.get(n)
        if m is not None and layout_of(m) != layout_of(_read(Path(results) / "lights.json") or {}):
            m = None  # another region's model: its figures are not this run's to stand beside
        if m is not None and not any(r["kind"] == "model" for r in rows):
            # the model's own SIRENs: where the sweep mixed them with the blend, "generated" is the mix's answer
            seen, unseen = (m["quality"][k].get("model_alone") or m["quality"][k]["generated"]
                            for k in ("seen", "unseen"))
            for name, nbytes in (("fp32", m["storage_bytes"]["model"]), ("fp16", m["storage_bytes"]["model"] // 2)):
                rows.append({"cache": f"diffusion model {name}", "kind": "model", "bytes": int(nbytes),
                             "seen_psnr": seen, "unseen_psnr": unseen,
                             "source": f"{model_source} (fp16: half the bytes, the figures of fp32, which the "
                                       "README run measured 0.01 dB apart)"})
        points.append({"lights": n, "unseen_lights": table["lights"]["unseen"], "caches": rows,
                       "equal_bytes": equal_bytes(rows),
                       **({"auto": {k: choice[k] for k in ("choice", "why", "target_psnr", "tolerance")
                                          if k in choice}} if choice else {})})
    return {"points": sorted(points, key=lambda p: p["lights"])}


def _read(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def equal_bytes(rows: list[dict]) -> dict | None:
    """The model (fp16, its smaller form) against the stored-SIREN cache of most unseen PSNR no larger than it."""
    model = next((r for r in rows if r["cache"] == "diffusion model fp16"), None)
    if model is None:
        return None
    stored = [r for r in rows if r["kind"] in ("stored", "codec") and r["bytes"] <= model["bytes"]]
    best = max(stored, key=lambda r: r.get("unseen_psnr", -np.inf), default=None)
    if best is None:
        return {"model_bytes": model["bytes"], "best": None}
    return {"model_bytes": model["bytes"], "model_unseen_psnr": model["unseen_psnr"], "best": best["cache"],
            "best_bytes": best["bytes"], "best_unseen_psnr": best["unseen_psnr"],
            "model_gain_db": model["unseen_psnr"] - best["unseen_psnr"]}


def write(data: dict, out: Path) -> None:
    """`out` (JSON) and scaling_caches.png beside it."""
    out = Path(out)
    atomic_write_text(out, json.dumps(finite_json(data), indent=1) + "\n")
    save_figure(out.parent / "scaling_caches.png", figure(data))


COLOURS = {"stored": "tab:blue", "codec": "tab:green", "model": "tab:red", "mix": "tab:purple", "grids": "tab:gray"}


def figure(data: dict) -> Figure:
    """One panel per light count: bytes (log) against unseen median voxel PSNR, one point per cache, seen PSNR
    as a faint marker above or below it."""
    pts = data["points"]
    fig, axes = pyplot().subplots(1, len(pts), figsize=(4.2 * len(pts), 4.4), sharey=True, squeeze=False)
    labelled = []
    for ax, p in zip(axes[0], pts, strict=True):
        points, labels = [], []
        for r in p["caches"]:
            if "unseen_psnr" not in r:
                continue
            c = COLOURS.get(r["kind"], "black")
            ax.scatter(r["bytes"], r["unseen_psnr"], color=c, marker="*" if r["kind"] == "model" else "o",
                       s=90 if r["kind"] == "model" else 30, zorder=3)
            ax.scatter(r["bytes"], r["seen_psnr"], color=c, marker="_", s=60, alpha=0.5, zorder=2)
            if r["cache"] == "diffusion model fp32" or (r["kind"] == "mix" and "fp32" in r["cache"]):
                continue  # one label for the model's (or the mix's) two points (the same PSNR within 0.1 dB)
            label = r["cache"].replace("stored SIRENs ", "").replace("dense shadow grids ", "grids ")
            if r["kind"] == "mix":
                label = f"mix, model share {r['share']:g}: fp16 | fp32"
            points.append((r["bytes"], r["unseen_psnr"]))
            labels.append(label.replace("diffusion model fp16", "model fp16 | fp32"))
        ax.set_xscale("log")
        ax.set_title(f"{p['lights']} training lights")
        ax.set_xlabel("bytes")
        ax.grid(alpha=0.3)
        labelled.append((ax, points, labels))
    axes[0][0].set_ylabel("median voxel PSNR, unseen lights (dB); – seen")
    fig.suptitle("caches as rate (bytes) against distortion: stored SIRENs (blue), codecs (green), diffusion "
                 "model (red stars: fp16, fp32), its mix with the stored SIRENs (purple), dense grids (grey)\n"
                 "markers: unseen lights; dashes: seen lights",
                 fontsize=9)
    fig.tight_layout()
    for ax, points, labels in labelled:  # after the layout: labels are placed where they will be drawn
        label_points(ax, points, labels)
    return fig


def markdown(data: dict) -> str:
    """The table for docs: one row per cache and light count."""
    lines = ["| lights | cache | MiB | seen dB | unseen dB | validation dB |", "|---|---|---|---|---|---|"]
    for p in data["points"]:
        for r in sorted(p["caches"], key=lambda r: r["bytes"]):
            lines.append(f"| {p['lights']} | {r['cache']} | {r['bytes'] / 2**20:.3f} | {r['seen_psnr']:.2f} | "
                         f"{r.get('unseen_psnr', float('nan')):.2f} | {_or_dash(r.get('val_psnr'))} |")
    for p in data["points"]:
        eq = p.get("equal_bytes") or {}
        if eq.get("best"):
            lines.append(f"\n{p['lights']} lights: the model (fp16, {eq['model_bytes'] / 2**20:.2f} MiB) against "
                         f"{eq['best']} ({eq['best_bytes'] / 2**20:.2f} MiB), the best stored cache no larger: "
                         f"{eq['model_gain_db']:+.2f} dB on unseen lights."
                         + (f" cache: auto chose {p['auto']['choice']}." if "auto" in p else ""))
    return "\n".join(lines) + "\n"


def _or_dash(x) -> str:
    return "–" if x is None else f"{x:.2f}"
