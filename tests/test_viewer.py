"""The viewer without a browser: which SIREN a light gets (stored row, generated once, cached), how a light is
described, the frame modes, the camera taken from the browser, the command that reproduces a frame, and the
one-line errors. The browser itself is driven in tests/test_workflow.py (test_viewer_in_a_browser)."""

import json
import math
import socket
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from diffshadow.analytic import gaussian_blob
from diffshadow.cli import build_parser
from diffshadow.lights import as_direction
from diffshadow.render import Camera, Interrupted, RenderScene
from diffshadow.siren import SirenConfig, WeightLayout, init_siren
from diffshadow.store import WeightStore
from diffshadow.transfer import TransferFunction
from diffshadow.viewer import ViewerError, ViewerScene, azimuth_elevation, direction
from diffshadow.viewer.app import STEP_UP_S, Session, aim_initial_camera, camera_of, port_problem
from diffshadow.viewer.scene import GENERATED_KEEP
from diffshadow.volume import Volume

TF = TransferFunction.from_config({"opacity": [[0.0, 0.0], [0.2, 0.0], [1.0, 0.8]],
                                   "color": [[0.0, 0.1, 0.3, 0.9], [1.0, 1.0, 0.2, 0.1]], "density_scale": 25.0})
SIREN = SirenConfig(16, 1)
LAYOUT = WeightLayout.for_siren(SIREN)


class CountingSampler:
    """A stand-in for the diffusion model: a SIREN per light, counted."""

    def __init__(self):
        self.calls = 0

    def __call__(self, light):
        self.calls += 1
        seed = int(abs(as_direction(light)[0]) * 1e6)
        return LAYOUT.flatten(init_siren(SIREN, torch.Generator().manual_seed(seed)))


@pytest.fixture(scope="module")
def viewer():
    vol = Volume(data=gaussian_blob(25, 0.15), extent=np.ones(3), name="blob")
    train = np.stack([direction(0, 60), direction(90, 60), direction(180, 60)])
    unseen = np.stack([direction(45, 50)])
    lights = np.concatenate([train, unseen])
    weights = torch.stack([LAYOUT.flatten(init_siren(SIREN, torch.Generator().manual_seed(i)))
                           for i in range(len(lights))]).numpy()
    store = WeightStore(weights=weights, lights=lights, psnr=np.zeros(4), psnr_visible=np.zeros(4), layout=LAYOUT,
                        siren=SIREN, config={"checkpoint": "results/blob/diffusion.ckpt"},
                        seen=np.array([True, True, True, False]))
    return ViewerScene(RenderScene(vol, TF), name="blob", lights={"train": train, "unseen": unseen},
                       generated=store, sampler=CountingSampler(), results=Path("results/blob"),
                       checkpoint=Path("results/blob/diffusion.ckpt"))


CAM = Camera.orbit(np.ones(3), azimuth=30, elevation=25, size=(20, 16))


def test_the_initial_camera_is_the_start_view_in_visers_own_fields():
    """A new tab and "Reset View" get the start view, up vector and all, each sent to the browser: viser's
    initial camera takes fields that a misnamed one would not set (a new attribute, silently)."""
    import viser

    sent = []
    initial = viser.InitialCameraConfig(sent.append)
    start = Camera.look_at((2.0, -1.0, 0.5), (0.5, 0.5, 0.5), up=(0.0, 1.0, 0.0), fov=50.0, size=16)
    aim_initial_camera(initial, start)
    assert np.allclose(initial.position, start.eye) and np.allclose(initial.look_at, start.target)
    assert initial.up is not None and np.allclose(initial.up, (0.0, 1.0, 0.0))
    assert initial.fov == pytest.approx(math.radians(50.0))
    assert sorted(type(m).__name__ for m in sent) == ["SetCameraFovMessage", "SetCameraLookAtMessage",
                                                       "SetCameraPositionMessage", "SetCameraUpDirectionMessage"]


def test_azimuth_elevation_round_trip():
    for az, el in ((0, 0), (30, 25), (-120, -60), (179, 89)):
        assert np.allclose(azimuth_elevation(direction(az, el)), (az, el))
    assert np.allclose(direction(0, 90), (0, 0, 1), atol=1e-12)


