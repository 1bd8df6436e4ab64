"""The collect stage end to end on the tiny task: the real simulator, the real expert, MCAP out."""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from stages.collect.run import episode_dir, job_order, run
from worldenv_core.contract import TaskContract
from worldenv_core.data.mcap_io import read_episode
from worldenv_core.envs.collection import ExpertEpisodeJob, collect_expert_episode
from worldenv_core.envs.tasks import UnknownTaskError
from worldenv_core.manifest import Manifest
from worldenv_core.stage import CONF_DIR, ConfigError

REPO = Path(__file__).resolve().parents[3]


def make_cfg(tmp_path, *overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("collect", overrides=[
            "+task=tiny", "scale=tiny", f"experiment_dir={tmp_path / 'exp'}", f"data_dir={tmp_path / 'data'}",
            "workers=1", "progress=false", *overrides])


@pytest.mark.parametrize("override, message", [
    ("source=teleop", "source must be one of expert, policy"),
    ("episodes_per_task=-2", "episodes_per_task must be an integer >= 0"),
    ("max_attempts=0", "max_attempts must be an integer > 0"),
    ("init_states=random", "init_states must be one of sampled, benchmark"),
    ("workers=0", "workers must be an integer > 0"),
    ("expert_eval.init_states=51", "at most 50"),
])
def test_bad_settings_fail_before_anything_is_written(tmp_path, override, message):
    with pytest.raises(ConfigError, match=message):
        run(make_cfg(tmp_path, override))
    assert not (tmp_path / "data").exists() and not (tmp_path / "exp").exists()


def test_unknown_task_id_and_unwritable_output(tmp_path):
    with pytest.raises(UnknownTaskError, match=r"tasks 0\.\.9"):
        run(make_cfg(tmp_path, "task.task_ids=[42]"))
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    with pytest.raises(ConfigError, match="not writable"):
        run(make_cfg(tmp_path, f"experiment_dir={blocker / 'exp'}"))


def test_missing_task_lists_valid_tasks(tmp_path):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("collect", overrides=[f"experiment_dir={tmp_path}"])
    with pytest.raises(ConfigError, match="libero_goal, libero_object, libero_spatial, suite, tiny"):
        run(cfg)


def test_cli_rejects_an_unknown_task_with_the_valid_ones():
    out = subprocess.run([sys.executable, "-m", "stages.collect", "+task=libero_nope"], cwd=REPO,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode != 0
    assert "Could not find 'task/libero_nope'" in out.stderr and "libero_goal" in out.stderr


@pytest.mark.sim
@pytest.mark.slow
def test_killed_collection_resumes_and_reproduces_the_episodes(tmp_path):
    """Kill a real collection run after its first episode, restart it, and check the result is the
    set of episodes an uninterrupted run produces (seeds and file names depend on the job alone)."""
    cfg = make_cfg(tmp_path, "episodes_per_task=2")
    out_dir = episode_dir(cfg)
    args = [sys.executable, "-m", "stages.collect", "+task=tiny", "scale=tiny", "workers=1", "progress=false",
            "episodes_per_task=2", f"experiment_dir={tmp_path / 'exp'}", f"data_dir={tmp_path / 'data'}"]
    proc = subprocess.Popen(args, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    first = out_dir / "task00" / "expert_0000.mcap"
    deadline = time.time() + 300
    while not first.exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert first.exists(), "the first episode was never written"
    assert not (out_dir / "task00" / "expert_0001.mcap").exists(), "killed too late to test resume"
    assert Manifest(tmp_path / "exp").records() == [], "a killed stage must not claim its outputs"

    summary = run(cfg)
    col = summary["collection"]
    assert (col["resumed"], col["kept"], col["failed"]) == (1, 1, 0)
    files = sorted(out_dir.rglob("*.mcap"))
    assert [f.name for f in files] == ["expert_0000.mcap", "expert_0001.mcap"]
    assert not list(out_dir.rglob("*.tmp"))

    record = Manifest(tmp_path / "exp").latest("collect", task="tiny", source="expert")
    assert sorted(Manifest(tmp_path / "exp").resolve(record, kind="episodes")) == [f.resolve() for f in files]
    assert record.metrics["collection"]["kept_frames_per_s"] > 0
    assert (out_dir / "lerobot" / "meta" / "info.json").exists()
    assert record.files("lerobot"), "the LeRobot export is recorded in the manifest"
    info = out_dir / "lerobot" / "meta" / "info.json"
    built = info.stat().st_mtime_ns
    again = run(cfg)  # finished with these settings: nothing is collected, read or exported again
    assert info.stat().st_mtime_ns == built and again["collection"] == summary["collection"]
    repeat = Manifest(tmp_path / "exp").latest("collect", task="tiny", source="expert")
    assert repeat.repeats == record.id and repeat.files("lerobot")

    # Same job, fresh file: bit-identical to what the killed run wrote.
    ref = tmp_path / "ref.mcap"
    job = ExpertEpisodeJob(TaskContract.from_config(cfg.task), 0, 0, str(ref), cfg.seed, cfg.init_states,
                           cfg.max_attempts)
    assert collect_expert_episode(job)["status"] == "kept"
    a, b = read_episode(first), read_episode(ref)
    assert a.equals(b)
    ep = read_episode(files[1])
    assert ep.meta.success and ep.success[-1] and not ep.success[0]
    assert ep.meta.source == "expert" and ep.meta.init_state_index == -1
    assert ep.images["agentview"].shape == (ep.length + 1, 64, 64, 3)
    assert np.isfinite(ep.sim_state).all()


def test_lerobot_dataset_import_becomes_mcap_episodes_in_the_manifest(tmp_path):
    """A user's local LeRobotDataset of LIBERO demos: imported, matched to benchmark tasks by
    instruction, written as MCAP, recorded, and exported back as LeRobot v3."""
    from worldenv_core.data.episode import Episode, EpisodeMeta
    from worldenv_core.data.lerobot_io import export_lerobot
    from worldenv_core.envs.tasks import get_task

    rng = np.random.default_rng(0)
    episodes = []
    for task_id in (3, 5):
        spec = get_task("libero_object", task_id)
        T = 6
        episodes.append(Episode(
            meta=EpisodeMeta(suite="", task_id=99, task_name="x", instruction=spec.instruction, init_state_index=-1,
                             seed=-1, source="import", success=True, cameras=["agentview"]),
            images={"agentview": rng.integers(0, 255, (T + 1, 16, 16, 3), dtype=np.uint8)},
            proprio=rng.normal(size=(T + 1, 7)).astype(np.float32), joint_pos=np.zeros((T + 1, 7)),
            sim_state=np.zeros((T + 1, 0)), success=np.arange(T + 1) == T,
            actions=rng.uniform(-1, 1, (T, 7)).astype(np.float32)))
    export_lerobot(episodes, tmp_path / "users_dataset", repo_id="someone/libero_object_demos", fps=20)

    summary = run(make_cfg(tmp_path, "source=lerobot", f"lerobot_import.root={tmp_path / 'users_dataset'}",
                           "lerobot_import.repo_id=someone/libero_object_demos"))
    assert summary["collection"]["episodes"] == 2
    m = Manifest(tmp_path / "exp")
    rec = m.latest("collect", task="tiny", source="lerobot")
    paths = m.resolve(rec, kind="episodes")
    loaded = sorted((read_episode(p) for p in paths), key=lambda e: e.meta.task_id)
    assert [e.meta.task_id for e in loaded] == [3, 5]
    assert loaded[0].meta.task_name == get_task("libero_object", 3).name
    assert np.array_equal(loaded[1].actions, episodes[1].actions)
    assert rec.files("lerobot")


def test_lerobot_import_needs_a_folder(tmp_path):
    with pytest.raises(ConfigError, match="lerobot_import.root"):
        run(make_cfg(tmp_path, "source=lerobot"))


@pytest.mark.sim
def test_expert_evaluation_on_a_local_ray_instance(tmp_path):
    # one Ray worker: the launcher's fan-out is test_parallel's; each worker's start (torch, MuJoCo) is most of the cost
    summary = run(make_cfg(tmp_path, "episodes_per_task=0", "expert_eval.init_states=2", "launcher=ray", "workers=1"))
    (row,) = summary["expert_eval"]
    assert row["n"] == 2 and row["successes"] >= 1
    assert "| 0 | " in (tmp_path / "exp" / "expert_table.md").read_text()


def test_a_long_collection_goes_round_by_round_so_any_prefix_covers_every_task():
    order = job_order([0, 3, 7], 25, rounds_of=10)
    assert sorted(order) == sorted((t, k) for t in (0, 3, 7) for k in range(25))  # every episode once
    assert order[:12] == [(0, k) for k in range(10)] + [(3, 0), (3, 1)]
    first = order[:30]  # a collection stopped after 30 episodes: ten of every task
    assert {t: sum(1 for x, _ in first if x == t) for t in (0, 3, 7)} == {0: 10, 3: 10, 7: 10}
    assert order[-5:] == [(7, k) for k in range(20, 25)]
    assert job_order([1, 2], 5) == [(1, k) for k in range(5)] + [(2, k) for k in range(5)]  # demos: task by task
