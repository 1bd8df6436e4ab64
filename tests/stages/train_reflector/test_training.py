"""How train_reflector trains: cross-validation folds and the eta they choose."""
from pathlib import Path

import pytest

from stages.train_reflector.evaluation import ETA_SWEEP
from stages.train_reflector.training import cross_validate_eta, cross_validation_folds
from worldenv_core.stage import ConfigError, compose_config

SMALL = ["train.steps=6", "train.batch_size=4", "train.log_every=2", "train.checkpoint_every=3", "holdout_every=2",
         "reflector.d_model=16", "reflector.layers=1", "reflector.heads=2", "reflector.frame_encoder.widths=[8,16]",
         "reflector.frame_encoder.keypoints=4", "plots=1", "train.mine.every=3", "eta_folds=0"]


def test_cross_validation_folds_partition_the_training_episodes_in_sorted_order():
    paths = [Path(f"c/task00/e{i}.mcap") for i in (3, 0, 5, 1, 4, 2)]
    folds = cross_validation_folds(paths, 3)
    assert [[paths[i].stem for i in f] for f in folds] == [["e0", "e3"], ["e1", "e4"], ["e2", "e5"]]
    assert sorted(i for f in folds for i in f) == list(range(6))
    with pytest.raises(ConfigError, match="eta_folds=7 needs 2 <= folds <= the 6 training episodes"):
        cross_validation_folds(paths, 7)


def test_eta_cross_validation_scores_every_training_episode_out_of_fold_and_resumes(tmp_path, synthetic_episodes,
                                                                                    contract):
    """Two fold reflectors on synthetic episodes: each episode is scored once, by the model that
    did not train on it; a rerun finds the finished folds and trains nothing."""
    from worldenv_core.models.checkpoint import read_config
    from worldenv_core.models.text import InstructionEncoder

    eps = synthetic_episodes(0, 8)
    paths = [Path(f"c/task00/e{i}.mcap") for i in range(8)]
    c = compose_config("train_reflector", ["+task=tiny", "scale=tiny", "eta_folds=2", "frame_stride=4",
                                           *[o for o in SMALL if not o.startswith(("holdout", "plots", "eta_folds"))]])
    out = cross_validate_eta(c, contract(), paths, eps, tmp_path, "cpu", InstructionEncoder())
    assert out["folds"] == 2 and out["episodes"] == 8 and out["chosen_eta"] in ETA_SWEEP
    assert all(m["episodes"] == 8 for m in out["eta_sweep"].values())  # every training episode once, out of fold
    for k, fold in enumerate(cross_validation_folds(paths, 2)):
        meta = read_config(tmp_path / "folds" / f"{k + 1}-of-2" / "checkpoints" / "last")["meta"]
        assert meta["held_out"] == [f"c/task00/e{i}.mcap" for i in fold] and meta["episodes"] == 4
    assert cross_validate_eta(c, contract(), paths, eps, tmp_path, "cpu", InstructionEncoder()) == out  # resumed: same choice
