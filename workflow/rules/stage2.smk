# Stage 2 (paper §3.3): presampled geometry points, diffusion training, sampling, voxel evaluation.


rule presample:
    input:
        volume=extinction_volume,  # its colours alone changed: not rerun
        lights="results/{scene}/lights.json",
    output:
        directory("results/{scene}/geometry_points.zarr"),
    params:
        cfg=lambda wc: as_json(wc.scene, "diffusion"),
    threads: 1  # one core beside a fit: train_diffusion needs it as soon as the fits are done
    priority: 5
    benchmark:
        "results/{scene}/benchmarks/presample.tsv",
    log:
        "results/{scene}/logs/presample.log",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow --phases results/{wildcards.scene}/benchmarks/presample.phases.json presample --volume {input.volume} --lights {input.lights} --config-json {params.cfg:q}"
        " --threads {threads} --out {output}"
        + _JOB_LOG


rule train_diffusion:
    input:
        weights="results/{scene}/weights.zarr",
        points="results/{scene}/geometry_points.zarr",
    output:
        "results/{scene}/diffusion_geometry.ckpt",
    params:
        cfg=lambda wc: as_json(wc.scene, "diffusion"),
    threads: diffusion_threads
    priority: 10  # the longest job: it starts before the side jobs (targets, data INR, truth) take a core
    log:
        "results/{scene}/logs/train_diffusion.log",
    benchmark:
        "results/{scene}/benchmarks/train_diffusion.tsv",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow --phases results/{wildcards.scene}/benchmarks/train_diffusion.phases.json train-diffusion --weights {input.weights} --points {input.points}"
        " --config-json {params.cfg:q} --threads {threads} --out {output}" + _JOB_LOG


rule eval_truth:
    input:
        volume=extinction_volume,  # its colours alone changed: not rerun
        lights="results/{scene}/lights.json",
    output:
        directory("results/{scene}/eval_truth.zarr"),
    params:
        points=lambda wc: scene_config(wc.scene)["evaluate"]["points"],
        seed=lambda wc: scene_config(wc.scene)["evaluate"]["seed"],
        device=evaluate_device,
    threads: 1  # a second thread sped it up 1.19x: better spent on the job beside it
    log:
        "results/{scene}/logs/eval_truth.log",
    benchmark:
        "results/{scene}/benchmarks/eval_truth.tsv",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow --phases results/{wildcards.scene}/benchmarks/eval_truth.phases.json eval-truth --volume {input.volume} --lights {input.lights} --seed {params.seed}"
        " --eval-points {params.points} {params.device}"
        " --threads {threads} --out {output}" + _JOB_LOG


# cache: auto, right after stage 1: the smallest stored-SIREN cache whose blend reaches cache_auto.target_psnr
# on validation lights, within cache_auto.tolerance of the best, else diffusion; a checkpoint, so stage 2's jobs
# enter the DAG only when it says diffusion
checkpoint choose_cache:
    input:
        weights="results/{scene}/weights.zarr",
        truth="results/{scene}/eval_truth.zarr",
        volume=extinction_volume,  # its colours alone changed: not rerun
        lights="results/{scene}/lights.json",
    output:
        "results/{scene}/cache_choice.json",
    params:
        target=lambda wc: scene_config(wc.scene)["cache_auto"]["target_psnr"],
        tolerance=lambda wc: scene_config(wc.scene)["cache_auto"]["tolerance"],
        candidates=lambda wc: " ".join(scene_config(wc.scene)["cache_auto"]["candidates"]),
        blend=lambda wc: blend_args(wc.scene),
        val=lambda wc: "--val-lights {val_lights} --val-points {val_points} --seed {seed}".format(
            **scene_config(wc.scene)["cache_auto"]),
        device=evaluate_device,
    threads: 1
    log:
        "results/{scene}/logs/choose_cache.log",
    benchmark:
        "results/{scene}/benchmarks/choose_cache.tsv",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow --phases results/{wildcards.scene}/benchmarks/choose_cache.phases.json choose-cache --weights {input.weights}"
        " --truth {input.truth} --volume {input.volume} --lights {input.lights} {params.blend}"
        " --target-psnr {params.target} --tolerance {params.tolerance} --candidates {params.candidates} {params.val} {params.device} --threads {threads}"
        " --out {output}" + _JOB_LOG


# the blend's correction (correction.steps over 0): an MLP of the light direction fitted after stage 1 on
# exact-shadow lights, which corrects the stored SIRENs' blend between the training lights (diffshadow/correction.py)
rule fit_correction:
    input:
        weights="results/{scene}/weights.zarr",
        volume=extinction_volume,  # its colours alone changed: not rerun
        lights="results/{scene}/lights.json",
    output:
        "results/{scene}/correction.pt",
    params:
        cfg=lambda wc: as_json(wc.scene, "correction"),
        blend=lambda wc: blend_args(wc.scene),
    # one, beside train_diffusion, and up to two while the run's other core idles (runtime.SpareThreads; the same
    # bytes on any threads, tests/test_correction.py): both start when stage 1 ends, off each other's chain
    threads: 1
    priority: 10
    log:
        "results/{scene}/logs/fit_correction.log",
    benchmark:
        "results/{scene}/benchmarks/fit_correction.tsv",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow --phases results/{wildcards.scene}/benchmarks/fit_correction.phases.json fit-correction --weights {input.weights}"
        " --volume {input.volume} --lights {input.lights} {params.blend} --config-json {params.cfg:q}"
        " --threads {threads} --out {output}" + _JOB_LOG


