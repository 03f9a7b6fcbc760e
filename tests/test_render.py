"""The renderer: wavefront vs all-at-once, gt against shadow_grid and the exact march, skipping,
bounded batches, analytic shadow values, extremes and bad input."""

import math
import re

import numpy as np
import pytest
import torch
from conftest import Asker, default_device_meta

from diffshadow.analytic import gaussian_blob
from diffshadow.render import (
    Camera,
    GridScalar,
    GridShadow,
    Interrupted,
    MacroGrid,
    MarchedShadow,
    MarchPlan,
    RenderError,
    RenderScene,
    Shading,
    render,
    render_all_at_once,
)
from diffshadow.render.cells import Runs
from diffshadow.render.marcher import _whole_rays
from diffshadow.shadow import ShadowField, shadow_grid, transmittance
from diffshadow.siren import SirenConfig, WeightLayout, init_siren
from diffshadow.transfer import TransferFunction
from diffshadow.volume import Volume

LIGHT = (0.3, -0.5, 0.8)
TF = TransferFunction.from_config({
    # opacity 0 below 0.2 leaves the corners of the blob's box empty: skipping has work to do
    "opacity": [[0.0, 0.0], [0.2, 0.0], [1.0, 0.8]],
    "color": [[0.0, 0.1, 0.3, 0.9], [0.5, 0.9, 0.8, 0.4], [1.0, 1.0, 0.2, 0.1]],
    "density_scale": 25.0,
})


@pytest.fixture(scope="module")
def blob():
    # two blobs, so that one shadows the other
    a = gaussian_blob(49, 0.12)
    b = np.roll(a, (8, -6, 10), axis=(0, 1, 2))
    return Volume(data=np.maximum(a, b), extent=np.array([1.0, 1.0, 1.0]), name="blobs")


def shadow_inr(seed: int = 0) -> tuple:
    """(weights, layout, blocks) of a freshly initialised width-16 shadow SIREN, as `render(..., siren=)` takes."""
    cfg = SirenConfig(16, 1)
    layout = WeightLayout.for_siren(cfg)
    return layout.flatten(init_siren(cfg, torch.Generator().manual_seed(seed))), layout, cfg.blocks


def scene_of(vol, size=24):
    # not `setup`: pytest 8.0 calls a module-level `setup` as the module's xunit set-up, with the module
    cam = Camera.orbit(vol.extent, azimuth=40, elevation=20, size=size)
    return cam, GridScalar(vol), float(np.min(vol.voxel_size))


def test_the_raw_grids_gradient_is_made_only_for_phong_and_is_exact_on_a_ramp():
    """GridScalar's gradient channels (3 float32 grids, from float64 ones: 12 GiB at once on a 512³ volume) wait
    for the first gradient asked for; values alone read the volume's own grid. On a linear ramp over an
    anisotropic box, central differences are the ramp's slope exactly, and the value is the ramp's."""
    nz, ny, nx = 6, 9, 12
    extent = np.array([1.0, 0.5, 0.25])  # (x, y, z): voxel sizes 1/11, 1/16, 1/20
    z, y, x = np.meshgrid(*(np.arange(n) * h for n, h in zip((nz, ny, nx), (0.25 / 5, 0.5 / 8, 1 / 11), strict=True)),
                          indexing="ij")
    vol = Volume(data=(0.5 * x - 0.25 * y + 2.0 * z).astype(np.float32) + 0.25, extent=extent, name="ramp")
    scalar = GridScalar(vol)
    p = torch.tensor([[0.3, 0.2, 0.1], [0.9, 0.45, 0.2], [0.05, 0.01, 0.24]])
    value = scalar.value(p)
    assert scalar._channels is None  # values alone made no gradient
    torch.testing.assert_close(value, 0.5 * p[:, 0] - 0.25 * p[:, 1] + 2.0 * p[:, 2] + 0.25, rtol=0, atol=1e-6)
    v, g = scalar.value_and_grad(p)
    assert torch.equal(v, value)
    torch.testing.assert_close(g, torch.tensor([[0.5, -0.25, 2.0]]).expand(3, 3), rtol=0, atol=1e-5)
    gz, gy, gx = np.gradient(vol.data.astype(np.float64), *(vol.voxel_size[::-1]))
    assert np.array_equal(scalar.channels[0].numpy(), np.stack([vol.data, gx, gy, gz]).astype(np.float32))


