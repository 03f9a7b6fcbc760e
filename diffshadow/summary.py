"""The run's front page: one scene's headline numbers (an RST block for the report's landing page) and its
tables (one HTML page: shadow INRs seen and unseen with their baselines, sampling, fine-tuning, images per
mode, renderer speed, storage, stage costs), read from the results the rules wrote. Nothing is recomputed."""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from diffshadow.capacity import size_text, steps_text
from diffshadow.io import atomic_write_text, read_json
from diffshadow.lights import blend_label, describe_blend, recorded_weighting
from diffshadow.report import ELAPSED_ROW, PHASE_COLUMNS, label_image, mixed_runtimes

MIB = 2**20


def _num(value, fmt: str = ".2f") -> str:
    return "n/a" if value is None else f"{value:{fmt}}"


def _sampled_on(sampling: dict) -> str:
    """Where evaluate_voxels timed its samplers (`evaluate.device`); runs before the record say so vaguely."""
    if "device" not in sampling:
        return "evaluate_voxels' device"
    threads = f", {sampling['threads']} thread{'s' * (sampling['threads'] != 1)}" if sampling.get("threads") else ""
    return f"{sampling['device']}{threads}" if sampling["device"].startswith("cpu") else sampling["device"]


def _table(title: str, header: list[str], rows: list[list], note: str = "") -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows)
    caption = f"<p class='note'>{html.escape(note)}</p>" if note else ""
    table = f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"
    return f"<h2>{html.escape(title)}</h2>\n{table}{caption}\n"


def _kept(validation: dict | None) -> str:
    """The fine-tuning table's word on which checkpoint validation kept."""
    if not validation or not validation.get("history"):
        return ""
    history = validation["history"]
    last, floor = history[-1], history[0][1]
    where = "validation lights (random in the training cap, not the test set)"
    stopped = (f" Stopped early at epoch {validation['stopped_epoch']}: the last checkpoints all scored under it."
               if validation.get("stopped_epoch") else "")
    if validation.get("images_worse"):
        picked = validation.get("validated_epoch")
        score = {int(e): s for e, s in history}.get(picked)
        scored = f" ({score:.2f} dB)" if score is not None else ""
        # Kept the geometry stage although validation picked a later epoch: say that once, not as the rule's pick.
        return (f" Kept: epoch 0 of {last[0]}, the geometry-stage model. The {where} had picked epoch {picked}, the "
                f"last whose median voxel PSNR{scored} is not below the geometry stage's {floor:.2f} dB, but it "
                "rendered the training lights worse than the geometry stage (table), so the geometry-stage model "
                f"is used.{stopped}")
    return (f" Kept: epoch {validation['kept_epoch']} of {last[0]}, the last whose median voxel PSNR at {where} is "
            f"not below the geometry stage's {floor:.2f} dB (last epoch {last[1]:.2f} dB); epoch 0 means the "
            f"geometry-stage model is used.{stopped}")


def _read_json(path: Path, what: str) -> dict | None:
    return read_json(path, what) if path.exists() else None


def peak_memory(bench: dict) -> tuple[list[str], dict[str, dict[str, int]]]:
    """Every image size `bench.json` rendered (timed, then memory-only: `memory_scaling`), in numeric order, and
    the peak memory added per mode and size where it was measured."""
    peaks: dict[str, dict[str, int]] = {}
    for mode, row in bench.get("memory_scaling", {}).items():
        peaks.setdefault(mode, {}).update(row)
    for size, row in bench["sizes"].items():
        for mode, b in row.get("peak_mem_bytes", {}).items():
            peaks.setdefault(mode, {})[size] = b
    sizes = sorted({*bench["sizes"], *(s for row in peaks.values() for s in row)}, key=int)
    return sizes, peaks


def networks_text(bench: dict) -> str:
    """How the renderer evaluated its SIRENs (render.kernel and what ran), for the report's renderer table."""
    net = bench["networks"]
    asked = net["kernel"]
    if asked == "auto":
        return f"{net['used']} (render.kernel: auto)"
    return net["used"] if net["used"] == asked else f"{net['used']} (render.kernel: {asked}, not available here)"


