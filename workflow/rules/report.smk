# Figures for `snakemake --report report.html` (captions in workflow/report/).


rule shadow_bench:
    input:
        extinction_volume,
    output:
        json="results/{scene}/bench_shadow.json",
        png="results/{scene}/bench_shadow.png",
    # one thread, on the core the side jobs leave idle near fit_siren's end: with two it ran between fit_siren
    # and train_diffusion, on the critical path (its ratios are of one process; the JSON names the threads)
    threads: 1
    log:
        "results/{scene}/logs/shadow_bench.log",
    benchmark:
        "results/{scene}/benchmarks/shadow_bench.tsv"
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow --phases results/{wildcards.scene}/benchmarks/shadow_bench.phases.json bench shadow --volumes {input} --out results/{wildcards.scene} --threads {threads}"
        " --device cpu" + _JOB_LOG


rule report_figures:
    input:
        weights="results/{scene}/weights.zarr",
        generated="results/{scene}/generated.zarr",
        voxel_metrics="results/{scene}/voxel_metrics.json",
        images="results/{scene}/images",
        lights="results/{scene}/lights.json",
        shadow_bench="results/{scene}/bench_shadow.json",
    output:
        config=report("results/{scene}/report/config.yaml", caption="../report/config.rst",
                      category="{scene}", subcategory="configuration"),
        siren=report("results/{scene}/report/siren_psnr.png", caption="../report/siren_psnr.rst",
                     category="{scene}", subcategory="shadow INRs"),
        generated=report("results/{scene}/report/generated_psnr.png", caption="../report/generated_psnr.rst",
                         category="{scene}", subcategory="shadow INRs"),
        table=report("results/{scene}/report/generated_psnr.csv", caption="../report/generated_table.rst",
                     category="{scene}", subcategory="shadow INRs"),
        grid=report("results/{scene}/report/image_grid.png", caption="../report/image_grid.rst",
                    category="{scene}", subcategory="images"),
        ddim=report("results/{scene}/report/ddim_curve.png", caption="../report/ddim_curve.rst",
                    category="{scene}", subcategory="time vs error"),
        shadow=report("results/{scene}/report/shadow_curve.png", caption="../report/shadow_curve.rst",
                      category="{scene}", subcategory="time vs error"),
        storage=report("results/{scene}/report/storage.png", caption="../report/storage.rst",
                       category="{scene}", subcategory="storage"),
    params:
        cfg=lambda wc: report_json(wc.scene),
        run=lambda wc: caption_values(wc.scene),  # for the captions
    threads: 1  # figures only (matplotlib, no torch): it starts beside `caches` when evaluate_images is done
    log:
        "results/{scene}/logs/report_figures.log",
    benchmark:
        "results/{scene}/benchmarks/report_figures.tsv",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow --phases results/{wildcards.scene}/benchmarks/report_figures.phases.json report-figures --weights {input.weights} --generated {input.generated} --lights {input.lights}"
        " --images {input.images} --voxel-metrics {input.voxel_metrics} --shadow-bench {input.shadow_bench}"
        " --config-json {params.cfg:q}"
        " --threads {threads} --out-dir results/{wildcards.scene}/report" + _JOB_LOG


rule stage_costs:
    input:
        stage_benchmarks,
    output:
        costs=report("results/{scene}/stage_costs.tsv", caption="../report/stage_costs.rst", category="{scene}",
                     subcategory="run"),
        timeline=report("results/{scene}/report/timeline.png", caption="../report/timeline.rst",
                        category="{scene}", subcategory="run"),
    log:
        "results/{scene}/logs/stage_costs.log",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow stage-costs --benchmarks {input} --out {output.costs} --timeline {output.timeline}" + _JOB_LOG


rule summary:
    input:
        unpack(summary_inputs),
    output:
        tables=report("results/{scene}/report/summary.html", caption="../report/summary.rst", category="{scene}",
                      subcategory="summary", labels={"scene": "{scene}", "what": "all tables"}),
        landing="results/{scene}/report/landing.rst",
    log:
        "results/{scene}/logs/summary.log",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow summary --results results/{wildcards.scene} --scene {wildcards.scene}"
        " --out-dir results/{wildcards.scene}/report" + _JOB_LOG
