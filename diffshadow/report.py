"""Figures for the Snakemake report (`snakemake --report report.html`): one PNG or CSV per question a
user asks of a finished scene. Each is computed from the scene's results; nothing is re-trained."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from diffshadow.io import atomic_path, atomic_write_text, read_json
from diffshadow.phases import NUMERIC_LIBRARIES

if TYPE_CHECKING:  # matplotlib and the stores are imported where a figure is drawn
    from types import ModuleType

    from matplotlib.axes import Axes
    from matplotlib.axis import Axis
    from matplotlib.figure import Figure

    from diffshadow.store import WeightStore


def shading_name(phong: bool) -> str:
    """How the image modes shade a sample (what a report states beside image metrics)."""
    return "Blinn-Phong" if phong else "unlit (colour x (0.1 + 0.9 g))"


def save_figure(path: Path, fig: Figure) -> None:
    """A figure as a PNG, written atomically, then closed."""
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    import matplotlib.pyplot as plt

    plt.close(fig)


def pyplot() -> ModuleType:
    """matplotlib.pyplot on the file-only Agg backend (no display on compute nodes)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def decade_labels(axis: Axis) -> None:
    """Label a log axis at its decades only (the minor labels overlap); an axis that spans less than two
    decades (one that would show one label or none) at 1, 2 and 5 of each decade, and at every digit below a
    factor of 3. Call it once the data are plotted."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    ax = axis.axes  # get_xlim / get_ylim bring a lazily autoscaled view up to date first
    lo, hi = sorted(ax.get_xlim() if axis is ax.xaxis else ax.get_ylim())
    if lo > 0 and hi / lo < 100:
        axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0) if hi / lo >= 3 else tuple(range(1, 10))))
        axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    axis.set_minor_formatter(NullFormatter())


def siren_psnr_figure(stage1: WeightStore, out: Path) -> None:
    """Stage-1 voxel PSNR of every light's SIREN (over the box and in the visible region)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 3.5))
    idx = np.arange(len(stage1.psnr))
    ax.plot(idx, stage1.psnr, ".", label="box")
    ax.plot(idx, stage1.psnr_visible, ".", label="visible region")
    ax.set_xlabel("training light")
    ax.set_ylabel("voxel PSNR (dB)")
    ax.set_title(f"stage 1: median {np.median(stage1.psnr):.2f} dB, min {np.min(stage1.psnr):.2f} dB")
    ax.legend()
    fig.tight_layout()
    save_figure(out, fig)


NO_UNSEEN = "no unseen lights (lights.unseen: 0)"


def _say(ax, text: str) -> None:
    """A panel with nothing to plot: `text` in its middle, no axes."""
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes)
    ax.set_axis_off()


def generated_figure(stage1: WeightStore, generated: WeightStore, out_png: Path, out_csv: Path) -> None:
    """Generated vs stage-1 PSNR on seen lights; generated PSNR on unseen lights (plot and table)."""
    plt = pyplot()
    seen = generated.seen
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ax[0].plot(stage1.psnr, generated.psnr[seen], ".")
    lo, hi = float(min(stage1.psnr.min(), generated.psnr[seen].min())), float(stage1.psnr.max())
    ax[0].plot([lo, hi], [lo, hi], "k--", lw=0.8)
    ax[0].set_xlabel("stage-1 SIREN PSNR (dB)")
    ax[0].set_ylabel("generated SIREN PSNR (dB)")
    ax[0].set_title(f"seen lights (median {np.median(generated.psnr[seen]):.2f} dB)")
    if (~seen).any():
        from matplotlib.ticker import MaxNLocator

        ax[1].hist(generated.psnr[~seen], bins=20)
        ax[1].set_xlabel("generated SIREN PSNR (dB)")
        ax[1].set_ylabel("unseen lights")
        ax[1].yaxis.set_major_locator(MaxNLocator(integer=True))  # counts of lights
        ax[1].set_title(f"unseen lights (median {np.median(generated.psnr[~seen]):.2f} dB)")
    else:
        _say(ax[1], NO_UNSEEN)
    fig.tight_layout()
    save_figure(out_png, fig)
    rows = ["set,light,x,y,z,stage1_psnr,generated_psnr"]
    for i in range(len(generated.psnr)):
        s = "seen" if seen[i] else "unseen"
        st = f"{stage1.psnr[i]:.3f}" if seen[i] else ""
        x, y, z = generated.lights[i]
        rows.append(f"{s},{i},{x:.4f},{y:.4f},{z:.4f},{st},{generated.psnr[i]:.3f}")
    atomic_write_text(out_csv, "\n".join(rows) + "\n")


