"""A signal (SIGTERM at a PBS walltime or preemption, Ctrl-C) stops a training loop at its next step with a
checkpoint there, and the rerun resumes to the bytes of an uninterrupted run."""

import dataclasses
import os
import signal
import threading

import numpy as np
import pytest
import torch

from diffshadow import stopping
from diffshadow.stopping import Stopped, stop_signals


@pytest.fixture(autouse=True)
def python_signal_handlers():
    """Python's own SIGINT handler and the default SIGTERM, as a command typed in a terminal has them: a test run
    started in the background of a shell without job control inherits SIGINT ignored, which stop_signals keeps."""
    before = {s: signal.getsignal(s) for s in stopping.SIGNALS}
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    yield
    for sig, handler in before.items():
        signal.signal(sig, handler)


def signal_at(obj, name: str, call: int, sig=signal.SIGTERM):
    """Wrap `obj.name` so that its `call`-th call (from 1) sends `sig` to this process first: a signal that
    arrives in the middle of a step, as a scheduler's does."""
    inner = getattr(obj, name)
    calls = []

    def wrapped(*args, **kwargs):
        calls.append(1)
        if len(calls) == call:
            os.kill(os.getpid(), sig)
        return inner(*args, **kwargs)

    return wrapped


def test_a_signal_sets_the_request_and_the_handlers_come_back():
    before = {s: signal.getsignal(s) for s in stopping.SIGNALS}
    with stop_signals() as stop:
        assert not stop.requested
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.signum == signal.SIGTERM
        os.kill(os.getpid(), signal.SIGTERM)  # PBS's and torchrun's: the same request
        assert stop.signum == signal.SIGTERM
        e = stop.stopped("at step 3/9", "x.ckpt")
    assert {s: signal.getsignal(s) for s in stopping.SIGNALS} == before
    assert isinstance(e, BaseException) and not isinstance(e, Exception) and e.signum == signal.SIGTERM
    assert str(e) == ("stopped by SIGTERM at step 3/9; checkpoint x.ckpt written, and the same command run again "
                      "resumes from it")


def test_a_second_ctrl_c_stops_at_once():
    with pytest.raises(KeyboardInterrupt), stop_signals() as stop:
        os.kill(os.getpid(), signal.SIGINT)
        assert stop.signum == signal.SIGINT
        os.kill(os.getpid(), signal.SIGINT)
        pytest.fail("the second SIGINT did not interrupt")


def test_a_signal_the_loop_did_not_answer_is_sent_again_after_it():
    with pytest.raises(KeyboardInterrupt), stop_signals() as stop:  # SIGINT's own handler: KeyboardInterrupt
        os.kill(os.getpid(), signal.SIGINT)
    assert stop.requested and not stop.honoured


def test_off_the_main_thread_and_where_ignored_nothing_is_installed():
    seen = {}

    def worker():
        with stop_signals() as stop:
            seen["handler"] = signal.getsignal(signal.SIGTERM)
            seen["stop"] = stop

    before = signal.getsignal(signal.SIGTERM)
    thread = threading.Thread(target=worker)
    thread.start()
    thread.join()
    assert seen["handler"] is before and not seen["stop"].requested
    previous = signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        with stop_signals():
            assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN
            assert signal.getsignal(signal.SIGINT) != signal.default_int_handler
        with stop_signals(enabled=False):
            assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_the_subset_fit_stops_at_its_next_step_and_resumes_to_the_same_bytes(tmp_path, monkeypatch):
    from conftest import identity_tf
    from test_fit import CFG, LAYOUT, init

    from diffshadow import fit
    from diffshadow.fit import FitConfig, fit_sirens
    from diffshadow.volume import Volume

    vol = Volume(data=np.random.default_rng(0).uniform(0, 1, (9, 9, 9)).astype(np.float32), extent=np.ones(3),
                 name="noise")
    tf, lights = identity_tf(2.0), np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])
    cfg = FitConfig.from_config(dict(steps=12, points=64, checkpoint_every=4, eval_points=16))
    whole = fit_sirens(init(), LAYOUT, CFG, vol, tf, lights, cfg, log=lambda *a: None)
    ckpt = tmp_path / "subset.ckpt"
    with monkeypatch.context() as m:
        m.setattr(fit.SubsetFit, "step", signal_at(fit.SubsetFit, "step", 7))
        with pytest.raises(Stopped, match=r"^stopped by SIGTERM at step 7/12; checkpoint .*subset.ckpt written"):
            fit_sirens(init(), LAYOUT, CFG, vol, tf, lights, cfg, checkpoint=ckpt, log=lambda *a: None)
    assert torch.load(ckpt, weights_only=True)["step"] == 7  # not the periodic checkpoint's 4
    messages = []
    resumed = fit_sirens(init(), LAYOUT, CFG, vol, tf, lights, cfg, checkpoint=ckpt, log=messages.append)
    assert messages[0].startswith(f"resuming from {ckpt} at step 7")
    assert torch.equal(resumed, whole) and not ckpt.exists()


