"""The real LIBERO simulator: task registry, env factory, recording, scripted experts."""

from worldenv_core.envs.libero_env import Frame, LiberoEnv, SimulationError
from worldenv_core.envs.tasks import SUITE_MAX_STEPS, SUITES, TaskSpec, UnknownTaskError, get_task, init_states

__all__ = ["Frame", "LiberoEnv", "SimulationError", "SUITE_MAX_STEPS", "SUITES", "TaskSpec", "UnknownTaskError",
           "get_task", "init_states"]