def diff_range(diffs: list[np.ndarray]) -> float:
    """The difference maps' colour scale: the 99.5th percentile of |ours - gt| over every row, rounded up to 1, 2
    or 5 times a power of ten (a fixed 0.1 left nucleon's ~0.01 errors black); the same in every row."""
    top = max(float(np.percentile(d, 99.5)) for d in diffs) if diffs else 0.0
    if top <= 0:
        return 0.01
    power = 10.0 ** np.floor(np.log10(top))
    return float(next(m * power for m in (1, 2, 5, 10) if m * power >= top))


# the image grid's rows of one light set: the default run's 2 lights x 2 views each; a run that renders more
# (render.lights_per_set: 32 makes 128 rows, a PNG 30,000 px high) shows some, and every image stays in images/
GRID_ROWS_PER_SET = 4
_IMAGE_TAG = re.compile(r"(train|unseen)(\d+)_view(\d+)")


def grid_rows(tags: list[str], keep: set[str] | frozenset[str] = frozenset(),
              per_set: int = GRID_ROWS_PER_SET) -> list[str]:
    """The image tags (`<set><light>_view<view>`) the image grid shows, training lights then unseen, each in light
    order: all of a set's where it has at most `per_set`, else those in `keep` (the naive baseline's) and lights
    spread evenly over the rest, one view each (the next light the next view), filled up from what is left."""
    keys = {}
    for tag in tags:
        m = _IMAGE_TAG.fullmatch(tag)
        keys[(m[1], int(m[2]), int(m[3])) if m else (tag, 0, 0)] = tag
    shown = []
    for name in sorted({k[0] for k in keys}):
        rows = sorted(k for k in keys if k[0] == name)
        if len(rows) > per_set:
            chosen = [k for k in rows if keys[k] in keep][:per_set]
            views: dict[int, list] = {}
            for k in rows:
                views.setdefault(k[1], []).append(k)
            others = [light for light in views if light not in {k[1] for k in chosen}]
            if (n := per_set - len(chosen)) > 0 and others:
                picks = np.unique(np.linspace(0, len(others) - 1, n).round().astype(int))
                chosen += [views[others[i]][(j + len(chosen)) % len(views[others[i]])] for j, i in enumerate(picks)]
            chosen += [k for k in rows if k not in chosen][:per_set - len(chosen)]
            rows = sorted(chosen)
        shown += [keys[k] for k in rows]
    return shown


def image_grid_figure(images_dir: Path, lights: dict, out: Path,
                      modes: tuple[str, ...] = ("gt", "inr_generated", "naive", "noshadow")) -> None:
    """Rows: (light, view) pairs with every mode rendered (`grid_rows`: at most GRID_ROWS_PER_SET a light set),
    labelled with the light's direction; columns: gt / ours / naive / no shadow, then |ours - gt| and
    |no shadow - gt| (what the shadow term adds)."""
    from PIL import Image

    plt = pyplot()
    tags = sorted({p.name.rsplit("_gt.png", 1)[0] for p in images_dir.glob("*_gt.png")})
    # naive is rendered for the training lights only (it learns nothing from them): an unseen row shows the rest
    needed = [m for m in modes if m != "naive"]
    tags = [t for t in tags if all((images_dir / f"{t}_{m}.png").exists() for m in needed)]
    if not tags:
        raise ValueError(f"{images_dir}: no light/view with all of {needed} rendered")
    rendered = len(tags)
    tags = grid_rows(tags, keep={t for t in tags if (images_dir / f"{t}_naive.png").exists()})
    titles = {"gt": "ground truth", "inr_generated": "ours (generated)",
              "naive": "naive secondary rays\n(rows it was rendered for)", "noshadow": "no shadow"}
    diffs = [("inr_generated", "|ours - gt|"), ("noshadow", "|no shadow - gt|")]
    ncol = len(modes) + len(diffs)
    images = [{m: np.asarray(Image.open(images_dir / f"{tag}_{m}.png").convert("RGB"), dtype=np.float32) / 255
               for m in modes if (images_dir / f"{tag}_{m}.png").exists()} for tag in tags]
    vmax = diff_range([np.abs(img["inr_generated"] - img["gt"]).max(axis=2) for img in images
                       if "inr_generated" in img])
    fig, axes = plt.subplots(len(tags), ncol, figsize=(2.3 * ncol, 2.4 * len(tags)), squeeze=False)
    for r, (tag, img) in enumerate(zip(tags, images, strict=True)):
        for c, mode in enumerate(modes):
            if mode in img:
                axes[r, c].imshow(img[mode])
            else:  # the slow naive baseline draws only render.naive_lights x naive_views views: no cell here
                axes[r, c].set_axis_off()
            if r == 0:
                axes[r, c].set_title(titles.get(mode, mode), fontsize=9)
        for k, (mode, title) in enumerate(diffs):
            shown = axes[r, len(modes) + k].imshow(np.abs(img[mode] - img["gt"]).max(axis=2), cmap="magma",
                                                  vmin=0, vmax=vmax)
            if r == 0:
                axes[r, len(modes) + k].set_title(title, fontsize=9)
        for a in axes[r]:
            a.set_xticks([])
            a.set_yticks([])
        m = _IMAGE_TAG.fullmatch(tag)
        if m:
            x, y, z = lights[m[1]][int(m[2])]
            kind = "training" if m[1] == "train" else "unseen"
            label = f"{kind} light {m[2]}\n({x:+.2f}, {y:+.2f}, {z:+.2f})\nview {m[3]}"
        else:
            label = tag
        axes[r, 0].set_ylabel(label, fontsize=8)
    top = 1.0
    if len(tags) < rendered:
        top = 1 - 0.35 / fig.get_figheight()
        fig.suptitle(f"{len(tags)} of the {rendered} renderings, at most {GRID_ROWS_PER_SET} a light set (every one "
                     f"is in {images_dir.name}/)", fontsize=9, y=0.995, va="top")
    fig.tight_layout(rect=(0, 0, 0.93, top))
    bar = fig.colorbar(shown, ax=axes[:, -2:].ravel().tolist(), fraction=0.04, pad=0.02, extend="max")
    bar.set_label(f"max over RGB of the difference, 0 to {vmax:g} of full scale (|ours - gt|'s 99.5th "
                  "percentile; larger saturates)", fontsize=7)
    save_figure(out, fig)


