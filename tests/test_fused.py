"""The fused SIREN kernel against the eager SIREN (the reference), run on the CPU by Triton's interpreter:
widths and depths, ragged tails, empty input, the renderer's images, the setting and bad input."""

import importlib.util
import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from conftest import data_inr_stub

from diffshadow import fused
from diffshadow.analytic import gaussian_blob
from diffshadow.fused import FusedSiren, FusedSirenError
from diffshadow.render import Camera, Networks, RenderError, RenderScene
from diffshadow.siren import Siren, SirenConfig, WeightLayout, init_siren
from diffshadow.transfer import TransferFunction
from diffshadow.volume import Volume

# Triton reads TRITON_INTERPRET when it is first imported; conftest sets it on a machine without CUDA. With
# CUDA, tests/gpu/test_cuda.py runs the compiled kernel instead.
FP32 = Networks("fused", "fp32")  # the kernels in fp32: equal to the eager SIREN within float rounding
pytestmark = [
    pytest.mark.skipif(importlib.util.find_spec("triton") is None,
                       reason="Triton not installed (`pip install -e .[dev]` brings it; CUDA PyTorch has it)"),
    pytest.mark.skipif(os.environ.get("TRITON_INTERPRET") != "1", reason="a CUDA machine: tests/gpu runs the kernel"),
]


