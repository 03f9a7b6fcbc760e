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

from diffshadow.analytic import gaussian_blob
from diffshadow.render import Camera, Networks, RenderError, RenderScene, fused
from diffshadow.render.fused import FusedSiren, FusedSirenError
from diffshadow.siren import Siren, SirenConfig, WeightLayout, box_to_siren, init_siren
from diffshadow.transfer import TransferFunction
from diffshadow.volume import Volume

# Triton reads TRITON_INTERPRET when it is first imported; conftest sets it on a machine without CUDA. With
# CUDA, tests/gpu/test_cuda.py runs the compiled kernel instead. The interpreter computes TF32 products in fp32
# and the sine as numpy's sin of the reduced argument: the kernels equal the eager SIREN within float rounding.
FUSED = Networks("fused")
pytestmark = [
    pytest.mark.skipif(importlib.util.find_spec("triton") is None,
                       reason="Triton not installed (`pip install -e .[dev]` brings it; CUDA PyTorch has it)"),
    pytest.mark.skipif(os.environ.get("TRITON_INTERPRET") != "1", reason="a CUDA machine: tests/gpu runs the kernel"),
]


@pytest.mark.parametrize("width, blocks", [(16, 0), (32, 2), (64, 2), (64, 1)])
def test_kernel_equals_the_eager_siren(width, blocks):
    """The interpreter computes TF32 products in fp32; tests/gpu bounds their rounding on a GPU."""
    model = Siren(SirenConfig(width, blocks), torch.Generator().manual_seed(width + blocks))
    # trained-looking weights, not only the init: larger hidden weights make the sines' arguments larger
    with torch.no_grad():
        for p in model.parameters():
            p.mul_(1.5)
    x = torch.rand(1000, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1  # 1000: a ragged last tile
    with torch.no_grad():
        ref = model(x)
    got = FusedSiren(model.named_tensors(), blocks)(x)
    assert got.shape == ref.shape and float((got - ref).abs().max()) <= 1e-5
    assert FusedSiren(model.named_tensors(), blocks)(x[:0]).shape == (0,)


def test_the_kernels_sine_reduction_is_exact():
    """`_kernels.sine`'s reduction x = 2kπ + r against float64 sin over the range trained SIRENs' arguments take
    and well beyond, with its hard points: multiples of π/2 and halfway points. The interpreter takes sin of r
    where the GPU takes its special-function unit (tests/gpu: within 2e-6)."""
    import triton

    from diffshadow.render._kernels import sine_kernel

    k = torch.arange(-3000, 3001, dtype=torch.float64)
    x = torch.cat([(torch.rand(100_000, generator=torch.Generator().manual_seed(2)) * 2 - 1) * 1e4,
                   (torch.rand(100_000, generator=torch.Generator().manual_seed(3)) * 2 - 1) * 4,
                   (k * torch.pi / 2).float(), ((k + 0.5) * torch.pi).float(), torch.tensor([0.0, 1e-30, -1e-30])])
    y = torch.empty_like(x)
    sine_kernel[(triton.cdiv(len(x), 4096),)](x, y, len(x), COPY=False, BLOCK=4096)
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


@pytest.mark.parametrize("mode", ["noshadow", "inr", "naive"])
def test_renderer_images_equal_with_the_fused_kernels(monkeypatch, mode):
    """With `render.kernel: fused`, `inr` and `noshadow` march each primary ray from entry to exit in one kernel
    (`FusedSamples.march`: value, shadow, transfer function, shading, compositing); `naive` its secondary rays
    likewise (`FusedExtinction.march`). With nothing stopped early (min_transmittance 0, an optical depth bound
    no ray reaches) the images equal the eager renderer's, and so do the samples taken."""
    from diffshadow import render
    from diffshadow.render import fused

    volume, tf, data_inr, siren = _blob_scene()
    cls = fused.FusedExtinction if mode == "naive" else fused.FusedSamples
    calls = []
    real = cls.march

    def spy(self, *args):
        calls.append(len(args[0]))
        return real(self, *args)

    monkeypatch.setattr(cls, "march", spy)
    monkeypatch.setattr(render.marcher, "SHADOW_TAU_MAX", 1e9)  # no secondary ray stops early
    cam = Camera.orbit(volume.extent, azimuth=30.0, elevation=25.0, size=12 if mode == "naive" else 24)
    images = {}
    for setting in ("0", "1"):
        scene = RenderScene(volume, tf, data_inr, device="cpu", networks=FUSED if setting == "1" else None)
        assert scene.kernel_used == (None if setting == "0" else "fused")
        images[setting] = scene.render(mode, cam, light=(0.3, -0.5, 0.8), siren=siren, skip=False,
                                       min_transmittance=0.0)
        assert bool(calls) == (setting == "1")
    a, b = images["0"], images["1"]
    assert float((a.rgb - b.rgb).abs().max()) <= 1e-5
    assert (a.counters.primary_samples, a.counters.secondary_samples) == (b.counters.primary_samples,
                                                                          b.counters.secondary_samples)


@pytest.mark.parametrize("skip", [False, True])
def test_whole_rays_stop_at_the_first_sample_below_the_threshold(monkeypatch, skip):
    """A whole-ray kernel stops a ray at the sample that takes its transmittance T below min_transmittance; the
    wavefront loop (the eager renderer) stops it at the end of an iteration, later. What either leaves out is
    seen through T, and colours and background lie in [0, 1], so the images differ by less than the threshold. A
    dense TF makes most rays stop early here."""
    volume, tf, data_inr, siren = _blob_scene(density_scale=200)
    scene = RenderScene(volume, tf, data_inr, device="cpu", networks=FUSED)
    eager = RenderScene(volume, tf, data_inr, device="cpu", networks=Networks("eager"))
    cam = Camera.orbit(volume.extent, azimuth=30.0, elevation=25.0, size=24)
    kw = {"light": (0.3, -0.5, 0.8), "siren": siren, "skip": skip, "min_transmittance": 1e-3}
    whole = scene.render("inr", cam, **kw)
    wave = eager.render("inr", cam, **kw)
    complete = eager.render("inr", cam, **{**kw, "min_transmittance": 0.0})
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
    scene = RenderScene(volume, tf, data_inr, device="cpu", networks=FUSED)
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


def test_one_march_kernel_serves_any_number_of_runs_per_ray(monkeypatch):
    """The runs per ray (J) are a launch argument, not a kernel constant: a constant compiled a kernel per value (on
    an H200 the README run's benchmark compiled J=1's beside J=7's, 2-3 s). The same samples of each ray given as
    other runs march to the same bytes, through one first-launched (compiled) kernel for each kind of ray: one run,
    or cut into three (one empty); three runs with gaps between them, or four (an empty one inserted, whose offset no
    sample uses). And a ray's samples are where `Runs.samples` puts them."""
    from diffshadow.render.cells import Runs

    _, tf, data_inr, _ = _blob_scene()
    extent = torch.tensor([1.0, 0.8, 1.25])
    scalar = FusedSiren(data_inr.model.named_tensors(), data_inr.model.cfg.blocks)
    kernel = fused.FusedSamples(scalar, None, extent, tf.optics_knots(torch.device("cpu")), tf.density_scale, 0.01)
    g = torch.Generator().manual_seed(0)
    n = 40
    o = torch.rand(n, 3, generator=g) * extent
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=1)
    t0, t1 = torch.zeros(n), torch.full((n,), 4.0)
    size, gap = torch.randint(0, 20, (n, 3), generator=g), torch.randint(1, 30, (n, 3), generator=g)
    cum, total = size.cumsum(1), size.sum(1)
    offset = torch.cat([torch.zeros(n, 1, dtype=torch.long), gap[:, 1:].cumsum(1)], dim=1)

    def runs(cum, offset):
        return Runs(cum, offset, cum[:, -1])

    zeros = torch.zeros(n, 3, dtype=torch.long)
    cases = [(runs(total[:, None], zeros[:, :1]), runs(torch.stack([cum[:, 0], cum[:, 0], total], 1), zeros)),
             (runs(cum, offset), runs(torch.cat([cum[:, :1], cum], 1),
                                      torch.cat([offset[:, :1], torch.full((n, 1), 999), offset[:, 1:]], 1)))]
    monkeypatch.setattr(fused, "_LAUNCHED", set())
    for fewer, more in cases:
        a, b = (fused._march(kernel, o, d, t0, t1, r, 0.0, absorb=False, dt=kernel.dt, shadow=None)
                for r in (fewer, more))
        for x, y in zip(a, b, strict=True):
            assert torch.equal(x, y)
        assert int(a[2].sum()) == int(total.sum())  # every sample taken: nothing stopped early
    # and the gapped runs' samples are where `Runs.samples` puts them: the secondary-ray march's optical depth is
    # the sum of μ dt over those samples (the data INR by the SIREN kernel, μ by the TF)
    gapped = cases[1][0]
    extinction = fused.FusedExtinction(scalar, extent, tf.optics_knots(torch.device("cpu")), tf.density_scale)
    tau, count, _ = extinction.march(o, d, t0, t1, gapped, kernel.dt, float("inf"))
    k, valid = gapped.samples(torch.arange(n), torch.zeros(n, dtype=torch.long), int(total.max()))
    t = t0[:, None] + (k + 0.5) * kernel.dt
    values = scalar(box_to_siren((o[:, None] + t[..., None] * d[:, None]).reshape(-1, 3), extent)).view(t.shape)
    expected = (tf.extinction(values) * valid).sum(1) * kernel.dt
    assert torch.equal(count, total.int()) and torch.allclose(tau, expected, rtol=1e-5, atol=1e-6)
    assert sum(key[0] == "march_kernel" for key in fused._LAUNCHED) == 2  # primary rays, secondary rays