def ddim_curve_figure(sampling: dict | None, out: Path) -> None:
    """Time per INR against median voxel PSNR for DDIM step counts, and 500-step DDPM: the rows that
    evaluate_voxels measured (`voxel_metrics.json` → sampling.curve; quality over `sampling.lights` training
    lights generated in one batch, time that of one INR alone, best of 3; DDPM once). None (`cache: blend`):
    a figure that says there is no sampler; no `curve` (`evaluate.ddpm_lights: 0`): one that says there is none."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    if sampling is None or "curve" not in sampling:
        _say(ax, "cache: blend\nno diffusion model: a light's SIREN is the weight blend\nof the stored SIRENs "
             "nearest to it (no sampler to time)" if sampling is None else
             f"evaluate.ddpm_lights: 0\nno sampler curve (the run samples with DDIM, {sampling['ddim_steps']} steps)")
        save_figure(out, fig)
        return
    rows = sampling["curve"]
    d = [r for r in rows if r["method"] == "ddim"]
    ax.plot([r["seconds_per_inr"] for r in d], [r["psnr_median"] for r in d], "o-", label="DDIM")
    p = rows[-1]
    ax.plot([p["seconds_per_inr"]], [p["psnr_median"]], "s", label="DDPM 500")
    ax.set_xscale("log")
    decade_labels(ax.xaxis)
    ax.set_xlabel("seconds per shadow INR (one INR alone, on evaluate_voxels' device)")
    ax.set_ylabel(f"median voxel PSNR over {sampling['lights']} training lights (dB)")
    # at least 2 dB of axis: a spread of a tenth of a dB is sampling noise, not a trend
    mid = float(np.median([r["psnr_median"] for r in rows]))
    lo, hi = min(r["psnr_median"] for r in rows), max(r["psnr_median"] for r in rows)
    ax.set_ylim(min(lo - 0.3, mid - 1.0), max(hi + 0.3, mid + 1.0))
    ax.legend()
    fig.tight_layout()
    label_points(ax, [(r["seconds_per_inr"], r["psnr_median"]) for r in d], [f"{r['steps']}" for r in d], fontsize=9)
    save_figure(out, fig)


def storage_figure(voxel_metrics: dict, n_lights: int, out: Path) -> None:
    """Bytes of the diffusion cache against the N SIRENs and N dense float16 grids it replaces."""
    plt = pyplot()
    sb = voxel_metrics["storage_bytes"]
    mixed = "mix" in voxel_metrics  # the cache keeps the model and the stored SIRENs it mixes in
    fig, ax = plt.subplots(figsize=(6.5, 3.8))
    names = ["model + SIRENs (the mix)" if mixed else "diffusion model" if sb["model"] else "no model (cache: blend)",
             f"{n_lights} SIRENs (fp32)", f"{n_lights} dense grids (fp16)"]
    kept = sb["model"] + (sb["sirens"] + sb.get("correction", 0) if mixed else 0)  # the blend's correction too
    values = np.asarray([kept, sb["sirens"], sb["grids"]]) / 2**20
    ax.bar(names, values, color=["C0", "C1", "C2"])
    for i, v in enumerate(values):
        ax.annotate(f"{v:.2f} MiB", (i, v), ha="center", va="bottom")
    ax.set_ylabel("MiB")
    ax.set_ylim(0, values.max() * 1.2)
    ratio = values[0] / values[2]
    # the model's size does not grow with the light count; the grids grow with lights x voxels
    cache = "the model and the SIRENs" if mixed else "the model"
    verdict = ("the stored SIRENs are the cache (cache: blend)" if not sb["model"] else
               f"{cache} take {ratio:.1f}x the grids' bytes at this scale" if ratio > 1
               else f"{cache} take {1 / ratio:.1f}x fewer bytes than the grids")
    ax.set_title(f"{verdict}\n(the model's size is fixed; grids grow with lights x voxels)", fontsize=9)
    fig.tight_layout()
    save_figure(out, fig)


def caches_figure(table: dict, out: Path) -> None:
    """Rate against distortion (`caches.json`): each cache's bytes against its median voxel PSNR on unseen
    lights (its own answer for a new light) and on the seen ones; up and to the left is better."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=False)
    colours = {"stored": "C1", "codec": "C1", "corrected": "C3", "model": "C0", "mix": "C4", "grids": "C2"}
    mixed = any(row["kind"] == "mix" for row in table["caches"])
    corrected = any(row["kind"] == "corrected" for row in table["caches"])
    panels = []
    for ax, key, title in ((axes[0], "unseen_psnr", "unseen lights (the cache's answer)"),
                           (axes[1], "seen_psnr", "seen (training) lights")):
        points, labels = [], []
        for row in table["caches"]:
            if row.get(key) is None:
                continue
            marker = "s" if row["kind"] == "stored" else "o"
            ax.scatter(row["bytes"] / 2**20, row[key], color=colours[row["kind"]], marker=marker, s=36)
            label = (row["cache"].replace("stored SIRENs ", "" if row["kind"] == "codec" else "SIRENs ")
                     .replace("diffusion model", "model").replace("dense shadow grids", "grids"))
            if row["kind"] == "mix":
                label = f"mix {row['share']:g}, {label.rsplit(' ', 1)[-1]}"
            points.append((row["bytes"] / 2**20, row[key]))
            labels.append(label)
        if not points:
            _say(ax, NO_UNSEEN)
            ax.set_title(title, fontsize=10)
            continue
        ax.set_xscale("log")
        lo, hi = ax.get_xlim()
        ax.set_xlim(lo / 3, hi * 4)  # room for the labels on both sides, and above the best caches
        lo, hi = ax.get_ylim()
        ax.set_ylim(lo, hi + 0.12 * (hi - lo))
        ax.set_xlabel("bytes stored (MiB, log)")
        ax.set_ylabel("median voxel PSNR (dB)")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
        panels.append((ax, points, labels))
    n = table["lights"]
    # two lines where every kind is there: one ran past the figure's edges
    fig.suptitle(f"caches of {n['train']} training lights: orange stored SIRENs and their codecs, "
                 f"{'red with the blend correction,' + chr(10) if corrected else ''}blue the diffusion model, "
                 f"{'purple the two mixed (both kept), ' if mixed else ''}green dense shadow grids",
                 fontsize=9)
    fig.tight_layout()
    for ax, points, labels in panels:  # after the layout: labels are placed where they will be drawn
        label_points(ax, points, labels)
    save_figure(out, fig)


