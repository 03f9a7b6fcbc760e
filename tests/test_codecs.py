"""The codecs of the stored SIRENs (`diffshadow.codecs`): what each stores, what it gives back, and the blend of
SIRENs done on their coefficients."""

import numpy as np
import pytest
import torch

from diffshadow.codecs import BasisCodec, HalfCodec
from diffshadow.layout import SirenConfig, WeightLayout
from diffshadow.siren import init_siren

SIREN = SirenConfig(8, 1)
LAYOUT = WeightLayout.for_siren(SIREN)


def _weights(n: int = 12) -> np.ndarray:
    """SIRENs near one init, as stage 1 leaves them."""
    init = LAYOUT.flatten(init_siren(SIREN, torch.Generator().manual_seed(0))).numpy()
    rng = np.random.default_rng(1)
    return (init + 0.01 * rng.standard_normal((n, LAYOUT.n_params))).astype(np.float32)


def test_half_codecs_store_two_bytes_and_round_as_their_format():
    w = _weights()
    fp16 = HalfCodec("float16")
    enc = fp16.encode(w, LAYOUT)
    assert enc.nbytes == w.size * 2
    assert np.array_equal(fp16.decode(enc), w.astype(np.float16).astype(np.float32))
    assert np.array_equal(fp16.decode(enc, rows=[3, 5]), fp16.decode(enc)[[3, 5]])
    bf16 = HalfCodec("bfloat16")
    back = bf16.decode(bf16.encode(w, LAYOUT))
    # torch's bf16 rounding (nearest even) is the reference
    assert np.array_equal(back, torch.from_numpy(w).bfloat16().float().numpy())


def test_a_basis_as_wide_as_the_lights_is_exact_and_a_narrower_one_errs_more():
    w = _weights(10)
    errors = []
    for k in (2, 5, 10):
        codec = BasisCodec(k)
        enc = codec.encode(w, LAYOUT)
        assert enc.nbytes == 4 * (LAYOUT.n_params * (1 + k) + len(LAYOUT.sizes) + len(w) * k)
        errors.append(float(np.abs(codec.decode(enc, LAYOUT) - w).max()))
    assert errors[0] > errors[1] > errors[2] and errors[2] < 1e-5


def test_a_blend_of_coefficients_is_the_blend_of_the_sirens():
    w, codec = _weights(), BasisCodec(6)
    enc = codec.encode(w, LAYOUT)
    mix = np.array([0.5, 0.3, 0.2])
    rows = [1, 4, 7]
    blended = codec.decode(enc, LAYOUT, (enc.arrays["coefficients"][rows] * mix[:, None]).sum(0, keepdims=True))
    expected = (codec.decode(enc, LAYOUT)[rows].astype(np.float64) * mix[:, None]).sum(0)
    assert np.allclose(blended[0], expected, atol=1e-6)


@pytest.mark.parametrize(("codec", "weights", "match"), [
    (HalfCodec(), np.zeros((3, 5)), r"expected weights \(N, 185\), got \(3, 5\)"),
    (BasisCodec(2), np.full((3, LAYOUT.n_params), np.nan), "not all finite"),
    (HalfCodec(), np.full((3, LAYOUT.n_params), 1e6), "exceeds fp16's range"),
])
def test_bad_weights_get_one_line(codec, weights, match):
    with pytest.raises(ValueError, match=match):
        codec.encode(weights, LAYOUT)


def test_bad_settings_are_named():
    with pytest.raises(ValueError, match="expected float16 or bfloat16, got 'int8'"):
        HalfCodec("int8")
    with pytest.raises(ValueError, match="k must be at least 1, got 0"):
        BasisCodec(0)
