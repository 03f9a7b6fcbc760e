"""`caches.json` (`diffshadow.caches.cache_table`) resumes: a job stopped between its groups of rows (a codec's,
the model's, the grids') starts again at the first group not done, with the rows it had saved, and the table it
writes is the one an unbroken job writes."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from diffshadow import caches
from diffshadow.layout import SirenConfig, WeightLayout
from diffshadow.lights import fibonacci_sphere
from diffshadow.siren import init_siren
from diffshadow.truth import EvalTruth

SIREN = SirenConfig(8, 1)
LAYOUT = WeightLayout.for_siren(SIREN)


class Killed(Exception):
    pass


def _inputs(n: int = 12, unseen: int = 3, seed: int = 1):
    init = LAYOUT.flatten(init_siren(SIREN, torch.Generator().manual_seed(0))).numpy()
    w = (init + 0.01 * np.random.default_rng(seed).standard_normal((n, LAYOUT.n_params))).astype(np.float32)
    lights = fibonacci_sphere(4 * (n + unseen))[:n + unseen]
    g = torch.Generator().manual_seed(2)
    truth = EvalTruth(points={"box": torch.rand(64, 3, generator=g) * 2}, lights=lights,
                      values={"box": torch.rand(n + unseen, 64, generator=g)}, extent=torch.full((3,), 2.0))
    store = SimpleNamespace(weights=w, layout=LAYOUT, siren=SIREN)
    return store, truth, {"train": lights[:n], "unseen": lights[n:]}


def _table(store, truth, sets, *, log=lambda line: None, checkpoint=None, weighting: str = "triangle"):
    return caches.cache_table(store, truth, sets, blend_k=4, weighting=weighting, log=log, checkpoint=checkpoint)


def _stop_at_group(k: int):
    """A log that stops the job at the k-th group's row, after that group was saved."""
    seen = []

    def log(line: str):
        if line.startswith("[caches] {"):
            seen.append(line)
            if len(seen) == k:
                raise Killed
    return log


def _without_times(table: dict) -> dict:
    return {**table, "caches": [{k: v for k, v in r.items() if k != "answer_s"} for r in table["caches"]]}


def test_a_stopped_table_resumes_at_its_first_group_not_done(tmp_path):
    store, truth, sets = _inputs()
    whole = _table(store, truth, sets)
    assert [r["cache"] for r in whole["caches"]] == ["stored SIRENs fp32", "stored SIRENs fp16",
                                                      "stored SIRENs bf16", "stored SIRENs basis-4",
                                                      "stored SIRENs basis-8"]
    ckpt = tmp_path / "caches.json.ckpt"
    with pytest.raises(Killed):
        _table(store, truth, sets, log=_stop_at_group(3), checkpoint=ckpt)
    saved = torch.load(ckpt, weights_only=True)["groups"]
    assert [name for name, _ in saved] == ["stored SIRENs fp32", "stored SIRENs fp16", "stored SIRENs bf16"]

    lines = []
    resumed = _table(store, truth, sets, log=lines.append, checkpoint=ckpt)
    assert f"[caches] resuming from {ckpt} after 3 of 5 groups of rows" in lines
    # the saved rows are kept as they were (their times too: a row measured again would time otherwise)
    assert resumed["caches"][:3] == [row for _, rows in saved for row in rows]
    assert _without_times(resumed) == _without_times(whole)
    assert sum(line.startswith("[caches] {") for line in lines) == 2  # only the two groups not done
    assert not ckpt.exists()


def test_without_unseen_lights_no_row_has_an_unseen_figure():
    """`lights.unseen: 0`: the rows state the seen lights' PSNR alone, no unseen PSNR and no answer time (the
    blends' answers were once timed as NaN, which reached caches.json as the string "nan")."""
    store, truth, sets = _inputs(unseen=0)
    table = _table(store, truth, sets)
    assert table["lights"] == {"train": 12, "unseen": 0}
    for row in table["caches"]:
        assert "unseen_psnr" not in row and "answer_s" not in row, row
        assert np.isfinite(row["seen_psnr"]), row


@pytest.mark.parametrize("change", ["weights", "weighting"])
def test_a_checkpoint_of_other_inputs_is_not_resumed(tmp_path, change):
    store, truth, sets = _inputs()
    ckpt = tmp_path / "caches.json.ckpt"
    with pytest.raises(Killed):
        _table(store, truth, sets, log=_stop_at_group(2), checkpoint=ckpt)
    weighting = "triangle"
    if change == "weights":
        store, _, _ = _inputs(seed=2)
    else:
        weighting = "inverse-angle"
    lines = []
    table = _table(store, truth, sets, log=lines.append, checkpoint=ckpt, weighting=weighting)
    assert f"ignoring {ckpt}: it belongs to other inputs or settings" in lines
    assert not any("resuming" in line for line in lines)
    assert _without_times(table) == _without_times(_table(store, truth, sets, weighting=weighting))


