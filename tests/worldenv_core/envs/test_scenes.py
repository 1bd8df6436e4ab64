"""A kept scene put back without rebuilding the simulator is the hard reset's, bit for bit (real LIBERO)."""
import numpy as np

from worldenv_core.envs.libero_env import LiberoEnv

ACTIONS = np.random.default_rng(0).uniform(-0.6, 0.6, (24, 7))
ACTIONS[:, 6] = np.sign(ACTIONS[:, 6])  # the gripper closes and opens: its smoothed command is state too


def _episode(env, frame):
    """An episode prefix: the state, proprioception and success at every step, renders at its ends."""
    states, proprio, success, images = [frame.sim_state], [frame.proprio], [frame.success], [env.render()["agentview"]]
    for a in ACTIONS:
        frame = env.step(a)
        states.append(frame.sim_state), proprio.append(frame.proprio), success.append(frame.success)
    images.append(env.render()["agentview"])
    return np.array(states), np.array(proprio), np.array(success), np.array(images)


def test_a_kept_scene_comes_back_as_the_hard_reset_made_it():
    """libero_spatial 4: a drawer's open/close sampler and the cabinet's placement are drawn at reset (a stove's
    on/off sampler, libero_goal 7, was measured the same way when this was written)."""
    suite, task, start = "libero_spatial", 4, {"seed": 1000}
    fresh = LiberoEnv(suite, task, cameras=("agentview",), image_size=64)
    expected = _episode(fresh, fresh.reset(**start))
    fresh.close()
    env = LiberoEnv(suite, task, cameras=("agentview",), image_size=64, scene_cache=2)
    env.reset(**start)
    _episode(env, env.reset(seed=start["seed"] + 1))  # another scene, an episode run in it
    got = _episode(env, env.reset(**start))  # put back from the cache, not rebuilt
    assert len(env._scenes) == 2
    env.reset(init_state=3, seed=start["seed"])  # a benchmark init state: a hard reset, never kept
    assert len(env._scenes) == 2
    for name, a, b in zip(("state", "proprio", "success", "render"), expected, got):
        assert np.array_equal(a, b), f"{name} differs after a restored reset"
    env.close()