def test_a_scene_knows_every_kernel_its_frames_launch(monkeypatch):
    """`render.warm_kernels` compiles a scene's kernels at its first frame, all at once, from
    `RenderScene.kernel_variants`: the kernels its frames launch in every mode and shading, no fewer (a kernel left
    out compiles at its own first launch, as before) and no more (one compiled for nothing). Only CUDA compiles
    ahead: on a CPU `warm` asks nothing of the interpreter."""
    volume, tf, data_inr, siren = _blob_scene()
    scene = RenderScene(volume, tf, data_inr, device="cpu", networks=FUSED)
    cam = Camera.orbit(volume.extent, azimuth=30.0, elevation=25.0, size=8)
    monkeypatch.setattr(fused, "_LAUNCHED", set())
    assert fused.warm(scene.kernel_variants(siren), torch.device("cpu")) == 0 and not fused._WARMED
    light = (0.3, -0.5, 0.8)
    # unlit: whole-ray marches (noshadow, inr, naive's secondary rays); Phong: the wavefront loop's SIRENs alone
    for mode, phong in (("noshadow", False), ("inr", False), ("naive", False), ("inr", True), ("gt", False)):
        scene.render(mode, cam, light=light, siren=siren, phong=phong)
    assert set(scene.kernel_variants(siren)) == fused._LAUNCHED
    assert set(scene.kernel_variants()) < fused._LAUNCHED  # without a shadow INR: the data INR's three
    assert RenderScene(volume, tf, None, device="cpu", networks=FUSED).kernel_variants(siren) == []
    assert Networks.from_config({}).warm and not Networks.from_config({"warm_kernels": False}).warm
    with pytest.raises(RenderError, match="render.warm_kernels: expected true or false, got 'yes'"):
        Networks(warm="yes")


