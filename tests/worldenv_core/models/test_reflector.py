"""The instant reflector: sub-sampling, learning a synthetic success task, incremental scoring,
checkpoints, eta validation."""
import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from worldenv_core.models.checkpoint import CheckpointError, save_model
from worldenv_core.contract import ContractError
from worldenv_core.models.checkpoint import load_checkpoint
from worldenv_core.models.reflector import IncrementalScorer, score_prefixes, subsample_indices
from worldenv_core.rl.termination import ReflectorStop, check_eta, reflector_eta
from worldenv_core.models.reflector_data import PrefixSampler, prefix_frames, settled_labels


def small_config(max_frames=8, input_size=None):
    return {"_target_": "worldenv_core.models.reflector.Reflector", "camera": "agentview", "input_size": input_size,
            "max_frames": max_frames, "d_model": 32, "layers": 1, "heads": 2, "instruction_dim": 16,
            "frame_encoder": {"_target_": "worldenv_core.models.backbones.SmallConvBackbone", "cameras": ["agentview"],
                              "cond_dim": 16, "widths": [8, 16], "keypoints": 4}}


def test_subsample_keeps_first_and_last_and_spreads_uniformly():
    assert subsample_indices(5, 8).tolist() == [0, 1, 2, 3, 4]
    idx = subsample_indices(100, 8)
    assert len(idx) == 8 and idx[0] == 0 and idx[-1] == 99 and (idx.diff() > 0).all()
    assert prefix_frames(20, 8, 32).tolist() == [0, 4, 12, 20]  # what a chunked rollout has at frame 20
    assert prefix_frames(16, 8, 32).tolist() == [0, 8, 16]
    assert len(prefix_frames(300, 1, 32)) == 32


LANG = {"red": torch.nn.functional.one_hot(torch.tensor(0), 16).float(),
        "blue": torch.nn.functional.one_hot(torch.tensor(1), 16).float()}


def test_a_tiny_reflector_learns_a_synthetic_instruction_dependent_success_task(synthetic_episodes):
    torch.manual_seed(0)
    model = instantiate(small_config())
    sampler = PrefixSampler(synthetic_episodes(0, 24), "agentview", stride=4, max_frames=8, hard_negative_fraction=0.25,
                            hard_window=4)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    for step in range(150):
        b = sampler.batch(16, seed=step)
        lang = torch.stack([LANG[s] for s in b["instruction"]])
        loss = torch.nn.functional.binary_cross_entropy_with_logits(model(b["frames"], b["mask"], lang), b["label"])
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval()
    correct = total = 0
    for ep in synthetic_episodes(1, 12):  # held out
        video = torch.from_numpy(ep.images["agentview"]).permute(0, 3, 1, 2)
        steps = list(range(0, ep.length + 1, 4))
        probs = score_prefixes(model, video, LANG[ep.meta.instruction], steps)
        correct += int(((probs > 0.5).numpy() == ep.success[steps]).sum())
        total += len(steps)
    assert correct / total > 0.9, correct / total


def test_incremental_scoring_equals_scoring_each_prefix_from_scratch():
    torch.manual_seed(0)
    model = instantiate(small_config(max_frames=4)).eval()
    videos = torch.randint(0, 255, (2, 11, 3, 16, 16), dtype=torch.uint8)
    lang = torch.randn(2, 16)
    scorer = IncrementalScorer(model, lang)
    scorer.add(videos[:, :3])  # a chunk of frames at once ...
    got = [scorer.score()]
    for t in range(3, 11):  # ... then one at a time
        scorer.add(videos[:, t])
        got.append(scorer.score())
    for i in range(2):
        full = [model.score_video(videos[i, : t + 1], lang[i]) for t in range(2, 11)]
        assert torch.allclose(torch.stack([g[i] for g in got]), torch.stack(full), atol=1e-5)
        batched = score_prefixes(model, videos[i], lang[i], list(range(11)))[2:]
        assert torch.allclose(batched, torch.stack(full), atol=1e-5)


