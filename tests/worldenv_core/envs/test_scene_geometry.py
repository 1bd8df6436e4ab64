"""A task's camera and arm, read from the real simulator once and then from the experiment's cache: the same
values, no env built the second time, and another simulator version reads them again."""
import json

import numpy as np
import pytest

import worldenv_core.envs.libero_env as libero_env
from worldenv_core.envs import scene_geometry
from worldenv_core.envs.scene_geometry import scenes_file, task_scenes


@pytest.mark.sim
def test_a_tasks_scene_is_read_once_and_kept_for_this_simulator(tmp_path, monkeypatch, contract):
    c = contract()
    cache = scenes_file(tmp_path)
    cameras, arms = task_scenes(c, "agentview", [0], cache)
    kept = json.loads(cache.read_text())
    assert list(kept["scenes"]) == [f"{c.suite}/0/agentview/{c.image_size}"] and "mujoco==" in kept["versions"]

    def no_env(*args, **kwargs):
        raise AssertionError("the kept scene was read from the simulator again")

    monkeypatch.setattr(libero_env, "LiberoEnv", no_env)
    again_cameras, again_arms = task_scenes(c, "agentview", [0], cache)
    assert again_cameras[0].to_dict() == cameras[0].to_dict() and again_arms[0].to_dict() == arms[0].to_dict()
    monkeypatch.setattr(scene_geometry, "simulator_versions", lambda *also: "mujoco==another")
    with pytest.raises(AssertionError, match="read from the simulator again"):
        task_scenes(c, "agentview", [0], cache)
