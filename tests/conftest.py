"""Shared fixtures: real components at small sizes."""
import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import pytest  # noqa: E402

# The CI task: libero_object task 0 ("pick the alphabet soup and place it in the basket").
TINY_SUITE, TINY_TASK = "libero_object", 0


@pytest.fixture(scope="session")
def tiny_env():
    """One real LIBERO env for the whole session (building one costs seconds)."""
    from worldenv_core.envs.libero_env import LiberoEnv

    env = LiberoEnv(TINY_SUITE, TINY_TASK, cameras=["agentview", "robot0_eye_in_hand"], image_size=64)
    yield env
    env.close()