def renderer_rows(bench: dict) -> tuple[list[str], list[list]]:
    """The renderer table of `bench.json`: per image size, fps, peak memory and ops / host syncs per mode.

    Sizes measured for memory only (`memory_scaling`) get rows of their own, without fps or counts."""
    timed = bench["sizes"]
    sizes, peaks = peak_memory(bench)
    modes = [m for m in ("noshadow", "inr", "naive") if any(m in r.get("fps", {}) for r in timed.values())]
    counted = [m for m in modes if any(m in r.get("counts", {}) for r in timed.values())]
    relit = any(r.get("fps_light_moved") for r in timed.values())  # inr from a view's kept samples
    rows = []
    for s in sizes:
        r = timed.get(s, {})
        fps, counts = r.get("fps", {}), r.get("counts", {})
        peak = [peaks.get(m, {}).get(s) for m in modes]
        moved = [_num(r.get("fps_light_moved"))] if relit else []
        rows.append([f"{s}²", *(_num(fps.get(m)) for m in modes), *moved,
                     *(_num(None if b is None else b / MIB, ".0f") for b in peak),
                     *(f"{counts[m]['ops']:,} / {counts[m]['syncs']}" if m in counts else "n/a" for m in counted)])
    header = ["image", *(f"{m} fps" for m in modes), *(["inr fps, light moved"] if relit else []),
              *(f"{m} peak MiB" for m in modes), *(f"{m} ops / syncs" for m in counted)]
    return header, rows