# a codec's cache (cache: fp16 | bf16 | basis-<k>, or auto's choice): the stored SIRENs through the codec, decoded
rule encode_cache:
    input:
        weights="results/{scene}/weights.zarr",
        truth="results/{scene}/eval_truth.zarr",
        lights="results/{scene}/lights.json",
    output:
        directory("results/{scene}/cache.zarr"),
    params:
        codec=lambda wc: cache_choice(wc.scene),
        device=evaluate_device,
    threads: 1
    log:
        "results/{scene}/logs/encode_cache.log",
    benchmark:
        "results/{scene}/benchmarks/encode_cache.tsv",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow --phases results/{wildcards.scene}/benchmarks/encode_cache.phases.json encode-cache --weights {input.weights}"
        " --truth {input.truth} --lights {input.lights} --codec {params.codec} {params.device} --threads {threads}"
        " --out {output}" + _JOB_LOG


# the generated SIRENs of every evaluation light: sampled by the diffusion model, or (cache: blend or a codec) the
# stored SIRENs and their weight blends, which leaves train_diffusion and finetune_render out of the run
rule sample_shadows:
    input:
        unpack(shadow_source),
        truth="results/{scene}/eval_truth.zarr",
        lights="results/{scene}/lights.json",
    output:
        directory("results/{scene}/generated.zarr"),
    params:
        command=lambda wc, input: (f"blend-shadows --weights {input.weights} {blend_args(wc.scene)} "
                                   f"{evaluate_device(wc)}{correction_flag(input)}"
                                   if "weights" in input.keys()
                                   else sample_command(wc.scene, input)
                                   if "checkpoint" in input.keys() else ""),  # "": cache: auto, not yet chosen
        # what the command's flags carry, as a param of the wildcards alone: Snakemake reruns the job when it
        # changes (a param that reads `input`, as `command` does, is not compared with the run's record)
        settings=lambda wc: mix_settings(wc.scene),
    # the model samples on the run's device; the SIRENs are scored on the CPU unless evaluate.device is run
    threads: lambda wc: device_threads(2) if scene_config(wc.scene)["evaluate"]["device"] == "run" else 2
    priority: 10  # the chain's next job after finetune_render, before the side jobs still waiting
    log:
        "results/{scene}/logs/sample_shadows.log",
    benchmark:
        "results/{scene}/benchmarks/sample_shadows.tsv",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow --phases results/{wildcards.scene}/benchmarks/sample_shadows.phases.json {params.command} --truth {input.truth} --lights {input.lights} --threads {threads}"
        " --out {output}" + _JOB_LOG


rule evaluate_voxels:
    input:
        unpack(geometry_checkpoint),
        unpack(model_checkpoint),
        unpack(codec_store),
        unpack(blend_correction),
        weights="results/{scene}/weights.zarr",
        generated="results/{scene}/generated.zarr",
        truth="results/{scene}/eval_truth.zarr",
        volume=extinction_volume,  # its colours alone changed: not rerun
        lights="results/{scene}/lights.json",
    output:
        "results/{scene}/voxel_metrics.json",
    params:
        geometry=lambda wc, input: f"--geometry-checkpoint {input.geometry}" if "geometry" in input.keys() else "",
        checkpoint=lambda wc, input: f"--checkpoint {input.checkpoint}" if "checkpoint" in input.keys() else "",
        cache=lambda wc, input: f"--cache-weights {input.cache}" if "cache" in input.keys() else "",
        correction=lambda wc, input: correction_flag(input),
        blend=lambda wc: blend_args(wc.scene),
        ddpm_lights=lambda wc: scene_config(wc.scene)["evaluate"]["ddpm_lights"],
        wide=lambda wc: "--wide-lights {wide_lights} --wide-points {wide_points} --seed {seed}".format(
            **scene_config(wc.scene)["evaluate"]),
        device=evaluate_device,
    # one thread, beside evaluate_images (both wait only for sample_shadows): a second thread sped each up
    # 1.5-1.6x, so on 2 cores the pair ends sooner side by side than one after the other (docs/performance.md)
    threads: 1
    priority: 5  # report_figures waits for it; `caches` does not
    log:
        "results/{scene}/logs/evaluate_voxels.log",
    benchmark:
        "results/{scene}/benchmarks/evaluate_voxels.tsv",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow --phases results/{wildcards.scene}/benchmarks/evaluate_voxels.phases.json evaluate-voxels {params.checkpoint} --weights {input.weights}"
        " --generated {input.generated} --truth {input.truth} --volume {input.volume} --lights {input.lights}"
        " {params.geometry} {params.cache} {params.blend} --ddpm-lights {params.ddpm_lights} {params.wide}"
        " {params.device}{params.correction}"
        " --threads {threads}"
        " --out {output}" + _JOB_LOG


