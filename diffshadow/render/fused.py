"""Fused SIRENs for inference: Triton kernels that evaluate SIRENs per tile of points, activations kept on chip,
so a layer costs its matrix product and its sines and no trip through GPU memory.

- `FusedSiren`: one SIREN, (N, 3) → (N,).
- `FusedSamples.march`: whole primary rays in one kernel: per sample the data INR's value, the shadow INR's
  coefficient, the transfer function (one search of `TransferFunction.optics`' knots), the sample's opacity and
  shaded colour, composited front to back in registers.
- `FusedExtinction.march`: whole secondary rays (the naive baseline) likewise: optical depth through the data INR.

The eager SIREN (`siren.forward_folded`) and the renderer's eager sample step are the reference: the kernels apply
the same pre-scaled weights (`siren.fold`) in the same order, the hidden layers as TF32 `tl.dot` (tensor cores,
10-bit mantissa inputs, fp32 sums), the first layer as three TF32 products of split operands, close to fp32
(`_kernels.first_layer`), the sines on the special-function unit after an exact reduction (`_kernels.sine`). Tests
run the kernels on the CPU through Triton's interpreter (`TRITON_INTERPRET=1`) when Triton is installed.

The CUDA default (`render.kernel: auto`): on an H200 these were the fastest of the variants measured side by side,
and their images are within 78 dB of the eager fp32 ones (docs/performance.md). A kernel compiles on its first
launch; if that fails (`FusedKernelError`: an older Triton, a GPU it cannot target), `RenderScene` warns and
renders with the eager SIREN from then on.
"""

from __future__ import annotations

import functools
import importlib.util
import os
from typing import TYPE_CHECKING

import torch
from torch.profiler import record_function

from diffshadow.phases import phase
from diffshadow.siren import RES_WEIGHT, fold

if TYPE_CHECKING:
    from diffshadow.render.cells import Runs

WARPS = 4  # Triton's default
# Multiply-adds contract to FMAs (Triton's default up to 3.9; 3.10 turns it off unless asked). The kernels are
# written for it (the sine's reduction, the transfer function's interpolation): asked for explicitly, on every
# launch and every ahead-of-time compile, so a Triton upgrade does not change the machine code underneath.
FP_FUSION = True