class RunResults:
    """The files of one finished scene, read once."""

    def __init__(self, results: Path, scene: str):
        self.scene = scene
        self.voxel = read_json(results / "voxel_metrics.json", "the voxel metrics of evaluate_voxels")
        self.images = read_json(results / "image_metrics.json", "the image metrics of evaluate_images")
        self.bench = _read_json(results / "bench.json", "the renderer benchmark's figures")
        # no model, no fine-tuning: a finished run switched to a stored-SIREN cache keeps the old run's file
        self.finetune = (None if self.voxel.get("cache") == "blend"
                         else _read_json(results / "finetune_metrics.json", "the metrics of finetune_render"))
        self.choice = _read_json(results / "cache_choice.json", "the choice of choose_cache")  # cache: auto's decision
        self.results = results
        costs = results / "stage_costs.tsv"
        lines = costs.read_text().splitlines() if costs.exists() else []
        self.costs = [dict(zip(lines[0].split("\t"), line.split("\t"), strict=True)) for line in lines[1:]]
        self.mixed = mixed_runtimes(sorted(results.glob("benchmarks/*.tsv")))  # the jobs' phases files

    def headline(self) -> list[tuple[str, str]]:
        v, seen, unseen = self.voxel, self.voxel["seen"], self.voxel.get("unseen")
        made = "blended" if v.get("cache") == "blend" else "generated"  # no model: nothing is generated
        rows = [("lights", f"{seen['count']} training, {unseen['count'] if unseen else 0} unseen"),
                ("stage-1 SIRENs (median voxel PSNR)", f"{seen['stage1_psnr_median']:.2f} dB"),
                (f"{made}, seen lights", f"{seen['generated_psnr_median']:.2f} dB "
                 f"({seen['generated_minus_stage1_median_db']:+.2f} dB against stage 1{_alone(seen)})")]
        if unseen:
            rows.append((f"{made}, unseen lights",
                         f"{unseen['generated_psnr_median']:.2f} dB ({blend_label(unseen)} true "
                         f"shadows {unseen['blend_psnr_median']:.2f} dB, nearest training SIREN "
                         f"{unseen['nearest_psnr_median']:.2f} dB{_alone(unseen)})"))
        if v.get("mix"):
            rows.append(("the cache's answer", mix_words(v["mix"], v.get("corrected", False))))
        if v.get("correction_check"):
            rows.append(("the blend's correction", correction_words(v["correction_check"])))
        verdict = cache_verdict(self.voxel)
        if verdict:
            rows.append(("model or stored SIRENs?", verdict))
        deployed = self.images["modes"].get("inr_generated_data_inr")
        if deployed:
            rows.append(("image PSNR, deployed path (data INR + generated shadow)", f"{deployed['psnr']:.2f} dB"))
        if self.finetune:
            rows.append(("rendering-loss fine-tuning (image PSNR, training lights)",
                         f"{self.finetune['image_psnr_geometry_only']['mean']:.2f} → "
                         f"{self.finetune['image_psnr_finetuned']['mean']:.2f} dB"
                         + ("; the geometry-stage model is used" if self.finetune.get("kept") == "geometry stage"
                            else "")))
        fps = self._fps()
        if fps:
            rows.append(("rendering speed", fps))
        total = next((r for r in self.costs if r["stage"].startswith("total")), None)
        elapsed = next((r for r in self.costs if r["stage"] == ELAPSED_ROW), None)
        if total:
            rows.append(("run cost", (f"{float(elapsed['wall_s']) / 60:.1f} min elapsed, " if elapsed else "")
                         + f"{float(total['wall_s']) / 60:.1f} min summed over {int(total['jobs'])} jobs"
                         + critical_words(self.costs)))
        if self.mixed:
            rows.append(("WARNING: mixed runtimes", " ".join(w.removeprefix("WARNING: ") for w in self.mixed)))
        if self.choice:
            rows.append(("shadow cache chosen (cache: auto)", self.choice["why"]))
        if "seconds_per_inr" in v:
            rows.append(("time per shadow INR (DDIM)",
                         f"{v['seconds_per_inr']['ddim']:.3f} s on {_sampled_on(v.get('sampling', {}))}"))
        elif "codec" in v:
            rows.append(("shadow cache", f"cache: {v['codec']} (the weight blend of the stored SIRENs kept in "
                         f"{v['codec']}, {v['storage_bytes']['cache'] / 2**20:.3f} MiB; no diffusion model)"))
        else:
            fixed = ", corrected by the blend's correction (correction.pt)" if v.get("corrected") else ""
            rows.append(("shadow cache", f"cache: blend (the stored SIRENs' weight blend{fixed}; no diffusion model)"))
        sizes = self.sizes()
        if sizes:
            rows.append(("SIREN sizes chosen", ", ".join(f"{r[0]} width {r[1]} ({r[4]})" for r in sizes)))
        dm = v.get("diffusion_model")
        if dm:
            rows.append(("diffusion model", f"'{dm['preset']}': {dm['layers']} blocks of width {dm['width']}, "
                         f"{dm['parameters']:,} parameters (for SIRENs of width {dm['siren_width']})"
                         + (f"; {dm['epochs']} epochs: {dm['stopped']}" if dm.get("epochs") else "")
                         + (f"; trained with {dm['precision']} products" if dm.get("precision", "float32")
                            != "float32" else "")))
        return rows

    def _fps(self) -> str:
        if not self.bench or not self.bench.get("sizes"):
            return ""
        size = max(self.bench["sizes"], key=int)
        fps = self.bench["sizes"][size].get("fps", {})
        parts = [f"{mode} {fps[mode]:.2f}" for mode in ("noshadow", "inr", "naive") if mode in fps]
        if moved := self.bench["sizes"][size].get("fps_light_moved"):
            parts.append(f"inr with the light moved over a still view {moved:.2f} (the view's kept samples)")
        return f"frames per second at {size}²: " + ", ".join(parts) if parts else ""

    def sizes(self) -> list[list]:
        """Rows of the chosen-sizes table: stage-1 SIRENs and the data INR, with every size tried."""
        rows = []
        # stage 1's size is probed on one light: beside it, what every training light reached
        for name, size, median in (("stage-1 shadow SIRENs", self.voxel.get("stage1"),
                                    self.voxel.get("seen", {}).get("stage1_psnr_median")),
                                   ("data INR", self.images.get("data_inr"), None)):
            if not size:
                continue
            cap = size.get("capacity") or {}
            tried = "; ".join(f"{size_text(r)}: {_num(r['psnr'])} dB" for r in cap.get("rungs", []))
            steps = steps_text(cap) if "steps" in cap else "n/a"
            target = cap.get("target_psnr") or None
            reached = _num(cap.get("psnr")) + ("" if cap.get("met", True) else " (missed)")
            if target and median is not None:
                reached += f"; every training light's median {_num(median)}" + (" (below it)" if median < target
                                                                                else "")
            rows.append([name, size["width"], size["blocks"], f"{size['parameters']:,}", steps,
                         _num(target, "g"), reached, tried or "n/a"])
        return rows

    def front_picture(self) -> tuple[bytes, str] | None:
        """The landing page's picture: the scene under an unseen light, ours (the deployed path: data INR and the
        cache's shadow SIREN) beside the exact image, labelled, and a caption naming its image PSNR
        (image_metrics.json); None where evaluate_images rendered no unseen light."""
        import io

        from PIL import Image

        images = self.results / "images"
        rows = [r for r in self.images.get("images", []) if r["set"] == "unseen"]
        # the deployed path first (data INR and the cache's shadow SIREN), else the cache's SIREN on the raw volume
        for row in sorted(rows, key=lambda r: r["mode"] != "inr_generated_data_inr"):
            if row["mode"] not in ("inr_generated_data_inr", "inr_generated"):
                continue
            tag = f"unseen{row['light']}_view{row['view']}"
            ours, gt = images / f"{tag}_{row['mode']}.png", images / f"{tag}_gt.png"
            if not (ours.exists() and gt.exists()):
                continue
            a, b = (np.asarray(img.resize((2 * img.width, 2 * img.height), Image.Resampling.NEAREST))
                    for img in (Image.open(p).convert("RGB") for p in (ours, gt)))
            side = np.concatenate([label_image(a, "ours", 0), label_image(b, "exact (gt)", 0)], axis=1)
            buf = io.BytesIO()
            Image.fromarray(side).save(buf, format="PNG")
            what = "data INR and the cached shadow SIREN" if row["mode"] == "inr_generated_data_inr" else (
                "the cached shadow SIREN on the raw volume")
            return buf.getvalue(), (f"Unseen test light {row['light']}, view {row['view']}: ours ({what}) beside the "
                                    f"exact shadow; image PSNR {row['psnr']:.2f} dB.")
        return None

    def rst(self) -> str:
        """The scene's block of the landing page: a title, its picture (`front_picture`) and a two-column table of
        the headline numbers."""
        title = f"Scene {self.scene}"
        lines = [title, "-" * len(title), ""]
        if (picture := self.front_picture()) is not None:
            png, caption = picture
            # the URI on indented lines (docutils joins them): one line would pass its 10,000-character limit
            uri = _png_uri(png)
            lines += [".. figure::", *(f"   {uri[i:i + 100]}" for i in range(0, len(uri), 100)),
                      "   :alt: " + caption, "", "   " + caption, ""]
        lines += [".. list-table::", "   :widths: 45 55", ""]
        for name, value in self.headline():
            lines += [f"   * - {name}", f"     - {value}"]
        return "\n".join(lines) + "\n"

    def tables(self) -> str:
        v, seen, unseen = self.voxel, self.voxel["seen"], self.voxel.get("unseen")
        parts = [_table("Headline", ["", "value"], [list(r) for r in self.headline()])]
        made = (f"blended (cache: {v.get('codec', 'blend')})" if v.get("cache") == "blend" else
                f"generated (DDIM), mixed: model share {v['mix']['model_share']:g}" if v.get("mix") else
                "generated (DDIM)")
        rows = [["seen", "stage-1 SIREN (fitted)", _num(seen["stage1_psnr_median"]),
                 _num(seen.get("stage1_psnr_visible_median")), ""],
                ["seen", made, _num(seen["generated_psnr_median"]),
                 _num(seen.get("generated_psnr_visible_median")),
                 f"min {seen['generated_psnr_min']:.2f}; {seen['generated_minus_stage1_median_db']:+.2f} vs stage 1"]]
        if "model_alone_psnr_median" in seen:
            rows.append(["seen", "the model alone (the paper's cache)", _num(seen["model_alone_psnr_median"]), "", ""])
        if unseen:
            if "geometry_only_psnr_median" in unseen:
                rows.append(["unseen", "generated before fine-tuning (geometry loss only)",
                             _num(unseen["geometry_only_psnr_median"]), "",
                             f"fine-tuning changed it by {unseen['finetune_change_median_db']:+.2f} dB"])
            if "model_alone_psnr_median" in unseen:
                rows.append(["unseen", "the model alone (the paper's cache)", _num(unseen["model_alone_psnr_median"]),
                             "", ""])
            rows += [["unseen", made, _num(unseen["generated_psnr_median"]), "", ""],
                     ["unseen", f"{blend_label(unseen)} true shadows",
                      _num(unseen["blend_psnr_median"]), "", "baseline"],
                     ["unseen", "nearest training SIREN", _num(unseen["nearest_psnr_median"]), "",
                      f"baseline; nearest light {unseen['nearest_angle_median_deg']:.1f}° away (median)"]]
            if "weight_blend_psnr_median" in unseen:
                rows.append(["unseen", f"{blend_label(unseen)} training SIRENs' weights",
                             _num(unseen["weight_blend_psnr_median"]), "", "baseline (one SIREN per light)"])
            if "siren_blend_psnr_median" in unseen:
                rows.append(["unseen", f"{blend_label(unseen)} training SIRENs' values",
                             _num(unseen["siren_blend_psnr_median"]), "",
                             f"baseline ({len_blend(unseen)} SIRENs per sample; stage 1's fit error included)"])
            if unseen.get("pool_lights"):
                # a count, not a PSNR: it goes in the description, the PSNR columns stay empty
                rows.append(["unseen", f"{unseen['pool_lights']} pool lights (exact shadows, no fitted SIREN) in "
                             "training", "", "",
                             f"nearest light trained on {unseen['nearest_trained_angle_median_deg']:.1f}° away "
                             f"(median); no unseen test light is one of them"])
        wide = v.get("wide")
        if wide:  # the same comparison on many more lights drawn like the test ones (box points only)
            rows += _further_rows(wide, made)
        parts.append(_table("Shadow INRs: voxel PSNR against the marched ground truth (median over lights, dB)",
                            ["lights", "shadow INR", "box", "visible region", ""], rows,
                            f"{v['eval_points']:,} fresh points per light and region that no fit used."))
        if "curve" in v.get("sampling", {}):  # not with cache: blend, nor evaluate.ddpm_lights: 0
            s = v["sampling"]
            t = v["seconds_per_inr"]
            parts.append(_table(f"Sampling: DDIM against 500-step DDPM ({s['lights']} training lights)",
                                ["sampler", "median voxel PSNR (dB)", "seconds per INR"],
                                [[f"DDIM {s['ddim_steps']} steps", _num(s["ddim_psnr_median"]),
                                  _num(t["ddim"], ".3f")],
                                 ["DDPM 500 steps", _num(s["ddpm_psnr_median"]), _num(t["ddpm"], ".3f")]],
                                f"DDIM is {s['speedup']:.0f}x faster; one INR alone, on {_sampled_on(s)}."))
        if self.finetune:
            f = self.finetune
            parts.append(_table(
                "Rendering-loss fine-tuning: image PSNR of generated shadows on training lights (dB)",
                ["model", "mean", "min"],
                [["geometry loss only", _num(f["image_psnr_geometry_only"]["mean"]),
                  _num(f["image_psnr_geometry_only"]["min"])],
                 ["fine-tuned", _num(f["image_psnr_finetuned"]["mean"]), _num(f["image_psnr_finetuned"]["min"])]],
                f"{f['lights']} lights x {f['views']} views, foreground pixels; {f['processes']} process(es), "
                f"{f['seconds']:.0f} s." + _kept(f.get("validation"))))
        im = self.images
        rows = [[mode, m["count"], _num(m["psnr"]), _num(m["ssim"], ".4f"), _num(m.get("ms_ssim"), ".4f"),
                 _num(m.get("lpips"), ".4f")] for mode, m in im["modes"].items()]
        parts.append(_table(
            "Images: every mode against the ground truth (mean over images)",
            ["mode", "images", "PSNR (dB)", "SSIM", "MS-SSIM", "LPIPS"], rows,
            f"{im['image_size']}² images, {im['views']} views, step {im['step']} voxel; shading "
            f"{im.get('shading', 'unlit')}; reference: {im['reference']}; MS-SSIM {im.get('ms_ssim', 'n/a')}; "
            f"LPIPS {im['lpips']}. inr_stage1 and "
            "inr_generated use the raw scalar field (only the shadow's error shows); inr_generated_data_inr is "
            "the deployed path; naive marches secondary rays through the data INR; noshadow drops the shadow."
            + _blend_images(im.get("weight_blend_images"))))
        if self.bench and self.bench.get("sizes"):
            header, rows = renderer_rows(self.bench)
            where = self.bench.get("device", "device n/a")
            where += f", SIRENs: {networks_text(self.bench)}"
            parts.append(_table(f"Renderer ({where})", header, rows,
                                "Measured side by side in one process (diffshadow bench render); full figures "
                                "in bench.json. Peak memory is what a frame adds; a size without fps was rendered "
                                "for its memory only (does memory stay bounded as the image grows?). ops / syncs: "
                                "kernel-launching ops and host syncs per frame, counted with torch.profiler, so "
                                "they do not drift with the machine's load. naive and inr evaluate their SIRENs "
                                "the same way (both eager, or both fused: naive's secondary rays are whole-ray "
                                "kernels as inr's primary rays are), so naive/inr compares methods, not code. "
                                "inr fps, light moved: the same view under a moved light, drawn as the viewer "
                                "draws it from the samples it kept of the view (the same image)."))
        sizes = self.sizes()
        if sizes:
            parts.append(_table("SIREN sizes chosen for this scene", ["network", "width", "blocks", "parameters",
                                                                     "fit", "target (dB)", "reached (dB)", "tried"],
                                sizes, "A stage with a target grows its SIREN until the target is reached: stage 1 "
                                "steps x2 first, then width x2, each width x2 also doubling a step's points and "
                                "halving the steps; the data INR width x2 alone (capacity.ladder). Stage 1's "
                                "PSNR is preoptimize's probe light (held-out points), beside the median the "
                                "subsets' fits reached; the data INR's is over every voxel."))
        sb = v["storage_bytes"]
        n = seen["count"]
        # a run without a model (cache: blend, or a codec's store) has no model row; a codec's cache its own
        rows = [*([["diffusion model (weights and standardiser)", _num(sb["model"] / MIB)]] if sb["model"] else []),
                [f"{n} stage-1 SIRENs (fp32)", _num(sb["sirens"] / MIB)],
                *([["the blend's correction (its network, fp32)", _num(sb["correction"] / MIB)]]
                  if "correction" in sb else []),
                *([["the cache: the model and the stored SIRENs it mixes in" +
                    (", with the blend's correction" if "correction" in sb else ""),
                    _num((sb["model"] + sb["sirens"] + sb.get("correction", 0)) / MIB)]] if v.get("mix") else []),
                *([[f"the cache: the {n} SIRENs in {v.get('codec')}", _num(sb["cache"] / MIB)]] if "cache" in sb
                  else []),
                [f"{n} dense shadow grids (fp16)", _num(sb["grids"] / MIB)]]
        parts.append(_table("Storage of the shadow cache", ["what", "MiB"], rows,
                            ("The model's size is fixed; " if sb["model"] else "") +
                            "SIRENs and grids grow with the light count."))
        if self.costs:
            parts.append(_table("Stage costs (Snakemake benchmark files)",
                                ["stage", "jobs", "wall s", "CPU s", "max RSS MiB", "import s", "device s",
                                 "compile s", "io s", "compute s", "launch s", "on the critical path s"],
                                [[r["stage"], r["jobs"], r["wall_s"], r["cpu_s"], r["max_rss_mib"],
                                  *(r.get(k, "NA") for k in (*PHASE_COLUMNS, "critical_s"))] for r in self.costs],
                                "Wall and CPU seconds summed over a stage's jobs; jobs that ran side by side "
                                "overlap, so the total exceeds the run's wall time, which is the last row: the time "
                                "in which at least one job ran. A job's CPU seconds and peak memory are the larger "
                                "of Snakemake's polls and its process's own count. Where the wall time went, per "
                                "job's process: interpreter start and imports, device start (CUDA's context), "
                                "compilation (Triton's, of the fused renderer kernels), reading and writing "
                                "files (checksums included), compute (the rest), and launch: the job's time "
                                "outside its diffshadow process (shell, torchrun and its helper). On the critical "
                                "path: the seconds of a stage's jobs on the chain the run's end waited on (each "
                                "job started as the one before it ended: its input's maker or the job whose slot "
                                "it took); in the total row their sum, in the last row the chain from its first "
                                "start to its last end."))
        timeline = self.results / "report" / "timeline.png"
        if timeline.exists():  # stage_costs draws it from the same benchmark files
            uri = _png_uri(timeline.read_bytes())
            parts.append(f"<p><img src='{uri}' alt='every job of this run over its wall time' "
                         "style='max-width:100%'></p>\n<p class='note'>Every job over the run's wall time, one row "
                         "per rule: start-up (imports, device, launch), compilation and work; framed, the critical "
                         "path (the jobs the run's end waited on: shortening any other job would not have ended it "
                         "sooner). A row with no neighbour beside it left a core (or the GPU) waiting.</p>\n")
        return "".join(parts)


