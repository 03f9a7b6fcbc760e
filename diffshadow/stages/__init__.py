"""The stage layer: one typed function per workflow rule, grouped like `workflow/rules/*.smk`.

Each takes paths, config objects and a `torch.device`, reads its inputs through `diffshadow.artifacts`
and `diffshadow.store`, calls the concept modules and writes its outputs atomically. The CLI only parses
arguments and dispatches here; the Parsl worker calls `stage1.fit_subset` directly.

- `stage1`: lights, prepare_volume, preoptimize, fit_subset, collect_weights
- `stage2`: presample, train_diffusion, finetune_render, sample_shadows, evaluate_voxels
- `images`: train_data_inr, render_targets, evaluate_images, render_image (the `benchmark` rule runs
  `bench.render.run`, report_figures `report.scene_figures`, which needs no torch)
"""