# every cache the run can serve a light from, as rate (bytes) against distortion (seen and unseen voxel PSNR)
rule caches:
    input:
        unpack(model_checkpoint),
        unpack(blend_correction),
        weights="results/{scene}/weights.zarr",
        generated="results/{scene}/generated.zarr",
        truth="results/{scene}/eval_truth.zarr",
        volume=extinction_volume,  # its colours alone changed: not rerun
        lights="results/{scene}/lights.json",
    output:
        table="results/{scene}/caches.json",
        figure=report("results/{scene}/report/caches.png", caption="../report/caches.rst", category="{scene}",
                      subcategory="storage"),
    params:
        checkpoint=lambda wc, input: f"--checkpoint {input.checkpoint}" if "checkpoint" in input.keys() else "",
        correction=lambda wc, input: correction_flag(input),
        blend=lambda wc: blend_args(wc.scene),
        device=evaluate_device,
        run=lambda wc: caption_values(wc.scene),  # for the caption
    threads: 1
    log:
        "results/{scene}/logs/caches.log",
    benchmark:
        "results/{scene}/benchmarks/caches.tsv",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow --phases results/{wildcards.scene}/benchmarks/caches.phases.json caches --weights {input.weights}"
        " --generated {input.generated} --truth {input.truth} --volume {input.volume} --lights {input.lights}"
        " {params.checkpoint} {params.blend} {params.device}{params.correction} --threads {threads} --figure {output.figure}"
        " --out {output.table}" + _JOB_LOG


rule render_targets:
    input:
        volume="results/{scene}/volume.zarr",
        lights="results/{scene}/lights.json",
    output:
        directory("results/{scene}/targets.zarr"),
    params:  # only what the images depend on: a new learning rate must not re-render them
        cfg=lambda wc: json.dumps({"finetune": {k: scene_config(wc.scene)["finetune"][k]
                                                for k in ("views", "image_size", "fov", "step", "targets")},
                                   "fit": {"grid_upsample": scene_config(wc.scene)["fit"]["grid_upsample"]}},
                                  sort_keys=True),
    threads: 1  # a sweep and 64² images per light: small work (the march took a second thread at 1.0x)
    # finetune_render waits for it: on the H200 the side jobs took the free slot first, and finetune_render waited
    # 7.5-8.5 s for it after train_diffusion (on a CPU every side job ends beside fit_siren whatever the order)
    priority: 5
    log:
        "results/{scene}/logs/render_targets.log",
    benchmark:
        "results/{scene}/benchmarks/render_targets.tsv",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow --phases results/{wildcards.scene}/benchmarks/render_targets.phases.json render-targets --volume {input.volume} --lights {input.lights} --config-json {params.cfg:q}"
        " --threads {threads} --out {output}" + _JOB_LOG


rule finetune_render:
    input:
        checkpoint="results/{scene}/diffusion_geometry.ckpt",
        weights="results/{scene}/weights.zarr",
        points="results/{scene}/geometry_points.zarr",
        targets="results/{scene}/targets.zarr",
        volume="results/{scene}/volume.zarr",
        lights="results/{scene}/lights.json",
    output:
        checkpoint="results/{scene}/diffusion.ckpt",
        metrics="results/{scene}/finetune_metrics.json",
    params:
        # nproc and the launcher are left out: they change how the step runs, not its result (DDP equals
        # one process, tests/test_finetune.py), so a profile that sets them reruns nothing
        cfg=lambda wc: finetune_json(wc.scene),
    threads: lambda wc: device_threads(scene_config(wc.scene)["finetune"]["nproc"], processes=True)
    # the chain after train_diffusion: on the H200 train_data_inr took the core train_diffusion freed, and this job
    # waited 5.9 s (2.4 s under evaluate.device: run) though it needs nothing of it (docs/performance.md)
    priority: 10
    resources:
        gpu=lambda wc: scene_config(wc.scene)["finetune"]["nproc"],
    log:
        "results/{scene}/logs/finetune_render.log",
    benchmark:
        "results/{scene}/benchmarks/finetune_render.tsv",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        # finetune.nproc processes as `threads` (so -j caps them on a laptop), no more than the device takes
        # (one per GPU on CUDA), said in one line; one process runs without the launcher, which would only
        # import PyTorch once more (4 s on an H200 node, 1 s here)
        "n=$(diffshadow ddp-processes --nproc {threads}) &&"
        " if [ $n -gt 1 ]; then launch=\"$DIFFSHADOW_TORCHRUN --nproc_per_node=$n -m diffshadow.cli\"; else launch=diffshadow; fi &&"
        " $launch --phases results/{wildcards.scene}/benchmarks/finetune_render.phases.json finetune-render"
        " --checkpoint {input.checkpoint} --weights {input.weights} --points {input.points}"
        " --targets {input.targets} --volume {input.volume} --lights {input.lights} --config-json {params.cfg:q} --threads 1"
        " --metrics {output.metrics} --out {output.checkpoint}" + _JOB_LOG
