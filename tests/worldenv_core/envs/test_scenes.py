"""A kept scene put back without rebuilding the simulator is the hard reset's (real LIBERO): the same renders and
success, and the physics to float64's last bits (see `test_a_kept_scene_comes_back_as_the_hard_reset_made_it`)."""
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
    # Before the first step every float of MjData, the model, the controller and the robot is equal; on some CPUs
    # (an AMD EPYC, not CI's) the first step's arm torques still come out ~1e-15 apart (one velocity 3e-18 apart
    # after it), as if a fresh and a reused buffer took different SIMD paths. A hard reset of a reused env does not.
    for name, a, b in zip(("state", "proprio"), expected, got):
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-12, err_msg=f"{name} differs after a restored reset")
    for name, a, b in zip(("success", "render"), expected[2:], got[2:]):
        assert np.array_equal(a, b), f"{name} differs after a restored reset"
    # hard=True rebuilds the scene although one is kept (a replay that missed its recorded state from the kept scene
    # tries again from the reset the recording made: `replay.restore`), and keeps the rebuilt one
    kept = env._scenes[start["seed"]]
    env.reset(**start)
    assert env.restored  # `restored` tells a kept scene put back (where restore may try again) from a rebuild
    rebuilt = _episode(env, env.reset(hard=True, **start))
    assert env._scenes[start["seed"]] is not kept and not env.restored
    np.testing.assert_array_equal(rebuilt[0], expected[0], err_msg="a hard reset of a reused env is a fresh env's")
    env.close()


def test_a_kept_moment_inside_an_episode_comes_back_as_it_was_left():
    """A point 20 steps into an episode (the gripper closed and opened on the way, so its smoothed command and the
    arm controller's goal are state), kept, left for another scene, and put back: the proprioception and render
    there are the same, the next 24 steps' physics the same to 1e-6 (measured 1e-15 ... 2e-6 on libero_spatial
    demos' keyframes), and two continuations from the same moment equal bit for bit."""
    env = LiberoEnv("libero_spatial", 1, cameras=("agentview",), image_size=64, scene_cache=4)
    frame = env.reset(seed=2000)
    for a in ACTIONS[:20]:
        frame = env.step(a)
    env.keep_moment("k", info="checked")
    expected = _episode(env, frame)
    env.reset(seed=2001)
    assert env.back_to("missing") is None
    back, info = env.back_to("k")
    assert info == "checked"
    got = _episode(env, back)
    again = _episode(env, env.back_to("k")[0])
    np.testing.assert_allclose(got[0], expected[0], rtol=0, atol=1e-6, err_msg="state differs after a kept moment")
    np.testing.assert_array_equal(got[1][0], expected[1][0])  # the proprioception a policy reads there
    assert np.array_equal(got[3][0], expected[3][0])  # and its render
    assert np.array_equal(got[2], expected[2])
    for a, b in zip(got, again):
        assert np.array_equal(a, b)
    env.close()
