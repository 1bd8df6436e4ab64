"""Data-parallel training (worldenv_core/distributed.py): batch slices, settings checked before
work, gradient accumulation equal to the whole batch, and a training stage run by torchrun over 2
gloo ranks against the same stage in one process, killed and resumed."""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from worldenv_core.distributed import random_rows, shard, trainer_options
from worldenv_core.errors import ConfigError
from worldenv_core.manifest import Manifest
from worldenv_core.models.checkpoint import load_weights
from worldenv_core.training import Phase, Trainer, optimize

REPO = Path(__file__).resolve().parents[2]


def test_random_rows_draw_where_the_generator_lives_and_move_to_the_tensors_device():
    """A CPU generator for another device's tensor (LOOP's per-context streams on a GPU): torch
    refuses it, so rows are drawn on the generator's device, the same numbers, then moved."""
    gens = lambda: [torch.Generator().manual_seed(s) for s in (1, 2)]  # noqa: E731
    here = random_rows(torch.rand, (4, 3), gens(), device="cpu")
    assert torch.equal(here, torch.cat([torch.rand((2, 3), generator=g) for g in gens()]))
    asked = []

    def rand(shape, generator=None, device=None, **kwargs):  # torch.rand, noting where it was asked to draw
        asked.append(torch.device(device))
        return torch.rand(shape, generator=generator, device=device, **kwargs)
    moved = random_rows(rand, (4, 3), gens(), device="meta")  # "meta" stands in for a GPU here
    assert asked == [torch.device("cpu")] * 2 and moved.device.type == "meta" and moved.shape == (4, 3)
    seeds = random_rows(lambda shape, generator: torch.randint(9, shape, generator=generator), (4,), gens())
    assert seeds.shape == (4,)  # no device asked: a sampler that takes none works as before
    one = torch.Generator().manual_seed(3)
    random_rows(torch.randn, (5,), one, device="meta")
    assert torch.equal(torch.randn(2, generator=one), torch.randn(7, generator=torch.Generator().manual_seed(3))[5:])


def test_a_rank_takes_its_contiguous_slice_of_every_part_of_a_batch():
    batch = (7, {"x": torch.arange(8), "names": list("abcdefgh"), "nested": (torch.ones(8, 2),)})
    step, mine = shard(batch, 1, 2)
    assert step == 7  # a step number is nobody's slice
    assert mine["x"].tolist() == [4, 5, 6, 7] and mine["names"] == list("efgh") and mine["nested"][0].shape == (4, 2)
    assert shard(batch, 0, 1) is batch


def test_settings_that_cannot_split_the_batch_are_refused_before_training(monkeypatch):
    cfg = OmegaConf.create({"train": {"batch_size": 6}, "accumulate": 2})
    assert trainer_options(cfg, "train.batch_size") == {"accumulate": 2, "precision": "fp32"}
    monkeypatch.setenv("WORLD_SIZE", "4")  # as torchrun would set it
    with pytest.raises(ConfigError, match=r"train.batch_size=6 does not split over 4 rank\(s\) x 2 .*multiple of 8"):
        trainer_options(cfg, "train.batch_size")
    with pytest.raises(ConfigError, match="accumulate"):
        trainer_options(OmegaConf.create({"accumulate": 0}))
    with pytest.raises(ConfigError, match="precision"):
        trainer_options(OmegaConf.create({"precision": "fp8"}))


def _linear_run(work: Path, accumulate: int) -> torch.Tensor:
    torch.manual_seed(0)
    model = torch.nn.Linear(4, 1)
    opt = torch.optim.SGD(model.parameters(), lr=0.1)
    data = torch.Generator().manual_seed(1)
    x, y = torch.randn(6, 8, 4, generator=data), torch.randn(6, 8, 1, generator=data)

    def step(b):
        loss = (model(b[0]) - b[1]).pow(2).mean()
        optimize(loss, opt, clip=10.0)
        return {"loss": loss.item()}
    trainer = Trainer(work, model, {"opt": opt}, model_config={}, meta={}, log_every=1, checkpoint_every=100,
                      progress=False, accumulate=accumulate)
    trainer.fit([Phase("fit", 6, lambda start: iter(zip(x[start:], y[start:])), step)])
    return torch.cat([model.weight.flatten(), model.bias]).detach()


def test_gradient_accumulation_steps_as_the_whole_batch_would(tmp_path):
    torch.testing.assert_close(_linear_run(tmp_path / "whole", 1), _linear_run(tmp_path / "in4", 4))


POLICY = ["+task=tiny", "scale=tiny", "train.steps=20", "scale_head.steps=10", "train.log_every=5",
          "train.checkpoint_every=5", "demos_per_task=1", "policy.hidden=32", "policy.backbone.widths=[8,8,8,8]",
          "policy.backbone.keypoints=4", "train.augment_shift=0", "logger=none"]


