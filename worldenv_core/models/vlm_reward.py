"""The paper's "no reward head" ablation: ask a frozen vision-language model the yes/no question
and use P(yes) as the reward.

The VLM (any `AutoModelForImageTextToText` with its processor, e.g. LLaVA-1.5, saved with
`save_pretrained` in a local folder) sees up to `grid_frames` frames of the prefix, uniformly
sub-sampled and tiled into one image, and the prompt. P(yes) is the softmax over the logits of
the answer tokens `yes` and `no` at the position after the prompt. Nothing is trained.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from worldenv_core.models.reflector import subsample_indices
from worldenv_core.viz import tile

PROMPT = ("USER: <image> The image shows a robot's camera over time, left to right and top to bottom. "
          "Has the robot completed the task: {instruction} ? Answer yes or no . ASSISTANT:")


class VLMYesNoReward(nn.Module):
    """A reward model with the trained reflector's interface (`scorer`, `score_prefixes`) and no
    trainable parameters: train_reflector only evaluates it."""

    reward_kind = "VLM yes/no"

    def __init__(self, pretrained_path: str, camera: str = "agentview", grid_frames: int = 4, prompt: str = PROMPT,
                 yes_token: str = "yes", no_token: str = "no", max_frames: int = 32):
        super().__init__()
        from transformers import AutoModelForImageTextToText, AutoProcessor

        self.camera, self.grid_frames, self.prompt, self.max_frames = camera, int(grid_frames), prompt, int(max_frames)
        self.processor = AutoProcessor.from_pretrained(pretrained_path, local_files_only=True)
        vlm = AutoModelForImageTextToText.from_pretrained(pretrained_path, local_files_only=True).eval()
        vlm.requires_grad_(False)
        # Kept out of the state dict: the weights live in the pretrained folder, and a reflector
        # checkpoint of this mode is its config alone (which names that folder).
        self.__dict__["vlm"] = vlm
        ids = self.processor.tokenizer.convert_tokens_to_ids([yes_token, no_token])
        unk = self.processor.tokenizer.unk_token_id
        if any(i is None or (unk is not None and i == unk) for i in ids):
            raise ValueError(f"the VLM's tokenizer has no single token for {yes_token!r} / {no_token!r}")
        self.answer_ids = ids

    def _grid(self, frames: torch.Tensor) -> np.ndarray:
        idx = subsample_indices(frames.shape[0], self.grid_frames)
        return tile([f.permute(1, 2, 0).numpy() for f in frames[idx]])

    @torch.no_grad()
    def probability(self, videos: list[torch.Tensor], instructions: list[str]) -> torch.Tensor:
        """videos: (F, 3, H, W) uint8 each; -> (B,) P(yes)."""
        inputs = self.processor(images=[self._grid(v) for v in videos],
                                text=[self.prompt.format(instruction=g) for g in instructions],
                                return_tensors="pt", padding=True)
        logits = self.vlm(**inputs).logits  # (B, L, V)
        mask = inputs["attention_mask"]
        last = mask.shape[1] - 1 - mask.flip(1).argmax(1)  # the last real token, either padding side
        answer = logits[torch.arange(len(videos)), last][:, self.answer_ids]
        return torch.softmax(answer.float(), dim=-1)[:, 0]

    def scorer(self, instructions: list[str], encoder=None) -> "VLMIncrementalScorer":
        return VLMIncrementalScorer(self, instructions)

    @torch.no_grad()
    def score_prefixes(self, frames: torch.Tensor, instruction: str, steps, encoder=None) -> torch.Tensor:
        """R at each of `steps` of one video, seeing only the frames at those steps (as `score_prefixes`
        of the trained reflector)."""
        chosen = frames[torch.as_tensor(list(steps))]
        return self.probability([chosen[: j + 1] for j in range(len(chosen))], [instruction] * len(chosen))


class VLMIncrementalScorer:
    """The `IncrementalScorer` interface for the yes/no mode: keeps the frames, asks the VLM."""

    def __init__(self, model: VLMYesNoReward, instructions: list[str]):
        self.model, self.instructions, self.frames = model, list(instructions), []

    def add(self, frames: torch.Tensor) -> None:
        self.frames += list((frames if frames.dim() == 5 else frames[:, None]).unbind(1))

    def score(self) -> torch.Tensor:
        videos = torch.stack(self.frames, dim=1)  # (B, T, 3, H, W)
        return self.model.probability(list(videos), self.instructions)