def _alone(lights: dict) -> str:
    """", the model alone X dB" where the cache mixed its SIRENs with the stored ones (voxel_metrics' `mix`)."""
    alone = lights.get("model_alone_psnr_median")
    return "" if alone is None else f"; the model alone {alone:.2f} dB"


def len_blend(record: dict) -> int:
    """SIRENs in one light's blend: a triangle's 3, or blend_k."""
    return 3 if record.get("blend_weights") == "triangle" else int(record["blend_k"])


def mix_words(mix: dict, corrected: bool = False) -> str:
    """The cache's answer for a light in words (voxel_metrics.json's `mix`, and whether its blend was corrected)."""
    share = float(mix["model_share"])
    how = "chosen on validation lights" if mix.get("chosen") == "validation lights" else "set in the config"
    blend = describe_blend(recorded_weighting(mix), mix["blend_k"])
    if corrected:
        blend += ", corrected by the blend's correction (correction.pt)"
    return f"{share:g} x the diffusion model's SIREN + {1 - share:g} x {blend} (mix.model_share {how}; both are kept)"


def correction_words(check: dict) -> str:
    """The blend correction's held-out check in words (voxel_metrics.json's `correction_check`)."""
    sets = [f"{c['corrected_psnr_median']:.2f} dB at {k} points (plain {c['plain_psnr_median']:.2f}; better on "
            f"{c['better']}, worse on {c['worse']})" for k in ("box", "visible") if (c := check.get(k))]
    on = f"on its {check['lights']} held-out lights the corrected blend scores {' and '.join(sets)}"
    test = f"a sign test ({check['significant']} of {check['lights']} lights, 5 %)"
    if check["kept"]:
        return f"kept: {on}; {test} finds it better at one point set at least and worse at none"
    return f"declined: {on}; {test} does not find it better at one point set, or finds it worse at one, so the plain " \
           f"blend answers"


