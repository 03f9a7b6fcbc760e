#!/usr/bin/env bash
# The GPU figures of docs/performance.md, in one device call (15 minutes of device time a session):
#
#   bash scripts/gpu_prepare.sh                                     # here, once per session
#   device run, carry [".devwheels"], timeout_s 600:
#       END=555 bash .devwheels/on-device.sh bash scripts/gpu_session.sh all
#   then at once, on the still-warm machine (it goes back after 30 s idle), with what is left, e.g.:
#       END=230 SWITCHES="evaluate: {device: run}" PARTS="workflow:0" bash .devwheels/on-device.sh \
#           bash scripts/gpu_session.sh all
#
# `all` runs PARTS (default "workflow:300 checks:0": the README run and the whole `pytest -m gpu`, which the GPU
# issue asks for at every change of a CUDA default; the renderer's plans and bench were measured on an H200 at
# 6a79efd, the geometry stage's graphs at 437d7d4), each cut short so the whole ends by END seconds (a cap of 0 =
# the time left), and packs everything into $OUT/all.tgz (a call brings back at most 8 files). PYTEST_K narrows
# `checks` (e.g. "not tiny_workflow": that test is a whole workflow, ~2 minutes on the H200).
# A part alone: `... gpu_session.sh render`.
#
# plans:    scripts/render_plans.py at 128², 512², 1024², inr and naive: every way the code can evaluate the
#           SIRENs (eager fp32, TF32 matmuls, torch.compile, the fused kernels) side by side, with the PSNR
#           against the eager fp32 image, then
#           torch.profiler's top kernels and the device's busy fraction of one 1024² inr frame per variant.
# render:   bench render on hydrogen_atom at 128², 512², 1024² (fps, ops and host syncs per frame, skipping,
#           peak memory up to 2048²), the fused kernels (the CUDA default) first, then eager.
# workflow: the README's run (`snakemake --profile local -j2`, the profile from profiles/; SNAKEMAKE_ARGS added)
#           on an empty results/, its wall time, each rule's phases (stage_costs.tsv), the GPU's busy share and
#           the run's metrics. SWITCHES, YAML over config/config.yaml, times a config switch (e.g.
#           "evaluate: {device: run}": eval_truth and evaluate_voxels on the GPU), and every process's Triton compile
#           requests (triton_compiles.jsonl: kernel, specialisation, options).
# checks:   pytest -m gpu (PYTEST_K narrows it with -k).
# stages:   `bench stages` on the GPU at the paper's sizes (the JSON profiles/paper is generated from), at the
#           defaults, and at the defaults with every training step's points and batch raised (STAGES_BIG, a YAML
#           overlay): whether a bigger step costs a GPU more than a few launches.
# precision: `bench stages` of the two training stages at the paper's sizes (where the products, not the launches,
#           take the time), diffusion.precision float32 then bfloat16 then both again: what bfloat16 autocast saves
#           a step (its quality was measured on a CPU: docs/performance.md, stage 2).
# graph:    `bench stages` of the five training stages (GRAPH_STAGES names fewer) at the README's config and at
#           the paper's, every stage's cuda_graph false then true (fine-tuning in one process: DDP steps eagerly),
#           twice (ROUNDS="1" once), then `pytest -m gpu -k graph` (graphed steps train what eager steps train):
#           what one replayed graph a step saves. The fits', the data INR's and the geometry stage's graphs are the
#           CUDA default since a GPU timed them; finetune.cuda_graph (false) waits on this.
# stage1:   stage 1 alone (snakemake ... results/nucleon/weights.zarr) at 512 of 2,048 lights, wall time
#           and each fit_siren job's benchmark (a job cut short still leaves the finished subsets' figures).
# viewer:   `ViewerScene.frame` on a finished results/nucleon (after `workflow`) at 512² and 1024² from the framed
#           view: each mode's first frame (its kernels compiled) and median, the light moved among training
#           lights, and new directions (the SIREN generated, then its frame).
# sampler:  `generate` on a finished results/nucleon, its denoiser eager then as replayed CUDA graphs (the default on
#           CUDA), alternating: the 500-step DDPM of evaluate_voxels, a new direction, sample_shadows' batch.
#
# On a CPU it runs too (DIFFSHADOW_DEVICE=cpu, QUICK=1 for small sizes): that is how the script is tested.
set -uo pipefail
case ${1:-} in
    -h|--help) sed -n '2,/^set -uo/p' "$0" | sed '$d;s/^# \{0,1\}//'; exit 0 ;;