def test_lights_are_described_by_kind_and_angle(viewer):
    assert viewer.light_info(viewer.train[1]).describe() == "training light 1, 0.0° from the nearest training light"
    info = viewer.light_info(viewer.unseen[0])
    assert (info.kind, info.index) == ("unseen", 0)
    # 45° azimuth at 50° elevation against the training lights at 0° and 90° azimuth, 60° elevation
    expected = math.degrees(math.acos(float(np.clip(direction(45, 50) @ direction(0, 60), -1, 1))))
    assert info.nearest_deg == pytest.approx(expected, abs=1e-9)
    assert viewer.light_info(direction(10, -30)).kind == "new"


def test_listed_lights_use_their_stored_row_and_new_ones_are_generated_once(viewer):
    sampler = viewer.sampler
    before = sampler.calls
    w, info = viewer.shadow_weights(viewer.unseen[0])
    assert torch.equal(w, torch.as_tensor(viewer.generated.weights[3])) and info.generate_s is None
    assert sampler.calls == before
    new = direction(12, 34)
    w1, info1 = viewer.shadow_weights(new)
    w2, info2 = viewer.shadow_weights(new)
    assert sampler.calls == before + 1 and torch.equal(w1, w2)
    assert info1.kind == "new" and info1.generate_s is not None and info2.generate_s is None


def test_generated_sirens_kept_are_bounded(viewer):
    for i in range(GENERATED_KEEP + 5):
        viewer.shadow_weights(direction(0.5 * i, -10))
    assert len(viewer._made) == GENERATED_KEEP


def test_frames_of_every_mode(viewer):
    light = viewer.unseen[0]
    images = {m: viewer.frame(m, CAM, light, step=1.0) for m in viewer.modes if m != "naive"}
    for mode, (img, _) in images.items():
        assert img.dtype == np.uint8 and img.shape == (16, 20, 3), mode
    assert not np.array_equal(images["inr"][0], images["noshadow"][0])  # the shadow darkens the blob
    with pytest.raises(ViewerError, match="mode: expected one of"):
        viewer.frame("shadows", CAM, light, step=1.0)


@pytest.mark.parametrize("mode", ["inr", "inr | gt"])
def test_a_frame_given_up_leaves_nothing_behind(viewer, mode):
    """A still frame the viewer gives up for a newer view (`interrupt`) raises `Interrupted`, and the next frame of
    the same view is the same bytes as one never interrupted."""
    light = viewer.unseen[0]
    before, _ = viewer.frame(mode, CAM, light, step=1.0)
    asked = []
    with pytest.raises(Interrupted):
        viewer.frame(mode, CAM, light, step=1.0, interrupt=lambda: not asked.append(1))
    assert len(asked) == 1
    after, _ = viewer.frame(mode, CAM, light, step=1.0)
    assert np.array_equal(before, after)


def test_a_scene_without_a_cache_offers_noshadow_and_gt():
    vol = Volume(data=gaussian_blob(17, 0.2), extent=np.ones(3), name="blob")
    bare = ViewerScene(RenderScene(vol, TF), name="blob")
    assert bare.modes == ("noshadow", "gt")
    with pytest.raises(ViewerError, match="mode: expected one of noshadow, gt, got 'inr'"):
        bare.frame("inr", CAM, direction(0, 45), step=1.0)


def still_rungs(seconds_per_pixel: float | None, full: int = 480, version: int = 1, state=None) -> list[int]:
    """A tab's still-frame heights (`Session._rungs`) for a square canvas, where its last still frame cost
    `seconds_per_pixel` (None: nothing drawn yet)."""
    tab = state or SimpleNamespace(rungs=(-1, []), per_pixel={}, still_per_pixel={},
                                   client=SimpleNamespace(camera=SimpleNamespace(aspect=1.0)))
    if seconds_per_pixel is not None:
        tab.per_pixel["inr"] = tab.still_per_pixel["inr"] = seconds_per_pixel
    tab._preview_height = lambda mode, height: Session._preview_height(tab, mode, height)
    return Session._rungs(tab, version, "inr", full)


