"""Physics substeps split around the controller (mj_step1 / controller / mj_step2): robosuite's results, bit for bit."""

import contextlib

import mujoco
import numpy as np
import pytest

pytestmark = pytest.mark.sim


def test_split_substeps_leave_every_step_bit_for_bit_robosuites(monkeypatch):
    """Over 60 steps (the gripper closing and opening, a hard reset between, which builds a new sim and new
    controllers) the states, proprioception, success and the final render equal those of robosuite's own loop,
    with one pass of MuJoCo's stages per substep (one mj_step1 and one mj_step2) where robosuite makes three."""
    import worldenv_core.envs.libero_env as libero_env
    from worldenv_core.envs.libero_env import LiberoEnv

    actions = np.random.default_rng(3).uniform(-0.6, 0.6, (60, 7))
    actions[:, 6] = np.sign(actions[:, 6])
    calls = {"mj_forward": 0, "mj_step": 0, "mj_step1": 0, "mj_step2": 0}
    for name in calls:
        def counted(*args, _f=getattr(mujoco, name), _n=name):
            calls[_n] += 1
            return _f(*args)
        monkeypatch.setattr(mujoco, name, counted)
    runs = {}
    for name in ("robosuite", "split"):
        with monkeypatch.context() as m:
            if name == "robosuite":
                m.setattr(libero_env, "SplitSubsteps", lambda raw: contextlib.nullcontext())
            env = LiberoEnv("libero_spatial", 4, cameras=("agentview",), image_size=64, scene_cache=0)
            frames = []
            for seed, part in ((7, actions[:30]), (8, actions[30:])):
                env.reset(seed=seed)  # scene_cache=0: a hard reset, a new MjSim
                before = dict(calls)
                frames += [env.step(a) for a in part]
            stepped = {k: calls[k] - before[k] for k in calls}
            runs[name] = (frames, env.render()["agentview"], stepped)
            env.close()
    (a, render_a, calls_a), (b, render_b, calls_b) = runs["robosuite"], runs["split"]
    assert all(np.array_equal(x.sim_state, y.sim_state) and np.array_equal(x.proprio, y.proprio)
               and x.success == y.success for x, y in zip(a, b))
    assert np.array_equal(render_a, render_b)
    substeps = len(actions[30:]) * 25
    assert calls_b == {"mj_forward": 0, "mj_step": 0, "mj_step1": substeps, "mj_step2": substeps}
    assert calls_a["mj_step"] == substeps and calls_a["mj_forward"] >= 2 * substeps - 1  # the first substep after a reset: one
    assert calls_a["mj_step1"] == calls_a["mj_step2"] == 0


def test_split_substeps_behave_like_mj_step_outside_the_pattern_and_refuse_rk4():
    """A step with no forward before it integrates as mj_step; leaving between a forward and its step completes the
    stages; RK4 (its own stages) is refused."""
    from worldenv_core.envs.substeps import SplitSubsteps

    xml = "<mujoco><worldbody><body><freejoint/><geom size='0.1'/></body></worldbody></mujoco>"

    class Sim:  # MjSim's shape: .model._model, .data._data
        def __init__(self, model):
            self.model, self.data = type("M", (), {"_model": model})(), type("D", (), {"_data": mujoco.MjData(model)})()

    model = mujoco.MjModel.from_xml_string(xml)
    raw, ref = type("Env", (), {"sim": Sim(model)})(), mujoco.MjData(model)
    with SplitSubsteps(raw):
        raw.sim.step()
        raw.sim.forward()
    mujoco.mj_step(model, ref)
    mujoco.mj_forward(model, ref)
    d = raw.sim.data._data
    assert np.array_equal(d.qpos, ref.qpos) and np.array_equal(d.qacc, ref.qacc) and d.time == ref.time
    assert "forward" not in vars(raw.sim)  # the shadows are gone
    model.opt.integrator = mujoco.mjtIntegrator.mjINT_RK4
    with pytest.raises(ValueError, match="RK4"):
        SplitSubsteps(type("Env", (), {"sim": Sim(model)})())
