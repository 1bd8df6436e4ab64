"""Context packs: what LOOP on a GPU host reads instead of the episodes and the instruction encoder."""
import pytest
import torch
from safetensors.torch import save_file

from worldenv_core.errors import ConfigError
from worldenv_core.imagination.context_pack import read_context_pack, write_context_pack
from worldenv_core.imagination.env import Context

TASK = {"task": "tiny", "suite": "libero_goal", "image_size": 8, "chunk": 4, "action_dim": 7, "proprio_dim": 7}


def encoder(texts):  # a stand-in encoder: one distinct vector per string
    return torch.stack([torch.full((3,), float(len(t))) + torch.arange(3) for t in texts])


def contexts(n=3):
    g = torch.Generator().manual_seed(0)
    return [Context(task_id=i % 2, instruction=["open the drawer", "push the plate"][i % 2],
                    frame=torch.randint(0, 256, (3, 8, 8), dtype=torch.uint8, generator=g),
                    proprio=torch.randn(7, generator=g, dtype=torch.float64)) for i in range(n)]


def test_a_pack_reads_back_its_contexts_keys_embeddings_task_and_settings(tmp_path):
    made = contexts()
    path = write_context_pack(tmp_path / "sub" / "c.st", made, ["a@0", "b@0", "c@3"], encoder, "agentview", TASK,
                              {"mid_episode_frames": 1})
    pack = read_context_pack(path)
    assert pack.keys == ["a@0", "b@0", "c@3"] and pack.camera == "agentview"
    assert pack.task == TASK and pack.settings == {"mid_episode_frames": 1}
    for a, b in zip(pack.contexts, made):
        assert (a.task_id, a.instruction) == (b.task_id, b.instruction)
        assert torch.equal(a.frame, b.frame) and torch.equal(a.proprio, b.proprio)
    assert torch.equal(pack.encoder(["push the plate", "open the drawer"]), encoder(["push the plate", "open the drawer"]))
    with pytest.raises(KeyError, match="no embedding of \\['close it'\\]"):
        pack.encoder(["close it"])
    assert [p.name for p in (tmp_path / "sub").iterdir()] == ["c.st"]  # no temporary file left
    assert all(c.history is None for c in pack.contexts) and all(c.joint_pos is None for c in pack.contexts)


def test_the_arms_joint_angles_travel_in_the_pack(tmp_path):
    """What a world model that draws the arm starts its rollouts from."""
    made = contexts()
    for c in made:
        c.joint_pos = torch.randn(7, dtype=torch.float64)
    pack = read_context_pack(write_context_pack(tmp_path / "c.st", made, ["a", "b", "c"], encoder, "agentview", TASK))
    assert all(torch.equal(a.joint_pos, b.joint_pos) for a, b in zip(pack.contexts, made))


def test_mid_episode_contexts_recorded_pasts_travel_in_the_pack(tmp_path):
    made = contexts()
    made[0].history = torch.randint(0, 256, (2, 3, 8, 8), dtype=torch.uint8)
    made[2].history = torch.randint(0, 256, (5, 3, 8, 8), dtype=torch.uint8)
    pack = read_context_pack(write_context_pack(tmp_path / "c.st", made, ["a@16", "b@0", "c@40"], encoder,
                                                "agentview", TASK))
    assert torch.equal(pack.contexts[0].history, made[0].history) and pack.contexts[1].history is None
    assert torch.equal(pack.contexts[2].history, made[2].history)


def test_what_is_not_a_pack_is_one_line_naming_it(tmp_path):
    with pytest.raises(ConfigError, match="no context pack at .*contexts_to="):
        read_context_pack(tmp_path / "missing.st")
    save_file({"x": torch.zeros(1)}, str(tmp_path / "weights.st"))
    with pytest.raises(ConfigError, match="is not a context pack"):
        read_context_pack(tmp_path / "weights.st")
    with pytest.raises(ValueError, match="one key per context"):
        write_context_pack(tmp_path / "c.st", contexts(2), ["a@0"], encoder, "agentview", TASK)