AGAINST_COUNT = "Against the light count: docs/performance.md, \"Scaling with the light count\""


def cache_verdict(voxel: dict) -> str:
    """What a run says about the method (voxel_metrics.json): is the model smaller than the stored SIRENs it
    regenerates, and better than their weight blend (the same render cost, no model) on unseen lights? Empty
    without a model (`cache: blend`) or without the weight-blend baseline."""
    unseen = voxel.get("unseen") or {}
    sb, n = voxel["storage_bytes"], voxel["seen"]["count"]
    if not sb["model"] or "weight_blend_psnr_median" not in unseen:
        return ""
    size = (f"the model is {sb['model'] / sb['sirens']:.1f}x the {n} stored SIRENs (smaller past "
            f"{sb['model'] / (sb['sirens'] / n):,.0f} lights at these sizes)" if sb["model"] > sb["sirens"]
            else f"the model is {sb['sirens'] / sb['model']:.1f}x smaller than the {n} stored SIRENs")
    if voxel.get("mix"):  # the cache keeps both, so its bytes are their sum
        fix = " and the blend's correction" if "correction" in sb else ""
        size += (f"; mixing the two, the cache keeps both{fix} "
                 f"({(sb['model'] + sb['sirens'] + sb.get('correction', 0)) / MIB:.2f} MiB)")
        if float(voxel["mix"]["model_share"]) == 0:  # the mix is the blend: say what the model adds instead
            return f"{size}; {_share_zero(unseen, voxel.get('wide'), voxel.get('corrected', False))}. {AGAINST_COUNT}"
    gap = unseen["generated_psnr_median"] - unseen["weight_blend_psnr_median"]
    lo, hi = unseen.get("weight_blend_gap_interval95_db") or (None, None)  # absent from an older voxel_metrics.json
    spread = ("" if lo is None else f" (better on {unseen['better_than_weight_blend']} of {unseen['count']} lights; "
              f"95 % interval over resampled test lights {lo:+.2f} to {hi:+.2f} dB)")
    wide = voxel.get("wide")
    if wide:  # many more lights drawn like the test ones decide; the test lights' own gap is said beside
        test_gap = gap
        gap = wide["generated_psnr_median"] - wide["weight_blend_psnr_median"]
        lo, hi = wide["weight_blend_gap_interval95_db"]
        spread = (f" (on {wide['lights']:,} further test lights: better on {wide['better_than_weight_blend']:,}, 95 % "
                  f"interval {lo:+.2f} to {hi:+.2f} dB; on the {unseen['count']} test lights {test_gap:+.2f} dB)")
    who = "the mix" if voxel.get("mix") else "it"
    if lo is not None and lo <= 0 <= hi:
        better = (f"{who} ties with their weight blend on unseen lights: {gap:+.2f} dB{spread}, so other test lights "
                  f"could reverse it")
        if voxel.get("mix") or sb["model"] > sb["sirens"]:  # the blend alone keeps fewer bytes, and no stage 2
            better += ("; the stored SIRENs alone (`cache: blend`, or a codec of it) would answer as well, without "
                       "stage 2")
    elif gap > 0:
        better = f"{who} beats their weight blend on unseen lights by {gap:.2f} dB{spread}"
    else:
        better = (f"their weight blend beats {who} on unseen lights by {-gap:.2f} dB{spread}: `cache: blend` would "
                  f"skip stage 2")
    return f"{size}; {better}. {AGAINST_COUNT}"


