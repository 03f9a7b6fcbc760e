"""A renderable scene: one volume, its TF and data INR on one device, the per-mode pieces cached, and the one
choice of how its networks are evaluated (`Networks`: config `render.kernel`)."""

from __future__ import annotations

import hashlib
import warnings
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from numpy.typing import ArrayLike

from diffshadow.config import defaults
from diffshadow.data_inr import DataInr, inr_cell_ranges
from diffshadow.io import atomic_save
from diffshadow.layout import WeightLayout
from diffshadow.lights import as_direction
from diffshadow.render.camera import Camera, RenderError, visible_sphere
from diffshadow.render.cells import RENDER_CELL, MacroGrid
from diffshadow.render.fields import GridScalar, GridShadow, InrScalar, SirenShadow
from diffshadow.render.fused import (
    FUSED,
    FusedExtinction,
    FusedKernelError,
    FusedKernelWarning,
    FusedSamples,
    FusedSiren,
    warm,
)
from diffshadow.render.fused import available as fused_available
from diffshadow.render.marcher import (
    BACKGROUND,
    DEFAULT_STEP,
    MIN_TRANSMITTANCE,
    Image,
    MarchedShadow,
    Samples,
    Scalar,
    Shading,
    render,
)
from diffshadow.shadow import seen_voxels, shadow_grid
from diffshadow.transfer import TransferFunction
from diffshadow.volume import Volume, extinction_id, refine

# a shadow SIREN as the renderer takes it: its flat weights (n_params,), their layout and its block count
ShadowSirenSpec = tuple[ArrayLike, WeightLayout, int]

MODES = ("noshadow", "gt", "inr", "naive")
# torch.compile of the eager SIRENs was a third: it tied with eager on 2 CPU cores once eager went in passes, and was
# 4 % slower on an H200, for ~7 s of compiling per process (docs/performance.md, the renderer's section)
KERNELS = ("auto", "eager", FUSED)
# The samples a scene keeps to draw a view again under another light (`RenderScene(keep_samples=)`): ~26 bytes a
# sample, so a 256² frame of nucleon (3.5M samples) takes 85 MiB and a 480² one about 300 MiB
KEEP_SAMPLES_BYTES = 512 << 20


@dataclass(frozen=True)
class Networks:
    """How the renderer evaluates its SIRENs: the one place that chooses (config `render.kernel`; recorded in
    bench.json and image_metrics.json).

    `kernel`: "eager" (folded PyTorch SIRENs: every device, the reference), "fused" (Triton kernels: whole rays
    per kernel, TF32 matrix products, the special-function unit's sine; CUDA, or Triton's interpreter on a CPU;
    elsewhere the scene renders eagerly and records so), or "auto": "fused" on CUDA where Triton is installed, else
    "eager" (the interpreter is for tests, not speed).
    On an H200 "fused" gave 3.4-3.9x the eager fps at 512²-1024², images within 78 dB of the eager fp32 ones
    (d19920d; docs/performance.md, "The renderer", has the fused kernels' figures since).
    """

    kernel: str = field(default_factory=lambda: defaults()["render"]["kernel"])  # one home: defaults.yaml
    # the fused kernels a scene can launch compiled at its first frame, all at once on threads, instead of each at
    # its own first launch (`RenderScene.kernel_variants`); the same kernels, so the same images
    warm: bool = field(default_factory=lambda: defaults()["render"]["warm_kernels"])

    def __post_init__(self):
        if self.kernel not in KERNELS:
            raise RenderError(f"render.kernel: expected one of {', '.join(KERNELS)}, got {self.kernel!r}")
        if not isinstance(self.warm, bool):
            raise RenderError(f"render.warm_kernels: expected true or false, got {self.warm!r}")

    @classmethod
    def from_config(cls, render_cfg: dict) -> Networks:
        """From a config's `render` section (a key it lacks: the package default)."""
        return cls(**{name: render_cfg[key] for name, key in (("kernel", "kernel"), ("warm", "warm_kernels"))
                      if key in render_cfg})

    def setting(self, device: torch.device) -> str | None:
        """What the fields take on `device`: None (eager) or "fused"."""
        if self.kernel == "auto":
            return FUSED if device.type == "cuda" and fused_available(device) else None
        return None if self.kernel == "eager" else self.kernel


