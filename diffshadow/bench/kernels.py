"""What the fused kernels ask of a GPU, measured without one: each kernel compiled ahead of time for a CUDA
architecture by Triton's compiler and ptxas (both ship with Triton; no device or driver is needed), and ptxas'
resource use read back from the binary (cuobjdump): registers per thread, stack per thread (registers spilled to
local memory) and shared memory per program. From the registers follows how many programs an SM holds at once.
The machine code (SASS) is counted too: instructions in all, local-memory loads and stores, branches, and the
FP32 and special-function (MUFU) instructions, which is where the SIRENs' sines go (`_kernels.sine`).

These are counts, not timings: the same on any machine with the same Triton. A kernel that spills (a large
stack) or holds one program per SM is slow whatever the device.

The shapes are those of `bench render`'s hydrogen_atom: a data INR of width 64 and 2 blocks, a shadow SIREN of
width 32 and 2 blocks, 5 optics knots (the runs per ray are a launch argument, which no compile sees).
"""

from __future__ import annotations

import collections
import json
import os
import re
import subprocess
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path

import torch

from diffshadow.io import atomic_write_text
from diffshadow.render.fused import FP_FUSION, WARPS, block_points, placeholder
from diffshadow.siren import RES_WEIGHT

ARCHS = (80, 90)  # A100 (Polaris, Sophia); H100/H200
REGISTERS_PER_SM, MAX_WARPS_PER_SM = 65536, 64  # both architectures
DATA, SHADOW = (64, 2), (32, 2)  # (width, blocks)
KNOTS = 5
SINE_BLOCK = 128  # sine_kernel: one sine per thread at 4 warps


class KernelCompileError(RuntimeError):
    pass


def kernel_shapes() -> dict[str, tuple[str, dict]]:
    """name → (kernel, its compile-time constants) for the hydrogen_atom shapes."""
    (w, b), (sw, sb) = DATA, SHADOW
    both = min(block_points(w), block_points(sw))
    common = {"KNOTS": KNOTS, "RES": RES_WEIGHT}
    return {
        "siren (data INR)": ("siren_kernel", {"W": w, "BLOCKS": b, "BLOCK": block_points(w), "RES": RES_WEIGHT}),
        "march (inr, whole rays)": ("march_kernel", {"W": w, "BLOCKS": b, "SW": sw, "SBLOCKS": sb,
                                                     "SHADOW": True, "ABSORB": False, "BLOCK": both, **common}),
        "march (noshadow, whole rays)": ("march_kernel", {"W": w, "BLOCKS": b, "SW": w, "SBLOCKS": b,
                                                          "SHADOW": False, "ABSORB": False, "BLOCK": block_points(w),
                                                          **common}),
        "march (naive's secondary rays)": ("march_kernel", {"W": w, "BLOCKS": b, "SW": w, "SBLOCKS": b,
                                                            "SHADOW": False, "ABSORB": True,
                                                            "BLOCK": block_points(w), **common}),
    }


def _tools() -> Path:
    import triton

    return Path(triton.__file__).parent / "backends" / "nvidia" / "bin"


def _triton_type(value) -> str:
    """Triton's signature type of a runtime argument, from what the renderer's warm-up passes for it."""
    pointers = {torch.int32: "*i32", torch.float32: "*fp32"}
    return pointers[value] if isinstance(value, torch.dtype) else "fp32" if isinstance(value, float) else "i32"