esac
part=${1:?usage: scripts/gpu_session.sh all|plans|render|workflow|checks|stages|precision|graph|viewer|sampler|stage1}
# Parts write under $root and are packed into $OUT/<part>.tgz at the end: a device call brings back at most 8
# files, and one run writes dozens. `all` hands its root to the parts it runs (PART_ROOT) and packs once each.
dest=${OUT:-gpu_session}
root=${PART_ROOT:-$(mktemp -d)}
out=$root/$part
mkdir -p "$out" "$dest"
pack() { [ -n "${PART_ROOT:-}" ] || tar czf "$dest/$part.tgz" -C "$root" . ; }
device=${DIFFSHADOW_DEVICE:-cuda}
quick=${QUICK:-0}
failed=0

compiled() {  # Python's bytecode for every module a job imports, as an installation leaves it: the GPU machine's
    # image sets PYTHONDONTWRITEBYTECODE and ships PyTorch without it, so each job compiled ~1,000 modules from source
    # (2 s of its ~3 s import there); a run timed that way would count what no user's installation pays
    python -c "import sys; sys.exit(not sys.flags.dont_write_bytecode)" || return 0
    local sp pp=${PYTHONPATH:-} t0=$SECONDS
    sp=$(python -c "import os, torch; print(os.path.dirname(os.path.dirname(torch.__file__)))")
    python -m compileall -q -j 0 diffshadow "$sp" ${pp//:/ } >"$out/compileall.log" 2>&1
    echo "== bytecode compiled: $((SECONDS - t0)) s" | tee -a "$out/times.txt"
}

step() {  # step NAME CMD...: run, log to $out/NAME.log, time it, go on past a failure
    local name=$1; shift
    local t0=$SECONDS
    echo "== $name: $*"
    "$@" >"$out/$name.log" 2>&1
    local rc=$?
    echo "== $name: exit $rc, $((SECONDS - t0)) s" | tee -a "$out/times.txt"
    tail -n 15 "$out/$name.log"
    [ "$rc" -eq 0 ] || failed=1
}

with_setting() {  # with_setting IN SECTION KEY VALUE OUT: the config IN with SECTION.KEY set to VALUE (YAML), as OUT
    python -c "import sys, yaml; c = yaml.safe_load(open(sys.argv[1])); \
c.setdefault(sys.argv[2], {})[sys.argv[3]] = yaml.safe_load(sys.argv[4]); yaml.safe_dump(c, open(sys.argv[5], 'w'))" "$@"
}

{ python -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'available', torch.cuda.is_available())"
  nvidia-smi -L 2>/dev/null; nproc; git rev-parse HEAD 2>/dev/null; } >"$out/machine.txt" 2>&1
cat "$out/machine.txt"

case $part in
checks)
    # the GPU checks are one file: one process, without the thread share the parallel suite gives its workers
    step pytest_gpu pytest -q -n 0 -m gpu -rs --durations=10 ${PYTEST_K:+-k "$PYTEST_K"}
    ;;
stages)
    paper=(--configfile config/paper.yaml --budget 3 --max-steps 20)
    [ "$quick" = 1 ] && paper=(--configfile config/paper.yaml --stages eval_truth --budget 0 --max-steps 1)
    step bench_stages_paper diffshadow bench stages --device "$device" "${paper[@]}" --out "$out/bench_stages_paper.json"
    step bench_stages_default diffshadow bench stages --device "$device" --out "$out/bench_stages_default.json"
    if [ -n "${STAGES_BIG:-}" ]; then cp "$STAGES_BIG" "$out/big.yaml"; else cat >"$out/big.yaml" <<'YAML'
fit: {points: 16384}
data_inr: {points: 16384}
diffusion: {batch_size: 64}
finetune: {batch_size: 64}
YAML
    fi
    step bench_stages_big diffshadow bench stages --device "$device" --configfile "$out/big.yaml" \
        --stages fit_siren preoptimize train_data_inr train_diffusion finetune_render --out "$out/bench_stages_big.json"
    ;;
render)
    sizes=(--sizes 128 512 1024 --memory-sizes 2048); [ "$quick" = 1 ] && sizes=(--sizes 32 64 --memory-sizes 96)
    [ "$device" = cuda ] && step bench_render_fused diffshadow bench render --kernel fused --device cuda \
        --scene-config config/scenes/hydrogen_atom.yaml "${sizes[@]}" --out "$out/render_fused.json"
    step bench_render diffshadow bench render --kernel eager --device "$device" \
        --scene-config config/scenes/hydrogen_atom.yaml "${sizes[@]}" --out "$out/render.json"
    ;;