def critical_words(costs: list[dict]) -> str:
    """The run's critical path from `stage_costs.tsv`'s `critical_s` column, its longest rules first, and the time
    between its jobs where that is a minute or more (a batch queue's waits while other jobs ran: `job_spans` leaves
    out a stretch with no job running); empty for a file without the column (a run before it)."""
    total = next((r for r in costs if r["stage"].startswith("total")), {})
    elapsed = next((r for r in costs if r["stage"] == ELAPSED_ROW), {})
    if total.get("critical_s", "NA") == "NA" or elapsed.get("critical_s", "NA") == "NA":
        return ""
    rules = sorted(((float(r["critical_s"]), r["stage"]) for r in costs if r not in (total, elapsed)
                    and float(r["critical_s"]) > 0), reverse=True)
    named = ", ".join(f"{rule} {s:.0f} s" for s, rule in rules[:4]) + (
        f" and {len(rules) - 4} more rule{'s' if len(rules) > 5 else ''}" if len(rules) > 4 else "")
    between = float(elapsed["critical_s"]) - float(total["critical_s"])
    return (f"; the critical path (the timeline's framed jobs) {float(elapsed['critical_s']) / 60:.1f} min: {named}"
            + (f", and {between / 60:.1f} min between its jobs while others ran (a batch queue's waits)"
               if between >= 60 else ""))