def compile_kernel(name: str, constants: dict, arch: int, warps: int = WARPS, sass: bool = False,
                   fp_fusion: bool = FP_FUSION, registers: int | None = None) -> dict:
    """Compile `_kernels.<name>` for sm_<arch> with `constants`; its resources as ptxas assigned them.
    `fp_fusion`: multiply-adds as FMAs, as the renderer launches the kernels (False: what Triton 3.10's default
    would compile). `registers`: at most this many per thread (`FusedSiren.registers`; None: no cap)."""
    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    if os.environ.get("TRITON_INTERPRET") == "1":
        raise KernelCompileError("bench kernels compiles for a GPU: run it without TRITON_INTERPRET=1")
    from diffshadow.render import _kernels

    fn = getattr(_kernels, name)
    signature = {p.name: "constexpr" if p.name in constants else _triton_type(placeholder(p.name)) for p in fn.params}
    try:
        compiled = triton.compile(ASTSource(fn=fn, signature=signature, constexprs=dict(constants)),
                                  target=GPUTarget("cuda", arch, 32),
                                  options={"num_warps": warps, "enable_fp_fusion": fp_fusion, "maxnreg": registers})
    except Exception as e:  # Triton's and ptxas' errors come in many types; say which kernel and target
        raise KernelCompileError(f"{name} for sm_{arch}: {type(e).__name__}: {str(e).splitlines()[0]}") from e
    with tempfile.TemporaryDirectory() as tmp:
        cubin = Path(tmp) / "kernel.cubin"
        cubin.write_bytes(compiled.asm["cubin"])
        res, sass = (subprocess.run([str(_tools() / "cuobjdump"), flag, str(cubin)], capture_output=True, text=True,
                                    check=False) for flag in ("-res-usage", "-sass"))
    usage = dict(re.findall(r"(REG|STACK|SHARED|LOCAL):(\d+)", res.stdout))
    if "REG" not in usage:
        raise KernelCompileError(f"{name} for sm_{arch}: cuobjdump gave no resource usage ({res.stderr.strip()!r})")
    regs = int(usage["REG"])
    per_program = -(-regs // 8) * 8 * 32 * warps  # registers are allocated in units of 8 per thread
    return {"registers": regs, "stack_bytes": int(usage.get("STACK", 0)), "shared_bytes": int(usage.get("SHARED", 0)),
            "warps": warps, "programs_per_sm": min(REGISTERS_PER_SM // per_program, MAX_WARPS_PER_SM // warps),
            **sass_counts(sass.stdout), **({"sass": sass.stdout} if sass else {})}


# SASS lines: "/*0a70*/   @!P0 FFMA.FTZ R6, R7, ..., R0 ;" → address, predicate, opcode, modifiers and operands
_SASS = re.compile(r"^\s+/\*([0-9a-f]{4,})\*/\s+(@!?U?P[T0-9]\s+)?([A-Z][A-Z0-9_]*)(\S*)(.*)$", re.MULTILINE)
FP32 = {"FFMA", "FMUL", "FADD", "FMNMX", "FSEL", "FSETP", "FRND"}


def _sass_lines(sass: str) -> list[tuple[int, bool, str, str]]:
    """A kernel's instructions as (address, predicated, opcode without modifiers, operands)."""
    return [(int(a, 16), bool(pred), op, rest) for a, pred, op, _, rest in _SASS.findall(sass)]


def sass_counts(sass: str) -> dict:
    """Instructions in a kernel's machine code (static, so straight-line code counts what a trip executes;
    code behind a branch counts too): in all, FP32 pipe, special-function unit, local memory (spills and
    local arrays), branches."""
    ops = [op for _, _, op, _ in _sass_lines(sass) if op != "NOP"]
    return {"instructions": len(ops), "fp32": sum(op in FP32 for op in ops), "mufu": ops.count("MUFU"),
            "local": ops.count("LDL") + ops.count("STL"), "branches": ops.count("BRA")}


def sine_cost(arch: int, fp_fusion: bool = FP_FUSION) -> dict:
    """One sine's machine code: `_kernels.sine_kernel` (one sine per thread) less the same kernel copying its
    input. `executed`: instructions on the path from start to exit (the sine is branch-free, so all of them; a
    count can differ from the code's by an instruction of layout). `fp_fusion`: as `compile_kernel`."""
    def compiled(copy):
        return compile_kernel("sine_kernel", {"COPY": copy, "BLOCK": SINE_BLOCK}, arch, sass=True, fp_fusion=fp_fusion)

    base, r = compiled(True), compiled(False)
    counts = {k: r[k] - base[k] for k in ("instructions", "fp32", "mufu", "local", "branches")}
    return {**counts, "executed": _fast_path(r["sass"]) - _fast_path(base["sass"])}


def _fast_path(sass: str) -> int:
    """Instructions on the shortest path from a kernel's start to its (unpredicated) EXIT, a conditional branch
    taken or not as suits. The load's bounds check takes its short way in both kernels `sine_cost` subtracts, so
    the difference is the sine's."""
    lines = _sass_lines(sass)
    at = {a: i for i, (a, _, _, _) in enumerate(lines)}
    steps = {0: 1}
    queue = collections.deque([0])
    while queue:  # breadth first: every instruction costs one
        i = queue.popleft()
        _, predicated, op, rest = lines[i]
        if op == "EXIT" and not predicated:
            return steps[i]
        target = re.match(r"\s*(0x[0-9a-f]+)", rest)
        nexts = []
        if op == "BRA" and target:
            nexts.append(at[int(target.group(1), 16)])
        if not (op == "BRA" and not predicated) and i + 1 < len(lines):  # fall through unless the branch always goes
            nexts.append(i + 1)
        for k in nexts:
            if k not in steps:
                steps[k] = steps[i] + 1
                queue.append(k)
    raise KernelCompileError("no path to EXIT in the kernel's SASS")


def bench_kernels(out: Path, *, archs: Sequence[int] = ARCHS, log: Callable[[str], None] = print) -> dict:
    """Every fused kernel at the hydrogen_atom shapes, per architecture; printed and saved."""
    import triton

    rows = []
    for arch in archs:
        for label, (name, constants) in kernel_shapes().items():
            r = {"kernel": label, "arch": arch, "block": constants["BLOCK"], **compile_kernel(name, constants, arch)}
            rows.append(r)
            log(f"[bench kernels] sm_{arch} {label:32s} {r['block']:3d} points/program: {r['registers']:3d} "
                f"registers, {r['stack_bytes']:5d} B stack, {r['programs_per_sm']} programs/SM; SASS "
                f"{r['instructions']:6d} instructions, {r['fp32']:5d} FP32, {r['mufu']:4d} MUFU, {r['local']:5d} "
                f"local, {r['branches']:4d} branches")
        sine = sine_cost(arch)
        log(f"[bench kernels] sm_{arch} one sine: {sine['executed']:3d} instructions executed; in the code "
            f"{sine['instructions']:3d} instructions, {sine['fp32']:2d} FP32, {sine['mufu']} MUFU")
        rows.append({"kernel": "one sine", "arch": arch, **sine})
    # the counts depend on the compiler: say which, and how it was asked to compile
    result = {"triton": triton.__version__, "fp_fusion": FP_FUSION,
              "shapes": {"data": DATA, "shadow": SHADOW, "knots": KNOTS}, "kernels": rows}
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, json.dumps(result, indent=1))
    log(f"[bench kernels] wrote {out}")
    return result