@pytest.mark.parametrize("case", ["noshadow_phong", "gt", "naive"])
def test_wavefront_equals_all_at_once(blob, case):
    cam, scalar, vox = scene_of(blob)
    phong = case == "noshadow_phong"
    shadow = None
    if case == "gt":
        shadow = GridShadow(shadow_grid(blob, TF, LIGHT, method="sweep"), blob.extent)
    elif case == "naive":
        shadow = MarchedShadow(scalar, TF, blob.extent, vox, macro=MacroGrid.build(blob, TF, cell=8), batch=512)
    # a small batch forces many pool refills; skipping on; termination far below the tolerance
    wave = render(cam, scalar, TF, blob.extent, vox, light=LIGHT, shadow=shadow, shading=Shading(phong=phong),
                  macro=MacroGrid.build(blob, TF, cell=8), batch=256, min_transmittance=1e-7)
    if case == "naive":
        shadow = MarchedShadow(scalar, TF, blob.extent, vox, macro=None)
    ref = render_all_at_once(cam, scalar, TF, blob.extent, vox, light=LIGHT, shadow=shadow,
                             shading=Shading(phong=phong))
    assert float(wave.alpha.max()) > 0.5  # the image shows something
    assert float((wave.rgb - ref.rgb).abs().max()) <= 1e-4
    assert float((wave.alpha - ref.alpha).abs().max()) <= 1e-4


def test_gt_mode_uses_shadow_grid_and_agrees_with_exact_march(blob):
    cam, scalar, vox = scene_of(blob)
    scene = RenderScene(blob, TF)
    gt = scene.render("gt", cam, light=LIGHT, min_transmittance=1e-7)
    direct = GridShadow(shadow_grid(blob, TF, LIGHT, method="march"), blob.extent)
    ref = render_all_at_once(cam, scalar, TF, blob.extent, vox, light=LIGHT, shadow=direct)
    assert float((gt.rgb - ref.rgb).abs().max()) <= 1e-4
    field = ShadowField.build(blob, TF)
    exact = render_all_at_once(cam, scalar, TF, blob.extent, vox, light=LIGHT,
                               shadow=lambda p: transmittance(field, TF, LIGHT, p))
    err = (gt.rgb - exact.rgb).abs()
    assert float(err.mean()) <= 2e-3 and float(err.max()) <= 5e-2, (float(err.mean()), float(err.max()))
    # and the shadow shows: the same scene without it is brighter somewhere by a visible amount
    plain = scene.render("noshadow", cam)
    assert float((plain.rgb - gt.rgb).max()) > 0.05


def test_the_exact_reference_is_the_shadow_marched_at_every_sample(blob):
    """evaluate_images' reference (`render.reference: exact`) is the naive mode on the raw grid: the shadow marched
    from every sample. It matches the image rendered all at once with `transmittance` at every sample, and misses it
    by far less than the gt mode's shadow grid at the voxels (`grid`, the reference before) does."""
    cam, scalar, vox = scene_of(blob)
    field = ShadowField.build(blob, TF)
    exact = render_all_at_once(cam, scalar, TF, blob.extent, vox, light=LIGHT,
                               shadow=lambda p: transmittance(field, TF, LIGHT, p))
    scene = RenderScene(blob, TF)
    err = {mode: float((scene.render(mode, cam, light=LIGHT, scalar="grid", min_transmittance=1e-7).rgb
                        - exact.rgb).abs().mean()) for mode in ("naive", "gt")}
    assert err["naive"] < 0.2 * err["gt"], err


def test_naive_through_the_grid_matches_gt(blob):
    cam, _, _ = scene_of(blob)
    scene = RenderScene(blob, TF)
    gt = scene.render("gt", cam, light=LIGHT)
    naive = scene.render("naive", cam, light=LIGHT, scalar="grid")
    assert float((gt.rgb - naive.rgb).abs().mean()) <= 2e-3


def test_skipping_drops_only_empty_samples(blob):
    cam, _, _ = scene_of(blob, size=32)
    scene = RenderScene(blob, TF, cell=8)
    a = scene.render("gt", cam, light=LIGHT, skip=True)
    b = scene.render("gt", cam, light=LIGHT, skip=False)
    assert a.counters.primary_samples < 0.8 * b.counters.primary_samples
    assert float((a.rgb - b.rgb).abs().max()) <= 1e-6


def test_inference_batches_never_exceed_batch(blob):
    cam, scalar, vox = scene_of(blob, size=32)
    sizes = []

    class Spy:
        def value(self, p):
            sizes.append(len(p))
            return scalar.value(p)

    shadow = MarchedShadow(Spy(), TF, blob.extent, vox, batch=128)
    render(cam, Spy(), TF, blob.extent, vox, light=LIGHT, shadow=shadow, batch=128)
    assert max(sizes) <= 128 and len(sizes) > 10


@pytest.mark.parametrize("gib, batch", [(80, 1 << 22), (40, 1 << 21), (8, 1 << 19), (1, 1 << 18), (640, 1 << 22)])
def test_cuda_batch_follows_the_device_memory(monkeypatch, gib, batch):
    """A GPU's batch is the largest power of two within 1/12 of its memory, clamped to [2^18, 2^22]; an
    explicit batch wins; the CPU keeps its cache-sized default."""
    class Props:
        total_memory = gib * 2**30

    monkeypatch.setattr(torch.cuda, "get_device_properties", lambda device: Props)
    assert MarchPlan.for_device(torch.device("cuda")).batch == batch
    assert MarchPlan.for_device(torch.device("cuda"), batch=4096).batch == 4096
    assert MarchPlan.for_device(torch.device("cpu")).batch == 1 << 16