@pytest.mark.parametrize("width, blocks", [(16, 0), (32, 2), (64, 2), (64, 1)])
@pytest.mark.parametrize("precision", ["ieee", "tf32"])
def test_kernel_equals_the_eager_siren(width, blocks, precision):
    """The interpreter computes TF32 products in fp32; tests/gpu bounds their rounding on a GPU."""
    model = Siren(SirenConfig(width, blocks), torch.Generator().manual_seed(width + blocks))
    # trained-looking weights, not only the init: larger hidden weights make the sines' arguments larger
    with torch.no_grad():
        for p in model.parameters():
            p.mul_(1.5)
    x = torch.rand(1000, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1  # 1000: a ragged last tile
    with torch.no_grad():
        ref = model(x)
    got = FusedSiren(model.named_tensors(), blocks, precision)(x)
    assert got.shape == ref.shape and float((got - ref).abs().max()) <= 1e-5
    assert FusedSiren(model.named_tensors(), blocks, precision)(x[:0]).shape == (0,)


@pytest.mark.parametrize("sine", ["poly", "libdevice"])
def test_the_kernels_sine_is_sin(sine):
    """`_kernels.sine` against float64 sin over the range trained SIRENs' arguments take and well beyond, with
    the reduction's hard points: multiples of π/2 (the sign flips, the polynomial's end) and halfway points."""
    import triton

    from diffshadow._kernels import sine_kernel

    k = torch.arange(-3000, 3001, dtype=torch.float64)
    x = torch.cat([(torch.rand(100_000, generator=torch.Generator().manual_seed(2)) * 2 - 1) * 1e4,
                   (torch.rand(100_000, generator=torch.Generator().manual_seed(3)) * 2 - 1) * 4,
                   (k * torch.pi / 2).float(), ((k + 0.5) * torch.pi).float(), torch.tensor([0.0, 1e-30, -1e-30])])
    y = torch.empty_like(x)
    sine_kernel[(triton.cdiv(len(x), 4096),)](x, y, len(x), SINE=sine, BLOCK=4096)
    assert float((y.double() - torch.sin(x.double())).abs().max()) <= 2e-7


BLOB_TF = {"opacity": [[0, 0], [0.2, 0], [0.5, 0.3], [0.5, 0.6], [1, 0.8]],
           "color": [[0, 0.2, 0.4, 0.9], [0.35, 0.9, 0.9, 0.1], [1, 1, 0.3, 0.2]], "density_scale": 20}


def _blob_scene(density_scale: float = 20):
    """A box that is not a cube and a TF with a step and colour knots of its own: they check the kernels' box
    mapping and knot search. A shadow SIREN of width 16, a data INR of width 32."""
    a = gaussian_blob(33, 0.15)
    volume = Volume(data=a, extent=np.array([1.0, 0.8, 1.25]), name="blob")
    tf = TransferFunction.from_config({**BLOB_TF, "density_scale": density_scale})
    siren = SirenConfig(16, 2)
    layout = WeightLayout.for_siren(siren)
    weights = layout.flatten(init_siren(siren, torch.Generator().manual_seed(4))).numpy()
    return volume, tf, data_inr_stub(32, 1), (weights, layout, siren.blocks)


@pytest.mark.parametrize("mode, kernel", [("noshadow", "samples"), ("inr", "samples"), ("noshadow", "march"),
                                          ("inr", "march"), ("naive", "extinction"), ("naive", "march")])
def test_renderer_images_equal_with_the_fused_kernels(monkeypatch, mode, kernel):
    """With `render.kernel: fused`, `inr` and `noshadow` take each primary sample's value, shadow, transfer
    function and shading from one kernel: per sample in the wavefront loop (FusedSamples, `whole_rays=False`) or
    each ray from entry to exit (`FusedSamples.march`); `naive` its secondary samples' extinction likewise
    (FusedExtinction, per sample or whole secondary rays). With nothing stopped early (min_transmittance 0, an
    optical depth bound no ray reaches) the images equal the eager renderer's, and so do the samples taken."""
    from diffshadow import fused, render

    volume, tf, data_inr, siren = _blob_scene()
    cls = fused.FusedExtinction if mode == "naive" else fused.FusedSamples
    method = "march" if kernel == "march" else "__call__"
    calls = []
    real = getattr(cls, method)

    def spy(self, *args):
        calls.append(len(args[0]))
        return real(self, *args)

    monkeypatch.setattr(cls, method, spy)
    monkeypatch.setattr(render.marcher, "SHADOW_TAU_MAX", 1e9)  # no secondary ray stops early
    cam = Camera.orbit(volume.extent, azimuth=30.0, elevation=25.0, size=12 if mode == "naive" else 24)
    images = {}
    for setting in ("0", "1"):
        scene = RenderScene(volume, tf, data_inr, device="cpu", networks=FP32 if setting == "1" else None)
        assert scene.fused == (None if setting == "0" else "ieee")
        images[setting] = scene.render(mode, cam, light=(0.3, -0.5, 0.8), siren=siren, skip=False,
                                       min_transmittance=0.0, whole_rays=kernel == "march")
        assert bool(calls) == (setting == "1")
    a, b = images["0"], images["1"]
    assert float((a.rgb - b.rgb).abs().max()) <= 1e-5
    assert (a.counters.primary_samples, a.counters.secondary_samples) == (b.counters.primary_samples,
                                                                          b.counters.secondary_samples)


@pytest.mark.parametrize("skip", [False, True])
def test_whole_rays_stop_at_the_first_sample_below_the_threshold(monkeypatch, skip):
    """A whole-ray kernel stops a ray at the sample that takes its transmittance T below min_transmittance; the
    wavefront loop stops it at the end of an iteration, later. What either leaves out is seen through T, and
    colours and background lie in [0, 1], so the images differ by less than the threshold. A dense TF makes most
    rays stop early here."""
    volume, tf, data_inr, siren = _blob_scene(density_scale=200)
    scene = RenderScene(volume, tf, data_inr, device="cpu", networks=FP32)
    cam = Camera.orbit(volume.extent, azimuth=30.0, elevation=25.0, size=24)
    kw = {"light": (0.3, -0.5, 0.8), "siren": siren, "skip": skip, "min_transmittance": 1e-3}
    whole = scene.render("inr", cam, **kw)
    wave = scene.render("inr", cam, whole_rays=False, **kw)
    complete = scene.render("inr", cam, whole_rays=False, **{**kw, "min_transmittance": 0.0})
    assert whole.counters.primary_samples < 0.7 * complete.counters.primary_samples  # rays did stop early
    assert whole.counters.primary_samples <= wave.counters.primary_samples
    assert float((whole.rgb - complete.rgb).abs().max()) < 1e-3
    assert float((whole.rgb - wave.rgb).abs().max()) < 1e-3
    assert float((whole.alpha - complete.alpha).max()) <= 0 and float(whole.alpha.max()) > 0.99


def test_whole_ray_programs_take_rays_most_samples_first(monkeypatch):
    """A program of the whole-ray kernel runs until its last ray stops, so `slots` (its trips x rays per
    program, summed) is what the lanes did, and `primary_samples` what was useful. Rays go to programs most
    occupied samples first: with nothing stopped early, the slots are the sum over programs of their first ray's
    samples, x rays per program."""
    from diffshadow import render
    from diffshadow.grid import ray_span

    volume, tf, data_inr, siren = _blob_scene()
    scene = RenderScene(volume, tf, data_inr, device="cpu", networks=FP32)
    cam = Camera.orbit(volume.extent, azimuth=30.0, elevation=25.0, size=24)
    img = scene.render("noshadow", cam, min_transmittance=0.0, skip=True)
    o, d = cam.rays()
    t0, t1 = ray_span(o, d, torch.as_tensor(volume.extent, dtype=torch.float32))
    total = render.Runs.build(o, d, t0, t1, 0.5 * scene.voxel, scene.macro("inr", True)).total
    block = fused.block_points(32)
    first = total.sort(descending=True).values[::block]
    assert img.counters.primary_samples == int(total.sum())
    assert img.counters.slots == int(first.sum()) * block
    assert img.counters.slots < 2 * img.counters.primary_samples  # in image order: 4.2x here


def test_setting_and_bad_input(monkeypatch):
    for kernel, precision, expected in (("eager", "tf32", None), ("fused", "fp32", "ieee"),
                                        ("fused", "tf32", "tf32"), ("compile", "fp32", "compile")):
        assert Networks(kernel, precision).setting() == expected
    assert Networks.from_config({"kernel": "fused", "step": 0.5}) == Networks("fused", "tf32", "poly")
    for key, bad in (("kernel", "triton"), ("precision", "bf16"), ("sine", "cos")):
        with pytest.raises(RenderError, match=f"render.{key}: expected one of .*, got '{bad}'"):
            Networks(**{key: bad})
    named = Siren(SirenConfig(24, 1)).named_tensors()
    with pytest.raises(FusedSirenError, match=r"power-of-two width >= 16 and 3 inputs, got weights \(24, 3\)"):
        FusedSiren(named, 1)
    with pytest.raises(FusedSirenError, match="precision: expected one of ieee, tf32, got 'fp16'"):
        FusedSiren(Siren(SirenConfig(16, 1)).named_tensors(), 1, "fp16")
    with pytest.raises(FusedSirenError, match="sine: expected one of poly, libdevice, approx, got 'fast'"):
        FusedSiren(Siren(SirenConfig(16, 1)).named_tensors(), 1, sine="fast")
    with pytest.raises(FusedSirenError, match="'approx' is a GPU instruction .* interpreter cannot run"):
        FusedSiren(Siren(SirenConfig(16, 1)).named_tensors(), 1, sine="approx")
    volume = Volume(data=gaussian_blob(9, 0.15), extent=np.ones(3), name="blob")
    scene = RenderScene(volume, TransferFunction.from_config(BLOB_TF), data_inr_stub(16, 1),
                        networks=Networks("fused", "tf32", "libdevice"))
    assert scene.networks_used() == {"kernel": "fused", "precision": "tf32", "sine": "libdevice",
                                     "used": "fused tf32 libdevice"}
    poly, libdevice = (FusedSiren(Siren(SirenConfig(16, 1)).named_tensors(), 1, "ieee", sine)
                       for sine in ("poly", "libdevice"))
    with pytest.raises(FusedSirenError, match="one precision and sine, got 'ieee'/'poly' and 'ieee'/'libdevice'"):
        fused.FusedSamples(poly, libdevice, torch.ones(3), TransferFunction.from_config(BLOB_TF).optics_knots(), 1.0,
                           0.1)
    monkeypatch.delenv("TRITON_INTERPRET")
    assert not fused.available(torch.device("cpu")) and fused.available(torch.device("cuda"))


@pytest.mark.parametrize("value", [0.25, 0.5, 0.75, 0.6])
@pytest.mark.parametrize("shadow", [None, 0.25])
def test_samples_kernel_transfer_function_at_its_knots(value, shadow):
    """SIRENs with zero weights give the constant 0.5 · last bias + 0.5, so the kernels' transfer function is
    read exactly at a knot: at a step the upper value, as `TransferFunction.optics` (and the eager step) has it."""
    from diffshadow.fused import FusedExtinction, FusedSamples

    tf = TransferFunction.from_config({"opacity": [[0, 0], [0.25, 0.1], [0.25, 0.4], [0.5, 0.4], [0.5, 0.9], [1, 1]],
                                       "color": [[0, 0, 0, 1], [0.75, 1, 0, 0], [0.75, 0, 1, 0], [1, 1, 1, 1]],
                                       "density_scale": 30})

    def constant(v, width):
        model = Siren(SirenConfig(width, 1))
        named = {k: torch.zeros_like(t) for k, t in model.named_tensors().items()}
        named["last.bias"] = torch.tensor([2 * v - 1])
        return FusedSiren(named, 1)

    extent = torch.tensor([1.0, 0.5, 2.0])
    p = torch.rand(300, 3, generator=torch.Generator().manual_seed(0)) * extent
    fused = FusedSamples(constant(value, 32), constant(shadow, 16) if shadow is not None else None, extent,
                         tf.optics_knots(), tf.density_scale, dt=0.01)
    alpha, rgb = fused(p)
    mu, colour = tf.optics(torch.full((300,), value))
    g = 1.0 if shadow is None else 0.1 + 0.9 * shadow
    torch.testing.assert_close(alpha, 1 - torch.exp(-mu * 0.01), rtol=0, atol=1e-6)
    torch.testing.assert_close(rgb, (colour * g).clamp(0, 1), rtol=0, atol=1e-6)
    assert fused(p[:0])[0].shape == (0,) and fused(p[:0])[1].shape == (0, 3)
    extinction = FusedExtinction(constant(value, 32), extent, tf.optics_knots(), tf.density_scale)
    torch.testing.assert_close(extinction(p), mu, rtol=0, atol=1e-5)
    assert extinction(p[:0]).shape == (0,)


def test_a_launch_counts_as_one_op():
    """bench's op counts see a fused kernel as one launch, not as the aten ops Triton's interpreter runs."""
    from diffshadow.bench.profile import op_counts

    fast = FusedSiren(Siren(SirenConfig(16, 1)).named_tensors(), 1)
    x = torch.rand(300, 3)
    assert op_counts(lambda: fast(x)) == {"ops": 1, "syncs": 0}
    assert op_counts(lambda: [fast(x), fast(x)])["ops"] == 2


def test_every_launch_asks_for_fma_contraction(monkeypatch):
    """Triton 3.10 stops contracting multiply-adds to FMAs unless a launch asks; the kernels' sine and layers are
    written for FMAs, so each launch asks (`fused.FP_FUSION`) and the machine code does not change with Triton."""
    import types

    from diffshadow import fused

    seen = []
    kernel = _Indexable(lambda grid: lambda *args, **options: seen.append((grid, options)))
    monkeypatch.setattr(fused, "_kernels", lambda: types.SimpleNamespace(siren_kernel=kernel))
    fused._launch("siren_kernel", 300, 64, 4, "x", W=16)
    assert seen == [((5,), {"num_warps": 4, "enable_fp_fusion": True, "maxnreg": None, "W": 16})]
    fused._launch("siren_kernel", 300, 64, 4, "x", registers=168, W=16)  # a cap: the compiler's maxnreg
    assert seen[-1] == ((5,), {"num_warps": 4, "enable_fp_fusion": True, "maxnreg": 168, "W": 16})


def test_a_siren_the_kernel_cannot_take_falls_back_to_eager_with_a_warning(monkeypatch):
    """`render.kernel: fused` is a speed-up: a data INR of width 8 (the tiny workflow's) renders eagerly, and
    says so, instead of failing the stage."""
    from diffshadow.render import RenderScene

    data_inr = data_inr_stub(8, 1)

    volume = Volume(data=gaussian_blob(17, 0.15), extent=np.ones(3), name="blob")
    tf = TransferFunction.from_config({"opacity": [[0, 0], [1, 0.8]], "color": [[0, 1, 1, 1], [1, 1, 1, 1]],
                                       "density_scale": 20})
    cam = Camera.orbit(volume.extent, azimuth=30.0, elevation=25.0, size=8)
    eager = RenderScene(volume, tf, data_inr).render("noshadow", cam).rgb
    with pytest.warns(UserWarning, match=r"render.kernel=fused \(ieee\): .*power-of-two width >= 16.*eager SIREN"):
        image = RenderScene(volume, tf, data_inr, networks=FP32).render("noshadow", cam).rgb
    assert torch.equal(image, eager)


def test_a_kernel_that_fails_to_compile_leaves_the_scene_eager(monkeypatch):
    """A fused kernel's first launch compiles it; when that fails (here as Triton fails for a PTX version the
    driver lacks), the renderer says why and renders this and later frames with the eager SIREN, the same
    image as without the setting. A failure after a kernel has launched once is not a compile failure and is
    not hidden."""
    import types

    from diffshadow.fused import FusedKernelError, FusedKernelWarning

    volume, tf, data_inr, siren = _blob_scene()
    cam = Camera.orbit(volume.extent, azimuth=30.0, elevation=25.0, size=12)
    kw = {"light": np.array([0.0, 0.6, 0.8]), "siren": siren}
    eager = RenderScene(volume, tf, data_inr).render("inr", cam, **kw).rgb

    def broken(grid):
        def launch(*args, **kwargs):
            raise RuntimeError("ptxas fatal: Unsupported .version 8.7; current version is '8.4'")
        return launch

    monkeypatch.setattr(fused, "_kernels", lambda: types.SimpleNamespace(march_kernel=_Indexable(broken),
                                                                         samples_kernel=_Indexable(broken)))
    monkeypatch.setattr(fused, "_LAUNCHED", set())
    scene = RenderScene(volume, tf, data_inr, networks=Networks("fused", "tf32"))
    with pytest.warns(FusedKernelWarning, match=r"render.kernel=fused \(tf32\): march_kernel failed on its first "
                                                r"launch, compiling \(Triton .*\): RuntimeError: ptxas fatal: "
                                                r"Unsupported .version 8.7.*eager SIREN from now on"):
        image = scene.render("inr", cam, **kw).rgb
    assert torch.equal(image, eager) and scene.fused is None
    assert torch.equal(scene.render("inr", cam, **kw).rgb, eager)  # no second warning: the filter makes it an error

    # a kernel that compiled and launched: its later failures are not compile failures
    monkeypatch.undo()
    monkeypatch.setattr(fused, "_LAUNCHED", set())
    fast = FusedSiren(Siren(SirenConfig(16, 1)).named_tensors(), 1)
    x = torch.rand(40, 3)
    fast(x)
    monkeypatch.setattr(fused, "_kernels", lambda: types.SimpleNamespace(siren_kernel=_Indexable(broken)))
    with pytest.raises(RuntimeError, match="ptxas fatal") as caught:
        fast(x)
    assert not isinstance(caught.value, FusedKernelError)


class _Indexable:
    """A stand-in for a Triton kernel: kernel[grid](...)."""

    def __init__(self, at):
        self.at = at

    def __getitem__(self, grid):
        return self.at(grid)


def _compile_in_a_fresh_process(code: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}  # compiling, not interpreting
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600)