def test_a_history_of_its_own_length_per_video_is_scored_as_that_videos_prefix():
    """Rollouts started mid-episode: each video's recorded past (of its own length, or none) goes before its first
    frame, and every later score equals scoring that video's whole prefix from scratch."""
    torch.manual_seed(0)
    model = instantiate(small_config(max_frames=4)).eval()
    past = torch.randint(0, 255, (3, 5, 3, 16, 16), dtype=torch.uint8)
    videos = torch.randint(0, 255, (3, 4, 3, 16, 16), dtype=torch.uint8)
    lang = torch.randn(3, 16)
    lengths = [5, 0, 2]
    scorer = IncrementalScorer(model, lang)
    scorer.add_history([past[0], None, past[2, -2:]])
    for t in range(4):
        scorer.add(videos[:, t])
        got = scorer.score()
        for b, k in enumerate(lengths):
            whole = torch.cat([past[b, 5 - k:], videos[b, : t + 1]])
            assert torch.allclose(got[b], model.score_video(whole, lang[b]), atol=1e-5)
    with pytest.raises(RuntimeError, match="before the first add"):
        scorer.add_history([None, None, None])
    plain = IncrementalScorer(model, lang)
    plain.add_history([None] * 3)  # no past at all: the plain scorer
    plain.add(videos[:, 0])
    assert plain.first is None and torch.allclose(plain.score()[1], model.score_video(videos[1, :1], lang[1]), atol=1e-5)


def test_reflector_stop_fires_above_eta_only():
    model = instantiate(small_config()).eval()
    encoder = lambda texts: torch.randn(len(texts), 16)  # noqa: E731 - stands in for MiniLM
    stop = ReflectorStop(model, 0.5, "red", encoder)
    frame = {"agentview": np.zeros((16, 16, 3), dtype=np.uint8)}
    answer = stop(frame)
    assert answer == (stop.scores[-1] > 0.5) and len(stop.scores) == 1
    assert ReflectorStop(model, 1.0, "red", encoder)(frame) is False  # R < 1 always: never stops
    assert ReflectorStop(model, 0.0, "red", encoder)(frame) is True


@pytest.mark.parametrize("eta", [-0.1, 1.5, True, "0.5", float("nan")])
def test_eta_outside_the_unit_interval_is_rejected(eta):
    with pytest.raises(ValueError, match=r"eta .* must be in \[0, 1\]"):
        check_eta(eta)


def test_checkpoint_round_trip_and_contract_errors(tmp_path, contract):
    model = instantiate(small_config()).eval()
    cfg = small_config()
    save_model(tmp_path / "r", model, cfg, {"kind": "reflector", "image_size": 16, "camera": "agentview"})
    loaded, meta = load_checkpoint(tmp_path / "r", "reflector", contract(image_size=16))
    video, lang = torch.randint(0, 255, (5, 3, 16, 16), dtype=torch.uint8), torch.randn(16)
    assert torch.allclose(loaded.score_video(video, lang), model.score_video(video, lang))
    assert meta["camera"] == "agentview"
    with pytest.raises(ContractError, match="image_size=16.*has image_size=128"):
        load_checkpoint(tmp_path / "r", "reflector", contract(image_size=128))
    save_model(tmp_path / "p", model, cfg, {"kind": "policy"})
    with pytest.raises(CheckpointError, match="'policy' checkpoint, not a reflector"):
        load_checkpoint(tmp_path / "p", "reflector")


def test_a_stage_stops_at_the_reflectors_own_eta_unless_told_otherwise(tmp_path):
    model = instantiate(small_config()).eval()
    save_model(tmp_path / "cv", model, small_config(), {"kind": "reflector", "eta": 0.8, "camera": "agentview"})
    save_model(tmp_path / "old", model, small_config(), {"kind": "reflector", "camera": "agentview"})
    assert reflector_eta(tmp_path / "cv", None) == 0.8  # e.g. chosen by its eta cross-validation
    assert reflector_eta(tmp_path / "cv", 0.3) == 0.3
    assert reflector_eta(tmp_path / "old", None) == 0.5  # a checkpoint that names none: the paper's
    with pytest.raises(ValueError, match=r"eta .* must be in \[0, 1\], got 1.5"):
        reflector_eta(tmp_path / "cv", 1.5)