plans)
    sizes=(--sizes 128 512 1024); [ "$quick" = 1 ] && sizes=(--sizes 24 --inr-steps 200 --repeats 1)
    variants=("tf32 matmuls")  # the fused kernels run on CUDA (on a CPU only interpreted, slowly)
    [ "$device" = cuda ] && variants+=("fused")
    step render_plans python scripts/render_plans.py --device "$device" "${sizes[@]}" --profile \
        --variants "${variants[@]}"
    ;;
all)
    end=${END:-540}
    # a cap of 0 means whatever time is left
    for p in ${PARTS:-workflow:300 checks:0}; do
        left=$((end - SECONDS)); cap=${p#*:}; { [ "$cap" -eq 0 ] || [ "$left" -lt "$cap" ]; } && cap=$left
        if [ "$cap" -lt 30 ]; then echo "== ${p%%:*}: skipped, ${left} s left" | tee -a "$out/times.txt"; continue; fi
        PART_ROOT=$root PART_CAP=$cap timeout -k 5 "$cap" bash "$0" "${p%%:*}" || failed=1
        pack
    done
    ;;
workflow)
    [ -L results ] && rm results  # a link to this machine's results elsewhere travels as a dangling link
    rm -rf results/nucleon results/.kernel-cache  # a first run's kernels compile too
    compiled
    # every process's Triton compile requests (kernel, specialisation, options) into triton_compiles.jsonl, through
    # Triton's jit_cache_hook, set by a sitecustomize when triton.knobs loads (a process that renders nothing
    # imports no Triton for it): which launches of which jobs ask for kernels the run's cache lacks
    mkdir -p "$out/hook"
    cat >"$out/hook/sitecustomize.py" <<'PY'
import importlib.abc, importlib.util, json, os, sys
class _Knobs(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name != "triton.knobs":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)
        run = spec.loader.exec_module
        def exec_module(module):
            run(module)
            def hook(*, key, repr, fn, compile, is_manual_warmup, already_compiled):
                with open(os.environ["DIFFSHADOW_TRITON_LOG"], "a") as f:
                    f.write(json.dumps({"pid": os.getpid(), "job": sys.argv[1:5], "repr": repr, "key": str(key),
                                        "spec": compile.get("specialization_data"),
                                        "cache_dir": module.cache.dir}) + "\n")
            module.runtime.jit_cache_hook = hook
        spec.loader.exec_module = exec_module
        return spec
