"""The fault suite: each fault injected as it happens in practice, and what must follow: a clear
one-line error or a repair by the command the error advises, artefacts identical to an
uninterrupted run, no record lost. `make test` runs every case; `make faults` runs them alone and
prints the matrix (case, outcome, seconds), with the heavier `fault_full` cases (kill -9 of every
training stage) that `make test` leaves out."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from worldenv_core.cli import EXIT_USER_ERROR, multirun_flag_first
from worldenv_core.locks import RunLock, RunLockedError
from worldenv_core.manifest import ArtefactError, Manifest, StageRecord, StageRun, sha256_file
from worldenv_core.models.checkpoint import CheckpointError, load_model, save_model, verify_checkpoint
from worldenv_core.stage import ConfigError, compose_config, resolve_checkpoint
from worldenv_core.training import Checkpoints

pytestmark = pytest.mark.fault
REPO = Path(__file__).resolve().parent.parent
TINY_POLICY = ["train.steps=20", "scale_head.steps=10", "train.log_every=5", "train.checkpoint_every=10",
               "demos_per_task=1", "policy.hidden=32", "policy.backbone.widths=[8,8,8,8]",
               "policy.backbone.keypoints=4"]


def cfg(stage, exp, *overrides):
    return compose_config(stage, ["+task=tiny", "scale=tiny", f"experiment_dir={exp}", *overrides])


def cli(*args, timeout=300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *args], cwd=REPO, capture_output=True, text=True, timeout=timeout)


def tiny_linear(path) -> Path:
    model = torch.nn.Linear(3, 2)
    return save_model(path, model, {"_target_": "torch.nn.Linear", "in_features": 3, "out_features": 2}, {"kind": "x"})


# ---------------------------------------------------------------- the manifest


def test_a_torn_manifest_line_is_set_aside_and_the_next_record_kept(tmp_path, caplog):
    m = Manifest(tmp_path)
    m.append(StageRecord("collect", {"task": "a"}, {}, "h"))
    with open(m.path, "ab") as f:  # what a crash in the middle of an append leaves
        f.write(b'{"stage": "train_policy", "tags": {"ta')
    m.append(StageRecord("collect", {"task": "b"}, {}, "h"))
    assert [r.tags["task"] for r in m.records()] == ["a", "b"]
    (aside,) = tmp_path.glob("manifest.jsonl.torn-*")
    assert aside.read_bytes() == b'{"stage": "train_policy", "tags": {"ta'
    assert "torn line" in caplog.text
    with open(m.path, "ab") as f:  # readers repair too, and a whole record that lost its newline stays
        f.write(json.dumps({"stage": "evaluate", "tags": {}, "config": {}, "config_hash": "h"}).encode())
    assert [r.stage for r in m.records()] == ["collect", "collect", "evaluate"]
    assert m.path.read_bytes().endswith(b"\n")


def test_a_corrupt_line_inside_the_manifest_is_an_error_naming_it(tmp_path):
    m = Manifest(tmp_path)
    m.append(StageRecord("collect", {}, {}, "h"))
    with open(m.path, "ab") as f:
        f.write(b"garbage\n")
    m.append(StageRecord("collect", {}, {}, "h"))
    with pytest.raises(ArtefactError, match=r"manifest.jsonl:2: unreadable manifest line"):
        m.records()


# ---------------------------------------------------------------- checkpoints


@pytest.mark.parametrize("damage", ["truncate", "garble", "nan"])
def test_a_damaged_checkpoint_folder_is_refused_naming_the_file(tmp_path, damage):
    folder = tiny_linear(tmp_path / "ckpt")
    weights = folder / "model.safetensors"
    data = weights.read_bytes()
    if damage == "truncate":
        weights.write_bytes(data[: len(data) // 2])
    elif damage == "garble":
        weights.write_bytes(data[:8] + os.urandom(len(data) - 8))
    else:  # a readable file whose floats are NaN: what a diverged training or a bad overwrite leaves
        header = 8 + int.from_bytes(data[:8], "little")
        weights.write_bytes(data[:header] + np.full((len(data) - header) // 4, np.nan, np.float32).tobytes())
    with pytest.raises(CheckpointError, match="model.safetensors"):
        verify_checkpoint(folder)
    with pytest.raises(CheckpointError, match="model.safetensors"):
        load_model(folder)


def test_a_checkpoint_folder_given_by_hand_is_verified_and_its_sha256_recorded(tmp_path):
    folder = tiny_linear(tmp_path / "ckpt")
    with StageRun(Manifest(tmp_path / "exp"), "evaluate", {}, {}) as run:
        assert resolve_checkpoint(run, str(folder), "train_policy", "tiny", "tiny") == str(folder.resolve())
    (record,) = Manifest(tmp_path / "exp").records()
    assert {a.sha256 for a in record.input_files} == {sha256_file(folder / "model.safetensors"),
                                                       sha256_file(folder / "config.json")}
    with StageRun(Manifest(tmp_path / "exp"), "evaluate", {}, {}) as run, pytest.raises(ConfigError, match="no checkpoint folder"):
        resolve_checkpoint(run, str(tmp_path / "nowhere"), "train_policy", "tiny", "tiny")
    assert oct((folder / "model.safetensors").stat().st_mode & 0o777) == oct(0o666 & ~_umask())


def _umask():
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_resume_skips_a_damaged_last_checkpoint_for_the_one_before(tmp_path, caplog):
    model = torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(model.parameters())
    ckpts = Checkpoints(tmp_path, keep=2)
    spec = {"_target_": "torch.nn.Linear", "in_features": 3, "out_features": 2}
    ckpts.save(10, model, spec, {}, {"opt": opt}, [{"step": 10}])
    ckpts.save(20, model, spec, {}, {"opt": opt}, [{"step": 10}, {"step": 20}])
    (ckpts.last / "model.safetensors").write_bytes(b"\0" * 100)
    step, history = Checkpoints(tmp_path).restore(torch.nn.Linear(3, 2), {"opt": opt})
    assert step == 10 and history == [{"step": 10}] and "is damaged" in caplog.text
    assert list((tmp_path / "checkpoints").glob("0000020.damaged-*"))


# ---------------------------------------------------------------- locks, workers


def test_a_second_run_on_the_same_target_fails_naming_the_first(tmp_path):
    with RunLock(tmp_path, "train_policy into w"):
        with pytest.raises(RunLockedError, match=rf"already running \(pid {os.getpid()} on"):
            RunLock(tmp_path, "train_policy into w").acquire()
    RunLock(tmp_path, "again").acquire().release()  # released: free again


def test_a_lock_left_by_a_dead_run_is_taken_over_with_a_warning(tmp_path, caplog):
    holder = subprocess.Popen([sys.executable, "-c", "from worldenv_core.locks import RunLock; import os, sys; "
                               f"RunLock({str(tmp_path)!r}, 'x').acquire(); print('held', flush=True); "
                               "os.kill(os.getpid(), 9)"], cwd=REPO, stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    holder.wait(timeout=30)
    with RunLock(tmp_path, "collect into d"):
        assert f"pid {holder.pid}" in caplog.text and "gone" in caplog.text


def test_workers_die_with_their_parent(tmp_path):
    """kill -9 of the process that started a pool: its workers die too and write nothing after."""
    script = f"""