def test_constant_shadow_inr_scales_colour_by_the_authors_formula(blob):
    cam, scalar, vox = scene_of(blob)
    cfg = SirenConfig(16, 1)
    layout = WeightLayout.for_siren(cfg)
    p = init_siren(cfg, torch.Generator().manual_seed(0))
    g = 0.3
    p["last.weight"].zero_()
    p["last.bias"].fill_(2 * g - 1)  # output ½·b + ½ = g everywhere
    scene = RenderScene(blob, TF)
    inr = scene.render("inr", cam, light=LIGHT, siren=(layout.flatten(p), layout, cfg.blocks), scalar="grid")
    plain = scene.render("noshadow", cam, background=0.0)
    inr0 = scene.render("inr", cam, light=LIGHT, siren=(layout.flatten(p), layout, cfg.blocks), scalar="grid",
                        background=0.0)
    assert torch.allclose(inr0.rgb, plain.rgb * (0.1 + 0.9 * g), atol=1e-6)
    assert torch.allclose(inr.alpha, plain.alpha)


def test_an_inr_frame_reuses_the_last_frames_shadow_inr_only_for_the_same_weights(blob, monkeypatch):
    """Frames of one light (the viewer orbiting it) build its shadow INR once: the same image from the one built
    before, and other weights, however given (an array, a tensor, float64), a new one whose image is theirs."""
    from diffshadow.render import scene as scene_module

    cam = scene_of(blob)[0]
    (a, layout, blocks), b = shadow_inr(0), shadow_inr(1)[0]
    built = []
    real = scene_module.SirenShadow

    def counted(*args):
        built.append(args[0])
        return real(*args)

    monkeypatch.setattr(scene_module, "SirenShadow", counted)
    scene, fresh = RenderScene(blob, TF), RenderScene(blob, TF)

    def frame(rs, w):
        return rs.render("inr", cam, light=LIGHT, siren=(w, layout, blocks), scalar="grid").rgb

    first = frame(scene, a)
    assert torch.equal(frame(scene, a.numpy()), first) and torch.equal(frame(scene, a.double()), first)
    assert len(built) == 1
    other = frame(scene, b)
    assert len(built) == 2 and not torch.equal(other, first) and torch.equal(other, frame(fresh, b))
    assert torch.equal(frame(scene, a), first) and len(built) == 4  # the last frame's only, not every one seen


def test_a_view_under_another_light_is_drawn_from_its_kept_samples_to_the_byte(blob):
    """A scene that keeps samples draws a view it has marched again under any light from them (only the shadow
    evaluated): every mode's image and counters are a fresh scene's, to the byte."""
    cam = scene_of(blob, size=20)[0]
    siren = shadow_inr()
    keeping, fresh = RenderScene(blob, TF, keep_samples=1 << 26), RenderScene(blob, TF)
    lights = [LIGHT, (-0.6, 0.2, 0.7), (0.1, 0.9, -0.3)]
    for mode in ("noshadow", "gt", "inr", "naive"):
        for i, light in enumerate(lights):
            kw = {"light": light, "siren": siren, "scalar": "grid", "batch": 512}
            img, want = keeping.render(mode, cam, **kw), fresh.render(mode, cam, **kw)
            assert img.replayed == (i > 0 or mode != "noshadow") and not want.replayed, (mode, i)
            assert torch.equal(img.rgb, want.rgb) and torch.equal(img.alpha, want.alpha), (mode, i)
            assert img.counters == want.counters and img.samples is None  # the scene holds them, not the image
    assert len(keeping._samples) == 1  # one view: every mode's frames share its samples


