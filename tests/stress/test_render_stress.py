"""Stress: the renderer on generated volumes, cameras and image sizes (hypothesis): rays that graze the
box, start inside it or miss it; empty, opaque and random volumes; 1x1 and non-square images."""

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from test_ground_truth_stress import SETTINGS, directions, transfer_functions, volumes

from diffshadow.render import Camera, RenderScene

pytestmark = pytest.mark.stress


@st.composite
def cameras(draw, extent):
    kind = draw(st.sampled_from(["orbit", "inside", "grazing", "miss"]))
    w, h = draw(st.integers(1, 9)), draw(st.integers(1, 9))
    c = np.asarray(extent) / 2
    if kind == "orbit":
        return Camera.orbit(extent, azimuth=draw(st.floats(-180, 180)), elevation=draw(st.floats(-89, 89)),
                            size=(w, h)), kind
    if kind == "inside":  # the eye inside the box
        eye = np.asarray(extent) * np.array([draw(st.floats(0.05, 0.95)) for _ in range(3)])
        target = eye + np.array([draw(st.floats(-1, 1)) for _ in range(3)]) + 1e-3
        return Camera.look_at(eye, target, up=(0.3, 0.4, 0.87), size=(w, h)), kind
    if kind == "grazing":  # looking along a face of the box
        eye = np.array([-1.0, c[1], float(extent[2])])
        return Camera.look_at(eye, [float(extent[0]) + 1, c[1], float(extent[2])], fov=1.0, size=(w, h)), kind
    eye = c + np.array([3.0, 0, 0])  # looking away from the box
    return Camera.look_at(eye, eye + np.array([1.0, 0, 0]), size=(w, h)), kind


@SETTINGS
@given(data=st.data(), vol=volumes(), tf=transfer_functions(), light=directions())
def test_images_are_finite_and_background_where_nothing_is_hit(data, vol, tf, light):
    cam, kind = data.draw(cameras(vol.extent))
    scene = RenderScene(vol, tf, cell=4)
    for mode in ("noshadow", "gt", "naive"):
        img = scene.render(mode, cam, light=light, scalar="grid", phong=mode == "noshadow")
        assert img.rgb.shape == (cam.height, cam.width, 3)
        assert torch.isfinite(img.rgb).all() and torch.isfinite(img.alpha).all()
        # composited in float32: each sample's rounding may lift a pixel past 1 (179 samples gave 1 + 1.3e-6)
        assert float(img.rgb.min()) >= 0 and float(img.rgb.max()) <= 1 + img.counters.primary_samples * 2**-23
        assert float(img.alpha.min()) >= 0 and float(img.alpha.max()) <= 1 + 1e-6
        if kind == "miss" or tf.density_scale == 0:
            assert torch.all(img.alpha == 0) and torch.all(img.rgb == 1.0)


@SETTINGS
@given(data=st.data(), vol=volumes(), tf=transfer_functions(), lights=st.lists(directions(), min_size=2, max_size=3))
def test_a_view_from_its_kept_samples_is_the_marched_image_under_any_light(data, vol, tf, lights):
    """Kept samples (the viewer's light moves) on the same generated volumes, TFs and cameras: each light's image
    from the view's samples is a fresh scene's march, to the byte, empty, opaque and missed views included."""
    cam, _ = data.draw(cameras(vol.extent))
    batch = data.draw(st.sampled_from([None, 64]))  # 64: many iterations, each kept apart
    keeping = RenderScene(vol, tf, cell=4, keep_samples=1 << 24)
    for i, light in enumerate(lights):
        for mode in ("gt", "naive"):
            img = keeping.render(mode, cam, light=light, scalar="grid", batch=batch)
            want = RenderScene(vol, tf, cell=4).render(mode, cam, light=light, scalar="grid", batch=batch)
            assert img.replayed == (i > 0 or mode == "naive")
            assert torch.equal(img.rgb, want.rgb) and torch.equal(img.alpha, want.alpha)
            assert img.counters == want.counters
