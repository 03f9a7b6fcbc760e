rule lights:
    output:
        "results/{scene}/lights.json",
    params:
        lights=lambda wc: scene_config(wc.scene)["lights"],
    benchmark:
        "results/{scene}/benchmarks/lights.tsv",
    log:
        "results/{scene}/logs/lights.log",
    conda:
        "../envs/diffshadow.yaml"
    shell:
        "diffshadow --phases results/{wildcards.scene}/benchmarks/lights.phases.json lights --sphere {params.lights[sphere]} --count {params.lights[count]}"
        " --center {params.lights[center][0]} {params.lights[center][1]} {params.lights[center][2]}"
        " --unseen {params.lights[unseen]} --seed {params.lights[seed]} --layout {params.lights[layout]} --out {output}"
        + _JOB_LOG
