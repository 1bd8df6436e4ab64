"""Which collected episodes the world-simulator and reflector stages read, and their split."""
import pytest

from worldenv_core.data.selection import MissingEpisodesError, collected_episodes, holdout_split
from worldenv_core.manifest import Manifest, StageRun


def _collect(manifest, folder, source, names):
    folder.mkdir(parents=True, exist_ok=True)
    with StageRun(manifest, "collect", {"task": "goal", "scale": "small", "source": source}, {"n": len(names)}) as run:
        for name in names:
            (folder / name).write_bytes(name.encode())
            run.add_output(folder / name, kind="episodes")
    return [(folder / n).resolve() for n in names]


def test_latest_expert_and_latest_policy_collection(tmp_path):
    m = Manifest(tmp_path / "exp")
    _collect(m, tmp_path / "expert-old", "expert", ["e0.mcap"])
    expert = _collect(m, tmp_path / "expert-new", "expert", ["e0.mcap", "e1.mcap"])
    _collect(m, tmp_path / "policy-a", "policy", ["p0.mcap", "p1.mcap"])  # the same rollouts, shorter
    policy = _collect(m, tmp_path / "policy-b", "policy", ["p0.mcap", "p1.mcap"])
    with StageRun(m, "train_reflector", {}, {}) as stage:
        assert collected_episodes(m, stage, "goal", "small", expert_only=False) == sorted(expert + policy)
        assert len(stage.inputs) == 2  # the newest expert and the newest policy record
        assert collected_episodes(m, stage, "goal", "small", expert_only=True) == sorted(expert)


def test_all_policy_collections_are_the_newest_of_each_folder(tmp_path):
    """policy_collections=all (exploration at several noise scales, a refit round's improved policy): every
    collection folder once, at its newest record, each an input; a rerun into one folder is not read twice."""
    m = Manifest(tmp_path / "exp")
    expert = _collect(m, tmp_path / "expert" / "task00", "expert", ["e0.mcap"])
    _collect(m, tmp_path / "policy-sft" / "task00", "policy", ["p0.mcap"])
    sft = _collect(m, tmp_path / "policy-sft" / "task00", "policy", ["p0.mcap", "p1.mcap"])  # the same, extended
    improved = _collect(m, tmp_path / "policy-improved" / "task00", "policy", ["p0.mcap"])
    with StageRun(m, "train_worldsim", {}, {}) as stage:
        assert collected_episodes(m, stage, "goal", "small", False, "all") == sorted(expert + sft + improved)
        assert len(stage.inputs) == 3  # the expert record and the newest of each policy folder
    with StageRun(m, "train_worldsim", {}, {}) as stage:
        assert collected_episodes(m, stage, "goal", "small", False) == sorted(expert + improved)  # "latest"
        with pytest.raises(ValueError, match="policy_collections"):
            collected_episodes(m, stage, "goal", "small", False, "newest")


def test_missing_policy_rollouts_name_the_fix(tmp_path):
    m = Manifest(tmp_path / "exp")
    _collect(m, tmp_path / "expert", "expert", ["e0.mcap"])
    with StageRun(m, "train_reflector", {}, {}) as stage, pytest.raises(MissingEpisodesError, match="source=policy"):
        collected_episodes(m, stage, "goal", "small", expert_only=False)


def test_every_nth_episode_is_held_out_and_at_least_one():
    paths = [f"e{i}" for i in range(7)]
    train, held = holdout_split(paths, 3)
    assert held == ["e2", "e5"] and len(train) == 5
    assert holdout_split(paths[:2], 5)[1] == ["e1"]