def test_the_data_inr_stops_at_its_next_step_and_resumes_to_the_same_bytes(tmp_path, monkeypatch):
    from test_data_inr import CFG, TF

    from diffshadow import data_inr
    from diffshadow.analytic import gaussian_blob
    from diffshadow.data_inr import DataInrConfig, fit_data_inr
    from diffshadow.volume import Volume

    blob = Volume(data=gaussian_blob(17, 0.2), extent=np.ones(3), name="blob")
    # a voxel scoring (every 30 steps) between the periodic checkpoint and the stop
    short = DataInrConfig(**{**CFG.__dict__, "steps": 60, "checkpoint_every": 20, "error_every": 30})
    whole = fit_data_inr(blob, TF, short, log=lambda m: None)
    ckpt = tmp_path / "inr.ckpt"
    with monkeypatch.context() as m:
        m.setattr(data_inr.DataInrFit, "step", signal_at(data_inr.DataInrFit, "step", 37, signal.SIGINT))
        with pytest.raises(Stopped, match="^stopped by SIGINT at step 37/60") as e:
            fit_data_inr(blob, TF, short, checkpoint=ckpt, log=lambda m: None)
    assert e.value.signum == signal.SIGINT
    messages = []
    resumed = fit_data_inr(blob, TF, short, checkpoint=ckpt, log=messages.append)
    assert any("resuming" in m and "step 37/60" in m for m in messages)
    assert torch.equal(resumed.model.flat(), whole.model.flat())


@pytest.mark.parametrize("call, where, resumed_at", [
    (6, "at epoch 3;", "at epoch 3/6"),  # the last step of epoch 3: at the epoch's end
    (7, "at step 1 of epoch 4;", "at epoch 3/6, step 1 of epoch 4"),  # inside an epoch, whose draws go on
])
def test_the_geometry_stage_stops_at_its_next_step_and_resumes_to_the_same_bytes(tmp_path, monkeypatch, call, where,
                                                                                 resumed_at):
    from test_diffusion import CFG, tiny_data

    from diffshadow.diffusion import train
    from diffshadow.diffusion.train import train_diffusion

    data = tiny_data()  # 4 lights in batches of 2: 2 steps an epoch, checkpoints every 2 epochs
    whole = train_diffusion(data, CFG, tmp_path / "a.ckpt", log=lambda *a: None)
    ckpt = tmp_path / "b.ckpt"
    with monkeypatch.context() as m:
        m.setattr(train, "train_batch", signal_at(train, "train_batch", call))  # the signal comes inside the step
        with pytest.raises(Stopped, match=f"^stopped by SIGTERM {where}"):
            train_diffusion(data, CFG, ckpt, log=lambda *a: None)
    assert torch.load(ckpt, weights_only=False)["epoch"] == 3
    messages = []
    resumed = train_diffusion(data, CFG, ckpt, log=messages.append)
    assert any(m.startswith("resuming from") and m.endswith(resumed_at) for m in messages), messages
    assert "within_epoch" not in resumed
    for key in ("model", "ema"):
        assert all(torch.equal(v, resumed[key][k]) for k, v in whole[key].items()), key
    assert str(resumed["optimizer"]) == str(whole["optimizer"])


def test_the_geometry_stage_stopped_after_an_epochs_steps_saves_that_epoch(tmp_path):
    """A signal during an epoch's log line or its growth check (sampling the seen lights: minutes at the paper's
    sizes), after the epoch's steps: the message says the epoch's checkpoint is written, and it is (it said so
    while the checkpoint held the last periodic one, up to `checkpoint_every` epochs before)."""
    from test_diffusion import CFG, tiny_data

    from diffshadow.diffusion.train import train_diffusion

    data = tiny_data()
    whole = train_diffusion(data, CFG, tmp_path / "a.ckpt", log=lambda *a: None)
    ckpt = tmp_path / "b.ckpt"

    def log(line: str) -> None:
        if line.startswith("epoch 3/6"):  # checkpoints every 2 epochs: none due at 3
            os.kill(os.getpid(), signal.SIGTERM)

    with pytest.raises(Stopped, match="^stopped by SIGTERM at epoch 3;"):
        train_diffusion(data, CFG, ckpt, log=log)
    assert torch.load(ckpt, weights_only=False)["epoch"] == 3
    resumed = train_diffusion(data, CFG, ckpt, log=lambda *a: None)
    assert all(torch.equal(v, resumed["ema"][k]) for k, v in whole["ema"].items())