def _blend_images(pairs: dict | None) -> str:
    """The images table's word on the answer against stage 1's plain weight blend (image_metrics.json's
    `weight_blend_images`), or nothing where the run scored no such pair."""
    if not pairs:
        return ""
    lo, hi = pairs.get("gap_interval95_db") or (None, None)  # from PAIRED_INTERVAL_LIGHTS lights
    spread = "" if lo is None else (f" (the gap's 95 % interval over the {pairs['lights']} lights {lo:+.2f} to "
                                    f"{hi:+.2f} dB)")
    return (f" inr_weight_blend is stage 1's plain weight blend on the raw scalar field, unseen lights only: on those "
            f"{pairs['images']} images inr_generated {pairs['inr_generated_psnr_mean']:.2f} dB against "
            f"{pairs['inr_weight_blend_psnr_mean']:.2f}{spread}, better in {pairs['better']} of {pairs['images']}.")


def _png_uri(png: bytes) -> str:
    """A PNG's bytes as a data URI, for a page that must stand alone."""
    import base64

    return "data:image/png;base64," + base64.b64encode(png).decode()


def _tail(wide: dict, name: str) -> str:
    """The 10th percentile where evaluate_voxels recorded it (runs before it did not)."""
    value = wide.get(f"{name}_psnr_p10")
    return "" if value is None else f"; a tenth of the lights under {value:.2f} dB"