def test_frozen_hf_tower_trains_only_the_aggregator_and_head(tmp_path):
    """The paper's setting (a frozen pretrained tower, only the head learns), on a tiny CLIP
    vision tower saved to and loaded from a local folder: the real loading path."""
    from transformers import CLIPVisionConfig, CLIPVisionModel

    tiny = CLIPVisionModel(CLIPVisionConfig(hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                                            num_attention_heads=2, image_size=32, patch_size=8))
    tiny.save_pretrained(tmp_path / "clip")
    cfg = small_config(input_size=None)
    cfg["freeze_encoder"] = True
    cfg["frame_encoder"] = {"_target_": "worldenv_core.models.backbones.HFVisionBackbone", "cameras": ["agentview"],
                            "cond_dim": 16, "pretrained_path": str(tmp_path / "clip"), "lora_rank": 0}
    model = instantiate(cfg)
    trainable = {n.split(".")[0] for n, p in model.named_parameters() if p.requires_grad}
    assert "frame_encoder" not in trainable and {"head", "temporal", "frame_proj"} <= trainable
    frames = torch.randint(0, 255, (2, 3, 3, 48, 48), dtype=torch.uint8)
    logits = model(frames, torch.ones(2, 3, dtype=torch.bool), torch.randn(2, 16))
    logits.sum().backward()
    assert all(p.grad is None for p in model.frame_encoder.parameters())


def test_mining_makes_high_scoring_negatives_hard_and_never_positives(synthetic_episodes):
    eps = synthetic_episodes(2, 6)
    sampler = PrefixSampler(eps, "agentview", stride=4, max_frames=8, hard_negative_fraction=1.0, hard_window=4)
    window = {tuple(x) for x in sampler.hard}
    # a "model" that calls every prefix ending at frame 8 of episode 0 and frame 12 of episode 3 a success
    fake = {(0, 8), (3, 12)}
    mined = sampler.mine(lambda i, frames, steps: [0.9 if (i, s) in fake else 0.1 for s in steps], threshold=0.5)
    got = {tuple(x) for x in mined}
    expect = {(i, t) for i, s in fake for t in range(s - 3, s + 1) if not sampler.labels[i][t]}
    assert got == expect and expect  # the chunk of frames before each mined boundary, negatives only
    assert all(not sampler.labels[i][t] for i, t in got)
    sampler.set_mined(mined)
    assert {tuple(x) for x in sampler.hard} == window | got
    drawn = sampler.batch(64, seed=0)["label"]
    assert drawn.sum() == 32  # still half positives
    sampler.set_mined([])
    assert {tuple(x) for x in sampler.hard} == window


def test_settled_labels_turn_on_delay_steps_after_the_first_success():
    flags = np.array([0, 0, 1, 0, 1, 1, 1], dtype=bool)  # the oracle flickers once: done stays done
    assert settled_labels(flags, 0).tolist() == [0, 0, 1, 1, 1, 1, 1]
    assert settled_labels(flags, 2).tolist() == [0, 0, 0, 0, 1, 1, 1]
    assert settled_labels(flags, 50).tolist() == [0, 0, 0, 0, 0, 0, 1]  # a success keeps its last frame
    assert not settled_labels(np.zeros(5, dtype=bool), 3).any()


def test_label_delay_moves_the_positives_and_the_hard_window_with_them(synthetic_episodes):
    eps = synthetic_episodes(3, 6)
    plain = PrefixSampler(eps, "agentview", stride=4, max_frames=8, hard_window=4)
    late = PrefixSampler(eps, "agentview", stride=4, max_frames=8, hard_window=4, label_delay=3)
    assert len(late.pos) == len(plain.pos) - 3 * sum(ep.success.any() for ep in eps)
    onset = {i: int(np.argmax(y)) for i, y in enumerate(late.labels) if y.any()}
    assert {tuple(x) for x in late.hard} == {(i, t) for i, ts in onset.items() for t in range(ts - 4, ts)}