sys.meta_path.insert(0, _Knobs())
PY
    export DIFFSHADOW_TRITON_LOG=$out/triton_compiles.jsonl PYTHONPATH=$out/hook${PYTHONPATH:+:$PYTHONPATH}
    t0=$SECONDS
    # the GPU's busy share through the run, every half second
    nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv -lms 500 >"$out/gpu_util.csv" 2>/dev/null &
    smi=$!
    # stopped 25 s before the part's cap, so that a cut run still brings back its finished rules' phases
    switches=()
    if [ -n "${SWITCHES:-}" ]; then
        printf '%s\n' "$SWITCHES" >"$out/switches.yaml"
        switches=(--configfile config/config.yaml "$out/switches.yaml")
    fi
    step snakemake timeout $((${PART_CAP:-100000} - 25)) snakemake --profile profiles/local -j2 "${switches[@]}" \
        ${SNAKEMAKE_ARGS:-}
    echo "README run: $((SECONDS - t0)) s wall" | tee "$out/wall.txt"
    kill $smi 2>/dev/null
    cp results/nucleon/*.json "$out/" 2>/dev/null
    cp -r results/nucleon/benchmarks results/nucleon/logs "$out/" 2>/dev/null
    cp results/nucleon/stage_costs.tsv "$out/run_stage_costs.tsv" 2>/dev/null
    # the run's compiled kernels, oldest first, beside the jobs' start times: naive_images, evaluate_images and
    # benchmark each compiled their own (7 kernels at 6d4adc4, where one viewer process needs 4). Triton 3.6's
    # metadata names no specialisation, so each kernel's Triton IR goes along (kernel_ir/): its signature holds the
    # pointers' alignment, its body the constants
    python - results/.kernel-cache/triton "$out/kernel_ir" >"$out/kernel_cache.tsv" 2>&1 <<'PY'
import json, os, shutil, sys
rows = []
for root, _, files in os.walk(sys.argv[1]):
    for f in files:
        if f.endswith(".json") and not f.startswith("__grp__"):
            path = os.path.join(root, f)
            try:
                meta = json.load(open(path))
            except (OSError, ValueError):
                continue
            rows.append((os.path.getmtime(path), meta.get("name", f), root, meta))
os.makedirs(sys.argv[2], exist_ok=True)
for i, (t, name, root, meta) in enumerate(sorted(rows, key=lambda r: r[:2])):
    ttir = os.path.join(root, f"{name}.ttir")
    signature = ""
    if os.path.exists(ttir):
        shutil.copy(ttir, os.path.join(sys.argv[2], f"{i:02d}_{name}.ttir"))
        signature = next((line.strip() for line in open(ttir) if "tt.func public" in line), "")
    small = {k: v for k, v in meta.items() if not isinstance(v, (list, dict)) or len(json.dumps(v)) < 200}
    print(f"{t:.1f}\t{name}\t{json.dumps(small, sort_keys=True)}\t{signature}")
PY
    step stage_costs diffshadow stage-costs --out "$out/stage_costs.tsv" --timeline "$out/timeline.png" \
        --benchmarks results/nucleon/benchmarks/*.tsv
    cat "$out/stage_costs.tsv" 2>/dev/null
    ;;
precision)
    args=(--stages train_diffusion finetune_render --budget 3 --max-steps 20)
    [ "$quick" = 1 ] && args=(--stages train_diffusion --budget 0 --max-steps 2)
    for p in float32 bfloat16; do  # config/paper.yaml with the precision set
        with_setting config/paper.yaml diffusion precision "$p" "$out/paper_$p.yaml"
        [ "$quick" = 1 ] && printf 'diffusion: {preset: tiny, precision: %s}\n' "$p" >"$out/paper_$p.yaml"
    done
    for round in 1 2; do
        for p in float32 bfloat16; do
            step "bench_$p$round" diffshadow bench stages --device "$device" --configfile "$out/paper_$p.yaml" \
                "${args[@]}" --out "$out/bench_stages_paper_$p$round.json"
        done
    done
    ;;
graph)
    stages=(--stages ${GRAPH_STAGES:-fit_siren preoptimize train_data_inr train_diffusion finetune_render})
    args=("${stages[@]}" --budget 3 --max-steps 30)
    [ "$quick" = 1 ] && args=("${stages[@]}" --budget 0 --max-steps 2)
    for c in config paper; do
        for g in false true; do  # the config with every stage's cuda_graph set; fine-tuning in one process, which
            cp "config/$c.yaml" "$out/${c}_graph_$g.yaml"  # alone graphs (DDP steps eagerly)
            for section in fit data_inr diffusion finetune; do
                with_setting "$out/${c}_graph_$g.yaml" "$section" cuda_graph "$g" "$out/${c}_graph_$g.yaml"
            done
            with_setting "$out/${c}_graph_$g.yaml" finetune nproc 1 "$out/${c}_graph_$g.yaml"
            [ "$quick" = 1 ] && [ "$c" = paper ] && printf '%s\n' "diffusion: {preset: tiny, cuda_graph: $g}" \
                "fit: {cuda_graph: $g}" "data_inr: {cuda_graph: $g}" "finetune: {cuda_graph: $g, nproc: 1}" \
                >"$out/${c}_graph_$g.yaml"
        done
    done
    for round in ${ROUNDS:-1 2}; do
        for c in config paper; do
            for g in false true; do
                step "bench_${c}_graph_$g$round" diffshadow bench stages --device "$device" \
                    --configfile "$out/${c}_graph_$g.yaml" "${args[@]}" --out "$out/bench_stages_${c}_graph_$g$round.json"
            done
        done
    done
    step pytest_graph pytest -q -n 0 -m gpu -rs -k graph
    ;;
viewer)
    sizes="512 1024"; [ "$quick" = 1 ] && sizes="24 32"
    step viewer_frames python - "$out/viewer_frames.json" "$device" $sizes <<'PY'
import json, statistics, sys, time
from pathlib import Path
import numpy as np, torch
from diffshadow.viewer import ViewerScene, azimuth_elevation, direction
device, sizes = torch.device(sys.argv[2]), [int(s) for s in sys.argv[3:]]
t0 = time.perf_counter()
viewer = ViewerScene.from_results(Path("results/nucleon"), device)
out = {"open_s": time.perf_counter() - t0, "kernel": viewer.scene.kernel_used, "torch": torch.__version__}
light = np.asarray(viewer.train[0])
az, el = azimuth_elevation(light)
def frame(mode, camera, w):
    t = time.perf_counter()
    _, notes = viewer.frame(mode, camera, w, step=0.5)
    return time.perf_counter() - t, notes
for size in sizes:
    camera, row = viewer.scene.framed(size=size), {}
    for mode, n in (("noshadow", 8), ("inr", 8), ("gt", 4), ("naive", 2)):
        seconds = [frame(mode, camera, light)[0] for _ in range(n)]
        row[mode] = {"first_s": seconds[0], "median_s": statistics.median(seconds[1:])}
    row["inr_light_moved_s"] = statistics.median(frame("inr", camera, np.asarray(w))[0] for w in viewer.train[1:6])
    row["new_direction"] = []
    for i in range(3):  # near training light 0, listed nowhere: generated once, then drawn
        s, notes = frame("inr", camera, direction(az + 2 + i + size / 1000, el))
        row["new_direction"].append({"generate_s": notes["light"].generate_s, "frame_s": s})
    out[str(size)] = row
    print(size, json.dumps(row), flush=True)
json.dump(out, open(sys.argv[1], "w"), indent=1, default=float)
PY
    ;;
sampler)
    # generate() on a finished results/nucleon (after `workflow`), its denoiser eager and as replayed CUDA graphs,
    # alternating: evaluate_voxels' 500-step DDPM of 8 lights, a viewer's new direction (DDIM, 1 light),
    # sample_shadows' batch (DDIM, 64 lights); the first call of each (graphs captured) apart; the largest difference
    step sampler_graphs python - "$out/sampler_graphs.json" "$device" "$quick" <<'PY'
import json, statistics, sys, time
from pathlib import Path
import numpy as np, torch
from diffshadow.artifacts import load_checkpoint
from diffshadow.diffusion.sample import generate, load_sampler
device, quick = torch.device(sys.argv[2]), sys.argv[3] == "1"
model, std, _, _ = load_sampler(state := load_checkpoint(Path("results/nucleon/diffusion.ckpt")), device)
train = np.asarray(state["train_lights"])
cases = [("ddim", 5, 1, 2)] if quick else [("ddpm", 500, 8, 3), ("ddim", 10, 1, 10), ("ddim", 10, 64, 5)]
def run(method, steps, n, graph):
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    t = time.perf_counter()
    w = generate(model, std, np.resize(train, (n, 3)), method=method, steps=steps, device=device, cuda_graph=graph)
    return time.perf_counter() - t, w
out = {"torch": torch.__version__, "device": str(device), "cases": []}
for method, steps, n, repeats in cases:
    first = {g: run(method, steps, n, g) for g in (False, True)}
    times = {False: [], True: []}
    for _ in range(repeats):
        for g in (False, True):
            times[g].append(run(method, steps, n, g)[0])
    row = {"method": method, "steps": steps, "lights": n, "first_s": {str(g): first[g][0] for g in first},
           "median_s": {str(g): statistics.median(times[g]) for g in times},
           "max_abs_diff": float((first[True][1] - first[False][1]).abs().max())}
    out["cases"].append(row)
    print(json.dumps(row), flush=True)
json.dump(out, open(sys.argv[1], "w"), indent=1)
PY
    ;;
stage1)
    # stage 1 alone at 512 training lights, at the paper's cap fraction (a quarter of the sphere)
    n=512; [ "$quick" = 1 ] && n=40
    printf 'lights: {count: %d, sphere: %d, unseen: 32}\n' "$n" $((4 * n)) >"$out/lights.yaml"
    [ -L results ] && rm results
    rm -rf results/nucleon
    compiled
    t0=$SECONDS
    step snakemake snakemake results/nucleon/weights.zarr --profile profiles/local -j2 \
        --configfile "$out/lights.yaml"
    echo "stage 1 at $n lights: $((SECONDS - t0)) s wall" | tee "$out/wall.txt"
    cp -r results/nucleon/benchmarks results/nucleon/logs "$out/" 2>/dev/null
    ;;
*)
    echo "unknown part $part (all, plans, render, workflow, checks, stages, precision, graph, viewer, sampler or stage1)" >&2
    exit 2
    ;;
esac
pack
exit $failed