def _model_state(store, sets, tmp_path):
    """A tiny model trained for two epochs on the stored SIRENs (what its rows need: a checkpoint's state)."""
    from diffshadow.diffusion.config import DiffusionConfig
    from diffshadow.diffusion.train import TrainingData, train_diffusion

    n, g = len(sets["train"]), torch.Generator().manual_seed(0)
    data = TrainingData(weights=torch.as_tensor(store.weights),
                        lights=torch.as_tensor(sets["train"], dtype=torch.float32),
                        points=torch.rand(n, 32, 3, generator=g), values=torch.rand(n, 32, generator=g),
                        extent=torch.ones(3), layout=LAYOUT, siren=SIREN)
    cfg = DiffusionConfig.from_config(dict(preset="tiny", epochs=2, batch_size=4, geometry_points=16, pool_lights=0,
                                           target_gap=0.0, ddim_steps=4))
    return train_diffusion(data, cfg, tmp_path / "model.ckpt", device="cpu", log=lambda m: None)


def test_the_models_rows_sample_on_the_device_they_are_given(tmp_path, monkeypatch):
    """evaluate.device reaches the model's fp16 DDIM (the workflow passes --device cpu unless it is `run`), and each
    model row names the device its answer was timed on."""
    from diffshadow.diffusion import sample
    from diffshadow.hpc import device_name

    store, truth, sets = _inputs()
    state = _model_state(store, sets, tmp_path)
    n = len(sets["train"]) + len(sets["unseen"])
    generated = SimpleNamespace(psnr=np.linspace(30, 40, n), seen=np.arange(n) < len(sets["train"]), config={})
    asked, generate = [], sample.generate

    def recorded(*args, **kwargs):
        asked.append(kwargs.get("device"))  # None: sampled wherever generate's default is
        return generate(*args, **kwargs)

    monkeypatch.setattr(sample, "generate", recorded)
    table = caches.cache_table(store, truth, sets, blend_k=4, weighting="triangle", log=lambda m: None,
                               model_state=state, generated=generated, device=torch.device("cpu"))
    rows = {r["cache"]: r for r in table["caches"]}
    assert asked == [torch.device("cpu")]
    for name in ("diffusion model fp32", "diffusion model fp16"):
        assert rows[name]["device"] == device_name("cpu") and rows[name]["answer_s"] > 0
    assert rows["diffusion model fp32"]["seen_psnr"] == pytest.approx(np.median(generated.psnr[generated.seen]))


@pytest.mark.parametrize("share", [0.0, 0.5, 1.0])
def test_a_mix_rows_answer_is_timed_as_its_sampler_answers(tmp_path, share):
    """A mix row's time to answer is the model's DDIM where the model has a share and the stored SIRENs' blend (in
    the row's precision) where they have one: at share 0 the blend's alone, which is all `MixedSampler` asks."""
    store, truth, sets = _inputs()
    state = _model_state(store, sets, tmp_path)
    n = len(sets["train"]) + len(sets["unseen"])
    mix = {"model_share": share, "blend_k": 4, "blend_weights": "triangle", "model_alone_psnr": np.linspace(30, 40, n)}
    generated = SimpleNamespace(psnr=np.linspace(31, 41, n), seen=np.arange(n) < len(sets["train"]),
                                config={"mix": mix})
    table = caches.cache_table(store, truth, sets, blend_k=4, weighting="triangle", log=lambda m: None,
                               model_state=state, generated=generated, device=torch.device("cpu"))
    rows = {r["cache"]: r for r in table["caches"]}
    model = rows["diffusion model fp32"]["answer_s"]
    for precision in ("fp32", "fp16"):
        blend = rows[f"stored SIRENs {precision}"]["answer_s"]
        mixed = rows[f"model {share:g} + stored SIRENs {1 - share:g}, both {precision}"]["answer_s"]
        assert mixed == pytest.approx({0.0: blend, 0.5: model + blend, 1.0: model}[share], rel=1e-12)


def test_the_dense_grids_row_scores_stored_grids_and_times_an_answer_on_its_neighbours_alone(monkeypatch):
    """The dense grids' seen lights are their own grids read at the points: the exact shadow but for the grid's
    trilinear reading and fp16 (a Gaussian blob: within a fraction of its range); an unseen light is their blend.
    Its answer is timed on as many grids as the blend reads (3 corners of a triangle), not on a stack of every
    stored light's (at the paper's 1,024 lights on 256³: 64 GiB)."""
    from conftest import identity_tf

    from diffshadow.analytic import gaussian_blob
    from diffshadow.volume import Volume

    volume = Volume(data=gaussian_blob(17, 0.2), extent=np.ones(3), name="blob")
    lights = fibonacci_sphere(40)[:15]
    sets = {"train": lights[:12], "unseen": lights[12:]}
    truth = EvalTruth.compute(volume, identity_tf(), lights, 256, seed=0, sets=("box",))
    drawn, randn = [], torch.randn

    def recorded(*size, **kwargs):
        drawn.append(tuple(size))
        return randn(*size, **kwargs)

    monkeypatch.setattr(caches.torch, "randn", recorded)
    idx, mix = caches.blend_weights(sets["train"], sets["unseen"], 4, "triangle")
    row = caches._grid_row(volume, identity_tf(), truth, sets["train"], sets["unseen"], idx, mix)
    assert row["bytes"] == 12 * 17**3 * 2
    assert row["seen_psnr"] > 35 and np.isfinite(row["unseen_psnr"]) and row["answer_s"] > 0
    assert drawn == [(3, 17, 17, 17)]