@pytest.mark.skipif(not (importlib.util.find_spec("triton") and importlib.util.find_spec("triton.backends.nvidia")),
                    reason="Triton without its CUDA backend")
def test_the_whole_ray_kernel_compiles_for_a100_and_h100():
    """The interpreter runs a kernel as Python and misses what only the compiler checks (a loop-carried value
    that changes type, a constexpr used as a tensor). `bench kernels` compiles for a GPU without one: the
    whole-ray kernel compiles for sm_80 (A100) and sm_90 (H100/H200) at TF32 with both sines the GPU runs,
    fits at least one program per SM in registers, and has no per-sine branch or local memory (CUDA's sinf
    brings both: 867 branches and 1,440 local loads and stores; on sm_80 a few registers spill, 26 loads and
    stores). "approx" puts its sines on the MUFU unit: the interpreter cannot run it, so this is all that
    checks it without a GPU."""
    code = ("import json; from diffshadow.bench.kernels import kernel_shapes, compile_kernel; "
            "print(json.dumps([(sine, compile_kernel(*kernel_shapes('tf32', sine)['march (inr, whole rays)'], arch)) "
            "for sine in ('poly', 'approx') for arch in (80, 90)]))")
    res = _compile_in_a_fresh_process(code)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "FP_FUSION" not in res.stderr  # Triton >= 3.9 warns when a compile leaves FMA contraction unasked
    for sine, r in json.loads(res.stdout.strip().splitlines()[-1]):
        assert 0 < r["registers"] <= 255 and r["programs_per_sm"] >= 1
        assert r["local"] <= 32 and r["branches"] <= 3, (sine, r)
        # each thread's share of a trip's sines: 64 rays x (64 + 32) activations x 5 layers / 128 threads = 240
        assert (r["mufu"] >= 240) == (sine == "approx"), (sine, r)