def test_a_long_still_frame_is_drawn_at_a_quarter_of_its_height_first():
    """Each rung before the full frame is a quarter of the next, added while the next is predicted to take over
    STEP_UP_S, and stays above the preview's height; a fast frame (a GPU) is drawn whole at once."""
    assert still_rungs(None) == [480]  # no cost known yet
    assert still_rungs(0.9 * STEP_UP_S / 480 ** 2) == [480]
    assert still_rungs(22.0 / 480 ** 2) == [120, 480]  # 2 CPU cores: 22 s at 480², 1.4 s at 120²
    assert still_rungs(22.0 / 480 ** 2, full=1920) == [120, 480, 1920]
    # however slow, no rung at or under the preview's height (32 px here: a quarter of 120 is not drawn)
    assert still_rungs(1e3 / 480 ** 2, full=1920) == [120, 480, 1920]
    # the rungs of one view are kept while they are drawn (the loop takes them off); a new view gets its own
    tab = SimpleNamespace(rungs=(-1, []), per_pixel={}, still_per_pixel={},
                          client=SimpleNamespace(camera=SimpleNamespace(aspect=1.0)))
    first = still_rungs(22.0 / 480 ** 2, state=tab)
    first.pop(0)
    assert still_rungs(22.0 / 480 ** 2, state=tab) == [480]
    assert still_rungs(22.0 / 480 ** 2, version=2, state=tab) == [120, 480]


@pytest.mark.parametrize("mode", ["gt", "inr | gt"])
def test_a_preview_takes_the_quick_sweep_until_the_light_is_marched(viewer, mode):
    """While the light moves, a light whose exact shadow is not marched yet is previewed with the shear sweep's
    grid (under a second where the march takes 10-16 s on a 128³ volume), and the notes say so; the still frame
    marches it (what `diffshadow render --mode gt` draws), and the previews after it use the march."""
    light, scene = direction(33, 47), viewer.scene
    scene.forget_gt(light)
    quick, notes = viewer.frame(mode, CAM, light, step=1.0, preview=True)
    assert notes["exact_by"] == "sweep" and scene.has_gt(light, "sweep") and not scene.has_gt(light)
    swept = scene.render("gt", CAM, light=light, step=1.0, gt_method="sweep").to_uint8()
    still, notes = viewer.frame(mode, CAM, light, step=1.0)
    assert notes["exact_by"] == "march" and scene.has_gt(light)
    marched = scene.render("gt", CAM, light=light, step=1.0).to_uint8()
    if mode == "gt":
        assert np.array_equal(quick, swept) and np.array_equal(still, marched) and not np.array_equal(quick, still)
    again, notes = viewer.frame(mode, CAM, light, step=1.0, preview=True)
    assert notes["exact_by"] == "march" and np.array_equal(again, still)
    scene.forget_gt(light)


def test_a_frames_cost_per_pixel_leaves_out_the_exact_shadows_grid(viewer, tmp_path, monkeypatch):
    """The grid is paid once per light: what predicts the next frame's size (`Session.per_pixel`) is the frame's
    seconds less the grid's, and a preview drawn with the sweep says so in the status. The still frame of the same
    view is drawn from the preview's kept samples, which predict no other view: the cost stays the preview's. A
    preview is drawn on one of PyTorch's threads, a still frame on all."""
    threads, frame = [], viewer.frame
    monkeypatch.setattr(viewer, "frame", lambda *a, **k: threads.append(torch.get_num_threads()) or frame(*a, **k))
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    light = direction(-33, 52)
    viewer.scene.forget_gt(light)
    browser = SimpleNamespace(position=np.array([2.0, 1.0, 1.5]), look_at=np.full(3, 0.5),
                              up_direction=np.array([0.0, 0.0, 1.0]), fov=math.radians(50.0), aspect=1.25,
                              image_width=20, image_height=16)
    tab = SimpleNamespace(mode=SimpleNamespace(value="gt"), step=SimpleNamespace(value=1.0), light=light,
                          client=SimpleNamespace(camera=browser, scene=SimpleNamespace(
                              set_background_image=lambda *a, **k: None)),
                          viewer=viewer, run=lambda fn, *a, **k: fn(*a, **k), gt_light=None, version=1,
                          per_pixel={}, still_per_pixel={}, frames=0, gizmo=None, charted=light, record=tmp_path,
                          status=SimpleNamespace(content=""), light_note=SimpleNamespace(content=""),
                          command=SimpleNamespace(content=""))
    for name in ("_log_frame", "_notes", "_record"):
        setattr(tab, name, getattr(Session, name).__get__(tab))
    for kind in ("preview", "full"):
        assert Session._draw(tab, kind, 1, 16)
        entry = json.loads((tmp_path / "frames.jsonl").read_text().splitlines()[-1])
        assert entry["kind"] == kind and entry["exact_by"] == ("sweep" if kind == "preview" else "march")
        assert entry["replayed"] == (kind == "full")
        if kind == "preview":
            marched = entry
        assert tab.per_pixel["gt"] * 20 * 16 == pytest.approx(marched["seconds"] - marched["grid_s"], rel=1e-6)
        assert "gt" not in tab.still_per_pixel  # neither a preview's cost nor one from kept samples
        assert ("exact shadow by the quick sweep while moving" in tab.status.content) == (kind == "preview")
    assert threads == [1, 2] and torch.get_num_threads() == 2
    torch.set_num_threads(before)
    viewer.scene.forget_gt(light)


