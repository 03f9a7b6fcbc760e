# The renderer (paper §4.4 and appendix): the data INR, image evaluation against gt, the benchmark.


rule train_data_inr:
    input:
        volume=extinction_volume,  # its colours alone changed: not rerun
    output:
        "results/{scene}/data_inr.pt",
    params:
        cfg=lambda wc: as_json(wc.scene, "data_inr"),
    threads: 1  # small batches: a second thread sped it up 1.04x (23.9 -> 23.1 s); the core goes to a side job
    # first of the side jobs: naive_images, the longest, waits on it, and fit_siren borrows their core once they end
    priority: 6
    log:
        "results/{scene}/logs/train_data_inr.log",
    benchmark:
        "results/{scene}/benchmarks/train_data_inr.tsv",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow --phases results/{wildcards.scene}/benchmarks/train_data_inr.phases.json train-data-inr --volume {input.volume} --config-json {params.cfg:q} --threads {threads}"
        " --out {output}" + _JOB_LOG


rule naive_images:
    input:
        volume="results/{scene}/volume.zarr",
        lights="results/{scene}/lights.json",
        data_inr="results/{scene}/data_inr.pt",
    output:
        directory("results/{scene}/naive_images.zarr"),
    params:  # not render.reference: evaluate_images' reference is not a naive image, and this is the slow job
        cfg=lambda wc: render_json(wc.scene, "reference"),
    # the slowest of evaluate_images' renders (48 of its 74 s on 2 cores), needing no SIREN: beside fit_siren,
    # instead of after stage 2; the longest side job, so before the other side jobs that have no priority, and
    # after presample and render_targets, which the chain reads (on a GPU in time)
    threads: 1
    priority: 1
    log:
        "results/{scene}/logs/naive_images.log",
    benchmark:
        "results/{scene}/benchmarks/naive_images.tsv",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow --phases results/{wildcards.scene}/benchmarks/naive_images.phases.json naive-images --volume {input.volume} --lights {input.lights} --data-inr {input.data_inr}"
        " --config-json {params.cfg:q} --threads {threads} --out {output}" + _JOB_LOG


rule evaluate_images:
    input:
        volume="results/{scene}/volume.zarr",
        lights="results/{scene}/lights.json",
        data_inr="results/{scene}/data_inr.pt",
        weights="results/{scene}/weights.zarr",
        generated="results/{scene}/generated.zarr",
        naive="results/{scene}/naive_images.zarr",
    output:
        metrics="results/{scene}/image_metrics.json",
        images=directory("results/{scene}/images"),
    params:
        cfg=lambda wc: as_json(wc.scene, "render"),
    threads: 1  # beside evaluate_voxels (see there)
    # before `caches` (which only the summary reads): report_figures and benchmark wait for these images
    priority: 5
    log:
        "results/{scene}/logs/evaluate_images.log",
    benchmark:
        "results/{scene}/benchmarks/evaluate_images.tsv",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow --phases results/{wildcards.scene}/benchmarks/evaluate_images.phases.json evaluate-images --volume {input.volume} --lights {input.lights} --data-inr {input.data_inr}"
        " --weights {input.weights} --generated {input.generated} --naive {input.naive} --config-json {params.cfg:q}"
        " --images {output.images} --threads {threads} --out {output.metrics}" + _JOB_LOG


# the naive frame's ops, host syncs and peak memory that the benchmark reports at its smallest size: counts that do
# not drift with the load, so taken beside stage 1, not in the benchmark's cores of its own (profiled, that frame
# takes 3.4x its time: on tooth 33.5 s of the benchmark's 106; docs/performance.md)
rule bench_naive:
    input:
        volume="results/{scene}/volume.zarr",
        data_inr="results/{scene}/data_inr.pt",
        lights="results/{scene}/lights.json",
    output:
        "results/{scene}/bench_naive.json",
    params:
        size=lambda wc: min(scene_config(wc.scene)["render"]["bench_sizes"]),
        step=lambda wc: scene_config(wc.scene)["render"]["step"],
        kernel=bench_kernel,
    threads: 1
    log:
        "results/{scene}/logs/bench_naive.log",
    benchmark:
        "results/{scene}/benchmarks/bench_naive.tsv",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow --phases results/{wildcards.scene}/benchmarks/bench_naive.phases.json bench naive-counts --volume {input.volume} --data-inr {input.data_inr}"
        " --lights {input.lights} --size {params.size} --step {params.step} --kernel {params.kernel}"
        " --threads {threads} --out {output}" + _JOB_LOG


rule benchmark:
    input:
        unpack(bench_naive),
        volume="results/{scene}/volume.zarr",
        data_inr="results/{scene}/data_inr.pt",
        weights="results/{scene}/weights.zarr",
        after=benchmark_waits_for,  # not read: see there
    output:
        bench="results/{scene}/bench.json",
        plot=report("results/{scene}/bench.png", caption="../report/bench.rst", category="{scene}",
                    subcategory="renderer"),
    params:
        sizes=lambda wc: " ".join(str(n) for n in scene_config(wc.scene)["render"]["bench_sizes"]),
        step=lambda wc: scene_config(wc.scene)["render"]["step"],
        repeats=lambda wc: scene_config(wc.scene)["render"]["bench_repeats"],
        memory=lambda wc: " ".join(str(n) for n in scene_config(wc.scene)["render"].get("bench_memory_sizes", [])),
        kernel=bench_kernel,
        naive=lambda wc, input: f"--naive-counts {input.naive}" if "naive" in input.keys() else "",
    threads: 2
    log:
        "results/{scene}/logs/benchmark.log",
    benchmark:
        "results/{scene}/benchmarks/benchmark.tsv",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow --phases results/{wildcards.scene}/benchmarks/benchmark.phases.json bench render --volume {input.volume} --data-inr {input.data_inr} --weights {input.weights}"
        " --sizes {params.sizes} --memory-sizes {params.memory} --step {params.step} --repeats {params.repeats}"
        " --kernel {params.kernel} {params.naive} --threads {threads}"
        " --out {output.bench}" + _JOB_LOG
