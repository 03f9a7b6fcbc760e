# Stage 1 (paper §3.2): the prepared volume, the shared initial SIREN, subset fits, the weight store.


rule prepare_volume:
    input:
        volume_file,  # so a dry run already names a missing volume, and a changed file reruns the scene
    output:
        directory("results/{scene}/volume.zarr"),
    params:
        cfg=lambda wc: json.dumps({k: v for k, v in scene_config(wc.scene).items()
                                   if k in ("volume", "load", "transfer_function")}, sort_keys=True),
    benchmark:
        "results/{scene}/benchmarks/prepare_volume.tsv",
    log:
        "results/{scene}/logs/prepare_volume.log",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow --phases results/{wildcards.scene}/benchmarks/prepare_volume.phases.json prepare-volume --config-json {params.cfg:q} --out {output}"
        + _JOB_LOG


rule preoptimize:
    input:
        volume=extinction_volume,  # its colours alone changed: not rerun
        lights="results/{scene}/lights.json",
    output:
        "results/{scene}/siren_init.pt",
    params:
        cfg=lambda wc: fit_json(wc.scene, "siren", "fit", "preoptimize", halo=False),
    threads: 1
    priority: 10  # the head of the longest chain: the side jobs (targets, data INR, truth) fill the other core
    log:
        "results/{scene}/logs/preoptimize.log",
    benchmark:
        "results/{scene}/benchmarks/preoptimize.tsv",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow --phases results/{wildcards.scene}/benchmarks/preoptimize.phases.json preoptimize --volume {input.volume} --lights {input.lights} --config-json {params.cfg:q}"
        " --threads {threads} --out {output}" + _JOB_LOG


rule fit_siren:
    input:
        volume=extinction_volume,  # its colours alone changed: not rerun
        lights=subset_lights,  # a subset the scene's lights do not have stops the plan
        init="results/{scene}/siren_init.pt",
        held=held_subset_files,  # fit.rounds: the earlier rounds' subsets whose SIRENs it holds (read beside its output)
    output:
        "results/{scene}/sirens/subset_{subset}.npz",
    params:
        cfg=lambda wc: fit_json(wc.scene, "siren", "fit", "subset_size"),
    wildcard_constraints:
        subset=r"\d+",
    group:
        fit_group  # on a cluster only; Polaris packs four of a round to a node
    threads: 1  # and up to two while the run's other core idles (runtime.SpareThreads; the same bytes)
    priority: 10
    log:
        "results/{scene}/logs/fit_siren_{subset}.log",
    benchmark:
        "results/{scene}/benchmarks/fit_siren_{subset}.tsv",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow --phases results/{wildcards.scene}/benchmarks/fit_siren_{wildcards.subset}.phases.json fit-siren --volume {input.volume} --lights {input.lights} --init {input.init}"
        " --subset {wildcards.subset} --config-json {params.cfg:q} --threads {threads} --out {output}"
        + _JOB_LOG


rule collect_weights:
    input:
        lights="results/{scene}/lights.json",
        subsets=subset_files,
    output:
        directory("results/{scene}/weights.zarr"),
    # on the longest chain (fit_siren -> train_diffusion): where the fits take seconds (a GPU), the side jobs
    # waiting with it took the free slot first and held train_diffusion back ~19 s on the H200
    priority: 10
    log:
        "results/{scene}/logs/collect_weights.log",
    benchmark:
        "results/{scene}/benchmarks/collect_weights.tsv",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow --phases results/{wildcards.scene}/benchmarks/collect_weights.phases.json collect-weights --lights {input.lights} --subsets {input.subsets} --out {output}"
        + _JOB_LOG
