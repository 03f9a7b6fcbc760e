#!/usr/bin/env bash
# The GPU figures that issues 15, 16 and 19 ask for. One device call (15 minutes of device time a session):
#
#   bash ../shared/gpu/prepare.sh                                   # here, once per session
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#       -d .devwheels/whl pytest-xdist==3.8.0 execnet==2.1.2        # the `tests` part runs the suite in parallel
#   device run, carry [".devwheels"], timeout_s 600:
#       END=560 bash .devwheels/on-device.sh bash scripts/gpu_session.sh all
#   then at once, on the still-warm machine (it goes back after 30 s idle), with the ~250 s left, timeout_s 150:
#       END=140 PARTS=sweep:0 bash .devwheels/on-device.sh bash scripts/gpu_session.sh all
#   (through `all`, so the sweep is cut at END and still packed into $OUT/all.tgz; a part called alone packs only
#   when it ends, and a call's time limit would lose its logs)
#
# `all` runs render and tests (what issues 16 and 15 still miss), each cut short so the whole ends by END
# seconds (PARTS="part:cap ..." overrides; cap 0 = the time left), and packs everything into $OUT/all.tgz (a call
# brings back at most 8 files).
# A part alone: `... gpu_session.sh render`.
#
# workflow: the README's run (`snakemake --profile local -j2`, the profile from profiles/) on an empty
#           results/, its wall time and Snakemake's per-rule benchmark table, and the run's metrics.
# render:   bench render on hydrogen_atom at 128², 512², 1024² (fps, ops and host syncs per frame, skipping,
#           peak memory up to 2048²), then the same with the fused kernels in TF32.
# plans:    scripts/render_plans.py: batch sizes, TF32 matmuls and the fused kernels side by side, then
#           torch.profiler's top kernels and the device's busy fraction of one 1024² inr frame per variant.
# sweep:    render_plans.py at 512² and 1024², inr: eager against the fused kernels per wavefront step and whole
#           rays (TF32; whole rays with each sine: poly, approx, libdevice), with lane use and the profile of one
#           1024² frame each; then scripts/fused_sweep.py (the primary sample alone per points per program and
#           warps, then whole-ray frames per points, warps and cap on registers per thread).
# checks:   pytest -m gpu; bench siren (K=16 and K=50 jointly vs one by one, default chunking); the cost of
#           DIFFSHADOW_DETERMINISTIC=1 on the same K=16 run.
# tests:    the whole suite, with its slowest tests.
#
# On a CPU it runs too (DIFFSHADOW_DEVICE=cpu, QUICK=1 for small sizes): that is how the script is tested.
set -uo pipefail
case ${1:-} in
    -h|--help) sed -n '2,/^set -uo/p' "$0" | sed '$d;s/^# \{0,1\}//'; exit 0 ;;
esac
part=${1:?usage: scripts/gpu_session.sh all|workflow|render|plans|sweep|checks|tests}
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

{ python -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda, 'available', torch.cuda.is_available())"
  nvidia-smi -L 2>/dev/null; nproc; git rev-parse HEAD 2>/dev/null; } >"$out/machine.txt" 2>&1
cat "$out/machine.txt"

case $part in
checks)
    if [ "$quick" = 1 ]; then points=(--points 512 --widths 32); k50=(--k 4); else points=(); k50=(--k 50); fi
    w64=(--widths 64); [ "$quick" = 1 ] && w64=()
    [ "$quick" = 1 ] || step pytest_gpu pytest -q -m gpu -rs --durations=10
    step bench_siren_k16 diffshadow bench siren --device "$device" --k 16 "${points[@]}" --out "$out/siren_k16"
    step bench_siren_k50 diffshadow bench siren --device "$device" "${k50[@]}" "${points[@]}" "${w64[@]}" \
        --out "$out/siren_k50"
    step bench_siren_k16_deterministic env DIFFSHADOW_DETERMINISTIC=1 diffshadow bench siren --device "$device" \
        --k 16 "${points[@]}" --out "$out/siren_k16_deterministic"
    ;;
