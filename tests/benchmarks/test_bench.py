"""`make bench --only policy`: each policy config's cost per chunk, built as train_policy builds it; `--only
robot_layer`: the robot layer's cost per rollout and chunk beside a real chunk; `--only worldsim --worldsim
<checkpoint>`: a trained world model's env-steps/s beside the simulator's."""
import pytest

from benchmarks.bench import policy_costs, policy_episode_cost, robot_layer_cost, world_model_speed
from tests.conftest import TINY_SUITE, TINY_TASK


def test_policy_costs_time_each_configs_chunk_and_count_its_parameters():
    out = policy_costs(["small", "lerobot_act"], "libero_object", 32, repeats=2)
    assert set(out) == {"small", "lerobot_act"}
    for row in out.values():
        assert row["ms_per_chunk"] > 0 and row["chunk"] == 8 and row["parameters_m"] > 0.1
    assert out["lerobot_act"]["parameters_m"] > out["small"]["parameters_m"]  # ACT's ResNet-18 and transformer


@pytest.mark.sim
def test_robot_layer_cost_times_the_layer_per_rollout_beside_a_real_chunk():
    out = robot_layer_cost(TINY_SUITE, TINY_TASK, 32, "agentview", repeats=1, batch=2)
    assert out["chunk"] == 8 and out["batch"] == 2
    assert out["robot_layer_ms_per_rollout_chunk"] > 0 and out["real_chunk_ms"] > 0
    ratio = out["robot_layer_ms_per_rollout_chunk"] / out["real_chunk_ms"]
    assert abs(out["robot_layer_over_real_chunk"] - ratio) < 0.01 + 0.01 * ratio


@pytest.mark.sim
def test_policy_episode_cost_times_the_recording_with_and_without_the_kept_boundary_frames():
    out = policy_episode_cost(TINY_SUITE, TINY_TASK, 32, "agentview", repeats=2, steps=16)
    assert out["episodes"] == 2 and out["frames_median"] == 17
    assert out["episode_s_boundaries_kept"] > 0 and out["episode_s_boundaries_replayed"] > 0
    assert 0 < out["kept_over_replayed"] < 2


def _world_model(folder, image_size):
    """A small latent-flow world model saved as train_worldsim saves one (kind, frame size and chunk in its meta)."""
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from worldenv_core.models.checkpoint import save_model
    from worldenv_core.stage import CONF_DIR

    cfg = OmegaConf.load(CONF_DIR / "worldsim" / "latent_flow.yaml")
    cfg.image_size, cfg.chunk, cfg.action_dim, cfg.latent_size = image_size, 8, 7, 8
    cfg = OmegaConf.to_container(cfg)
    save_model(folder, instantiate(cfg, _convert_="all"), cfg,
               meta={"kind": "worldsim", "image_size": image_size, "chunk": 8, "action_dim": 7, "proprio_dim": 7})
    return str(folder)


@pytest.mark.sim
def test_world_model_speed_times_a_trained_checkpoint_and_names_one_made_for_other_frames(tmp_path):
    from worldenv_core.models.checkpoint import CheckpointError

    out = world_model_speed(TINY_SUITE, TINY_TASK, 32, "agentview", repeats=1, batch=2,
                            checkpoint=_world_model(tmp_path / "ws", 32), sampling_steps=(1,))
    assert out["batch"] == 2 and out["chunk"] == 8
    assert out["imagined_env_steps_per_s_1step"]["chunk_boundary_frames"] > 0
    assert out["speedup_1step"]["every_frame"] > 0
    with pytest.raises(CheckpointError, match="64-pixel frames"):
        world_model_speed(TINY_SUITE, TINY_TASK, 32, "agentview", repeats=1, batch=2,
                          checkpoint=_world_model(tmp_path / "ws64", 64), sampling_steps=(1,))
