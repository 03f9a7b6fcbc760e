import numpy as np
import pytest
import torch

from diffshadow.transfer import TransferFunction, TransferFunctionError

CONFIG = {
    "opacity": [[0.2, 0.0], [0.6, 0.8], [0.6, 0.4], [0.9, 1.0]],
    "color": [[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 1.0]],
    "density_scale": 5.0,
}


def test_piecewise_linear_clamped_and_steps():
    tf = TransferFunction.from_config(CONFIG)
    s = torch.tensor([0.0, 0.2, 0.4, 0.5999, 0.6, 0.75, 0.9, 1.0])
    expected = torch.tensor([0.0, 0.0, 0.4, 0.8, 0.4, 0.7, 1.0, 1.0])
    torch.testing.assert_close(tf.opacity(s), expected, atol=1e-3, rtol=0)
    torch.testing.assert_close(tf.extinction(s), 5.0 * tf.opacity(s))
    torch.testing.assert_close(tf.color(torch.tensor([0.25])), torch.tensor([[0.75, 0.0, 0.25]]))


def test_max_opacity_over_intervals_matches_dense_sampling():
    tf = TransferFunction.from_config(CONFIG)
    rng = np.random.default_rng(1)
    lo = rng.uniform(0, 1, 200)
    hi = np.minimum(1, lo + rng.uniform(0, 0.5, 200))
    bound = tf.max_opacity(lo, hi)
    for a, b, m in zip(lo, hi, bound, strict=True):
        dense = tf.opacity(torch.linspace(a, b, 2001)).max().item()
        assert m >= dense - 1e-6 and m <= dense + 2e-3


def test_round_trip_config():
    tf = TransferFunction.from_config(CONFIG)
    assert TransferFunction.from_config(tf.to_config()).to_config() == tf.to_config() == {
        **CONFIG, "opacity": CONFIG["opacity"], "density_scale": 5.0}


@pytest.mark.parametrize("change, message", [
    ({"opacity": [[0.0, 0.5]]}, "opacity needs at least 2 points"),
    ({"opacity": [[0.5, 0.0], [0.1, 1.0]]}, "opacity points must be sorted"),
    ({"color": [[0.0, 1.0, 0.0, 2.0], [1.0, 0, 0, 0]]},
     r"color values must lie in \[0, 1\], the position s as well as the r, g, b; point 0 is \[0.0, 1.0, 0.0, 2.0\]$"),
    # a position past the grid's range, not an opacity: the point is named
    ({"opacity": [[0.0, 0.0], [0.5, 0.2], [1.5, 1.0]]},
     r"opacity values must lie in \[0, 1\], the position s as well as the opacity; point 2 is \[1.5, 1.0\]$"),
    ({"color": [[0.0, 1.0], [1.0, 0.0]]}, "color must be a list of"),
    ({"density_scale": -1}, "density_scale must be finite and >= 0"),
    ({"density_scale": "lots"}, "density_scale must be a number"),
    ({"opacity": [[0.0, float("nan")], [1.0, 1.0]]}, "opacity has non-finite values"),
    ({"gamma": 2}, r"unknown key\(s\) \['gamma'\]"),
])
def test_malformed_transfer_functions(change, message):
    with pytest.raises(TransferFunctionError, match=message):
        TransferFunction.from_config({**CONFIG, **change})


def test_a_scene_needs_something_visible():
    """An all-transparent TF is valid for the renderer (the stress suites draw them) but refused for a scene."""
    clear = TransferFunction.from_config({**CONFIG, "opacity": [[0.0, 0.0], [1.0, 0.0]]})
    with pytest.raises(TransferFunctionError, match="scene x: transfer function: opacity is 0 at every point"):
        clear.require_visible("scene x")
    assert TransferFunction.from_config(CONFIG).require_visible("scene x") is not None


def test_missing_key():
    with pytest.raises(TransferFunctionError, match="missing key 'color'"):
        TransferFunction.from_config({"opacity": CONFIG["opacity"], "density_scale": 1})


@pytest.mark.parametrize("config", [
    CONFIG,
    {"opacity": [[0.0, 0.0], [0.3, 0.0], [0.3, 1.0], [0.6, 0.5], [0.9, 0.0]],
     "color": [[0.1, 1.0, 0.0, 0.0], [0.5, 0.0, 1.0, 0.0], [0.5, 0.0, 0.0, 1.0], [0.7, 1.0, 1.0, 1.0]],
     "density_scale": 40.0},
])
def test_optics_is_opacity_and_colour_from_one_search(config):
    """One search of the union of both polylines' knots gives the extinction and colour that two searches give,
    steps included (at a step's s, the upper value), and outside the knots the clamped ends."""
    tf = TransferFunction.from_config(config)
    knots = np.concatenate([tf.opacity_points[:, 0], tf.color_points[:, 0]])
    s = torch.cat([torch.rand(20000, generator=torch.Generator().manual_seed(0)) * 1.4 - 0.2,
                   torch.as_tensor(knots, dtype=torch.float32)])
    mu, rgb = tf.optics(s)
    torch.testing.assert_close(mu, tf.extinction(s), rtol=1e-6, atol=1e-6 * tf.density_scale)
    torch.testing.assert_close(rgb, tf.color(s), rtol=1e-6, atol=1e-6)
    mu2, rgb2 = tf.optics(s[:20000].view(100, 200))
    assert mu2.shape == (100, 200) and rgb2.shape == (100, 200, 3)