# where a point's label may go, in order of preference: (dx, dy) in points from the point, and its alignment
LABEL_PLACES = tuple((sx * dx, sy * dy, "left" if sx * dx > 0 else "right" if sx * dx < 0 else "center",
                      "bottom" if sy > 0 else "top")
                     for dx, dy in ((4, 3), (0, 7), (4, 11), (12, 3), (10, 18), (24, 8), (0, 24), (28, 20),
                                    (16, 32), (40, 4))
                     for sy in (1, -1) for sx in ((1, -1) if dx else (1,)))
LEADER_FROM = 10  # points: a label this far from its point is drawn with a line to it


def label_points(ax: Axes, points: list[tuple[float, float]], labels: list[str], *, fontsize: float = 7) -> list:
    """Each point's label beside it, at the first of `LABEL_PLACES` where it overlaps no label placed before it
    and no other point and stays inside the axes; where none is free, where it overlaps least (a label over a
    label counts double). The axes' limits and the figure's layout must be final: boxes are measured as drawn.
    Returns the labels' boxes (display units)."""
    from matplotlib.text import Text
    from matplotlib.transforms import Bbox

    renderer = ax.figure.canvas.get_renderer()
    ax.set_xlim(ax.get_xlim())  # frozen: a later autoscale would move the points from under their labels
    ax.set_ylim(ax.get_ylim())
    at = ax.transData.transform(np.asarray(points, dtype=float).reshape(-1, 2))
    half = 5 * ax.figure.dpi / 72  # a marker's half width and a margin, so that a label is not read as a neighbour's
    markers = [Bbox.from_extents(x - half, y - half, x + half, y + half) for x, y in at]
    frame = ax.get_window_extent(renderer)
    placed = []
    for i, (point, text) in enumerate(zip(points, labels, strict=True)):
        best = None
        for dx, dy, ha, va in LABEL_PLACES:
            leader = {"arrowprops": {"arrowstyle": "-", "lw": 0.5, "color": "0.5", "shrinkA": 0, "shrinkB": 3}
                      } if max(abs(dx), abs(dy)) > LEADER_FROM else {}
            note = ax.annotate(text, point, xytext=(dx, dy), textcoords="offset points", fontsize=fontsize,
                               ha=ha, va=va, **leader)
            # the text's box alone (an annotation's own box takes in its leader line), with a gap around it
            note.update_positions(renderer)
            box = Text.get_window_extent(note, renderer).padded(2 * ax.figure.dpi / 72)
            inside = (frame.x0 <= box.x0 and box.x1 <= frame.x1 and frame.y0 <= box.y0 and box.y1 <= frame.y1)
            cost = (2 * sum(box.overlaps(b) for b in placed)
                    + sum(box.overlaps(m) for j, m in enumerate(markers) if j != i) + 4 * (not inside))
            if best is None or cost < best[0]:
                if best is not None:
                    best[1].remove()
                best = (cost, note, box)
            else:
                note.remove()
            if cost == 0:
                break
        placed.append(best[2])
    return placed