@pytest.mark.parametrize("call, where, resumed_at", [
    (6, "at epoch 3/5;", "at epoch 3/5"),
    (7, "at step 1 of epoch 4/5;", "at epoch 3/5, step 1 of epoch 4"),
])
def test_fine_tuning_stops_at_its_next_step_and_resumes_to_the_same_bytes(tmp_path, monkeypatch, call, where,
                                                                          resumed_at):
    from test_finetune import FT, make_setup

    from diffshadow.analytic import gaussian_blob
    from diffshadow.diffusion import finetune as ft
    from diffshadow.volume import Volume

    volume = Volume(data=gaussian_blob(17, 0.3), extent=np.ones(3), name="blob")
    _, _, _, data, state = make_setup(volume, tmp_path)
    cfg = ft.FinetuneConfig(**{**FT.__dict__, "epochs": 5, "checkpoint_every": 2, "batch_size": 2})  # 2 steps an epoch
    whole = ft.finetune(state, data, cfg, tmp_path / "a.ckpt", log=lambda m: None)
    ckpt = tmp_path / "b.ckpt"
    with monkeypatch.context() as m:
        m.setattr(ft, "train_step", signal_at(ft, "train_step", call))
        with pytest.raises(Stopped, match=f"^stopped by SIGTERM {where}"):
            ft.finetune(state, data, cfg, ckpt, log=lambda m: None)
    assert torch.load(ckpt, weights_only=False)["finetune_epoch"] == 3
    messages = []
    resumed = ft.finetune(state, data, cfg, ckpt, log=messages.append)
    assert any("resuming from" in m and m.endswith(resumed_at) for m in messages), messages
    assert resumed["selection"] == whole["selection"] and "within_epoch" not in resumed
    assert all(torch.equal(v, resumed["model"][k]) for k, v in whole["model"].items())


def _stopping_rank(rank, world, port, data, state, out_dir, cfg, signalled_rank, call):
    """A rank of a 2-process fine-tuning job (test_finetune's `_ddp_worker`), of which `signalled_rank` alone gets
    SIGTERM in its `call`-th step; what each rank ended with, in `rank<r>.json`."""
    import json
    from pathlib import Path

    from test_finetune import _ddp_worker

    from diffshadow.diffusion import finetune as ft

    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if rank == signalled_rank:
        ft.train_step = signal_at(ft, "train_step", call)
    try:
        _ddp_worker(rank, world, port, data, state, out_dir, cfg)
    except Stopped as e:
        Path(out_dir, f"rank{rank}.json").write_text(json.dumps({"signum": e.signum, "said": str(e)}))
        from diffshadow.cli import _end

        _end(0)


def test_the_ranks_of_a_ddp_job_stop_at_one_step_and_resume_to_the_same_bytes(tmp_path):
    """Only rank 1 is signalled, in the last step of epoch 1: both ranks stop one step later, inside epoch 2, and
    rank 0's checkpoint holds that step; the job run again ends with an uninterrupted job's weights."""
    import json

    import torch.multiprocessing as mp
    from test_finetune import FT, _ddp_worker, _free_port, make_setup

    from diffshadow.analytic import gaussian_blob
    from diffshadow.volume import Volume

    volume = Volume(data=gaussian_blob(17, 0.3), extent=np.ones(3), name="blob")
    _, _, _, data, state = make_setup(volume, tmp_path)
    cfg = dataclasses.replace(FT, epochs=3, checkpoint_every=2, batch_size=2)  # 2 steps an epoch, 1 light a rank
    whole, stopped = tmp_path / "whole", tmp_path / "stopped"
    whole.mkdir(), stopped.mkdir()
    mp.spawn(_ddp_worker, args=(2, _free_port(), data, state, str(whole), cfg), nprocs=2, join=True)
    mp.spawn(_stopping_rank, args=(2, _free_port(), data, state, str(stopped), cfg, 1, 2), nprocs=2, join=True)
    said = [json.loads((stopped / f"rank{r}.json").read_text()) for r in (0, 1)]
    assert [s["signum"] for s in said] == [signal.SIGTERM] * 2  # rank 0 stopped with its peer
    assert all(s["said"].startswith("stopped by SIGTERM at step 1 of epoch 2/3;") for s in said), said
    saved = torch.load(stopped / "ddp.ckpt", weights_only=False)
    assert saved["finetune_epoch"] == 1 and saved["within_epoch"]["batches"] == 1
    mp.spawn(_ddp_worker, args=(2, _free_port(), data, state, str(stopped), cfg), nprocs=2, join=True)
    a, b = (torch.load(d / "ddp_model.pt", weights_only=True) for d in (whole, stopped))
    assert all(torch.equal(a[k], b[k]) for k in a)

