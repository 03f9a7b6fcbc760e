"""diffshadow: diffusion-based shadow caching for neural volume rendering."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("diffshadow")
except PackageNotFoundError:  # run from a checkout without installing
    __version__ = "0+unknown"