render)
    sizes=(--sizes 128 512 1024 --memory-sizes 2048); [ "$quick" = 1 ] && sizes=(--sizes 32 64 --memory-sizes 96)
    step bench_render diffshadow bench render --device "$device" --scene-config config/scenes/hydrogen_atom.yaml \
        "${sizes[@]}" --out "$out/render"
    [ "$device" = cuda ] && step bench_render_fused diffshadow bench render --kernel fused --precision tf32 \
        --device cuda --scene-config config/scenes/hydrogen_atom.yaml "${sizes[@]}" --out "$out/render_fused"
    ;;
plans)
    sizes=(--sizes 128 512 1024); [ "$quick" = 1 ] && sizes=(--sizes 24 --inr-steps 200 --repeats 1)
    step render_plans python scripts/render_plans.py --device "$device" "${sizes[@]}" --profile
    ;;
sweep)
    # whole rays against wavefront steps, then the primary sample alone (tile sizes and warps)
    if [ "$quick" = 1 ]; then
        sw=(--n 2048 --blocks 16 --warps 4 --registers 0 168 --repeats 1 --inr-steps 20 --frame 24)
        pf=(--sizes 24 --inr-steps 200 --repeats 1)
    else
        # whole rays also with registers capped at 168 a thread: 3 programs of 4 warps per SM instead of 2, for
        # 31 spilled loads and stores (sm_90; scripts/kernel_tiles.py)
        sw=(--precisions tf32 --blocks 64 --warps 4 8 --registers 0 168 --repeats 3); pf=(--sizes 512 1024 --repeats 3)
    fi
    variants=("compiled SIREN")
    [ "$device" = cuda ] && variants=("fused tf32" "fused tf32 approx" "fused tf32 libdevice" "fused tf32 steps")
    step frame_profile python scripts/render_plans.py --device "$device" --modes inr "${pf[@]}" \
        --variants "${variants[@]}" --profile
    step fused_sweep python scripts/fused_sweep.py --device "$device" "${sw[@]}"
    ;;
all)
    end=${END:-540}
    # the renderer with the whole-ray kernel first (issue 16's figures), then the whole suite (issue 15's last
    # item; its workflow tests start ~40 CUDA processes; on an H200 it had not finished in 330 s in one process);
    # a cap of 0 means whatever time is left
    for p in ${PARTS:-render:210 tests:0}; do
        left=$((end - SECONDS)); cap=${p#*:}; { [ "$cap" -eq 0 ] || [ "$left" -lt "$cap" ]; } && cap=$left
        if [ "$cap" -lt 30 ]; then echo "== ${p%%:*}: skipped, ${left} s left" | tee -a "$out/times.txt"; continue; fi
        PART_ROOT=$root PART_CAP=$cap timeout -k 5 "$cap" bash "$0" "${p%%:*}" || failed=1
        pack
    done
    ;;
workflow)
    rm -rf results/nucleon
    t0=$SECONDS
    step snakemake snakemake --profile profiles/local -j2
    echo "README run: $((SECONDS - t0)) s wall" | tee "$out/wall.txt"
    cp results/nucleon/*.json "$out/" 2>/dev/null
    cp -r results/nucleon/benchmarks results/nucleon/logs "$out/" 2>/dev/null
    step stage_costs diffshadow stage-costs --out "$out/stage_costs.tsv" --benchmarks results/nucleon/benchmarks/*.tsv
    cat "$out/stage_costs.tsv" 2>/dev/null
    ;;
tests)
    # -v names each test as it ends, and SIGINT before the part's cap makes pytest print its summary (failures
    # with short tracebacks, slowest tests): a suite cut short still says what failed and where the time went
    # The suite takes ~14 min in one process (the workflow and PBS-profile tests alone ~11), more than a device
    # call: with pytest-xdist it runs in 4 processes, a test file to each (module fixtures run once; the suite
    # passes that way, `pytest -n 2 --dist loadfile` here), else serially
    cap=${PART_CAP:-3600}
    xdist=(); python -c "import xdist" 2>/dev/null && xdist=(-n 4 --dist loadfile)
    step pytest timeout -s INT -k 10 $((cap - 15)) pytest -v -rfEs --tb=short --durations=25 "${xdist[@]}"
    ;;
*)
    echo "unknown part $part (all, workflow, render, plans, sweep, checks or tests)" >&2; exit 2
    ;;
esac
pack
exit $failed
