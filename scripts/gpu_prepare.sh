#!/usr/bin/env bash
# Here, once per session with a lent GPU, before the device call that runs scripts/gpu_session.sh:
#
#   bash scripts/gpu_prepare.sh
#
# It runs the shared prepare step ($SHARED/gpu/prepare.sh; SHARED defaults to the folder beside the checkout,
# ../shared) that fills .devwheels/, then adds the wheels of this package's runtime dependencies that neither the
# GPU machine's image nor that list has, for the machine's Python ($GPU_PYTHON, default 3.12): without them
# `import diffshadow` fails there on the first rule. Rehearsed on a CPU in a virtual environment holding only the
# image's packages (docs/performance.md, "On a lent GPU", under "The default run").
set -euo pipefail
case ${1:-} in
    -h|--help) sed -n '2,/^set -euo/p' "$0" | sed '$d;s/^# \{0,1\}//'; exit 0 ;;
esac
root=$(cd "$(dirname "$0")/.." && pwd)
shared=${SHARED:-$root/../shared}
if [ ! -f "$shared/gpu/prepare.sh" ]; then
    echo "gpu_prepare.sh: $shared/gpu/prepare.sh not found (set SHARED to the folder that holds gpu/prepare.sh)" >&2
    exit 2
fi
cd "$root"
bash "$shared/gpu/prepare.sh"
# runtime.set_threads (pure Python, so one wheel for every Python)
extra=(threadpoolctl==3.8.0)
python3 -m pip download -q --no-deps --only-binary=:all: --python-version "${GPU_PYTHON:-3.12}" -d .devwheels/whl \
    "${extra[@]}"
echo "gpu_prepare.sh: added ${extra[*]}"