def shadow_curve_figure(bench_json: dict, out: Path) -> None:
    """The ground-truth shadow methods' time against error on this scene's volume (from bench shadow)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    for name, vol in bench_json["volumes"].items():
        for method in ("march", "sweep"):
            rows = [r for r in vol["rows"] if r["method"] == method and r["max_err"] > 0]
            ax.plot([r["seconds"] for r in rows], [r["mean_err"] for r in rows], "o-", label=f"{name} {method}")
    ax.set_xscale("log")
    ax.set_yscale("log")
    decade_labels(ax.xaxis)
    decade_labels(ax.yaxis)
    ax.set_xlabel("seconds per shadow grid")
    ax.set_ylabel(f"mean |error| vs march at {bench_json['reference_step']} voxel")
    ax.legend()
    fig.tight_layout()
    save_figure(out, fig)


def scene_figures(weights: Path, generated: Path, lights_path: Path, images_dir: Path, voxel_metrics: Path,
                   shadow_bench: Path, cfg: dict, out: Path) -> None:
    """The report's figures for one finished scene, from its results (nothing is re-trained or re-timed, and
    torch is not imported: report_figures sits on the run's last stretch)."""
    from diffshadow.lights import read_lights
    from diffshadow.store import open_store

    out.mkdir(parents=True, exist_ok=True)
    write_config(out / "config.yaml", cfg)
    stage1, generated_store = open_store(weights), open_store(generated)
    siren_psnr_figure(stage1, out / "siren_psnr.png")
    generated_figure(stage1, generated_store, out / "generated_psnr.png", out / "generated_psnr.csv")
    lights = read_lights(lights_path)
    image_grid_figure(images_dir, lights, out / "image_grid.png")
    metrics = read_json(voxel_metrics, "the voxel metrics of evaluate_voxels")
    storage_figure(metrics, len(lights["train"]), out / "storage.png")
    ddim_curve_figure(metrics.get("sampling"), out / "ddim_curve.png")
    shadow_curve_figure(read_json(shadow_bench, "the shadow benchmark of shadow_bench"), out / "shadow_curve.png")
    print(f"wrote the report figures in {out}")


def write_config(path: Path, cfg: dict) -> None:
    import yaml

    atomic_write_text(path, yaml.safe_dump(json.loads(json.dumps(cfg)), sort_keys=False))


PHASE_COLUMNS = ("import_s", "device_s", "compile_s", "io_s", "compute_s", "launch_s")
STAGE_COST_COLUMNS = ("stage", "jobs", "wall_s", "cpu_s", "max_rss_mib", *PHASE_COLUMNS, "critical_s")


def job_phases(benchmark: Path, wall: float) -> dict[str, float] | None:
    """The phases of one job (`<benchmark stem>.phases.json`, which `diffshadow --phases` writes beside its
    benchmark file), with `launch_s`: the job's wall time outside its `diffshadow` process (the shell, `tee`,
    torchrun and its helper processes); and the process's own `cpu_s` and `max_rss_mib` where it recorded them
    (`phases.usage`). None where the job wrote none (a job of an older run)."""
    path, rec = _phases_record(benchmark)
    if rec is None:
        return None
    try:
        out = {k: float(rec[k]) for k in PHASE_COLUMNS[:-1]}
    except (KeyError, TypeError, ValueError):
        raise _not_a_phases_file(path) from None
    out["launch_s"] = max(0.0, wall - sum(out.values()))
    try:
        out.update({k: float(rec[k]) for k in ("cpu_s", "max_rss_mib") if k in rec})
    except (ValueError, TypeError):
        raise ValueError(f"{path}: cpu_s and max_rss_mib: expected numbers, got {rec.get('cpu_s')!r} and "
                         f"{rec.get('max_rss_mib')!r}") from None
    return out