def test_setting_and_bad_input(monkeypatch):
    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    for kernel, device, expected in (("eager", cuda, None), ("fused", cpu, "fused"), ("fused", cuda, "fused"),
                                     ("auto", cpu, None), ("auto", cuda, "fused")):
        assert Networks(kernel).setting(device) == expected, (kernel, device)
    assert Networks.from_config({"kernel": "fused", "step": 0.5}) == Networks("fused")
    assert Networks.from_config({"step": 0.5}) == Networks("auto")
    with pytest.raises(RenderError, match="render.kernel: expected one of auto, eager, fused, got 'triton'"):
        Networks("triton")
    named = Siren(SirenConfig(24, 1)).named_tensors()
    with pytest.raises(FusedSirenError, match=r"power-of-two width >= 16 and 3 inputs, got weights \(24, 3\)"):
        FusedSiren(named, 1)
    volume = Volume(data=gaussian_blob(9, 0.15), extent=np.ones(3), name="blob")
    tf = TransferFunction.from_config(BLOB_TF)
    scene = RenderScene(volume, tf, data_inr_stub(16, 1), networks=Networks("fused"))
    assert scene.networks_used() == {"kernel": "fused", "used": "fused"}
    # auto on a CPU renders eagerly even where the interpreter could run the kernels: it is for tests, not speed
    assert RenderScene(volume, tf, data_inr_stub(16, 1)).networks_used() == {"kernel": "auto", "used": "eager"}
    monkeypatch.delenv("TRITON_INTERPRET")
    assert not fused.available(cpu) and fused.available(cuda)