@pytest.mark.skipif(not (importlib.util.find_spec("triton") and importlib.util.find_spec("triton.backends.nvidia")),
                    reason="Triton without its CUDA backend")
def test_one_sine_costs_what_bench_kernels_says():
    """`bench kernels`' per-sine rows: compiled for sm_90, "approx" is one MUFU and a few FP32 instructions,
    "poly" is branch-free FP32 work, and libdevice's path for a SIREN's arguments is the longest (its exact
    reduction, behind a branch, is not on that path but is in the code)."""
    code = ("import json; from diffshadow.bench.kernels import sine_costs; "
            "print(json.dumps({**sine_costs(90), 'poly unfused': sine_costs(90, ['poly'], fp_fusion=False)['poly']}))")
    res = _compile_in_a_fresh_process(code)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "FP_FUSION" not in res.stderr  # Triton >= 3.9 warns when a compile leaves FMA contraction unasked
    c = json.loads(res.stdout.strip().splitlines()[-1])
    # why the kernels ask for FMA contraction (fused.FP_FUSION): its reduction and polynomial are multiply-adds
    assert c["poly unfused"]["executed"] > c["poly"]["executed"]
    # what each sine is, whatever Triton version compiles it: one hardware sine, or FP32 work and no MUFU; and
    # their order of cost (absolute counts moved between Triton versions: issue 55)
    assert c["approx"]["mufu"] == 1 and c["poly"]["mufu"] == 0 and c["poly"]["fp32"] > 0
    assert c["libdevice"]["executed"] > c["poly"]["executed"] > c["approx"]["executed"]
    assert c["libdevice"]["instructions"] > c["libdevice"]["executed"]  # the slow path's code is in the kernel


def test_bench_kernels_under_the_interpreter_says_so(monkeypatch):
    from diffshadow.bench.kernels import KernelCompileError, compile_kernel, kernel_shapes

    monkeypatch.setenv("TRITON_INTERPRET", "1")
    name, constants = kernel_shapes("tf32")["siren (data INR)"]
    with pytest.raises(KernelCompileError, match="without TRITON_INTERPRET=1"):
        compile_kernel(name, constants, 90)