class RenderScene:
    """One volume, its TF and (optionally) its data INR on one device, with the per-mode pieces cached.

    Modes: `noshadow`; `gt` (scalar and shadow from the raw volume; shadow by `shadow_grid`, on the volume
    refined `gt_upsample` times); `inr`
    (shadow INR co-rendered with the scalar field: ours); `naive` (secondary rays through the scalar
    field). `scalar="inr"` renders the data INR, `"grid"` the raw volume (to isolate the shadow's error).
    Not for frames from several threads at once: the viewer draws on one (`viewer.app.TorchThread`).
    """

    def __init__(self, volume: Volume, tf: TransferFunction, data_inr: DataInr | None = None, *,
                 device: torch.device | str = "cpu", gt_method: str = "march", gt_upsample: int = 1,
                 cell: int = RENDER_CELL, networks: Networks | None = None, keep_samples: int = 0):
        self.volume, self.tf, self.data_inr = volume, tf, data_inr
        self.device = torch.device(device)
        self.networks = networks or Networks()
        # the kernel the SIRENs' values take where it runs on this device, else None: eager (`networks_used`
        # records which)
        setting = self.networks.setting(self.device)
        self.kernel_used = setting if setting and fused_available(self.device) else None
        self.gt_method, self.gt_upsample, self.cell = gt_method, gt_upsample, cell
        self.voxel = float(np.min(volume.voxel_size))
        self._cache: dict = {}
        self._last_shadow: tuple | None = None  # (key, SirenShadow) of the last `inr` frame
        # (kernel, shadow layout and blocks) whose kernels `render.warm_kernels` compiled: once each, not every frame
        self._warmed: set[tuple] = set()
        # a view drawn again under another light takes its kept samples: up to this many bytes, the last views first
        self.keep_samples = keep_samples
        self._samples: OrderedDict[tuple, Samples] = OrderedDict()

    @property
    def extinction(self) -> str:
        """The extinction field this scene's shadows come from (`volume.extinction_id`), which a cache must match."""
        return extinction_id(self.volume, self.tf)

    def networks_used(self) -> dict:
        """The choice as configured and what this scene renders with now (after any fallback), for the
        metrics files and the report."""
        return {"kernel": self.networks.kernel, "used": self.kernel_used or "eager"}

    def _cached(self, key, make):
        if key not in self._cache:
            self._cache[key] = make()
        return self._cache[key]

    def _siren_shadow(self, weights, layout: WeightLayout, blocks: int) -> SirenShadow:
        """The shadow INR of `weights`: the last frame's again where its weights, layout, blocks and kernel are the
        same (as while the viewer orbits one light; a kernel that failed to compile leaves the scene eager). Built
        anew it copied the weights from the host and laid them out for the kernel at every frame."""
        w = np.ascontiguousarray(weights, dtype=np.float32)
        key = (hashlib.blake2b(w.tobytes(), digest_size=16).digest(), layout, blocks, self.kernel_used)
        last = self._last_shadow
        if last is None or last[0] != key:
            last = (key, SirenShadow(w, layout, blocks, self.volume.extent, self.device, self.kernel_used))
            self._last_shadow = last
        return last[1]

    def visible_sphere(self) -> tuple[np.ndarray, float]:
        """The sphere around what the TF shows (`camera.visible_sphere`): what the default views frame."""
        return self._cached("visible_sphere", lambda: visible_sphere(self.volume, self.tf))

    def framed(self, *, azimuth: float = 30.0, elevation: float = 25.0, fov: float = 60.0,
               size: int | tuple[int, int] = 128) -> Camera:
        """The default view of this scene: `Camera.framed` on its visible part."""
        return Camera.framed(self.visible_sphere(), azimuth=azimuth, elevation=elevation, fov=fov, size=size)

    def scalar(self, source: str) -> Scalar:
        if source == "grid":
            return self._cached("grid", lambda: GridScalar(self.volume, self.device))
        if source == "inr":
            if self.data_inr is None:
                raise RenderError("scalar 'inr' needs a data INR (train_data_inr's data_inr.pt)")
            return self._cached(("inr", self.kernel_used), lambda: InrScalar(
                self.data_inr.model, self.volume.extent, self.device, self.kernel_used))
        raise RenderError(f"scalar: expected 'grid' or 'inr', got {source!r}")

    def macro(self, source: str, skip: bool) -> MacroGrid | None:
        if not skip:
            return None
        ranges = None
        if source == "inr":
            ranges = (self.data_inr.cell_lo, self.data_inr.cell_hi)
            if ranges[0] is None or self.cell != RENDER_CELL:
                ranges = self._cached(("ranges", self.cell), lambda: inr_cell_ranges(
                    self.data_inr.model, self.volume, cell=self.cell, device=self.device))
        return self._cached(("macro", source), lambda: MacroGrid.build(self.volume, self.tf, cell=self.cell,
                                                                     ranges=ranges, device=self.device))

    @staticmethod
    def _gt_key(light, method: str) -> tuple:
        return ("gt", method, tuple(np.round(as_direction(light), 12).tolist()))

    def has_gt(self, light: ArrayLike, method: str | None = None) -> bool:
        """Whether the exact shadow of `light` by `method` (None: the scene's `gt_method`) is cached (else the
        next `gt` frame computes it)."""
        return self._gt_key(light, method or self.gt_method) in self._cache

    def forget_gt(self, light: ArrayLike) -> None:
        """Drop the cached shadow grids of `light`, by either method (a loop over many lights need not keep
        them all)."""
        for method in ("march", "sweep"):
            self._cache.pop(self._gt_key(light, method), None)

    def gt_shadow(self, light: ArrayLike, *, method: str | None = None,
                  interrupt: Callable[[], bool] | None = None) -> GridShadow:
        """The exact shadow grid of `light` (cached), by `method` (None: the scene's `gt_method`). `interrupt`:
        asked between the march's iterations (`Interrupted`; nothing is cached); the sweep is not asked (under a
        second on 128³ voxels, 2 CPU cores: docs/performance.md)."""
        method = method or self.gt_method
        key = self._gt_key(light, method)
        if key in self._cache:
            return self._cache[key]
        fine = self._cached("gt_volume", lambda: refine(self.volume, self.gt_upsample))
        options = {}
        if method == "march":  # only the voxels a frame reads: 11x faster on hydrogen_atom (docs/performance.md)
            options = {"interrupt": interrupt, "voxels": self._cached("gt_seen", lambda: seen_voxels(
                self.volume, self.tf, self.gt_upsample, self.device))}
        grid = shadow_grid(fine, self.tf, key[2], method=method, device=self.device, **options)
        self._cache[key] = GridShadow(grid, self.volume.extent, self.device)
        return self._cache[key]

    def render(self, mode: str, camera: Camera, *, light: ArrayLike | None = None,
               siren: ShadowSirenSpec | None = None, scalar: str | None = None,
               phong: bool = False, step: float = DEFAULT_STEP, skip: bool = True, batch: int | None = None,
               samples_per_iter: int | None = None, min_transmittance: float = MIN_TRANSMITTANCE,
               background: float = BACKGROUND, interrupt: Callable[[], bool] | None = None,
               gt_method: str | None = None) -> Image:
        """`siren`: (weights, layout, blocks) of the shadow INR, for mode `inr`. A fused kernel that fails to
        compile leaves this scene on the eager SIREN, with a warning: the setting is a speed-up, not a result.
        `interrupt`: `render`'s (the frame given up with `Interrupted` once it returns True), also asked while mode
        `gt` marches its shadow grid. `gt_method`: mode `gt`'s grid by this method, not the scene's."""
        kw = {"light": light, "siren": siren, "scalar": scalar, "phong": phong, "step": step, "skip": skip,
              "batch": batch, "samples_per_iter": samples_per_iter, "min_transmittance": min_transmittance,
              "background": background, "interrupt": interrupt, "gt_method": gt_method}
        try:
            warmed = (self.kernel_used, None if siren is None else tuple(siren[1:]))
            if self.networks.warm and self.device.type == "cuda" and warmed not in self._warmed:
                warm(self.kernel_variants(siren), self.device)
                self._warmed.add(warmed)
            return self._render(mode, camera, **kw)
        except FusedKernelError as e:
            warnings.warn(f"render.kernel={self.networks.kernel} ({self.kernel_used}): {e}; rendering with the eager "
                          "SIREN from now on", FusedKernelWarning, stacklevel=2)
            self.kernel_used = None
            return self._render(mode, camera, **kw)

    def _render(self, mode: str, camera: Camera, *, light, siren, scalar, phong, step, skip, batch,
                samples_per_iter, min_transmittance, background, interrupt, gt_method) -> Image:
        if mode not in MODES:
            raise RenderError(f"mode: expected one of {MODES}, got {mode!r}")
        if scalar is None:
            scalar = "grid" if mode == "gt" or self.data_inr is None else "inr"
        if mode == "gt":
            scalar = "grid"
        field_ = self.scalar(scalar)
        macro = self.macro(scalar, skip)
        shadow = None
        if mode != "noshadow" and light is None:
            raise RenderError(f"mode {mode!r}: needs a light direction")
        if mode == "gt":
            shadow = self.gt_shadow(light, method=gt_method, interrupt=interrupt)
        elif mode == "inr":
            if siren is None:
                raise RenderError("mode 'inr': needs the shadow INR's weights")
            shadow = self._siren_shadow(*siren)
        elif mode == "naive":
            shadow = MarchedShadow(field_, self.tf, self.volume.extent, self.voxel, step=step, macro=macro,
                                   samples_per_iter=samples_per_iter, batch=batch, device=self.device)
        # what the samples of a view depend on (a light changes only the shadow at them; unlit shading)
        key = None if phong or self.keep_samples <= 0 else (
            camera, scalar, self.kernel_used, step, skip, batch, samples_per_iter, min_transmittance)
        kept = self._samples.get(key) if key is not None else None
        if kept is not None:
            self._samples.move_to_end(key)
        elif key is not None:
            self._make_room(camera.width * camera.height)
        with torch.no_grad():
            img = render(camera, field_, self.tf, self.volume.extent, self.voxel, light=light, shadow=shadow,
                         shading=Shading(phong=phong, background=background), step=step, macro=macro,
                         min_transmittance=min_transmittance, samples_per_iter=samples_per_iter, batch=batch,
                         device=self.device, interrupt=interrupt, keep=self.keep_samples if key else 0,
                         samples=kept)
        if img.samples is not None:
            self._keep(key, img.samples)
            img.samples = None  # the scene holds them, within its budget; an image a caller keeps does not
        return img

    def kernel_variants(self, siren: ShadowSirenSpec | None = None) -> list[tuple]:
        """The fused kernels (`fused.variant`) this scene's frames launch with its data INR, and with the shadow INR
        `siren` ((weights, layout, blocks); None: none): the SIRENs alone and the whole-ray marches of `noshadow`,
        `naive`'s secondary rays and `inr`. None where the scene renders eagerly."""
        if not self.kernel_used or self.data_inr is None:
            return []
        scalar = self.scalar("inr")
        if not isinstance(scalar.fast, FusedSiren):
            return []
        knots = self.tf.optics_knots(self.device)
        nets = [scalar.fast.variant(), FusedExtinction(scalar.fast, scalar.extent, knots, 1.0).variant(),
                FusedSamples(scalar.fast, None, scalar.extent, knots, 1.0, 1.0).variant()]
        shadow = self._siren_shadow(*siren).fast if siren is not None else None
        if isinstance(shadow, FusedSiren):
            nets += [shadow.variant(), FusedSamples(scalar.fast, shadow, scalar.extent, knots, 1.0, 1.0).variant()]
        return nets

    def keep_views(self, nbytes: int) -> None:
        """Keep up to `nbytes` of views' samples from now on, the last views first (0: none, and drop those kept)."""
        self.keep_samples = nbytes
        self._evict(0.0)

    def _make_room(self, pixels: int) -> None:
        """Before a view is marched to be kept: room for its samples, estimated from the last kept view's bytes per
        pixel, so that the budget bounds what is held while it marches too, not twice the budget."""
        if self._samples:
            (camera, *_), last = next(reversed(self._samples.items()))
            self._evict(last.nbytes / (camera.width * camera.height) * pixels)

    def _keep(self, key: tuple, samples: Samples) -> None:
        self._samples[key] = samples
        self._evict(0.0)

    def _evict(self, room: float) -> None:
        """The oldest kept views go until `room` more bytes fit beside the rest within the budget."""
        total = sum(s.nbytes for s in self._samples.values())
        while self._samples and total + room > self.keep_samples:
            total -= self._samples.popitem(last=False)[1].nbytes


def write_png(path: str | Path, image: Image) -> None:
    """An 8-bit RGB PNG, written atomically."""
    from PIL import Image as PILImage  # only where a PNG is written

    atomic_save(path, lambda tmp: PILImage.fromarray(image.to_uint8()).save(tmp, format="PNG"), suffix=".png")