def test_a_launch_counts_as_one_op():
    """bench's op counts see a fused kernel as one launch, not as the aten ops Triton's interpreter runs."""
    from diffshadow.bench.profile import op_counts

    fast = FusedSiren(Siren(SirenConfig(16, 1)).named_tensors(), 1)
    x = torch.rand(300, 3)
    assert op_counts(lambda: fast(x)) == {"ops": 1, "syncs": 0, "host_tensors": 0}
    assert op_counts(lambda: [fast(x), fast(x)])["ops"] == 2


def test_every_launch_asks_for_fma_contraction(monkeypatch):
    """Triton 3.10 stops contracting multiply-adds to FMAs unless a launch asks; the kernels' sine and layers are
    written for FMAs, so each launch asks (`fused.FP_FUSION`) and the machine code does not change with Triton."""
    import types

    from diffshadow.render import fused

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
    with pytest.warns(UserWarning, match=r"render.kernel=fused: .*power-of-two width >= 16.*eager SIREN"):
        image = RenderScene(volume, tf, data_inr, networks=FUSED).render("noshadow", cam).rgb
    assert torch.equal(image, eager)


def test_a_kernel_that_fails_to_compile_leaves_the_scene_eager(monkeypatch):
    """A fused kernel's first launch compiles it; when that fails (here as Triton fails for a PTX version the
    driver lacks), the renderer says why and renders this and later frames with the eager SIREN, the same
    image as without the setting. A failure after a kernel has launched once is not a compile failure and is
    not hidden."""
    import types

    from diffshadow.render.fused import FusedKernelError, FusedKernelWarning

    volume, tf, data_inr, siren = _blob_scene()
    cam = Camera.orbit(volume.extent, azimuth=30.0, elevation=25.0, size=12)
    kw = {"light": np.array([0.0, 0.6, 0.8]), "siren": siren}
    eager = RenderScene(volume, tf, data_inr).render("inr", cam, **kw).rgb

    def broken(grid):
        def launch(*args, **kwargs):
            raise RuntimeError("ptxas fatal: Unsupported .version 8.7; current version is '8.4'")
        return launch

    monkeypatch.setattr(fused, "_kernels", lambda: types.SimpleNamespace(march_kernel=_Indexable(broken)))
    monkeypatch.setattr(fused, "_LAUNCHED", set())
    scene = RenderScene(volume, tf, data_inr, networks=FUSED)
    with pytest.warns(FusedKernelWarning, match=r"render.kernel=fused \(fused\): march_kernel failed on its first "
                                                r"launch, compiling \(Triton .*\): RuntimeError: ptxas fatal: "
                                                r"Unsupported .version 8.7.*eager SIREN from now on"):
        image = scene.render("inr", cam, **kw).rgb
    assert torch.equal(image, eager) and scene.kernel_used is None
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


