"""The real simulator's frames as a world model would show them to the policy.

In imagination the policy acts on what the world model shows it: its first frame is the real
context frame, every later one a decoded latent (with the context frame's static detail laid back
where the picture did not change), and its proprioception is the kinematic model's, integrated
from the context's state through the actions taken (no contact, no real state to correct it).
`WorldModelView` gives a policy in the *real* simulator either or both of these in place of the
real ones: `frames`, each true frame encoded and rendered by the world model as if imagined;
`proprio`, the kinematic model's state rolled forward through the executed actions (or part of it:
`pose`, the end effector's position and rotation, `gripper`, its opening). Real success
under each part against the plain one says which part of imagination costs the policy its skill,
before anything is predicted: the closed-loop gap left over is the world model's dynamics.
"""

from __future__ import annotations

import numpy as np
import torch

from worldenv_core.imagination.simulator import ImaginedSimulator


PARTS = ("frames", "proprio", "pose", "gripper")  # proprio = pose + gripper
PROPRIO_DIMS = {"proprio": slice(0, 7), "pose": slice(0, 6), "gripper": slice(6, 7)}


class WorldModelView:
    """A policy runner (`PolicyRunner`'s `act_chunk` / `cameras` / `encoder` / `generator`) shown
    `parts` of the real episode as imagination would show them. Call `new_episode()` before each
    episode: its first frame and state are the context, shown as they are (as in imagination)."""

    def __init__(self, runner, sim: ImaginedSimulator, camera: str, parts=("frames", "proprio")):
        if camera not in runner.cameras:
            raise ValueError(f"the world model imagines camera {camera!r}, which the policy does not see "
                             f"({runner.cameras})")
        unknown = sorted(set(parts) - set(PARTS))
        if unknown or not parts:
            raise ValueError(f"view parts must be some of {PARTS}, got {list(parts)}")
        self.runner, self.sim, self.camera, self.parts = runner, sim, camera, tuple(parts)
        self.fresh = True
        self.state = self.carry = self.actions = None  # the kinematic model's proprio, its momentum, the last chunk

    @property
    def cameras(self) -> list[str]:
        return self.runner.cameras

    @property
    def encoder(self):
        return self.runner.encoder

    @property
    def generator(self):
        return self.runner.generator

    def new_episode(self) -> None:
        self.fresh = True

    @torch.no_grad()
    def view(self, image: np.ndarray, proprio) -> tuple[np.ndarray, np.ndarray]:
        """The real frame ((H, W, 3) uint8) and state ((7,)) at a chunk boundary -> as imagination
        would show them."""
        x = torch.as_tensor(image).permute(2, 0, 1)[None, None].to(self.sim.device)
        if self.fresh:  # the context: anchors the static detail and the kinematic state; shown as it is
            self.sim.reset(x, torch.as_tensor(proprio, dtype=torch.float64)[None])
            self.state, self.carry, self.fresh = self.sim.proprio, None, False
            return image, proprio
        if "frames" in self.parts:
            rendered = self.sim.render(self.sim.model.encode(x))[0, 0]
            image = (rendered * 255).round().to(torch.uint8).permute(1, 2, 0).cpu().numpy()
        dims = [PROPRIO_DIMS[p] for p in self.parts if p in PROPRIO_DIMS]
        if dims:  # through the chunk just executed, as ImaginedSimulator.step integrates it
            states, self.carry = self.sim.kinematics.rollout(self.state, self.actions, self.carry)
            self.state = states[:, -1]
            proprio = np.array(proprio, dtype=np.float32, copy=True)
            for d in dims:
                proprio[d] = self.state[0, d].float().cpu().numpy()
        return image, proprio

    def act_chunk(self, images: dict, proprio, instruction: str):
        image, proprio = self.view(images[self.camera], proprio)
        out = self.runner.act_chunk({**images, self.camera: image}, proprio, instruction)
        self.actions = torch.as_tensor(out[0], dtype=torch.float64)[None].to(self.sim.device)
        return out


def world_model_view(runner, worldsim_path: str, task_id: int, contract=None,
                     parts=("frames", "proprio")) -> WorldModelView:
    """`runner` shown `parts` of the real episode as the world model at `worldsim_path` imagines them."""
    from worldenv_core.models.checkpoint import read_config

    sim = ImaginedSimulator.from_checkpoint(worldsim_path, task_id, contract=contract)
    return WorldModelView(runner, sim, read_config(worldsim_path)["meta"]["camera"], parts)