def _phases_record(benchmark: Path) -> tuple[Path, dict | None]:
    """The phases file beside a job's benchmark file and its record (None where the job wrote none); a file that
    is not a JSON object is named in one line."""
    path = Path(benchmark).with_suffix(".phases.json")
    if not path.exists():
        return path, None
    try:
        rec = json.loads(path.read_text())
    except ValueError:
        rec = None
    if not isinstance(rec, dict):
        raise _not_a_phases_file(path)
    return path, rec


def _not_a_phases_file(path: Path) -> ValueError:
    return ValueError(f"{path}: expected a phases file ({', '.join(PHASE_COLUMNS[:-1])}), as written by "
                      f"diffshadow --phases")


def _benchmark(path: Path) -> tuple[str, float, float, float, float]:
    """One job's Snakemake benchmark file: its rule (`<rule>_<n>.tsv` is job n of a fanned-out rule), wall and CPU
    seconds, peak resident set (MiB) and when it ended (the file's mtime: Snakemake writes it as the job ends)."""
    lines = Path(path).read_text().splitlines()
    if len(lines) < 2:
        raise ValueError(f"{path}: expected a Snakemake benchmark file (a header and one row)")
    rec = dict(zip(lines[0].split("\t"), lines[1].split("\t"), strict=False))
    try:
        # Snakemake writes NA where it could not measure (e.g. a job shorter than its poll)
        wall = float(rec["s"].replace("NA", "0"))
        cpu, rss = (float(rec.get(k, "0").replace("NA", "0")) for k in ("cpu_time", "max_rss"))
    except (KeyError, ValueError):
        raise ValueError(f"{path}: expected numeric columns s, cpu_time, max_rss; got {lines[:2]}") from None
    stem = Path(path).stem
    stage = stem.rsplit("_", 1)[0] if stem.rsplit("_", 1)[-1].isdigit() else stem
    return stage, wall, cpu, rss, Path(path).stat().st_mtime


def stage_costs(benchmarks: list[Path], out: Path, jobs: list[dict] | None = None) -> list[dict]:
    """One row per rule from Snakemake's `benchmark:` files (`<rule>.tsv`, or `<rule>_<n>.tsv` per job of a
    fanned-out rule): jobs, summed wall and CPU seconds, the largest resident set (each job's CPU seconds and
    peak the larger of Snakemake's polls and the process's own record, `job_phases`), and where the wall time went
    (`job_phases`, summed over the rule's jobs; NA where a job recorded none); a total row (the sum of
    jobs' wall times, which exceeds the run's wall time where jobs overlapped); and an elapsed row, the time
    in which at least one job ran. Snakemake writes a benchmark file as its job ends, so a job ran from the
    file's mtime minus its wall seconds to its mtime; the union of those spans is a whole run's elapsed time
    and, after a partial rerun, still counts each job once rather than the days between. `critical_s`: the wall
    seconds of the rule's jobs on the run's `critical_path`; in the total row the path's jobs' sum, in the elapsed
    row the path from its first job's start to its last job's end (the difference: time between its jobs), from
    `jobs` (`job_spans` of the same files, where the caller has them; else read here). Written as TSV."""
    rows: dict[str, dict] = {}
    for path in benchmarks:
        stage, wall, cpu, rss, _ = _benchmark(path)
        row = rows.setdefault(stage, {"stage": stage, "jobs": 0, "wall_s": 0.0, "cpu_s": 0.0, "max_rss_mib": 0.0,
                                      **dict.fromkeys(PHASE_COLUMNS, 0.0)})
        phases = job_phases(Path(path), wall)
        # both are lower bounds: Snakemake's polls miss a job's last stretch and peaks between polls, the process's
        # own record misses other processes of the job (torchrun's other ranks), so the larger is the closer
        own = phases or {}
        cpu, rss = max(cpu, own.get("cpu_s", 0.0)), max(rss, own.get("max_rss_mib", 0.0))
        row["jobs"] += 1
        row["wall_s"] += wall
        row["cpu_s"] += cpu
        row["max_rss_mib"] = max(row["max_rss_mib"], rss)
        for key in PHASE_COLUMNS:
            row[key] = None if phases is None or row[key] is None else row[key] + phases[key]
    table = sorted(rows.values(), key=lambda r: -r["wall_s"])
    total = {"stage": "total (sum over jobs)", "jobs": sum(r["jobs"] for r in table),
             "wall_s": sum(r["wall_s"] for r in table), "cpu_s": sum(r["cpu_s"] for r in table),
             "max_rss_mib": max((r["max_rss_mib"] for r in table), default=0.0),
             **{k: None if any(r[k] is None for r in table) else sum(r[k] for r in table) for k in PHASE_COLUMNS}}
    if jobs is None:
        jobs = job_spans(benchmarks)[0] if benchmarks else []
    # the union of the jobs' spans: job_spans took out only stretches with no job running, which add nothing to it
    elapsed = {**total, "stage": ELAPSED_ROW, "wall_s": _union_length([(j["start"], j["end"]) for j in jobs]),
               **dict.fromkeys(PHASE_COLUMNS)}
    path = critical_path(jobs)
    for r in table:
        r["critical_s"] = sum(j["end"] - j["start"] for j in path if j["stage"] == r["stage"])
    total["critical_s"] = sum(j["end"] - j["start"] for j in path)
    elapsed["critical_s"] = path[-1]["end"] - path[0]["start"] if path else 0.0

    def cells(r: dict) -> str:
        phases = "\t".join("NA" if r[k] is None else f"{r[k]:.1f}" for k in (*PHASE_COLUMNS, "critical_s"))
        return f"{r['stage']}\t{r['jobs']}\t{r['wall_s']:.1f}\t{r['cpu_s']:.1f}\t{r['max_rss_mib']:.0f}\t{phases}\n"

    atomic_write_text(out, "\t".join(STAGE_COST_COLUMNS) + "\n" + "".join(cells(r) for r in [*table, total, elapsed]))
    return [*table, total, elapsed]