def test_kept_samples_stay_within_the_scenes_budget_and_only_serve_their_own_view(blob, monkeypatch):
    from diffshadow.render import scene as scene_module

    cam, other = scene_of(blob, size=16)[0], Camera.orbit(blob.extent, azimuth=100, elevation=10, size=16)
    scene = RenderScene(blob, TF, keep_samples=1 << 26)
    held = []  # what the scene holds as each frame starts: a view to be kept is made room for before it marches
    real = scene_module.render
    monkeypatch.setattr(scene_module, "render", lambda *a, **k: held.append(len(scene._samples)) or real(*a, **k))
    scene.render("gt", cam, light=LIGHT)
    one = next(iter(scene._samples.values())).nbytes
    # another camera, step or shading is marched; Phong shading keeps nothing (the light lights every sample)
    assert not scene.render("gt", other, light=LIGHT).replayed
    assert not scene.render("gt", cam, light=LIGHT, step=0.25).replayed
    assert not scene.render("gt", cam, light=LIGHT, phong=True).replayed
    assert scene.render("gt", cam, light=LIGHT).replayed
    assert len(scene._samples) == 3
    scene.keep_views(int(1.5 * one))  # room for one view: the last stays, and a new one pushes it out
    assert len(scene._samples) == 1
    third = Camera.orbit(blob.extent, azimuth=-60, elevation=30, size=16)
    scene.render("gt", third, light=LIGHT)
    assert held[-1] == 0  # the older view dropped before the march, not after it
    assert len(scene._samples) == 1 and scene.render("gt", third, light=(-0.6, 0.2, 0.7)).replayed
    assert not scene.render("gt", cam, light=LIGHT).replayed
    small = RenderScene(blob, TF, keep_samples=one // 2)  # a frame past the budget keeps nothing
    small.render("gt", cam, light=LIGHT)
    assert not small._samples and not small.render("gt", cam, light=LIGHT).replayed


def test_a_replayed_frame_is_given_up_when_its_interrupt_says_so(blob):
    cam = scene_of(blob, size=16)[0]
    scene = RenderScene(blob, TF, keep_samples=1 << 26)
    first = scene.render("gt", cam, light=LIGHT, batch=256)
    never = Asker()
    again = scene.render("gt", cam, light=LIGHT, batch=256, interrupt=never)
    assert again.replayed and torch.equal(again.rgb, first.rgb) and never.asked == first.counters.iterations > 2
    stop = Asker(2)
    with pytest.raises(Interrupted):
        scene.render("gt", cam, light=(-0.6, 0.2, 0.7), batch=256, interrupt=stop)
    assert stop.asked == 2


@pytest.mark.parametrize("mode", ["noshadow", "gt", "inr", "naive"])
def test_a_repeated_frame_builds_from_host_numbers_only_its_camera_and_light(blob, mode):
    """On a GPU each tensor built from host numbers is a copy the host waits for: a frame builds one for the
    camera's vectors and one for the light (mode noshadow: no light), nothing per iteration or per sample."""
    from diffshadow.bench.profile import op_counts

    cam = scene_of(blob, size=12)[0]
    siren = shadow_inr()
    scene = RenderScene(blob, TF)

    def frame():
        return scene.render(mode, cam, light=LIGHT, siren=siren, scalar="grid")

    first = frame().rgb  # the scene's caches (grids, the shadow INR) are made at the first frame
    counts = op_counts(frame)
    assert counts["host_tensors"] == (1 if mode == "noshadow" else 2), counts
    assert torch.equal(frame().rgb, first)


@pytest.mark.parametrize("mode", ["noshadow", "gt", "inr", "naive"])
def test_a_frame_counted_a_march_iteration_at_a_time_counts_what_it_counts_whole(blob, mode):
    """`bench render` records a frame in pieces, cut at every march iteration through the frame's `interrupt`
    (a naive tooth frame's events held at once took 10 GB): the same ops, syncs, host tensors and peak bytes."""
    from diffshadow.bench.profile import op_counts

    cam = scene_of(blob, size=12)[0]
    scene = RenderScene(blob, TF)
    kwargs = {"light": LIGHT, "siren": shadow_inr(), "scalar": "grid"}
    scene.render(mode, cam, **kwargs)  # the scene's caches are made at the first frame
    cpu = torch.device("cpu")
    whole = op_counts(lambda: scene.render(mode, cam, **kwargs), memory=cpu)
    pieces = op_counts(lambda cut: scene.render(mode, cam, interrupt=cut, **kwargs), memory=cpu, pieces=True)
    assert pieces == whole and whole["ops"] > 0, (pieces, whole)


def test_the_naive_frame_counted_apart_is_the_frame_the_bench_counts(blob):
    """The workflow counts the naive frame in a job of its own (`bench naive-counts`, beside stage 1) and the
    benchmark takes its counts: the same ops, syncs, host tensors and peak bytes as counted in the bench's own
    process, after its other frames; a record of another frame (size, step, light, kernel) is refused, naming it."""
    from diffshadow.bench.render import bench_render, naive_counts

    light = np.asarray(LIGHT) / np.linalg.norm(LIGHT)
    kw = dict(sizes=(12, 16), repeats=1, memory_sizes=[], curve_steps=(1.0,), log=lambda m: None)
    inline = bench_render(RenderScene(blob, TF), shadow_inr(), light, **kw)
    apart = naive_counts(RenderScene(blob, TF), light, size=12)  # a fresh scene, as in a process of its own
    taken = bench_render(RenderScene(blob, TF), shadow_inr(), light, naive=apart, **kw)
    assert inline["naive_counted"] == "here" and taken["naive_counted"] == "apart (bench naive-counts)"
    assert taken["sizes"]["12"]["counts"] == inline["sizes"]["12"]["counts"]
    assert taken["sizes"]["12"]["peak_mem_bytes"] == inline["sizes"]["12"]["peak_mem_bytes"]
    assert inline["sizes"]["12"]["counts"]["naive"]["ops"] > 0 and "naive" not in inline["sizes"]["16"]["counts"]
    for key, value, named in (("size", 16, "size 16 (this bench: 12)"), ("step", 0.25, "step 0.25"),
                              ("light", [0.0, 0.0, 1.0], "light [0.0, 0.0, 1.0]"),
                              ("networks", {"kernel": "fused", "used": "eager"}, "networks")):
        with pytest.raises(ValueError, match=re.escape(f"--naive-counts: counted another frame than this bench's "
                                                       f"smallest: {named}")):
            bench_render(RenderScene(blob, TF), shadow_inr(), light, naive={**apart, key: value}, **kw)


def test_empty_and_opaque_extremes():
    vol = Volume(data=np.zeros((9, 9, 9), np.float32), extent=np.ones(3), name="zero")
    cam = Camera.orbit(vol.extent, azimuth=0, elevation=0, size=8)
    img = RenderScene(vol, TF).render("gt", cam, light=LIGHT)
    assert torch.all(img.rgb == 1.0) and torch.all(img.alpha == 0)
    dense = TransferFunction.from_config({**TF.to_config(), "density_scale": 1e6})
    full = Volume(data=np.ones((9, 9, 9), np.float32), extent=np.ones(3), name="one")
    img = RenderScene(full, dense).render("gt", cam, light=LIGHT)
    hit = img.alpha > 0  # the corner pixels miss the box
    assert torch.isfinite(img.rgb).all() and hit.sum() > 10 and float(img.alpha[hit].min()) > 0.999


def test_camera_geometry():
    cam = Camera.orbit([1.0, 0.5, 0.25], azimuth=90, elevation=0, distance=2.0, size=(5, 3))
    o, d = cam.rays()
    assert o.shape == d.shape == (15, 3)
    assert torch.allclose(d.norm(dim=1), torch.ones(15))
    centre = d[7]  # the middle pixel looks at the box centre
    to_target = torch.tensor(cam.target) - torch.tensor(cam.eye)
    assert torch.allclose(centre, (to_target / to_target.norm()).float(), atol=1e-6)
    assert math.isclose(float(np.linalg.norm(np.subtract(cam.eye, cam.target))), 2.0 * math.hypot(0.5, 0.25, 0.125))
    # row 0 is the top of the image: its rays point further up (z) than the last row's
    assert d[0, 2] > d[-1, 2]
    # on the device asked for, in float32
    with default_device_meta():
        om, dm = cam.rays(torch.device("meta"))
    assert om.device.type == dm.device.type == "meta" and dm.shape == (15, 3) and dm.dtype == torch.float32


def test_a_camera_looking_along_z_takes_y_up_unless_told():
    """`render --eye --target` straight down or up: +y up, as the orbit camera takes it (it was an error: the
    default +z up is parallel to the view); an up given is kept, and one parallel to the view is refused."""
    down = Camera.look_at((0.5, 0.5, 2.0), (0.5, 0.5, 0.5), size=8)
    assert down.up == (0.0, 1.0, 0.0) and down.rays()[1].isfinite().all()
    assert Camera.look_at((2.0, 0.5, 0.5), (0.5, 0.5, 0.5)).up == (0.0, 0.0, 1.0)
    assert Camera.orbit([1.0, 1.0, 1.0], azimuth=0, elevation=90).up == (0.0, 1.0, 0.0)
    assert Camera.look_at((0.5, 0.5, 2.0), (0.5, 0.5, 0.5), up=(1.0, 0.0, 0.0)).up == (1.0, 0.0, 0.0)
    with pytest.raises(RenderError, match=r"up \(0.0, 0.0, 1.0\) is parallel to the view direction"):
        Camera.look_at((0.5, 0.5, 2.0), (0.5, 0.5, 0.5), up=(0.0, 0.0, 1.0)).rays()


@pytest.mark.parametrize("kwargs, match", [
    ({"fov": 0.0}, "fov"),
    ({"fov": 180.0}, "fov"),
    ({"eye": (0.5, 0.5, 0.5)}, "must differ"),
])
def test_camera_rejects_bad_input(kwargs, match):
    args = {"eye": (2.0, 0.5, 0.5), "target": (0.5, 0.5, 0.5), **kwargs}
    with pytest.raises(RenderError, match=match):
        Camera(**args)


@pytest.mark.parametrize("kwargs, match", [
    ({"fov": 0.0}, r"fov: expected degrees in \(0, 180\), got 0.0"),
    ({"size": 0}, "image size: expected positive, got 0x0"),
    ({"size": (16, 0)}, "image size: expected positive, got 16x0"),
])
def test_the_framed_and_orbit_views_name_a_bad_fov_size_or_distance(kwargs, match):
    """framed() divides by the view's angle and aspect before it makes a camera: named, not a ZeroDivisionError."""
    with pytest.raises(RenderError, match=match):
        Camera.framed(((0.5, 0.5, 0.5), 0.3), **kwargs)
    with pytest.raises(RenderError, match="distance: expected a positive number of box half-diagonals, got -1"):
        Camera.orbit((1.0, 1.0, 1.0), azimuth=30, elevation=20, distance=-1)


@pytest.mark.parametrize("elevation", [95.0, -90.5, math.nan])
def test_an_orbit_past_a_pole_is_named_not_drawn_from_the_other_side(elevation):
    """An elevation past ±90° orbits over the pole: the image of azimuth + 180° upside down, not the view asked for
    (`render --elevation 95` drew it). Named, as a non-finite azimuth; the pole itself looks straight down."""
    with pytest.raises(RenderError, match=rf"camera elevation: expected degrees in \[-90, 90\], got {elevation}"):
        Camera.orbit((1.0, 1.0, 1.0), azimuth=30, elevation=elevation)
    with pytest.raises(RenderError, match=rf"camera elevation: expected degrees in \[-90, 90\], got {elevation}"):
        Camera.framed(((0.5, 0.5, 0.5), 0.3), elevation=elevation)
    with pytest.raises(RenderError, match="camera azimuth: expected finite degrees, got inf"):
        Camera.orbit((1.0, 1.0, 1.0), azimuth=math.inf, elevation=20)
    top = Camera.orbit((1.0, 1.0, 1.0), azimuth=30, elevation=90)
    assert np.allclose(np.subtract(top.target, top.eye)[:2], 0) and top.target[2] < top.eye[2]


def test_render_rejects_bad_input(blob):
    cam, scalar, vox = scene_of(blob, size=4)
    scene = RenderScene(blob, TF)
    with pytest.raises(RenderError, match="mode"):
        scene.render("shadowy", cam, light=LIGHT)
    with pytest.raises(RenderError, match="light"):
        scene.render("gt", cam)
    with pytest.raises(RenderError, match="data INR"):
        scene.render("noshadow", cam, scalar="inr")
    with pytest.raises(RenderError, match="shadow INR"):
        scene.render("inr", cam, light=LIGHT)
    with pytest.raises(RenderError, match="step"):
        render(cam, scalar, TF, blob.extent, vox, step=0.0)
    with pytest.raises(RenderError, match="step: 1e-09 voxels is finer than the finest step marched"):
        render(cam, scalar, TF, blob.extent, vox, step=1e-9)
    diagonal = float(np.linalg.norm(blob.extent)) / vox  # voxels
    with pytest.raises(RenderError, match=r"longer than the volume's diagonal \(\d+ voxels\): a ray would take one"):
        render(cam, scalar, TF, blob.extent, vox, step=diagonal * 1.01)
    render(cam, scalar, TF, blob.extent, vox, step=diagonal * 0.99)  # one sample a ray, at most: still allowed
    # a camera so far from its target that float32 rays cannot resolve a step (a 1e-6° field of view, framed,
    # once gave an empty image silently); 0.1° still frames the volume from close enough
    sphere = ((0.5, 0.5, 0.5), 0.5)
    for far in (lambda: Camera.framed(sphere, fov=1e-6),
                lambda: Camera.orbit(blob.extent, azimuth=0, elevation=0, distance=1e308)):
        with pytest.raises(RenderError, match=r"^camera: the eye is (\d\.\d+e\+07|over 1e308) box lengths from its"):
            far()
    assert Camera.framed(sphere, fov=0.1).fov == 0.1


def test_a_frame_is_given_up_when_its_interrupt_says_so_and_is_the_same_image_when_it_does_not(blob):
    """`interrupt` (the viewer's "the view changed") is asked before every iteration of the primary rays, and of
    the naive baseline's secondary rays; a frame it never stops is the same image, and once it says stop the frame
    ends with `Interrupted` without asking again."""
    cam, scalar, vox = scene_of(blob, size=32)
    macro = MacroGrid.build(blob, TF, cell=8)

    def frame(shadowed: bool, interrupt=None):
        shadow = MarchedShadow(scalar, TF, blob.extent, vox, macro=macro, batch=256) if shadowed else None
        return render(cam, scalar, TF, blob.extent, vox, light=LIGHT, shadow=shadow, macro=macro, batch=256,
                      interrupt=interrupt)

    for shadowed in (False, True):
        plain, never = frame(shadowed), Asker()
        kept = frame(shadowed, never)
        assert torch.equal(kept.rgb, plain.rgb) and torch.equal(kept.alpha, plain.alpha)
        if shadowed:  # the secondary rays' iterations are asked too
            assert never.asked > 2 * plain.counters.iterations, (never.asked, plain.counters.iterations)
        else:
            assert never.asked == plain.counters.iterations > 10
        for stop_at in (1, never.asked // 2):
            stop = Asker(stop_at)
            with pytest.raises(Interrupted):
                frame(shadowed, stop)
            assert stop.asked == stop_at


def test_whole_ray_kernels_are_asked_before_every_tile():
    """The fused path (`_whole_rays`): `interrupt` is asked before each tile's kernel, which does not run once it
    says stop."""
    n = 40
    o = torch.zeros(n, 3)
    d = torch.tensor([[1.0, 0.0, 0.0]]).expand(n, 3).contiguous()
    t0, t1 = torch.zeros(n), torch.ones(n)
    plan = MarchPlan(batch=64, min_samples=8)  # tiles of 8 rays: 5 tiles
    marched = []

    def march(sl, runs: Runs):
        marched.append(sl.start)
        return torch.ones(len(o[sl]), dtype=torch.int64), torch.ones(1, dtype=torch.int64), 1

    never = Asker()
    assert _whole_rays(o, d, t0, t1, 0.1, None, plan, march, never)[0] == 5
    assert never.asked == 5 and marched == [0, 8, 16, 24, 32]
    marched.clear()
    with pytest.raises(Interrupted):
        _whole_rays(o, d, t0, t1, 0.1, None, plan, march, Asker(3))
    assert marched == [0, 8]


def test_a_gt_frame_is_given_up_while_its_shadow_grid_is_marched_and_caches_nothing(blob):
    """Mode `gt` marches its exact shadow grid first (10-16 s for a 128³ volume on 2 CPU cores): `interrupt` is
    asked there too, a grid given up is not cached, and the next frame is the same image as one never asked."""
    cam, _, _ = scene_of(blob, size=16)
    plain = RenderScene(blob, TF, cell=8).render("gt", cam, light=LIGHT)
    scene = RenderScene(blob, TF, cell=8)
    with pytest.raises(Interrupted):
        scene.render("gt", cam, light=LIGHT, interrupt=Asker(1))
    assert not scene.has_gt(LIGHT)
    never = Asker()
    kept = scene.render("gt", cam, light=LIGHT, interrupt=never)
    assert torch.equal(kept.rgb, plain.rgb) and scene.has_gt(LIGHT)
    frame_only = Asker()
    scene.render("gt", cam, light=LIGHT, interrupt=frame_only)  # the grid cached: only the frame's iterations
    assert never.asked > frame_only.asked > 0


def test_a_gt_frame_takes_its_grid_by_the_method_asked_and_caches_each_apart(blob):
    """`gt_method` picks the grid's method for one frame (the viewer's previews: the sweep) without touching the
    scene's own, and `forget_gt` drops both."""
    cam, _, _ = scene_of(blob, size=16)
    scene = RenderScene(blob, TF, cell=8)  # gt_method "march"
    swept = scene.render("gt", cam, light=LIGHT, gt_method="sweep")
    assert scene.has_gt(LIGHT, "sweep") and not scene.has_gt(LIGHT)
    assert torch.equal(swept.rgb, RenderScene(blob, TF, cell=8, gt_method="sweep").render("gt", cam, light=LIGHT).rgb)
    marched = scene.render("gt", cam, light=LIGHT)
    assert scene.has_gt(LIGHT) and not torch.equal(marched.rgb, swept.rgb)
    assert float((marched.rgb - swept.rgb).abs().max()) < 0.05  # two ways to the same shadow
    scene.forget_gt(LIGHT)
    assert not scene.has_gt(LIGHT) and not scene.has_gt(LIGHT, "sweep")


@pytest.mark.parametrize("upsample", [1, 2])
def test_a_gt_frame_marches_only_the_voxels_it_reads_and_is_the_same_image(blob, upsample):
    """Mode `gt` marches its grid at `seen_voxels` alone (11x faster on hydrogen_atom): the same bytes as a frame
    from the grid marched at every voxel, with and without Phong shading and empty-space skipping."""
    from diffshadow.render.fields import GridShadow
    from diffshadow.shadow import seen_voxels
    from diffshadow.volume import refine

    scene = RenderScene(blob, TF, cell=8, gt_upsample=upsample)
    assert float(seen_voxels(blob, TF, upsample).float().mean()) < 0.6
    full = RenderScene(blob, TF, cell=8, gt_upsample=upsample)
    full._cache[full._gt_key(LIGHT, "march")] = GridShadow(
        shadow_grid(refine(blob, upsample), TF, LIGHT, method="march"), blob.extent)
    for phong, skip in ((False, True), (True, False)):
        cam = Camera.orbit(blob.extent, azimuth=40 + 90 * phong, elevation=20, size=24)
        a = scene.render("gt", cam, light=LIGHT, phong=phong, skip=skip)
        b = full.render("gt", cam, light=LIGHT, phong=phong, skip=skip)
        assert torch.equal(a.rgb, b.rgb) and torch.equal(a.alpha, b.alpha)


@pytest.mark.parametrize("mode", ["noshadow", "gt", "naive", "inr"])
def test_rendering_makes_no_tensor_on_the_implicit_default_device(blob, mode):
    """Guard for the CUDA path (see conftest.default_device_meta): the same image with the default device
    "meta" as without."""
    cam, _, _ = scene_of(blob, size=16)
    layout = WeightLayout.for_siren(SirenConfig(8, 1))
    siren = (layout.flatten(init_siren(SirenConfig(8, 1), torch.Generator().manual_seed(0))), layout, 1)
    light = None if mode == "noshadow" else LIGHT
    a = RenderScene(blob, TF, cell=8).render(mode, cam, light=light, siren=siren, phong=mode == "gt")
    with default_device_meta():
        b = RenderScene(blob, TF, cell=8, device="cpu").render(mode, cam, light=light, siren=siren,
                                                                phong=mode == "gt")
    assert torch.equal(a.rgb, b.rgb)


def test_a_prepared_volume_under_another_tf_keeps_its_grid_and_box(tmp_path):
    """`render --volume results/<scene>/volume.zarr --tf-json ...` recolours a finished run: the prepared grid and
    box as they were written, under the TF given. Read as a raw volume, a grid normalised from a value_range was
    normalised again and a box made from a spacing became the voxel counts' box."""
    from diffshadow.artifacts import load_render_scene
    from diffshadow.volume import load_prepared, save_prepared

    data = np.linspace(0.2, 0.7, 5 * 6 * 7, dtype=np.float32).reshape(5, 6, 7)  # a value_range's grid: not 0 to 1
    volume = Volume(data=data, extent=np.array([1.0, 0.4, 0.2]), name="spaced")  # a spacing's box
    tf = TransferFunction.from_config({"opacity": [[0, 0], [1, 1]], "color": [[0, 1, 1, 1], [1, 1, 1, 1]],
                                       "density_scale": 5.0})
    save_prepared(tmp_path / "volume.zarr", volume, tf)
    recolour = {**tf.to_config(), "color": [[0, 1, 0, 0], [1, 0, 0, 1]]}
    scene = load_render_scene(tmp_path / "volume.zarr", None, torch.device("cpu"), recolour)
    assert np.array_equal(scene.volume.data, data) and np.array_equal(scene.volume.extent, volume.extent)
    assert scene.tf.to_config() == recolour and load_prepared(tmp_path / "volume.zarr")[1].to_config() == tf.to_config()
    faint = {**recolour, "density_scale": 1e-6}  # a TF given on the command line is checked as a scene's is
    with pytest.raises(ValueError, match=r"volume.zarr: transfer function: nothing can show: .* raise density_scale"):
        load_render_scene(tmp_path / "volume.zarr", None, torch.device("cpu"), faint)


def test_the_visible_sphere_read_a_slab_at_a_time_holds_the_visible_voxels(monkeypatch):
    """`visible_sphere` (each evaluation view frames it) reads the TF a few planes at a time (every visible voxel's
    coordinates at once were 9.3 GiB on a 512³ volume): two visible voxels give their midpoint and half their
    distance plus a voxel's diagonal, whatever the slab height, and an invisible volume gives the box's sphere."""
    import diffshadow.render.camera as camera
    import diffshadow.volume as volume

    data = np.zeros((7, 5, 9), dtype=np.float32)  # (z, y, x)
    data[1, 4, 2] = data[6, 0, 8] = 1.0
    vol = Volume(data=data, extent=np.array([1.0, 0.5, 0.75]), name="two")  # voxel (1/8, 1/8, 1/8)
    tf = TransferFunction.from_config({"opacity": [[0.0, 0.0], [0.5, 0.0], [1.0, 1.0]],
                                       "color": [[0.0, 1, 1, 1], [1.0, 1, 1, 1]], "density_scale": 1.0})
    a, b = np.array([2, 4, 1]) / 8, np.array([8, 0, 6]) / 8  # (x, y, z) box coordinates
    for planes in (1, 2, 3, 7, 100):
        monkeypatch.setattr(volume, "SLAB_VOXELS", planes * 45)
        center, radius = camera.visible_sphere(vol, tf)
        np.testing.assert_allclose(center, (a + b) / 2, rtol=0, atol=1e-12)
        assert radius == pytest.approx(np.linalg.norm(b - a) / 2 + np.sqrt(3) / 8, abs=1e-12)
    center, radius = camera.visible_sphere(Volume(data=np.zeros_like(data), extent=vol.extent, name="none"), tf)
    np.testing.assert_allclose(center, vol.extent / 2)
    assert radius == pytest.approx(np.linalg.norm(vol.extent) / 2)


def test_an_image_becomes_bytes_rounded_to_the_nearest_level():
    """`Image.to_uint8`: k/255 is level k, a value a hair under or over the midpoint between two levels goes to
    the nearer, anything outside [0, 1] is 0 or 255, and the array is (H, W, 3) uint8 on the host."""
    from diffshadow.render.marcher import Image

    k = torch.arange(256, dtype=torch.float32)
    values = torch.cat([k / 255, (k[:-1] + 0.49) / 255, (k[:-1] + 0.51) / 255, torch.tensor([-0.5, 1.5, 2.0])])
    expect = torch.cat([k, k[:-1], k[:-1] + 1, torch.tensor([0.0, 255.0, 255.0])]).to(torch.uint8).numpy()
    rgb = values[:, None, None].expand(-1, 1, 3)
    out = Image(rgb=rgb, alpha=torch.ones(len(values), 1), seconds=0.0).to_uint8()
    assert out.dtype == np.uint8 and out.shape == (len(values), 1, 3) and isinstance(out, np.ndarray)
    assert np.array_equal(out[:, 0, 0], expect) and np.array_equal(out[..., 0], out[..., 2])