def block_points(width: int) -> int:
    """Points per program: tiles of 64 x 64 activations (a 64-point tile at width 64), to keep them on chip."""
    return max(16, min(128, 4096 // width))


FUSED = "fused"  # the scene's setting for these kernels (`render.Networks`)
LAUNCH = "diffshadow::fused"  # the profiler range around each launch: bench.profile counts it as one op


class FusedSirenError(RuntimeError):
    pass


class FusedKernelError(FusedSirenError):
    """A fused kernel failed on its first launch, which is when Triton compiles it: a Triton older than the
    kernels were written for (3.6-3.9), a GPU it cannot target, too few registers or too little shared
    memory. The renderer then goes on with the eager SIREN (`FusedKernelWarning`)."""


class FusedKernelWarning(UserWarning):
    """The renderer fell back to the eager SIREN after a `FusedKernelError` (the tests make it an error)."""


def available(device: torch.device) -> bool:
    """Whether the kernels run on `device`: on CUDA with Triton, or in Triton's interpreter on the CPU."""
    if importlib.util.find_spec("triton") is None:  # Triton ships with CUDA builds of PyTorch, not CPU ones
        return False
    return device.type == "cuda" or (device.type == "cpu" and os.environ.get("TRITON_INTERPRET") == "1")


@functools.cache
def _kernels():
    """The kernels (`_kernels.py`), imported on first use: importing Triton costs every process that renders a
    second."""
    from diffshadow.render import _kernels as k

    return k


_LAUNCHED: set[tuple] = set()  # kernels that launched once, with their constants: compiled
_WARMED: set[tuple] = set()  # kernels compiled (or taken from the kernel cache) ahead of their first launch

# the kernels' arguments that are int32 pointers and float scalars (the others: float32 pointers, int scalars)
INT_POINTERS = frozenset({"order_ptr", "cum_ptr", "off_ptr", "total_ptr", "count_ptr", "trips_ptr"})
FLOAT_SCALARS = frozenset({"density", "dt", "stop"})


def placeholder(arg: str) -> torch.dtype | float | int:
    """What a kernel's runtime argument `arg` is, as Triton's `warmup` takes it: a pointer's dtype, or a scalar of its
    type (J and n are not specialised on their values)."""
    if arg.endswith("_ptr"):
        return torch.int32 if arg in INT_POINTERS else torch.float32
    return 1.0 if arg in FLOAT_SCALARS else 2


def variant(name: str, block: int, warps: int, registers: int | None, constants: dict) -> tuple:
    """What makes Triton compile kernel `name` anew: its launch options and compile-time constants."""
    return (name, block, warps, registers, tuple(sorted(constants.items())))


def _launch(name: str, n: int, block: int, warps: int, *args, registers: int | None = None, **constants) -> None:
    """Kernel `name` over n points in tiles of `block`, `warps` warps each (its arguments, then n, then its
    constants), at most `registers` per thread (None: what the compiler takes), inside the profiler range that
    bench counts as one op. A failure on a kernel's first launch, which compiles it, is a `FusedKernelError`;
    later failures are the launch's own and pass unchanged."""
    import triton

    def launch():
        getattr(_kernels(), name)[(triton.cdiv(n, block),)](*args, n, num_warps=warps, enable_fp_fusion=FP_FUSION,
                                                             maxnreg=registers, **constants)

    # a kernel warmed ahead (`warm`) still has its first launch here: a compile that failed there, quietly, fails
    # again here and is reported, and the scene goes on eagerly
    key = variant(name, block, warps, registers, constants)
    with record_function(LAUNCH):
        if key in _LAUNCHED:
            return launch()
        try:
            with phase("compile"):  # the first launch compiles (or loads the run's kernel cache): the job's phases
                launch()
        except Exception as e:  # Triton's compile errors come in many types, and differ between versions
            first = str(e).strip().splitlines()[0] if str(e).strip() else ""
            raise FusedKernelError(f"{name} failed on its first launch, compiling (Triton "
                                   f"{getattr(triton, '__version__', '?')}): {type(e).__name__}: {first}") from e
        _LAUNCHED.add(key)


def warm(variants: list[tuple], device: torch.device) -> int:
    """Compile the kernel `variants` (`variant`) that this process has not launched, ahead of their first launch
    and all at once, on threads (Triton's compiler releases the GIL: four kernels for sm_90 took 3.5-3.7 s on two
    CPU cores against 6.0-6.7 s one after another), or load them from the run's kernel cache, where a job before
    compiled them (`render.warm_kernels`). Only on CUDA. A variant that fails here is left to its first launch,
    which says why (`FusedKernelError`). Returns how many were asked for."""
    todo = [v for v in dict.fromkeys(variants) if v not in _LAUNCHED and v not in _WARMED]
    if device.type != "cuda" or not todo:
        return 0
    from concurrent.futures import ThreadPoolExecutor

    try:
        from triton.runtime._async_compile import AsyncCompileMode  # Triton 3.5 and later
    except ImportError:
        AsyncCompileMode = None  # older: one after another, still ahead of the first frame
    with phase("compile"), torch.cuda.device(device):
        if AsyncCompileMode is None:
            done = [v for v in todo if _warmup(v)]
        else:
            with ThreadPoolExecutor(len(todo)) as pool, AsyncCompileMode(pool, ignore_errors=True):
                done = [v for v in todo if _warmup(v)]
    _WARMED.update(done)
    return len(todo)


def _warmup(v: tuple) -> bool:
    """Triton's `warmup` of one variant: its arguments as the launches pass them (tensors by dtype, scalars by
    type); False where it could not be asked for."""
    name, _, warps, registers, constants = v
    kernel = getattr(_kernels(), name)
    named = dict(constants)
    try:
        kernel.warmup(*(placeholder(p.name) for p in kernel.params if p.name not in named), grid=(1,),
                      num_warps=warps, enable_fp_fusion=FP_FUSION, maxnreg=registers, **named)
    except Exception:  # noqa: BLE001 - Triton's errors come in many types; the first launch reports them
        return False
    return True


class FusedSiren:
    """One SIREN (`named` tensors as `Siren.named_tensors()` or `WeightLayout.unflatten` give them, for one
    SIREN) as a callable (N, 3) → (N,), the same as `siren.forward_folded` up to the inputs' TF32 rounding and
    float32 summation order."""

    def __init__(self, named: dict[str, torch.Tensor], blocks: int):
        if importlib.util.find_spec("triton") is None:
            raise FusedSirenError("the fused SIREN needs Triton (it ships with CUDA builds of PyTorch)")
        first = named["first.weight"].detach().float()
        width = first.shape[0]
        if width < 16 or width & (width - 1) or first.shape[1] != 3:
            raise FusedSirenError(f"the fused SIREN needs a power-of-two width >= 16 and 3 inputs, got weights "
                                  f"{tuple(first.shape)}")
        with torch.no_grad():
            layers = [(w.detach().float(), b.detach().float()) for w, b in fold(named, blocks)]
            (w0, b0), hidden, (wl, bl) = layers[0], layers[1:-1], layers[-1]
            self.w0, self.b0 = w0.t().contiguous(), b0.contiguous()
            device = first.device
            self.wh = (torch.stack([w.t() for w, _ in hidden]) if hidden
                       else torch.zeros(1, width, width, device=device)).contiguous()
            self.bh = (torch.stack([b for _, b in hidden]) if hidden
                       else torch.zeros(1, width, device=device)).contiguous()
            self.wl, self.bl = wl.reshape(-1).contiguous(), bl.reshape(1).contiguous()
        self.width, self.blocks = width, blocks
        # points and warps per program, and a cap on registers per thread: attributes, so a script can try others
        # on a GPU. The whole-ray kernel takes 220-250 registers, 2 programs of 4 warps per SM;
        # capped at 168, 3 fit, for 31-39 spilled loads and stores (sm_90, `scripts/kernel_tiles.py --registers`)
        self.block, self.warps, self.registers = block_points(width), WARPS, None

    @property
    def tensors(self) -> tuple[torch.Tensor, ...]:
        return self.w0, self.b0, self.wh, self.bh, self.wl, self.bl

    def constants(self) -> dict:
        """siren_kernel's compile-time constants for this SIREN."""
        return {"W": self.width, "BLOCKS": self.blocks, "BLOCK": self.block, "RES": RES_WEIGHT}

    def variant(self) -> tuple:
        return variant("siren_kernel", self.block, self.warps, self.registers, self.constants())

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        x = x.float().contiguous()
        out = torch.empty(len(x), dtype=torch.float32, device=x.device)
        if len(x):
            _launch("siren_kernel", len(x), self.block, self.warps, x, *self.tensors, out,
                    registers=self.registers, **self.constants())
        return out


def _optics_inputs(extent: torch.Tensor, knots: tuple[torch.Tensor, torch.Tensor]) -> tuple[torch.Tensor, ...]:
    """The box extent and the optics table as the kernels read them: contiguous float32."""
    return tuple(t.float().contiguous() for t in (extent, *knots))


class FusedSamples:
    """Primary samples' opacity and colour, from data INR `scalar`, shadow INR `shadow` (None: no shadow), the
    transfer function's `knots` ((M,), (M, 4) of opacity and RGB, `TransferFunction.optics`' table) and
    `density_scale`, step `dt` in box units: the same arithmetic as the renderer's eager step (unlit shading:
    colour × (0.1 + 0.9·g), clamped to [0, 1])."""

    def __init__(self, scalar: FusedSiren, shadow: FusedSiren | None, extent: torch.Tensor,
                 knots: tuple[torch.Tensor, torch.Tensor], density_scale: float, dt: float):
        self.scalar, self.shadow = scalar, shadow
        self.extent, self.xs, self.ys = _optics_inputs(extent, knots)
        self.density, self.dt = float(density_scale), float(dt)
        # the wider network sets the tile, so both fit on chip
        self.block = min(scalar.block, shadow.block) if shadow is not None else scalar.block
        self.warps, self.registers = scalar.warps, scalar.registers

    def march(self, o: torch.Tensor, d: torch.Tensor, t0: torch.Tensor, t1: torch.Tensor, runs: Runs,
              min_transmittance: float) -> tuple[torch.Tensor, ...]:
        """Whole primary rays o + t d, t in [t0, t1), through their occupied samples `runs` (`render.Runs`), in
        one kernel: each ray's transmittance (R,) and composited colour (R, 3), the samples it took (R,) and the
        trips of each program of `block` rays. A ray stops once its transmittance is below `min_transmittance`."""
        return _march(self, o, d, t0, t1, runs, min_transmittance, absorb=False, dt=self.dt, shadow=self.shadow)

    def variant(self) -> tuple:
        constants = _march_constants(self, self.shadow, False)
        return variant("march_kernel", self.block, self.warps, self.registers, constants)


def _march(kernel, o, d, t0, t1, runs: Runs, stop: float, *, absorb: bool, dt: float, shadow: FusedSiren | None):
    """Launch `march_kernel` for `kernel` (FusedSamples or FusedExtinction) with shadow SIREN `shadow` over rays
    (R,): (acc, rgb or None, count, trips)."""
    import triton

    o, d, t0, t1 = (x.float().contiguous() for x in (o, d, t0, t1))
    cum, offset, total = (x.to(torch.int32).contiguous() for x in (runs.cum, runs.offset, runs.total))
    # a program runs until its last ray stops, so it takes rays of about as many samples: most first. On
    # hydrogen_atom (no ray stops early there) lanes then do 99.9% useful samples at 1024², against 75% in image
    # order (rows of pixels) and 92% in 8x8 pixel tiles
    order = torch.argsort(total, descending=True, stable=True).to(torch.int32)
    n, device = len(o), o.device
    acc = torch.empty(n, dtype=torch.float32, device=device)
    rgb = torch.empty(n if not absorb else 0, 3, dtype=torch.float32, device=device)
    count = torch.empty(n, dtype=torch.int32, device=device)
    trips = torch.empty(triton.cdiv(n, kernel.block), dtype=torch.int32, device=device)
    if n:
        _launch("march_kernel", n, kernel.block, kernel.warps, order, o, d, t0, t1, cum, offset, total,
                kernel.extent, *kernel.scalar.tensors, *(shadow or kernel.scalar).tensors, kernel.xs, kernel.ys,
                kernel.density, float(dt), float(stop), acc, rgb, count, trips, cum.shape[1],
                registers=kernel.registers, **_march_constants(kernel, shadow, absorb))
    return acc, (None if absorb else rgb), count, trips


def _march_constants(kernel, shadow: FusedSiren | None, absorb: bool) -> dict:
    """march_kernel's compile-time constants for `kernel` (FusedSamples or FusedExtinction) with shadow SIREN
    `shadow`; without one the data INR's weights stand in (SHADOW=False: never read)."""
    scalar, net = kernel.scalar, shadow or kernel.scalar
    return {"W": scalar.width, "BLOCKS": scalar.blocks, "ABSORB": absorb, "KNOTS": len(kernel.xs),
            "BLOCK": kernel.block, "RES": RES_WEIGHT, "SW": net.width, "SBLOCKS": net.blocks,
            "SHADOW": shadow is not None}


class FusedExtinction:
    """The naive baseline's secondary rays: extinction μ = density_scale · opacity of the data INR `scalar`, from
    `TransferFunction.optics`' table (`knots`), the same arithmetic as `TransferFunction.extinction` up to float32
    rounding, summed along each ray."""

    def __init__(self, scalar: FusedSiren, extent: torch.Tensor, knots: tuple[torch.Tensor, torch.Tensor],
                 density_scale: float):
        self.scalar = scalar
        self.extent, self.xs, self.ys = _optics_inputs(extent, knots)
        self.density = float(density_scale)
        self.block, self.warps, self.registers = scalar.block, scalar.warps, scalar.registers

    def march(self, o: torch.Tensor, d: torch.Tensor, t0: torch.Tensor, t1: torch.Tensor, runs: Runs, dt: float,
              tau_max: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Whole secondary rays through their occupied samples `runs` in one kernel, step `dt`: each ray's
        optical depth (R,), stopped once it reaches `tau_max`, the samples it took (R,) and the programs' trips."""
        tau, _, count, trips = _march(self, o, d, t0, t1, runs, tau_max, absorb=True, dt=dt, shadow=None)
        return tau, count, trips

    def variant(self) -> tuple:
        return variant("march_kernel", self.block, self.warps, self.registers, _march_constants(self, None, True))