import os, time
from worldenv_core.parallel import run_jobs
def job(i):
    while True:
        open({str(tmp_path)!r} + f"/w{{os.getpid()}}", "a").write("x")
        time.sleep(0.05)
if __name__ == "__main__":
    list(run_jobs(job, [0, 1], workers=2, progress=False))
"""
    (tmp_path / "pool.py").write_text(script)
    parent = subprocess.Popen([sys.executable, str(tmp_path / "pool.py")], cwd=REPO)
    deadline = time.time() + 60
    while len(list(tmp_path.glob("w*"))) < 2 and time.time() < deadline:
        time.sleep(0.2)
    workers = [int(p.name[1:]) for p in tmp_path.glob("w*")]
    assert len(workers) == 2
    parent.send_signal(signal.SIGKILL)
    parent.wait()
    time.sleep(1.0)
    alive = [w for w in workers if Path(f"/proc/{w}").exists() and "zombie" not in _state(w)]
    assert not alive, f"workers {alive} outlived their parent"
    sizes = {p: p.stat().st_size for p in tmp_path.glob("w*")}
    time.sleep(0.5)
    assert sizes == {p: p.stat().st_size for p in tmp_path.glob("w*")}


def _state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/status").read_text().lower()
    except OSError:
        return "zombie"


# ---------------------------------------------------------------- command line


def test_multirun_flag_is_accepted_anywhere():
    assert multirun_flag_first(["p", "+task=a", "-m", "x=1,2"]) == ["p", "-m", "+task=a", "x=1,2"]
    assert multirun_flag_first(["p", "--multirun", "x=1,2"]) == ["p", "--multirun", "x=1,2"]
    assert multirun_flag_first(["p", "x=1"]) == ["p", "x=1"]


def test_the_documented_sweep_order_parses_and_bad_settings_are_one_line(tmp_path):
    out = cli("stages.post_train_loop", "+task=tiny", "scale=tiny", f"experiment_dir={tmp_path}/exp", "-m",
              "rl.n_rollouts=0,1")
    assert "unrecognized arguments" not in out.stderr
    assert out.returncode == EXIT_USER_ERROR and "error: rl.n_rollouts must be at least 2" in out.stderr, out.stderr


def test_a_refused_run_leaves_no_empty_run_folder(tmp_path):
    out = cli("stages.evaluate", "+task=tiny", "scale=tiny", f"experiment_dir={tmp_path}/empty")
    assert out.returncode == EXIT_USER_ERROR and "no 'train_policy' artefact" in out.stderr
    assert not (tmp_path / "empty").exists()


def test_tiny_scale_checkpoints_inside_its_runs():
    for stage, steps, every in (("train_policy", "train.steps", "train.checkpoint_every"),
                                ("train_reflector", "train.steps", "train.checkpoint_every"),
                                ("train_worldsim", "flow.steps", "checkpoint_every")):
        c = compose_config(stage, ["+task=tiny", "scale=tiny"])
        from omegaconf import OmegaConf

        assert OmegaConf.select(c, every) < OmegaConf.select(c, steps), stage


# ---------------------------------------------------------------- the real stages


@pytest.mark.sim
@pytest.mark.slow
@pytest.mark.parametrize("damage", ["truncate", "delete"])
def test_a_damaged_or_deleted_episode_is_recollected_bit_identical_by_rerunning_collect(demo_experiment, damage):
    exp = demo_experiment
    (ep, _) = sorted(Manifest(exp).resolve(Manifest(exp).latest("collect", source="expert"), kind="episodes"))
    original = sha256_file(ep)
    if damage == "truncate":  # a disk filled, a copy cut short
        ep.write_bytes(ep.read_bytes()[: ep.stat().st_size // 2])
    else:
        ep.unlink()
    with pytest.raises(ArtefactError, match=("stale" if damage == "truncate" else "missing on disk")
                       + r".*`python -m stages.collect \+task=tiny scale=tiny source=expert post_success_steps=8"):
        Manifest(exp).resolve(Manifest(exp).latest("collect", source="expert"))
    from stages.collect.run import run as collect

    out = collect(cfg("collect", exp, f"data_dir={exp / 'data'}", "episodes_per_task=2", "post_success_steps=8",
                      "workers=1", "progress=false", "lerobot_export=false"))
    assert out["collection"]["recollected_damaged"] == (damage == "truncate") and out["collection"]["kept"] == 1
    assert sha256_file(ep) == original
    if damage == "truncate":
        assert list(ep.parent.glob(ep.name + ".damaged-*"))  # kept for inspection
    Manifest(exp).resolve(Manifest(exp).latest("collect", source="expert"))  # verified again


@pytest.mark.sim
@pytest.mark.slow
def test_a_stale_checkpoint_is_repaired_by_rerunning_its_stage(demo_experiment):
    from stages.train_policy.run import run as train_policy

    train_policy(cfg("train_policy", demo_experiment, *TINY_POLICY))
    m = Manifest(demo_experiment)
    weights = next(p for p in m.resolve(m.latest("train_policy")) if p.name == "model.safetensors")
    original = sha256_file(weights)
    weights.write_bytes(weights.read_bytes()[:1000])
    with pytest.raises(ArtefactError, match=r"stale.*re-running the stage .*`python -m stages.train_policy "
                                            r"\+task=tiny scale=tiny experiment_dir="):
        m.resolve(m.latest("train_policy"))
    again = train_policy(cfg("train_policy", demo_experiment, *TINY_POLICY))  # the advised repair
    assert again["train_wall_s"] < 5 and sha256_file(weights) == original
    m.resolve(m.latest("train_policy"))


WORLDSIM = ["expert_only=true", "ae.steps=30", "flow.steps=30", "ae.batch_size=4", "flow.batch_size=4",
            "holdout_every=2", "log_every=5", "checkpoint_every=10", "worldsim.ae_widths=[8,16]", "worldsim.width=16",
            "worldsim.map_channels=4", "fidelity.horizons=[8]", "fidelity.starts_per_episode=1", "fidelity.videos=0"]
REFLECTOR = ["expert_only=true", "train.steps=60", "train.batch_size=4", "train.log_every=5",
             "train.checkpoint_every=10", "train.mine.every=10", "holdout_every=2", "reflector.d_model=16",
             "reflector.layers=1", "reflector.heads=2", "reflector.frame_encoder.widths=[8,16]",
             "reflector.frame_encoder.keypoints=4", "plots=0", "imagined.enabled=false", "eta_folds=0"]
LOOP = ["expert_only=true", "rl.iterations=8", "rl.contexts_per_iteration=1", "rl.n_rollouts=2", "rl.horizon=16",
        "rl.minibatch=2", "eval.every=0", "eval.imagined_contexts=0", "eval.record_contexts=0", "progress=false"]
KILLS = {  # stage -> (its overrides, steps between checkpoints, how many there are)
    "train_policy": ([o for o in TINY_POLICY if not o.startswith(("train.steps", "scale_head.steps"))]
                     + ["train.steps=60", "scale_head.steps=20"], 10, 8),
    "train_worldsim": (WORLDSIM, 10, 6),
    "train_reflector": (REFLECTOR, 10, 6),
    "post_train_loop": (LOOP, 1, 8),
}


def _killed_at_random_and_resumed(stage: str, source: Path, tmp_path: Path) -> None:
    """kill -9 of `stage` after a random number of checkpoints, then the same command again: the
    weights are those of an uninterrupted run, bit for bit, and the killed run recorded nothing."""
    overrides, every, count = KILLS[stage]
    straight, killed = tmp_path / "straight", tmp_path / "killed"
    shutil.copytree(source, straight)
    shutil.copytree(source, killed)
    args = [f"stages.{stage}", "+task=tiny", "scale=tiny", *overrides]
    done = cli(*args, f"experiment_dir={straight}", timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    stop_after = int(np.random.default_rng().integers(1, count))
    before = len(Manifest(killed).find(stage))
    proc = subprocess.Popen([sys.executable, "-m", *args, f"experiment_dir={killed}"], cwd=REPO,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        steps = [int(p.name) for p in killed.glob(f"{stage}/*/checkpoints/[0-9]*[0-9]")]
        if steps and max(steps) >= every * stop_after:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before it could be killed"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert len(Manifest(killed).find(stage)) == before, "a killed stage records nothing"
    assert cli(*args, f"experiment_dir={killed}", timeout=600).returncode == 0
    weights = [sorted(p for p in Manifest(e).resolve(Manifest(e).latest(stage)) if p.name == "model.safetensors")
               for e in (straight, killed)]
    assert [sha256_file(p) for p in weights[0]] == [sha256_file(p) for p in weights[1]]


@pytest.mark.sim
@pytest.mark.slow
def test_a_training_killed_at_a_random_checkpoint_resumes_to_identical_weights(_tiny_demos, tmp_path):
    _killed_at_random_and_resumed("train_policy", _tiny_demos, tmp_path)  # the demos alone: nothing trained yet


@pytest.fixture(scope="module")
def trained_for_loop(_tiny_demos, tmp_path_factory):
    """The tiny demos with a policy, a world model and a reflector: what post_train_loop needs."""
    exp = tmp_path_factory.mktemp("loop") / "experiment"
    shutil.copytree(_tiny_demos, exp)
    for stage, overrides in (("train_policy", TINY_POLICY), ("train_worldsim", WORLDSIM),
                             ("train_reflector", REFLECTOR)):
        out = cli(f"stages.{stage}", "+task=tiny", "scale=tiny", *overrides, f"experiment_dir={exp}", timeout=600)
        assert out.returncode == 0, out.stderr[-2000:]
    return exp


@pytest.mark.fault_full
@pytest.mark.sim
@pytest.mark.slow
@pytest.mark.parametrize("stage", ["train_worldsim", "train_reflector"])
def test_every_training_stage_killed_at_a_random_checkpoint_resumes_identically(stage, _tiny_demos, tmp_path):
    _killed_at_random_and_resumed(stage, _tiny_demos, tmp_path)


@pytest.mark.fault_full
@pytest.mark.sim
@pytest.mark.slow
def test_post_train_loop_killed_at_a_random_iteration_resumes_identically(trained_for_loop, tmp_path):
    _killed_at_random_and_resumed("post_train_loop", trained_for_loop, tmp_path)


@pytest.mark.sim
@pytest.mark.slow
def test_two_collections_at_once_one_runs_the_other_is_refused_naming_it(tmp_path):
    args = ["stages.collect", "+task=tiny", "scale=tiny", f"experiment_dir={tmp_path}/exp", f"data_dir={tmp_path}/data",
            "episodes_per_task=1", "workers=1", "lerobot_export=false", "progress=false"]
    first = subprocess.Popen([sys.executable, "-m", *args], cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                             text=True)
    deadline = time.time() + 120
    while not list(tmp_path.glob("data/tiny/*/.lock")) and time.time() < deadline:
        time.sleep(0.05)
    second = cli(*args)
    assert first.wait(timeout=300) == 0
    assert second.returncode == EXIT_USER_ERROR, second.stderr
    (line,) = second.stderr.strip().splitlines()
    assert "collect into" in line and f"already running (pid {first.pid} on" in line
    assert len(Manifest(tmp_path / "exp").find("collect")) == 1


@pytest.mark.parametrize("override, needle", [
    ("rl.n_rollouts=0", "rl.n_rollouts must be at least 2"),
    ("eta=2", "eta (the reflector's success threshold) must be in [0, 1]"),
    ("rl.epsilon=0", "rl.epsilon (the PPO clip) must be > 0"),
    ("policy_from=./no/such/folder", "no checkpoint folder at ./no/such/folder"),
], ids=["n_rollouts=0", "eta=2", "epsilon=0", "policy_from=missing path"])
def test_bad_settings_are_refused_in_seconds_naming_the_key(tmp_path, override, needle):
    from stages.post_train_loop.run import run as post_train_loop

    t0 = time.perf_counter()
    with pytest.raises((ConfigError, ArtefactError)) as e:
        post_train_loop(cfg("post_train_loop", tmp_path, override))
    assert needle in str(e.value) and time.perf_counter() - t0 < 30
