"""Training curves in a tracker: TensorBoard event files that TensorBoard reads back, wandb
offline runs, nothing with logger=none, and the running means of a training loop sent to it."""

import math

import pytest
from omegaconf import OmegaConf
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from worldenv_core.stage import compose_config
from worldenv_core.tracking import TensorBoardTracker, Tracker, make_tracker, scalars
from worldenv_core.training import RunningMeans


def read_scalars(log_dir) -> dict[str, list[tuple[int, float]]]:
    acc = EventAccumulator(str(log_dir))
    acc.Reload()
    return {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}


def test_scalars_keep_finite_numbers_under_their_group():
    entry = {"step": 5, "loss": 0.5, "n": 3, "flag": True, "name": "x", "bad": math.nan, "list": [1.0]}
    assert scalars(entry, "train") == {"train/loss": 0.5, "train/n": 3.0}


def test_tensorboard_event_files_hold_what_was_logged_and_a_resumed_run_appends(tmp_path):
    with TensorBoardTracker(tmp_path / "tb") as tb:
        tb.log({"step": 1, "loss": 1.0}, 1)
        tb.log({"real_success": 0.25}, 1, group="eval")
    with TensorBoardTracker(tmp_path / "tb") as tb:  # a second sitting of the same run
        tb.log({"loss": 0.5}, 2)
    got = read_scalars(tmp_path / "tb")
    # TensorBoard reads the two sittings' event files in name order, which ties within a second (the order
    # of the points within a tag is not the claim; the plot goes by step)
    assert sorted(got["train/loss"]) == [(1, 1.0), (2, 0.5)] and got["eval/real_success"] == [(1, 0.25)]


def test_running_means_send_each_history_entry_to_the_tracker(tmp_path):
    history = []
    with TensorBoardTracker(tmp_path / "tb") as tb:
        running = RunningMeans(history, every=2, tracker=tb)
        for step in range(1, 6):
            running.add(loss=float(step))
            running.end_step(step, total=5)
    assert [h["step"] for h in history] == [2, 4, 5]
    assert read_scalars(tmp_path / "tb")["train/loss"] == [(2, 1.5), (4, 3.5), (5, 5.0)]


@pytest.mark.parametrize("logger, kind", [("tensorboard", "TensorBoardTracker"), ("none", "Tracker")])
def test_the_logger_group_selects_the_tracker(tmp_path, logger, kind):
    cfg = compose_config("train_policy", ["+task=tiny", "scale=tiny", f"logger={logger}"])
    with make_tracker(cfg.logger, tmp_path / "work", "train_policy", "tiny") as tracker:
        assert type(tracker).__name__ == kind
    assert (tmp_path / "work" / "tensorboard").is_dir() == (logger == "tensorboard")


def test_wandb_runs_offline_in_the_work_dir(tmp_path, monkeypatch):
    pytest.importorskip("wandb")
    monkeypatch.setenv("WANDB_MODE", "offline")
    cfg = compose_config("train_policy", ["+task=tiny", "scale=tiny", "logger=wandb"])
    assert cfg.logger.mode == "offline"
    with make_tracker(cfg.logger, tmp_path / "work", "train_policy", "tiny", OmegaConf.to_container(cfg.train)) as tracker:
        tracker.log({"loss": 1.0}, 1)
    runs = list((tmp_path / "work" / "wandb").glob("offline-run-*"))
    assert len(runs) == 1 and list(runs[0].glob("*.wandb"))


def test_none_tracker_accepts_anything():
    t = Tracker()
    t.log({"loss": 1.0}, 0)
    t.close()
