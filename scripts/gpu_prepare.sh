#!/usr/bin/env bash
# Here, once per session with a lent GPU, before the device call that runs scripts/gpu_session.sh:
#
#   bash scripts/gpu_prepare.sh
#
# It runs ../shared/gpu/prepare.sh (the shared wheels into .devwheels/), then adds the wheels of this package's
# runtime dependencies that neither the GPU machine's image nor that list has: without them `import diffshadow`
# fails there on the first rule. Rehearsed on a CPU in a virtual environment holding only the image's packages
# (docs/performance.md, "On a lent GPU", under "The default run").
set -euo pipefail
root=$(git rev-parse --show-toplevel)
cd "$root"
bash ../shared/gpu/prepare.sh
# runtime.set_threads (pure Python, so one wheel for every Python)
extra=(threadpoolctl==3.8.0)
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 -d .devwheels/whl "${extra[@]}"
echo "gpu_prepare.sh: added ${extra[*]}"
