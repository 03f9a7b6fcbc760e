"""diffshadow: diffusion-based shadow caching for neural volume rendering."""

import os
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("diffshadow")
except PackageNotFoundError:  # run from a checkout without installing
    __version__ = "0+unknown"

# MKL (PyTorch's CPU BLAS on x86) splits a long matrix product's inner sum across threads, so by default
# its last bits depend on the thread count: sample-shadows rerun with other threads wrote other bytes.
# Strict conditional numerical reproducibility fixes the split and keeps the fastest code path
# (docs/numerics.md). MKL reads this at its first call, so it holds when diffshadow is imported before
# any matrix product; a user's own MKL_CBWR wins.
os.environ.setdefault("MKL_CBWR", "AUTO,STRICT")
