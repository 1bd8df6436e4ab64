"""Fault suite, storage and signals: full and unwritable file systems (real ones: a small tmpfs
mounted for the test where the machine allows it), interrupts by real signals, checkpoints whose
files contradict each other, and collections too big for the disk. Part of `make faults`."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from worldenv_core.cli import EXIT_USER_ERROR
from worldenv_core.files import DiskFullError, write_bytes_atomic
from worldenv_core.manifest import Manifest, StageRecord
from worldenv_core.models.checkpoint import CheckpointError, load_checkpoint, load_model, save_model
from worldenv_core.stage import ConfigError, compose_config
from worldenv_core.training import Checkpoints

pytestmark = pytest.mark.fault
REPO = Path(__file__).resolve().parent.parent
PAGE = 4096
TINY_POLICY = ["train.steps=30", "scale_head.steps=10", "train.log_every=5", "train.checkpoint_every=10",
               "demos_per_task=1", "policy.hidden=32", "policy.backbone.widths=[8,8,8,8]",
               "policy.backbone.keypoints=4"]


def cli(*args, timeout=300, cwd=REPO) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *args], cwd=cwd, capture_output=True, text=True, timeout=timeout)


def _mount(target: Path, options: str) -> bool:
    target.mkdir(parents=True, exist_ok=True)
    return subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(target)],
                          capture_output=True).returncode == 0


@pytest.fixture
def small_fs(tmp_path):
    """A real 256 KiB tmpfs; `fill(free)` leaves about `free` bytes on it (whole pages)."""
    fs = tmp_path / "fs"
    if not _mount(fs, "size=256k"):
        pytest.skip("mounting a small tmpfs needs root (or CAP_SYS_ADMIN) on this machine")

    yield SmallFs(fs)
    subprocess.run(["umount", "-l", str(fs)], capture_output=True)


class SmallFs:
    def __init__(self, root: Path):
        self.root = root

    def fill(self, free: int) -> None:
        with open(self.root / ".filler", "ab") as f:
            while shutil.disk_usage(self.root).free > free:
                f.write(b"\0" * PAGE)
                f.flush()


def _record(n_bytes: int) -> StageRecord:
    return StageRecord("evaluate", {"task": "t"}, {}, "h", metrics={"blob": "x" * n_bytes})


# ---------------------------------------------------------------- full disks


def test_a_manifest_append_on_a_full_disk_leaves_the_manifest_as_it_was(small_fs):
    m = Manifest(small_fs.root / "exp")
    m.append(_record(100))
    before = m.path.read_bytes()
    small_fs.fill(PAGE)  # room for part of the next record only: the kernel's write comes back short
    with pytest.raises(DiskFullError, match=r"manifest.jsonl \(.* free there\)"):
        m.append(_record(12 * PAGE))
    assert m.path.read_bytes() == before
    assert [r.metrics["blob"][:1] for r in m.records()] == ["x"]
    assert sorted(p.name for p in m.root.iterdir()) == ["manifest.jsonl"]  # nothing torn, nothing set aside


def test_a_torn_line_on_a_full_disk_is_not_set_aside_half(small_fs):
    m = Manifest(small_fs.root / "exp")
    m.append(_record(100))
    torn = b'{"stage": "train_policy", "tags": {"ta' + b"y" * (3 * PAGE)
    with open(m.path, "ab") as f:
        f.write(torn)
    before = m.path.read_bytes()
    small_fs.fill(0)
    with pytest.raises(DiskFullError, match=r"manifest.jsonl \("):
        m.append(_record(10))
    assert m.path.read_bytes() == before  # the torn line stays for the next run to set aside, whole
    assert sorted(p.name for p in m.root.iterdir()) == ["manifest.jsonl"]


def test_the_short_writes_of_an_append_are_continued(tmp_path, monkeypatch):
    """What a nearly full disk or a signal does to one `write`: it returns short. The line is
    still written whole."""
    m = Manifest(tmp_path)
    real_write = os.write
    monkeypatch.setattr(os, "write", lambda fd, data: real_write(fd, bytes(data[:700])))
    m.append(_record(5000))
    monkeypatch.undo()
    assert [len(r.metrics["blob"]) for r in m.records()] == [5000]


def test_a_checkpoint_save_on_a_full_disk_is_one_line_and_leaves_nothing_half_made(small_fs):
    ckpts = Checkpoints(small_fs.root / "work", keep=2)
    small_model, spec = torch.nn.Linear(3, 2), {"_target_": "torch.nn.Linear", "in_features": 3, "out_features": 2}
    opt = torch.optim.Adam(small_model.parameters())
    ckpts.save(1, small_model, spec, {}, {"opt": opt}, [])
    big = torch.nn.Linear(256, 256)  # 257 KiB of weights: more than the device holds
    with pytest.raises(DiskFullError, match=r"0000002 \(.* free there\): free some space"):
        ckpts.save(2, big, {**spec, "in_features": 256, "out_features": 256}, {}, {"opt": opt}, [])
    assert sorted(p.name for p in ckpts.dir.iterdir()) == ["0000001", "last"]
    assert ckpts.last.name == "0000001"
    with pytest.raises(DiskFullError, match="weights.bin"):
        write_bytes_atomic(small_fs.root / "weights.bin", b"\0" * (300 << 10))
    assert not list(small_fs.root.glob("weights.bin*"))


@pytest.mark.fault_full
@pytest.mark.sim
@pytest.mark.slow
def test_a_disk_that_fills_during_training_is_one_line_naming_the_checkpoint(demo_experiment, tmp_path):
    used = sum(p.stat().st_size for p in demo_experiment.rglob("*") if p.is_file())
    fs = tmp_path / "fs"
    if not _mount(fs, f"size={(used >> 10) + 300}k"):  # the demos fit, the tiny scale's first checkpoint does not
        pytest.skip("mounting a small tmpfs needs root (or CAP_SYS_ADMIN) on this machine")
    try:
        shutil.copytree(demo_experiment, fs / "exp")
        policy = [o for o in TINY_POLICY if not o.startswith("policy.")]
        out = cli("stages.train_policy", "+task=tiny", "scale=tiny", *policy, f"experiment_dir={fs / 'exp'}")
        assert out.returncode == EXIT_USER_ERROR, out.stderr[-2000:]
        line = out.stderr.strip().splitlines()[-1]  # after the progress bar
        assert line.startswith("error: no space left on the device writing ") and "/checkpoints/0000010 (" in line
        assert "Traceback" not in out.stderr
        assert not [p for p in fs.rglob("*") if p.name.endswith((".tmp", ".staging"))]
        assert not Manifest(fs / "exp").find("train_policy")
    finally:
        subprocess.run(["umount", "-l", str(fs)], capture_output=True)


# ---------------------------------------------------------------- unwritable locations


@pytest.mark.parametrize("where", ["proc", "read_only", "under_a_file"])
def test_unwritable_output_folders_are_one_line_before_anything_is_made(tmp_path, where):
    if where == "proc":
        target = Path("/proc/worldenv-test/exp")
    elif where == "read_only":
        if not _mount(tmp_path / "ro", "size=64k,ro"):
            pytest.skip("mounting a read-only tmpfs needs root (or CAP_SYS_ADMIN) on this machine")
        target = tmp_path / "ro" / "exp"
    else:
        (tmp_path / "a_file").write_text("")
        target = tmp_path / "a_file" / "exp"
    try:
        for key in ("experiment_dir", "data_dir") if where == "proc" else ("experiment_dir",):
            args = ["stages.collect", "+task=tiny", "scale=tiny", f"experiment_dir={tmp_path / 'exp'}", f"{key}={target}"]
            out = cli(*args, timeout=120)
            assert out.returncode == EXIT_USER_ERROR, out.stderr[-2000:]
            (line,) = out.stderr.strip().splitlines()
            assert line.startswith(f"error: {key} {target} is not writable")
        assert not (tmp_path / "exp").exists() and not target.exists()
    finally:
        subprocess.run(["umount", "-l", str(tmp_path / "ro")], capture_output=True)


def test_a_collection_too_big_for_its_bound_or_the_disk_is_refused_naming_both(tmp_path, small_fs):
    from stages.collect.run import validate

    huge = compose_config("collect", ["+task=libero_spatial", f"experiment_dir={tmp_path}", "episodes_per_task=1000000"])
    with pytest.raises(ConfigError, match=r"up to about 55\.4 TiB, over max_collection_gb=200 \(.* free in"):
        validate(huge)
    small = compose_config("collect", ["+task=tiny", "scale=tiny", f"experiment_dir={tmp_path}",
                                       f"data_dir={small_fs.root}", "episodes_per_task=3"])
    with pytest.raises(ConfigError, match=rf"more than the .* free in data_dir {small_fs.root}"):
        validate(small)


# ---------------------------------------------------------------- interrupts

@pytest.mark.sim
@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGINT, pytest.param(signal.SIGTERM, marks=pytest.mark.fault_full)],
                         ids=["SIGINT", "SIGTERM"])  # the same path twice: make test runs the one, make faults both
def test_an_interrupt_is_one_line_and_the_same_command_resumes(demo_experiment, tmp_path, signum):
    exp = tmp_path / "exp"
    shutil.copytree(demo_experiment, exp)
    args = ["stages.train_policy", "+task=tiny", "scale=tiny", *TINY_POLICY, f"experiment_dir={exp}"]
    # A run started from a background job inherits SIGINT ignored (POSIX) and Python keeps it so: the run is given
    # the default disposition a terminal's Ctrl-C meets, whoever launched the tests.
    proc = subprocess.Popen([sys.executable, "-m", *args], cwd=REPO, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None and not list(exp.glob("train_policy/*/checkpoints/last")):
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before it could be interrupted"
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signum, err[-2000:]
    assert "Traceback" not in err
    last = err.strip().splitlines()[-1]
    assert last.startswith("interrupted train_policy") and "last checkpoint, step" in last
    assert last.endswith("the same command resumes")
    ckpts = [p for p in exp.glob("train_policy/*/checkpoints/*") if p.name != "last"]
    assert ckpts and all((p / "training_state.pt").is_file() and (p / "model.safetensors").is_file() for p in ckpts)
    assert not [p for p in ckpts if not p.name.isdigit()], "a checkpoint left half made"
    if signum == signal.SIGINT:  # resuming bit-identically is the kill -9 cases' subject; once here is enough
        again = cli(*args, timeout=600)
        assert again.returncode == 0, again.stderr[-2000:]


def test_an_interrupt_during_a_checkpoint_save_leaves_the_last_complete_one(tmp_path, monkeypatch):
    ckpts = Checkpoints(tmp_path, keep=3)
    model, spec = torch.nn.Linear(3, 2), {"_target_": "torch.nn.Linear", "in_features": 3, "out_features": 2}
    opt = torch.optim.Adam(model.parameters())
    ckpts.save(1, model, spec, {}, {"opt": opt}, [{"step": 1}])
    real_save = torch.save

    def interrupted(obj, f, *a, **k):  # Ctrl-C arriving between the weights and the training state
        real_save(obj, f, *a, **k)
        signal.raise_signal(signal.SIGINT)

    monkeypatch.setattr(torch, "save", interrupted)
    # Ctrl-C's own handler: a suite started in the background by a non-interactive shell inherits SIGINT ignored
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            ckpts.save(2, model, spec, {}, {"opt": opt}, [{"step": 2}])
    finally:
        signal.signal(signal.SIGINT, before)
    monkeypatch.undo()
    assert sorted(p.name for p in ckpts.dir.iterdir()) == ["0000001", "last"]
    assert ckpts.restore(model, {"opt": opt})[0] == 1


# ---------------------------------------------------------------- checkpoint contents


def _policy_folder(path: Path, hidden: int = 32) -> Path:
    from hydra.utils import instantiate

    cfg = {"_target_": "worldenv_core.models.policy.LaplacePolicy", "cameras": ["agentview"], "chunk": 4,
           "hidden": hidden, "proprio_rotation": "matrix", "instruction_dim": 384,
           "backbone": {"_target_": "worldenv_core.models.backbones.SmallConvBackbone", "cameras": ["agentview"],
                        "cond_dim": 384, "widths": [8, 8, 8, 8], "keypoints": 4}}
    model = instantiate(cfg, _convert_="all")
    meta = {"kind": "policy", "cameras": ["agentview"], "chunk": 4, "image_size": 32, "action_dim": 7, "proprio_dim": 7}
    return save_model(path, model, cfg, meta)


def test_a_checkpoint_whose_model_config_contradicts_its_meta_is_refused(tmp_path):
    folder = _policy_folder(tmp_path / "policy")
    config = json.loads((folder / "config.json").read_text())
    config["model"]["cameras"] = config["model"]["backbone"]["cameras"] = ["robot0_eye_in_hand"]
    (folder / "config.json").write_text(json.dumps(config))
    with pytest.raises(CheckpointError, match=r"model config has model.cameras=\['robot0_eye_in_hand'\] but its meta"):
        load_checkpoint(folder, "policy")
    from stages.evaluate.run import run as evaluate  # refused by the stage before any worker or simulator starts

    t0 = time.perf_counter()
    with pytest.raises(CheckpointError, match="contradicts itself"):
        evaluate(compose_config("evaluate", ["+task=tiny", "scale=tiny", f"experiment_dir={tmp_path / 'exp'}",
                                             f"policy_from={folder}"]))
    assert time.perf_counter() - t0 < 30 and not Manifest(tmp_path / "exp").records()


def test_weights_of_another_width_are_one_line_naming_the_folder(tmp_path):
    narrow, wide = _policy_folder(tmp_path / "narrow", hidden=32), _policy_folder(tmp_path / "wide", hidden=64)
    shutil.copyfile(narrow / "model.safetensors", wide / "model.safetensors")
    with pytest.raises(CheckpointError, match=rf"{wide}: the weights do not fit the model .* another shape") as e:
        load_model(wide)
    assert "\n" not in str(e.value)