def test_a_view_first_seen_still_gets_a_preview_if_its_still_frame_marches_a_new_lights_shadow(viewer):
    """`Session._kind`: a preview while the view changes (once), the still frame once it has been still for STILL_S;
    but a view the loop first sees already still (the previous frame took longer than STILL_S) gets a preview
    first where its still frame must march a new light's exact shadow, so the canvas shows the new light at once."""
    from diffshadow.viewer.app import STILL_S

    light = direction(71, 33)
    viewer.scene.forget_gt(light)
    tab = SimpleNamespace(drawn={"full": 1, "preview": 1}, viewer=viewer, mode=SimpleNamespace(value="gt"),
                          light=light)
    assert Session._kind(tab, 2, 0.0) == "preview"
    assert Session._kind(tab, 1, 0.0) is None  # its preview drawn: wait until still
    assert Session._kind(tab, 2, STILL_S) == "preview"  # first seen still, the grid not marched yet
    tab.drawn["preview"] = 2
    assert Session._kind(tab, 2, STILL_S) == "full"
    for mode in ("noshadow", "inr"):  # no grid to march: straight to the still frame
        tab.mode.value = mode
        assert Session._kind(tab, 3, STILL_S) == "full"
    tab.mode.value = "inr | gt"
    assert Session._kind(tab, 3, STILL_S) == "preview"
    viewer.frame("gt", CAM, light, step=1.0)  # marched
    assert Session._kind(tab, 3, STILL_S) == "full"
    viewer.scene.forget_gt(light)


def test_the_render_command_reproduces_the_camera_and_the_light(viewer):
    light = direction(12, 34)
    cmd = viewer.render_command("inr", CAM, light, step=0.75)
    a = build_parser().parse_args(cmd.split()[1:])
    assert (a.mode, a.step, a.size, a.diffusion) == ("inr", 0.75, [20, 16], "results/blob/diffusion.ckpt")
    assert np.allclose(a.eye, CAM.eye) and np.allclose(a.target, CAM.target) and np.allclose(a.light, light)
    stored = build_parser().parse_args(viewer.render_command("inr", CAM, viewer.unseen[0], step=0.5).split()[1:])
    assert (stored.weights, stored.light_index) == ("results/blob/generated.zarr", 3)


