"""The INR volume renderer (paper appendix, docs/design.md §3), by concept:

- `camera`: pinhole cameras, orbit and Fibonacci views;
- `cells`: 16³ macro-cells and the runs of occupied samples they leave on each ray;
- `fields`: the scalar field and the shadow source as the marcher samples them;
- `marcher`: the wavefront marcher, shading, compositing, the naive secondary-ray baseline;
- `scene`: `RenderScene` (modes `noshadow`, `gt`, `inr`, `naive`) and `Networks`, the one choice of how the
  networks are evaluated;
- `bundle`: light-independent ray bundles and target images for the rendering loss.
"""

from diffshadow.grid import Interrupted
from diffshadow.render.camera import Camera, RenderError, default_views, fibonacci_views
from diffshadow.render.cells import RENDER_CELL, MacroGrid, Runs
from diffshadow.render.fields import GridScalar, GridShadow, InrScalar, SirenShadow
from diffshadow.render.marcher import (
    BACKGROUND,
    DEFAULT_STEP,
    MIN_TRANSMITTANCE,
    Counters,
    Image,
    MarchedShadow,
    MarchPlan,
    Shading,
    front_to_back,
    render,
    render_all_at_once,
)
from diffshadow.render.scene import KERNELS, MODES, Networks, RenderScene, write_png

__all__ = ["BACKGROUND", "DEFAULT_STEP", "KERNELS", "MIN_TRANSMITTANCE", "MODES", "RENDER_CELL", "Camera", "Counters",
           "GridScalar", "GridShadow", "Image", "InrScalar", "Interrupted", "MacroGrid", "MarchPlan", "MarchedShadow",
           "Networks", "RenderError", "RenderScene", "Runs", "Shading", "SirenShadow", "default_views",
           "fibonacci_views", "front_to_back", "render", "render_all_at_once", "write_png"]