def _triton_compiles_for_cuda() -> bool:
    # find_spec of a submodule raises, not returns None, when its parent is missing: Triton 2.x has no backends
    try:
        return importlib.util.find_spec("triton.backends.nvidia") is not None
    except ModuleNotFoundError:
        return False


def _compile_in_a_fresh_process(code: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}  # compiling, not interpreting
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600)


@pytest.mark.skipif(not _triton_compiles_for_cuda(), reason="no Triton 3 with its CUDA backend")
def test_the_whole_ray_kernel_compiles_for_a100_and_h100():
    """The interpreter runs a kernel as Python and misses what only the compiler checks (a loop-carried value
    that changes type, a constexpr used as a tensor) and cannot run the special-function unit's sine. `bench
    kernels` compiles for a GPU without one: the whole-ray kernel compiles for sm_80 (A100) and sm_90
    (H100/H200), fits at least one program per SM in registers, has no branch per sine and little local memory
    (on sm_80 a few registers spill), and puts its sines on the MUFU unit."""
    code = ("import json; from diffshadow.bench.kernels import kernel_shapes, compile_kernel; "
            "print(json.dumps([compile_kernel(*kernel_shapes()['march (inr, whole rays)'], arch) "
            "for arch in (80, 90)]))")
    res = _compile_in_a_fresh_process(code)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "FP_FUSION" not in res.stderr  # Triton >= 3.9 warns when a compile leaves FMA contraction unasked
    for r in json.loads(res.stdout.strip().splitlines()[-1]):
        assert 0 < r["registers"] <= 255 and r["programs_per_sm"] >= 1
        # the loops over trips and over a ray's runs, not a branch per sine (~240)
        assert r["local"] <= 32 and r["branches"] <= 12, r
        # each thread's share of a trip's sines: 64 rays x (64 + 32) activations x 5 layers / 128 threads = 240
        assert r["mufu"] >= 240, r


@pytest.mark.skipif(not _triton_compiles_for_cuda(), reason="no Triton 3 with its CUDA backend")
def test_one_sine_costs_what_bench_kernels_says():
    """`bench kernels`' sine row: compiled for sm_90, one MUFU and a few FP32 instructions (the reduction), no
    branch; without FMA contraction the reduction takes more (why the kernels ask for it: fused.FP_FUSION)."""
    code = ("import json; from diffshadow.bench.kernels import sine_cost; "
            "print(json.dumps({'fused': sine_cost(90), 'unfused': sine_cost(90, fp_fusion=False)}))")
    res = _compile_in_a_fresh_process(code)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "FP_FUSION" not in res.stderr  # Triton >= 3.9 warns when a compile leaves FMA contraction unasked
    c = json.loads(res.stdout.strip().splitlines()[-1])
    assert c["fused"]["mufu"] == 1 and 0 < c["fused"]["fp32"] < 10 and c["fused"]["branches"] <= 0
    assert c["unfused"]["executed"] > c["fused"]["executed"]


def test_bench_kernels_under_the_interpreter_says_so(monkeypatch):
    from diffshadow.bench.kernels import KernelCompileError, compile_kernel, kernel_shapes

    monkeypatch.setenv("TRITON_INTERPRET", "1")
    name, constants = kernel_shapes()["siren (data INR)"]
    with pytest.raises(KernelCompileError, match="without TRITON_INTERPRET=1"):
        compile_kernel(name, constants, 90)