def _further_rows(wide: dict, made: str) -> list[list[str]]:
    """The "further" rows of the voxel table: the cache's answer on evaluate_voxels' further test lights, the
    model alone where there is a model, and the weight blend of stage 1's SIRENs, which alone is the answer of
    `cache: blend` (no row of its own then)."""
    further = f"further ({wide['lights']:,})"
    drawn = f"{wide['points']:,} points per light; drawn as the unseen test lights are, none of them"
    rows = []
    if "weight_blend_gap_interval95_db" in wide:
        lo, hi = wide["weight_blend_gap_interval95_db"]
        rows.append([further, made, _num(wide["generated_psnr_median"]), "",
                     f"better than the weight blend on {wide['better_than_weight_blend']:,}; 95 % interval of the "
                     f"gap {lo:+.2f} to {hi:+.2f} dB" + _tail(wide, "generated")])
    if "model_alone_psnr_median" in wide:
        rows.append([further, "the model alone (the paper's cache)", _num(wide["model_alone_psnr_median"]), "",
                     _tail(wide, "model_alone").lstrip("; ")])
    name = f"{blend_label(wide)} training SIRENs' weights" + (" (fp32)" if "codec" in wide else "")
    rows.append([further, name if rows else made, _num(wide["weight_blend_psnr_median"]), "",
                 drawn + _tail(wide, "weight_blend")])
    rows[0][-1] += _seams(wide.get("seams"))
    return rows


def _rings(halo: int) -> str:
    return "no halo" if not halo else f"a halo of {halo} ring{'s' if halo > 1 else ''}"


def _seams(seams: dict | None) -> str:
    """Where the further lights' blends span two fit_siren subsets: the answer's median there and inside one."""
    if not seams or not seams["lights"]:
        return ""
    inside = seams["answer_median_within"]
    rounds = ", in rounds" if seams.get("rounds") else ""  # fit.rounds; a record before the key: none
    return (f"; {seams['lights']:,} of them blend lights of two fit_siren subsets (subset_size {seams['subset_size']}, "
            f"{_rings(seams['halo'])}{rounds}): median {seams['answer_median_across']:.2f} dB there"
            + ("" if inside is None else f", {inside:.2f} inside one"))


def _share_zero(unseen: dict, wide: dict | None, corrected: bool = False) -> str:
    """The verdict where the validation lights chose model share 0: the answer is the (corrected) weight blend
    alone."""
    where = wide or unseen
    gap = where["generated_psnr_median"] - where["model_alone_psnr_median"]
    lo, hi = where.get("model_alone_gap_interval95_db") or (None, None)
    on = f"on {wide['lights']:,} further test lights" if wide else f"on the {unseen['count']} test lights"
    spread = "" if lo is None else f", 95 % interval {lo:+.2f} to {hi:+.2f} dB"
    blend = "weight blend"
    if corrected and "weight_blend_psnr_median" in where:
        blend = (f"corrected weight blend ({where['generated_psnr_median'] - where['weight_blend_psnr_median']:+.2f} "
                 f"dB over the plain blend)")
    return (f"the validation lights chose model share 0: the cache's answer is their {blend} alone, "
            f"{gap:+.2f} dB against the model alone {on}{spread}; the model adds nothing, and `cache: blend` (or a "
            f"codec of it, `cache: fp16`) would skip stage 2 and its bytes")


STYLE = """body{font-family:sans-serif;margin:1.5em;color:#222}table{border-collapse:collapse;margin:.4em 0}
th,td{border:1px solid #ccc;padding:.25em .6em;text-align:left}th{background:#f2f2f2}
td:not(:first-child){font-variant-numeric:tabular-nums}.note{color:#555;font-size:.9em;max-width:60em}
h2{font-size:1.1em;margin-top:1.4em}"""


def write_summary(results: Path, scene: str, out_html: Path, out_rst: Path) -> None:
    """`summary.html` (every table) and `landing.rst` (the landing page's block) for one finished scene."""
    run = RunResults(results, scene)
    page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>diffshadow: {html.escape(scene)}</title>"
            f"<style>{STYLE}</style></head><body><h1>diffshadow results: {html.escape(scene)}</h1>\n"
            f"{run.tables()}</body></html>\n")
    atomic_write_text(out_html, page)
    atomic_write_text(out_rst, run.rst())