IDLE_S = 60.0  # a stretch with no job running longer than this is not the run's (a rerun's jobs days later)


def job_spans(benchmarks: list[Path]) -> tuple[list[dict], list[float]]:
    """Every job on the run's clock, sorted by start: its rule, job (the benchmark file's stem), `start` and `end`
    in seconds from the first job's start, its `startup` seconds (interpreter and imports, device start, and the
    time outside its process: `job_phases`; 0 where it recorded none) and `compile` seconds; and the places on
    that clock where a stretch of over `IDLE_S` with no job running was taken out (so a partial rerun days later
    joins the run; shorter ones, Snakemake's own time between jobs, stay)."""
    if not benchmarks:
        raise ValueError("job_spans: no benchmark files given")
    jobs = []
    for path in benchmarks:
        stage, wall, _, _, end = _benchmark(path)
        phases = job_phases(Path(path), wall) or dict.fromkeys(PHASE_COLUMNS, 0.0)
        jobs.append({"stage": stage, "job": Path(path).stem, "start": end - wall, "end": end,
                     "startup": phases["import_s"] + phases["device_s"] + phases["launch_s"],
                     "compile": phases["compile_s"]})
    jobs.sort(key=lambda j: (j["start"], j["job"]))
    origin = reach = jobs[0]["start"]
    gaps = []
    for j in jobs:  # in start order, so `reach` (the latest end so far) says whether this job starts after a gap
        if j["start"] > reach + IDLE_S:  # no job ran from `reach` to this start: that stretch leaves the clock
            gaps.append(reach - origin)
            origin += j["start"] - reach
        reach = max(reach, j["end"])
        j["start"], j["end"] = j["start"] - origin, j["end"] - origin
    return jobs, gaps


CHAIN_SLACK_S = 0.5  # a job's start and the end it waited for, both from file times, agree to ~0.1 s


def critical_path(jobs: list[dict]) -> list[dict]:
    """The run's critical path through `job_spans`' jobs, first to last: from the job that ended last, back through,
    for each job, the job whose end came last before it started (to within `CHAIN_SLACK_S`): the job that made its
    input, or the one whose slot it waited for. The run would have ended sooner only had one of these been
    shorter; the time between two of them is Snakemake's own, or a batch queue's wait."""
    if not jobs:
        return []
    chain = [max(jobs, key=lambda j: (j["end"], j["start"]))]
    while True:
        head = chain[-1]
        before = [j for j in jobs if j["start"] < head["start"] and j["end"] <= head["start"] + CHAIN_SLACK_S]
        if not before:
            return chain[::-1]
        chain.append(max(before, key=lambda j: (j["end"], j["start"])))


