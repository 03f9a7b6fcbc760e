# Stage 2 (paper §3.3): presampled geometry points, diffusion training, sampling, voxel evaluation.


rule presample:
    input:
        volume="results/{scene}/volume.zarr",
        lights="results/{scene}/lights.json",
    output:
        directory("results/{scene}/geometry_points.zarr"),
    params:
        cfg=lambda wc: as_json(wc.scene, "diffusion"),
    threads: 2
    shell:
        "diffshadow presample --volume {input.volume} --lights {input.lights} --config-json {params.cfg:q}"
        " --threads {threads} --out {output}"


rule train_diffusion:
    input:
        weights="results/{scene}/weights.zarr",
        points="results/{scene}/geometry_points.zarr",
    output:
        "results/{scene}/diffusion_geometry.ckpt",
    params:
        cfg=lambda wc: as_json(wc.scene, "diffusion"),
    threads: 2
    log:
        "results/{scene}/logs/train_diffusion.log",
    shell:
        "diffshadow train-diffusion --weights {input.weights} --points {input.points}"
        " --config-json {params.cfg:q} --threads {threads} --out {output} 2>&1 | tee {log}"


rule sample_shadows:
    input:
        checkpoint="results/{scene}/diffusion_geometry.ckpt",
        volume="results/{scene}/volume.zarr",
        lights="results/{scene}/lights.json",
    output:
        directory("results/{scene}/generated.zarr"),
    threads: 2
    log:
        "results/{scene}/logs/sample_shadows.log",
    shell:
        "diffshadow sample-shadows --checkpoint {input.checkpoint} --volume {input.volume}"
        " --lights {input.lights} --threads {threads} --out {output} 2>&1 | tee {log}"


rule evaluate_voxels:
    input:
        checkpoint="results/{scene}/diffusion_geometry.ckpt",
        weights="results/{scene}/weights.zarr",
        generated="results/{scene}/generated.zarr",
        volume="results/{scene}/volume.zarr",
        lights="results/{scene}/lights.json",
    output:
        "results/{scene}/voxel_metrics.json",
    threads: 2
    log:
        "results/{scene}/logs/evaluate_voxels.log",
    shell:
        "diffshadow evaluate-voxels --checkpoint {input.checkpoint} --weights {input.weights}"
        " --generated {input.generated} --volume {input.volume} --lights {input.lights} --threads {threads}"
        " --out {output} 2>&1 | tee {log}"
