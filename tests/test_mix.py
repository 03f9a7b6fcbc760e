"""The cache's answer as the model's SIREN mixed with the stored SIRENs' weight blend (diffshadow/diffusion/mix.py):
the mix itself, the share chosen on validation lights, the sampler that mixes for any light, and the one-line
errors. The whole path (sample_shadows' choice, evaluate_voxels' model-alone figures, the viewer's and render's
mixed answer) runs in tests/test_workflow.py."""

from types import SimpleNamespace

import numpy as np
import pytest

from diffshadow.cli import build_parser
from diffshadow.diffusion.mix import SHARES, MixedSampler, check_share, choose_share, mix_weights

RNG = np.random.default_rng(0)
MODEL = RNG.normal(size=(6, 10)).astype(np.float32)
BLEND = RNG.normal(size=(6, 10)).astype(np.float32)


def test_the_mix_is_the_convex_combination_and_its_ends_are_exact():
    assert np.array_equal(mix_weights(MODEL, BLEND, 1.0), MODEL)
    assert np.array_equal(mix_weights(MODEL, BLEND, 0), BLEND)
    mixed = mix_weights(MODEL, BLEND, 0.3)
    assert mixed.dtype == np.float32
    expected = 0.3 * MODEL.astype(np.float64) + 0.7 * BLEND.astype(np.float64)
    assert np.array_equal(mixed, expected.astype(np.float32))


def test_a_mix_in_passes_has_the_bits_of_one_pass(monkeypatch):
    """A set larger than one pass (here 7 weights a pass over 60, the last pass short; a float64 blend as
    sample_shadows passes it) is mixed element by element as one pass would: every byte the same."""
    import diffshadow.diffusion.mix as mix

    blend = BLEND.astype(np.float64) / 3
    whole = mix_weights(MODEL, blend, 0.7)
    monkeypatch.setattr(mix, "MIX_CHUNK", 7)
    assert whole.tobytes() == mix_weights(MODEL, blend, 0.7).tobytes()
    assert whole.tobytes() == (0.7 * MODEL.astype(np.float64) + 0.3 * blend).astype(np.float32).tobytes()


@pytest.mark.parametrize("share, message", [(1.5, "expected a number from 0 to 1"),
                                            (-0.1, "expected a number from 0 to 1"),
                                            ("half", "expected auto or a number"), (None, "expected auto or")])
def test_a_bad_share_is_named(share, message):
    with pytest.raises(ValueError, match=rf"mix.model_share: {message}.*got {share!r}"):
        check_share(share)


def test_rows_of_other_shapes_are_refused():
    with pytest.raises(ValueError, match=r"\(6, 10\) and the stored SIRENs' blend \(6, 9\) differ"):
        mix_weights(MODEL, BLEND[:, :9], 0.5)


def _score_against(target: np.ndarray):
    """Per-light PSNR (peak 1) of SIREN rows against `target` rows: the validation lights' stand-in."""
    return lambda w: -10.0 * np.log10(((w.astype(np.float64) - target) ** 2).mean(axis=1))


@pytest.mark.parametrize("true_share", [0.0, 0.3, 0.7, 1.0])
def test_the_share_chosen_is_the_one_that_makes_the_truth(true_share):
    """Where the truth is an exact mix, the curve peaks at its share (ends included) and says so in its rows."""
    target = mix_weights(MODEL, BLEND, true_share).astype(np.float64) + 1e-4  # off the exact mix: finite PSNRs
    share, curve = choose_share(MODEL, BLEND, _score_against(target))
    assert share == true_share
    assert [row["share"] for row in curve] == list(SHARES)
    best = max(curve, key=lambda row: row["psnr_mean"])
    assert best["share"] == true_share and best["psnr_median"] >= max(r["psnr_median"] for r in curve) - 1e-9


def test_a_tie_goes_to_the_larger_share():
    share, curve = choose_share(MODEL, BLEND, lambda w: np.full(len(w), 30.0))
    assert share == 1.0 and {row["psnr_mean"] for row in curve} == {30.0}


def test_a_non_finite_score_is_refused_not_chosen():
    with pytest.raises(ValueError, match=r"mix: share 0.0: a validation light scored nan dB"):
        choose_share(MODEL, BLEND, lambda w: np.full(len(w), np.nan))


class Fixed:
    """A sampler that answers one row for every light."""

    def __init__(self, row, n_params=None, extinction=None):
        self.row = np.asarray(row, dtype=np.float32)
        self.layout = SimpleNamespace(n_params=n_params or len(self.row))
        self.siren, self.region, self.extinction = "siren", "region", extinction

    def __call__(self, light):
        return self.row