def test_a_mixed_cache_names_its_share_and_its_render_command_mixes_the_same_way(viewer):
    """With sample_shadows' mix, a new direction's SIREN is the model's and the stored SIRENs' blend mixed at the
    run's share, and the panel's command asks `render` for the same mix; a blend of a codec's store names the
    codec."""
    from diffshadow.diffusion.mix import MixedSampler, mix_weights
    from diffshadow.store import BlendSampler

    class Model(CountingSampler):
        layout, siren, region, extinction = LAYOUT, SIREN, None, None

    g = viewer.generated
    stored = WeightStore(weights=g.weights[:3], lights=viewer.train, psnr=np.zeros(3), psnr_visible=np.zeros(3),
                         layout=LAYOUT, siren=SIREN, config={})
    blend = BlendSampler(stored, 2, "triangle")
    mixed = ViewerScene(viewer.scene, name="blob", lights={"train": viewer.train, "unseen": viewer.unseen},
                        generated=g, sampler=MixedSampler(Model(), blend, 0.7), results=Path("results/blob"),
                        checkpoint=Path("results/blob/diffusion.ckpt"), stored=Path("results/blob/weights.zarr"))
    assert mixed.cache_name == "diffusion 0.7 + weight blend 0.3"
    for share, name in ((0.0, "weight blend, model share 0"), (1.0, "diffusion, model share 1")):
        mixed.sampler = MixedSampler(Model(), blend, share)  # one side alone: named as that side, not a mix
        assert mixed.cache_name == name
    for config, name in (({}, "weight blend"), ({"codec": "fp16"}, "weight blend, fp16")):  # a codec's store
        mixed.sampler = BlendSampler(WeightStore(**{**vars(stored), "config": config}), 2, "triangle")
        assert mixed.cache_name == name
    from diffshadow.correction import BlendCorrection, make_net

    fix = BlendCorrection(make_net(LAYOUT.n_params, 4, 1), torch.ones(LAYOUT.n_params), viewer.train, 1)
    mixed.sampler = MixedSampler(Model(), BlendSampler(stored, 2, "triangle", fix), 0.0)
    assert mixed.cache_name == "corrected blend, model share 0"  # the blend's correction is said
    mixed.sampler = MixedSampler(Model(), blend, 0.7)
    new = direction(21, 40)
    w, info = mixed.shadow_weights(new)
    expected = mix_weights(np.asarray(Model()(new))[None], blend(new)[None], 0.7)[0]
    assert info.kind == "new" and np.array_equal(w.numpy(), expected)
    a = build_parser().parse_args(mixed.render_command("inr", CAM, new, step=0.75).split()[1:])
    assert (a.diffusion, a.blend, a.blend_k, a.model_share) == ("results/blob/diffusion.ckpt",
                                                                "results/blob/weights.zarr", 2, 0.7)


def test_camera_of_a_browser_camera():
    eye, target = np.array([2.0, 1.0, 1.5]), np.array([0.5, 0.5, 0.5])
    browser = SimpleNamespace(position=eye, look_at=target, up_direction=np.array([0.0, 0.0, 1.0]),
                              fov=math.radians(50.0), aspect=1.5)
    cam = camera_of(browser, 64)
    assert (cam.width, cam.height) == (96, 64) and cam.fov == pytest.approx(50.0)
    origins, dirs = cam.rays()
    centre = dirs.view(64, 96, 3)[31:33, 47:49].mean((0, 1)).double()
    view = torch.as_tensor((target - eye) / np.linalg.norm(target - eye))
    assert torch.allclose(centre / centre.norm(), view, atol=1e-3)


def test_missing_results_name_the_file_and_the_rule(tmp_path):
    with pytest.raises(ViewerError, match="no such results folder"):
        ViewerScene.from_results(tmp_path / "nope", torch.device("cpu"))
    (tmp_path / "volume.zarr").mkdir()
    (tmp_path / "lights.json").write_text("{}")
    with pytest.raises(ViewerError, match=r"data_inr.pt is missing \(made by the rule `train_data_inr`: "
                       rf"`snakemake --profile <yours> results/{tmp_path.name}/data_inr.pt` makes it\)"):
        ViewerScene.from_results(tmp_path, torch.device("cpu"))


def test_a_results_folder_mistyped_or_one_level_up_names_the_scene_to_give(tmp_path):
    (tmp_path / "results/nucleon/volume.zarr").mkdir(parents=True)
    with pytest.raises(ViewerError, match=r"nucleonn: no such results folder; did you mean .*results/nucleon\?$"):
        ViewerScene.from_results(tmp_path / "results/nucleonn", torch.device("cpu"))
    with pytest.raises(ViewerError, match=r"results: a folder of scenes \(nucleon\), not one scene's results; give "
                                          r"one: diffshadow view .*results/nucleon$"):
        ViewerScene.from_results(tmp_path / "results", torch.device("cpu"))


