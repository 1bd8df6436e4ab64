"""The "no reward head" mode on a tiny LLaVA built from a config, saved and loaded from a local
folder: the real loading path, P(yes) from the answer-token logits."""
import pytest
import torch

from worldenv_core.models.checkpoint import save_model
from worldenv_core.models.checkpoint import load_checkpoint
from worldenv_core.rl.termination import ReflectorStop


def tiny_llava(folder):
    from tokenizers import Tokenizer, models, pre_tokenizers
    from transformers import (CLIPImageProcessor, CLIPVisionConfig, LlamaConfig, LlavaConfig,
                              LlavaForConditionalGeneration, LlavaProcessor, PreTrainedTokenizerFast)

    words = ("<unk> <s> </s> <pad> <image> USER: ASSISTANT: yes no the image shows a robot's camera over time , left "
             "to right and top bottom . has robot completed task : put bowl on plate ? answer or").split()
    tok = Tokenizer(models.WordLevel({w: i for i, w in enumerate(dict.fromkeys(words))}, unk_token="<unk>"))
    tok.pre_tokenizer = pre_tokenizers.WhitespaceSplit()
    tokenizer = PreTrainedTokenizerFast(tokenizer_object=tok, unk_token="<unk>", bos_token="<s>", eos_token="</s>",
                                        pad_token="<pad>", extra_special_tokens={"image_token": "<image>"})
    processor = LlavaProcessor(image_processor=CLIPImageProcessor(size={"shortest_edge": 32},
                                                                  crop_size={"height": 32, "width": 32}),
                               tokenizer=tokenizer, patch_size=8, vision_feature_select_strategy="default",
                               image_token="<image>", num_additional_image_tokens=1)
    config = LlavaConfig(
        vision_config=CLIPVisionConfig(hidden_size=32, intermediate_size=64, num_hidden_layers=1, num_attention_heads=2,
                                       image_size=32, patch_size=8),
        text_config=LlamaConfig(hidden_size=32, intermediate_size=64, num_hidden_layers=1, num_attention_heads=2,
                                num_key_value_heads=2, vocab_size=len(tokenizer)),
        image_token_index=tokenizer.convert_tokens_to_ids("<image>"), vision_feature_layer=-1)
    torch.manual_seed(0)
    LlavaForConditionalGeneration(config).save_pretrained(folder)
    processor.save_pretrained(folder)
    return folder


@pytest.fixture(scope="module")
def vlm_config(tmp_path_factory):
    folder = tiny_llava(tmp_path_factory.mktemp("llava"))
    return {"_target_": "worldenv_core.models.vlm_reward.VLMYesNoReward", "pretrained_path": str(folder),
            "camera": "agentview", "grid_frames": 4}


def test_p_yes_is_a_probability_per_prefix_and_batched_equals_single(vlm_config):
    from hydra.utils import instantiate

    model = instantiate(vlm_config)
    video = torch.randint(0, 255, (9, 3, 24, 24), dtype=torch.uint8)
    steps = [0, 4, 8]
    scores = model.score_prefixes(video, "put bowl on plate", steps)
    assert scores.shape == (3,) and ((scores > 0) & (scores < 1)).all()
    single = model.probability([video[torch.tensor(steps)]], ["put bowl on plate"])
    assert torch.allclose(scores[-1:], single, atol=1e-5)  # padding in a batch changes nothing
    assert not any(p.requires_grad for p in model.vlm.parameters())


def test_checkpoint_is_the_config_naming_the_vlm_and_the_stop_rule_uses_it(vlm_config, tmp_path, contract):
    from hydra.utils import instantiate

    model = instantiate(vlm_config)
    save_model(tmp_path / "r", model, vlm_config, {"kind": "reflector", "image_size": 24, "camera": "agentview"})
    assert (tmp_path / "r" / "model.safetensors").stat().st_size < 1024  # no copy of the VLM's weights
    loaded, _ = load_checkpoint(tmp_path / "r", "reflector", contract(image_size=24))
    stop = ReflectorStop(loaded, 0.0, "put bowl on plate", encoder=None)
    frame = {"agentview": torch.randint(0, 255, (24, 24, 3), dtype=torch.uint8).numpy()}
    assert stop(frame) is True and 0 < stop.scores[0] < 1
    stop(frame)
    assert len(stop.scores) == 2


def test_answer_words_missing_from_the_vocabulary_are_a_clear_error(vlm_config):
    from worldenv_core.models.vlm_reward import VLMYesNoReward

    with pytest.raises(ValueError, match="no single token for 'oui'"):
        VLMYesNoReward(vlm_config["pretrained_path"], yes_token="oui")