TINY = {
    "train_policy": POLICY,
    "train_worldsim": ["+task=tiny", "scale=tiny", "expert_only=true", "ae.steps=6", "flow.steps=6", "rollout.steps=4",
                       "ae.batch_size=4", "flow.batch_size=4", "holdout_every=2", "log_every=2", "checkpoint_every=4",
                       "worldsim.ae_widths=[8,16]", "worldsim.width=16", "worldsim.map_channels=4",
                       "fidelity.horizons=[8]", "fidelity.starts_per_episode=1", "fidelity.videos=0", "logger=none"],
    "train_reflector": ["+task=tiny", "scale=tiny", "expert_only=true", "train.steps=8", "train.batch_size=4",
                        "train.log_every=2", "train.checkpoint_every=4", "train.mine.every=4", "holdout_every=2",
                        "reflector.d_model=16", "reflector.layers=1", "reflector.heads=2",
                        "reflector.frame_encoder.widths=[8,16]", "reflector.frame_encoder.keypoints=4", "plots=0",
                        "imagined.enabled=false", "eta_folds=0", "logger=none"],
}


def _launch(ranks: int, exp: Path, *overrides: str, stage: str = "train_policy", **popen) -> subprocess.Popen:
    head = ([sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={ranks}"] if ranks > 1
            else [sys.executable])
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.Popen([*head, "-m", f"stages.{stage}", *TINY[stage], f"experiment_dir={exp}", *overrides],
                            cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, **popen)


def _descendants(pid: int) -> list[int]:
    """Every live process below `pid` (read from /proc)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    out, todo = [], [pid]
    while todo:
        kids = children.get(todo.pop(), [])
        out += kids
        todo += kids
    return out


def _wait_for_unlock(folder: Path, timeout: float = 60) -> None:
    """Until no process holds a work-dir lock under `folder` (a killed rank's goes when it is gone)."""
    import fcntl

    deadline = time.time() + timeout
    for lock in folder.glob("*/.lock"):
        with open(lock) as f:
            while True:
                try:
                    fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    fcntl.flock(f, fcntl.LOCK_UN)
                    break
                except BlockingIOError:
                    assert time.time() < deadline, f"{lock} still held {timeout} s after the kill"
                    time.sleep(0.05)


def _finish(proc: subprocess.Popen) -> None:
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err[-3000:]


def _weights(exp: Path, stage: str = "train_policy") -> dict[str, torch.Tensor]:
    m = Manifest(exp)
    (path,) = [p for p in m.resolve(m.latest(stage)) if p.name == "model.safetensors"]
    return load_weights(path)


def _difference(a: dict, b: dict) -> float:
    """|a - b| / |a| over all weights. Elementwise equality is not to be had: Adam's first steps move
    a weight by about lr * sign(gradient), so float-order noise in a near-zero gradient shows at
    full size on that weight."""
    assert a.keys() == b.keys()
    fa, fb = (torch.cat([w[k].float().flatten() for k in sorted(w)]) for w in (a, b))
    return ((fa - fb).norm() / fa.norm()).item()


@pytest.mark.sim
@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_two_gloo_ranks_train_like_one_process_and_a_killed_launch_resumes(_tiny_demos, tmp_path):
    import shutil

    exps = {name: tmp_path / name for name in ("one", "two", "half", "killed")}
    for exp in exps.values():
        shutil.copytree(_tiny_demos, exp)
    _finish(_launch(1, exps["one"]))
    _finish(_launch(2, exps["two"]))
    _finish(_launch(1, exps["half"], "train.batch_size=8", "scale_head.batch_size=4"))
    # the same effective batch split over 2 ranks: the same model up to float order and each rank
    # normalising its loss by its own valid steps; one rank's half batch alone is another model
    one, two, half = (_weights(exps[k]) for k in ("one", "two", "half"))
    assert _difference(one, two) < 0.01 and _difference(one, half) > 5 * _difference(one, two)
    (rec,) = Manifest(exps["two"]).find("train_policy")  # one record, from rank 0
    assert rec.metrics["ranks"] == 2 and rec.metrics["steps"] == 30

    proc = _launch(2, exps["killed"], start_new_session=True)
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        if any(int(p.name) >= 10 for p in exps["killed"].glob("train_policy/*/checkpoints/[0-9]*[0-9]")):
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before it could be killed"
    for pid in [proc.pid, *_descendants(proc.pid)]:  # torchrun and both ranks (which it starts in sessions of their own)
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    proc.wait()
    _wait_for_unlock(exps["killed"] / "train_policy")  # the ranks die a moment after torchrun: their lock goes with them
    assert Manifest(exps["killed"]).find("train_policy") == [], "a killed launch records nothing"
    _finish(_launch(1, exps["killed"]))  # resumed at another world size
    assert _difference(two, _weights(exps["killed"])) < 0.01


@pytest.mark.sim
@pytest.mark.slow
@pytest.mark.timeout(900)
@pytest.mark.parametrize("stage", ["train_worldsim", "train_reflector"])
def test_every_training_stage_runs_on_two_gloo_ranks(stage, _tiny_demos, tmp_path):
    import shutil

    shutil.copytree(_tiny_demos, tmp_path / "two")
    _finish(_launch(2, tmp_path / "two", stage=stage))
    (rec,) = Manifest(tmp_path / "two").find(stage)  # one record, rank 0's
    assert rec.metrics["ranks"] == 2 and _weights(tmp_path / "two", stage)
