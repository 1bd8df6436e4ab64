"""post_train_loop launched by torchrun on 2 gloo ranks: each rank imagines half of every
iteration's contexts, the rollouts are gathered, and the result is the one-process run's."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from worldenv_core.manifest import Manifest
from worldenv_core.models.checkpoint import load_weights

pytestmark = [pytest.mark.sim, pytest.mark.slow]
REPO = Path(__file__).resolve().parents[3]
LOOP = ["+task=tiny", "scale=tiny", "expert_only=true", "rl.iterations=2", "rl.contexts_per_iteration=2",
        "rl.n_rollouts=2", "rl.horizon=16", "rl.minibatch=2", "eval.every=0", "eval.imagined_contexts=0",
        "eval.record_contexts=0", "progress=false", "logger=none"]


def _run(exp: Path, ranks: int) -> None:
    head = ([sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={ranks}"] if ranks > 1
            else [sys.executable])
    out = subprocess.run([*head, "-m", "stages.post_train_loop", *LOOP, f"experiment_dir={exp}"], cwd=REPO,
                         env={**os.environ, "OMP_NUM_THREADS": "1"}, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]


@pytest.mark.timeout(1200)
def test_two_ranks_share_the_imagined_rollouts_and_train_the_one_process_policy(tiny_models, tmp_path):
    one, two = tmp_path / "one", tmp_path / "two"
    for exp in (one, two):
        shutil.copytree(tiny_models, exp)
    _run(one, 1)
    _run(two, 2)
    records = [Manifest(e).latest("post_train_loop") for e in (one, two)]
    assert len(Manifest(two).find("post_train_loop")) == 1 and records[1].metrics["ranks"] == 2
    weights = [load_weights(next(p for p in Manifest(e).resolve(r) if p.name == "model.safetensors"))
               for e, r in zip((one, two), records)]
    flat = [torch.cat([w[k].float().flatten() for k in sorted(w)]) for w in weights]
    assert ((flat[0] - flat[1]).norm() / flat[0].norm()).item() < 1e-3  # the same rollouts, the same updates
    history = [torch.load(next(e.glob("post_train_loop/*/checkpoints/last")) / "training_state.pt",
                          weights_only=False)["history"] for e in (one, two)]
    rewards = [[h["mean_reward"] for h in hist if "mean_reward" in h] for hist in history]
    assert len(rewards[0]) == 2 and rewards[0] == pytest.approx(rewards[1], abs=1e-4)