def test_the_mixed_sampler_mixes_its_two_answers_and_keeps_the_models_region():
    model, blend = Fixed(MODEL[0]), Fixed(BLEND[0])
    sampler = MixedSampler(model, blend, 0.25)
    w = sampler([0.0, 0.0, 1.0])
    assert np.array_equal(w, mix_weights(MODEL[:1], BLEND[:1], 0.25)[0])
    assert (sampler.layout, sampler.region, sampler.share) == (model.layout, "region", 0.25)
    with pytest.raises(ValueError, match="the model makes SIRENs of 10 parameters, the stored ones have 9"):
        MixedSampler(model, Fixed(BLEND[0, :9]), 0.5)
    # the two sides shade one scene: a model and stored SIRENs of two scenes are refused, an unknown side is not checked
    with pytest.raises(ValueError, match="^mix: the stored SIRENs: made for another volume or opacity than the "
                                         "model's \\(extinction field b against a\\)"):
        MixedSampler(Fixed(MODEL[0], extinction="a"), Fixed(BLEND[0], extinction="b"), 0.5)
    assert MixedSampler(Fixed(MODEL[0], extinction="a"), Fixed(BLEND[0]), 0.5).extinction == "a"
    assert MixedSampler(Fixed(MODEL[0]), Fixed(BLEND[0], extinction="b"), 0.5).extinction == "b"


class Refused:
    """A sampler that must not be asked."""

    layout, siren, region, extinction = SimpleNamespace(n_params=MODEL.shape[1]), "siren", "region", None

    def __call__(self, light):
        raise AssertionError("asked for a light its share gives no weight")


def test_a_side_with_no_share_is_not_asked():
    """At share 0 the answer is the blend's bytes without sampling the model (its DDIM is the slow side); at 1 the
    model's without blending."""
    light = [0.0, 0.0, 1.0]
    assert np.array_equal(MixedSampler(Refused(), Fixed(BLEND[0]), 0.0)(light), mix_weights(MODEL[:1], BLEND[:1], 0)[0])
    assert np.array_equal(MixedSampler(Fixed(MODEL[0]), Refused(), 1.0)(light), MODEL[0])
    with pytest.raises(AssertionError, match="no weight"):
        MixedSampler(Refused(), Fixed(BLEND[0]), 0.1)(light)


def test_render_mixes_only_when_asked_with_both_sources(tmp_path):
    """`render --model-share` needs --diffusion and --blend; the two without it are refused as before."""
    from diffshadow.stages.images import render_image

    args = build_parser().parse_args(["render", "--volume", "v.zarr", "--data-inr", "d.pt", "--mode", "inr",
                                      "--diffusion", "m.ckpt", "--blend", "w.zarr", "--model-share", "0.7",
                                      "--light", "0", "0", "1", "--out", "x.png"])
    assert (args.model_share, args.diffusion, args.blend) == (0.7, "m.ckpt", "w.zarr")
    common = {"mode": "inr", "camera": None, "light": [0.0, 0.0, 1.0], "blend_k": 4, "step": 1.0}
    with pytest.raises(ValueError, match="--model-share mixes .* give --diffusion and --blend with it"):
        render_image(None, tmp_path / "x.png", diffusion=tmp_path / "m.ckpt", model_share=0.5, **common)
    with pytest.raises(ValueError, match=r"give one \(or --diffusion and --blend with --model-share"):
        render_image(None, tmp_path / "x.png", diffusion=tmp_path / "m.ckpt", blend=tmp_path / "w.zarr", **common)


def test_sample_shadows_says_what_a_mix_needs(tmp_path):
    from diffshadow.stages.stage2 import _mix_inputs

    assert _mix_inputs("1", None, None, None, None) is None and _mix_inputs("1.0", None, None, None, None) is None
    with pytest.raises(ValueError, match=r"mix.model_share auto: .* give --weights \(stage 1's weights.zarr\) and "
                                         r"--volume, or model share 1 for the model alone"):
        _mix_inputs("auto", tmp_path / "w.zarr", None, None, None)
    with pytest.raises(ValueError, match=r"mix.model_share 0.5: .* give --weights \(stage 1's weights.zarr\), or"):
        _mix_inputs("0.5", None, None, None, None)
    with pytest.raises(ValueError, match="expected a number from 0 to 1"):
        _mix_inputs("3", tmp_path / "w.zarr", tmp_path / "v.zarr", None, None)


def test_model_alone_is_share_one_however_written():
    from diffshadow.diffusion.mix import model_alone

    assert model_alone(1) and model_alone(1.0) and model_alone("1") and model_alone("1.0")
    assert not model_alone("auto") and not model_alone(0.7) and not model_alone(0)
    with pytest.raises(ValueError, match="mix.model_share"):
        model_alone("most")