def test_port_in_use_is_one_line(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        assert port_problem("127.0.0.1", port).startswith(f"port {port} on 127.0.0.1 is in use")
        proc = subprocess.run([sys.executable, "-m", "diffshadow.cli", "view", "--scene-config", "no.yaml",
                               "--port", str(port)], capture_output=True, text=True, timeout=120)
    assert proc.returncode != 0
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and f"port {port} on 127.0.0.1 is in use" in lines[0], proc.stderr


@pytest.mark.parametrize("args, said", [(["--host", "999.1.1.1"], "--host 999.1.1.1: cannot listen there"),
                                        (["--size", "-1"], "--size -1: expected a still frame's height in pixels"),
                                        (["--size", "100000"], "--size 100000: expected")])
def test_a_host_it_cannot_listen_on_and_a_size_out_of_range_are_one_line(args, said):
    """Said before the scene loads; the host once read "port 8080 on 999.1.1.1 is in use", and a size of -1 or
    100000 started the viewer."""
    proc = subprocess.run([sys.executable, "-m", "diffshadow.cli", "view", "--scene-config", "no.yaml", *args],
                          capture_output=True, text=True, timeout=120)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and said in lines[0], proc.stderr
    assert port_problem("127.0.0.1", 0) is None


def test_view_needs_one_scene(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "diffshadow.cli", "view"], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode != 0 and "give a results folder" in proc.stderr.strip().splitlines()[-1]


BIG = Camera.orbit(np.ones(3), azimuth=30, elevation=25, size=(80, 64))  # tall enough for the labels


def test_side_by_side_and_difference_show_one_psnr_and_say_what_they_show(viewer):
    """`inr | gt`: the inr and gt frames at half size side by side, each whole (labelled where 48 px or taller);
    the difference: |inr - gt| times a
    power of two that brings its 99.5th percentile to full scale, labelled with it; both report the PSNR of the
    whole frames, so one light reads one PSNR."""
    from diffshadow.viewer.scene import DIFF, diff_scale, image_psnr

    light = viewer.unseen[0]
    inr, _ = viewer.frame("inr", BIG, light, step=1.0)
    gt, _ = viewer.frame("gt", BIG, light, step=1.0)
    side, n1 = viewer.frame("inr | gt", BIG, light, step=1.0)
    diff, n2 = viewer.frame(DIFF, BIG, light, step=1.0)
    band = 24  # rows under the labels
    small = {k: v.reshape(32, 2, 40, 2, 3).mean((1, 3)).round().astype(np.uint8) for k, v in (("inr", inr), ("gt", gt))}
    top = 16  # 32 rows centred in 64
    assert np.array_equal(side[top + band // 2:top + 32, :40], small["inr"][band // 2:])
    assert np.array_equal(side[top + band // 2:top + 32, 40:], small["gt"][band // 2:])
    assert (side[:top] == gt[0, 0]).all() and (side[top + 32:] == gt[0, 0]).all()  # the background around them
    assert n1["labels"] == ["cache (diffusion)", "exact (gt)"]
    assert n1["psnr_vs_gt"] == n2["psnr_vs_gt"] == image_psnr(inr, gt)
    k = n2["diff_scale"]
    expect = np.clip(np.abs(inr.astype(int) - gt.astype(int)) * k, 0, 255)
    assert k == diff_scale(np.abs(inr.astype(int) - gt.astype(int))) and np.array_equal(diff[band:], expect[band:])
    assert n2["labels"] == [f"|inr - gt| x {k}"]
    assert diff_scale(np.full((4, 4), 3)) == 64 and diff_scale(np.full((4, 4), 200)) == 1
    assert diff_scale(np.full((4, 4), 20)) == 8  # 20 x 8 = 160 <= 255 < 320
    commands = viewer.render_commands("inr | gt", BIG, light, step=1.0)
    assert [build_parser().parse_args(c.split()[1:]).mode for c in commands] == ["inr", "gt"]


@pytest.fixture(scope="module")
def regional(viewer):
    """The same scene with a cache that knows its light region: a cap around +z holding the training lights."""
    from diffshadow.lights import LightRegion

    sampler = CountingSampler()
    sampler.region = LightRegion.of(viewer.train, viewer.unseen, center=(0, 0, 1))
    return ViewerScene(viewer.scene, name="blob", lights={"train": viewer.train, "unseen": viewer.unseen},
                       generated=viewer.generated, sampler=sampler, results=Path("results/blob"),
                       checkpoint=Path("results/blob/diffusion.ckpt"))


def test_outside_the_region_the_cache_modes_draw_the_exact_shadow_and_say_so(regional):
    from diffshadow.viewer.scene import DIFF

    region = regional.region
    assert region.radius_deg == pytest.approx(30.0) and region.where(direction(0, 60)).inside
    outside = direction(0, 10)  # 80 degrees from +z
    calls = regional.sampler.calls
    gt, _ = regional.frame("gt", CAM, outside, step=1.0)
    for mode in ("inr", "inr | gt", DIFF):
        image, notes = regional.frame(mode, CAM, outside, step=1.0)
        assert notes["shown"] == "gt" and np.array_equal(image, gt), mode
        (command,) = regional.render_commands(mode, CAM, outside, step=1.0)
        assert build_parser().parse_args(command.split()[1:]).mode == "gt"
    assert regional.sampler.calls == calls  # the cache was not asked
    info = regional.light_info(outside)
    assert info.outside and "outside the cache's region" in info.describe() and "50.0° past its edge" in info.describe()
    inside, notes = regional.frame("inr", CAM, direction(45, 70), step=1.0)
    assert "shown" not in notes and not notes["light"].outside


def test_a_light_far_from_every_training_light_is_flagged(regional):
    far = direction(-90, 61)  # inside the 30-degree cap, but ~30 degrees from the training lights
    check = regional.region.where(far)
    assert check.inside and check.far and check.to_nearest_deg > regional.region.far_deg
    assert "farther than any unseen test light was" in regional.light_info(far).describe()
    assert not regional.region.where(regional.unseen[0]).far


def test_the_light_gizmo_marks_the_region_and_the_light(regional):
    from diffshadow.viewer.scene import region_chart

    def marks(light):
        img = region_chart(regional.region, regional.train, regional.unseen, light, size=160).astype(int)
        red = ((img[..., 0] > 200) & (img[..., 1] < 60) & (img[..., 2] < 60)).sum()
        green = ((img[..., 1] > 230) & (img[..., 0] < 220) & (img[..., 2] < 220)).sum()  # the cap's fill
        blue = ((img[..., 2] > 150) & (img[..., 0] < 80)).sum()
        return img.shape, red, green, blue

    shape, red, green, blue = marks(direction(30, 80))
    assert shape == (160, 160, 3) and red > 20 and green > 500 and blue > 10
    _, red_out, green_out, _ = marks(direction(0, -20))  # outside: a black cross, no red dot; the cap shrinks
    assert red_out == 0 and green_out < green


def test_the_viewers_pytorch_work_runs_on_one_thread(monkeypatch):
    """GNU OpenMP stops spinning between PyTorch's ops once several threads have teams (the scene loaded on the main
    thread and the frames drawn on a tab's: 3.9x slower frames on 2 cores), so the viewer loads its scene and draws
    every frame on one thread of its own; a call's error reaches its caller, and the thread ends when closed."""
    import threading

    from diffshadow.viewer import app

    worker = app.TorchThread()
    ran_on = {worker.run(threading.get_ident) for _ in range(3)}
    assert len(ran_on) == 1 and threading.get_ident() not in ran_on

    def fails():
        raise ViewerError("no such scene")

    with pytest.raises(ViewerError, match="no such scene"):
        worker.run(fails)
    worker.close()
    worker._thread.join(10)
    assert not worker._thread.is_alive()

    loaded_on = []

    def load(*args):
        loaded_on.append(threading.current_thread())
        raise ViewerError("loaded")

    monkeypatch.setattr(app.ViewerScene, "from_scene_config", staticmethod(load))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(ViewerError, match="loaded"):
        app.serve(results=None, scene_config=Path("scene.yaml"), device=torch.device("cpu"), port=port)
    assert loaded_on and loaded_on[0] is not threading.main_thread() and loaded_on[0].name == "viewer-torch"
    loaded_on[0].join(10)
    assert not loaded_on[0].is_alive()  # serve closed it