def timeline_figure(jobs: list[dict], gaps: list[float], out: Path, title: str = "") -> None:
    """`job_spans` as bars, one row per rule in the order the rules first started (a fanned-out rule's jobs share
    its row): what ran when, what waited, and each job's start-up and compile beside its work."""
    plt = pyplot()
    rules = list(dict.fromkeys(j["stage"] for j in jobs))
    fig, ax = plt.subplots(figsize=(9, 1.2 + 0.28 * len(rules)))
    colours = {"start-up (imports, device, launch)": "#e08a2c", "compile": "#b04fb0",
               "work (compute, files)": "#3b75af"}
    path = critical_path(jobs)
    for j in jobs:
        y = rules.index(j["stage"])
        startup = min(j["startup"], j["end"] - j["start"])
        compile_s = min(j["compile"], j["end"] - j["start"] - startup)
        parts = (startup, compile_s, j["end"] - j["start"] - startup - compile_s)
        left = j["start"]
        for width, colour in zip(parts, colours.values(), strict=True):
            ax.barh(y, width, left=left, height=0.7, color=colour, edgecolor="none", alpha=0.85)
            left += width
    for j in path:
        ax.barh(rules.index(j["stage"]), j["end"] - j["start"], left=j["start"], height=0.7, fill=False,
                edgecolor="black", linewidth=1.2)
    for y, rule in enumerate(rules):
        own = [j for j in jobs if j["stage"] == rule]
        wall = sum(j["end"] - j["start"] for j in own)
        ax.text(max(j["end"] for j in own), y, f" {wall:.1f} s" + (f" ({len(own)} jobs)" if len(own) > 1 else ""),
                va="center", fontsize=7)
    for gap in gaps:
        ax.axvline(gap, color="0.5", linestyle=":", linewidth=1)
    ax.set_yticks(range(len(rules)), rules, fontsize=8)
    ax.invert_yaxis()
    end = max(j["end"] for j in jobs)
    ax.set_xlim(0, end * 1.12)
    ax.set_xlabel("seconds from the run's first job" + ("; dotted: a stretch with no job running, left out"
                                                        if gaps else ""))
    ax.set_title(title or f"{len(jobs)} jobs in {end:.0f} s", fontsize=10)
    handles = [plt.Rectangle((0, 0), 1, 1, color=c, alpha=0.85) for c in colours.values()]
    handles.append(plt.Rectangle((0, 0), 1, 1, facecolor="white", edgecolor="black", linewidth=1.5))
    labels = [*colours, f"framed: the critical path, {sum(j['end'] - j['start'] for j in path):.0f} s in "
                        f"{len(path)} jobs"]
    ax.legend(handles, labels, fontsize=7, loc="upper right")  # the first rules' bars end early
    fig.tight_layout()
    save_figure(out, fig)


def _jobs_by(records: list[tuple[str, dict]], value) -> dict[str, list[str]]:
    """The jobs' names by `value(record)`; jobs for which it gives None (no phases record, an older run's, or a
    job without that library) are left out."""
    kinds: dict[str, list[str]] = {}
    for job, record in records:
        kind = value(record)
        if isinstance(kind, str):
            kinds.setdefault(kind, []).append(job)
    return kinds


def _named(kinds: dict[str, list[str]]) -> str:
    return "; ".join(f"{kind}: {', '.join(sorted(jobs)[:5])}{' ...' if len(jobs) > 5 else ''} "
                     f"({len(jobs)} job{'s' if len(jobs) > 1 else ''})" for kind, jobs in sorted(kinds.items()))


def mixed_runtimes(benchmarks: list[Path]) -> list[str]:
    """Warnings when a run's jobs ran on different PyTorch CPU kernels (`cpu_capability` in their phases files:
    the vector unit changes the last bits) or under different releases of Python or a numeric library (their
    `versions`: a run resumed after an upgrade), each naming the jobs of each kind; none when they agree. Such
    jobs' results are not comparable bit for bit."""
    records = [(Path(path).stem, _phases_record(path)[1] or {}) for path in benchmarks]
    said = []
    kernels = _jobs_by(records, lambda r: r.get("cpu_capability"))
    if len(kernels) > 1:
        said.append(f"WARNING: this run's jobs ran on different PyTorch CPU kernels ({_named(kernels)}); their "
                    "results differ in the last bits")
    versions = [(job, r["versions"] if isinstance(r.get("versions"), dict) else {}) for job, r in records]
    for name in ("python", *NUMERIC_LIBRARIES):
        releases = _jobs_by(versions, lambda v, name=name: v.get(name))
        if len(releases) > 1:
            said.append(f"WARNING: this run's jobs ran under different releases of {name} ({_named(releases)}); "
                        "their results may differ")
    return said


ELAPSED_ROW = "elapsed (a job running)"


def _union_length(spans: list[tuple[float, float]]) -> float:
    """Total length of the union of [start, end] intervals."""
    length, reach = 0.0, float("-inf")
    for start, end in sorted(spans):
        if end > reach:
            length += end - max(start, reach)
            reach = end
    return length


def label_image(image: np.ndarray, text: str, x: int) -> np.ndarray:
    """`image` with `text` on a dark band at its top left from column `x` (a copy)."""
    from PIL import Image, ImageDraw, ImageFont

    if image.shape[0] < 48:  # too small to hold a readable label
        return image
    out = Image.fromarray(np.ascontiguousarray(image))
    draw = ImageDraw.Draw(out)
    size = max(10, min(18, image.shape[0] // 14))
    try:
        font = ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: one bitmap size
        font = ImageFont.load_default()
    left, top, right, bottom = draw.textbbox((x + 4, 3), text, font=font)
    draw.rectangle((left - 3, top - 2, right + 3, bottom + 2), fill=(20, 20, 20))
    draw.text((x + 4, 3), text, fill=(255, 255, 255), font=font)
    return np.asarray(out)
