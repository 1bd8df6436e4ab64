"""The tiny imagined environment the imagination tests share: a random world model, two task
cameras and an untrained reflector (`make_env(eta, horizon)`), and three contexts (`contexts()`)."""
import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from worldenv_core.imagination.env import Context, ImaginedEnv
from worldenv_core.imagination.simulator import ImaginedSimulator
from worldenv_core.kinematics import NextStateModel, PinholeCamera
from worldenv_core.models.worldsim import WorldSimulator

TINY = dict(image_size=32, chunk=4, memory_offsets=(0, 2), latent_size=8, latent_channels=4, ae_widths=(8, 16),
            width=16, map_channels=4, use_raw_actions=True, sampling_steps=1)
REFLECTOR = {"_target_": "worldenv_core.models.reflector.Reflector", "camera": "agentview", "input_size": None,
             "max_frames": 8, "d_model": 16, "layers": 1, "heads": 2, "instruction_dim": 16,
             "frame_encoder": {"_target_": "worldenv_core.models.backbones.SmallConvBackbone", "cameras": ["agentview"],
                               "cond_dim": 16, "widths": [8, 8], "keypoints": 4}}


def camera(z):
    # looking down -z from above the table at height z
    return PinholeCamera("agentview", 32, 30.0, np.array([0.0, 0.0, z]), np.eye(3))


def _make_env(eta, horizon=12):
    torch.manual_seed(0)
    sim = ImaginedSimulator(WorldSimulator(**TINY), NextStateModel(), camera(2.0))
    encoder = lambda texts: torch.stack([torch.full((16,), float(len(t))) for t in texts])  # noqa: E731
    return ImaginedEnv(sim, {0: camera(2.0), 3: camera(2.5)}, instantiate(REFLECTOR), encoder, eta, horizon)


def _contexts():
    g = torch.Generator().manual_seed(0)
    return [Context(task_id=t, instruction=f"task {t}", frame=torch.randint(0, 255, (3, 32, 32), generator=g,
                                                                             dtype=torch.uint8),
                    proprio=torch.tensor([0.0, 0.0, 1.0, 3.14, 0.0, 0.0, 1.0])) for t in (0, 3, 0)]



@pytest.fixture
def make_env():
    return _make_env


@pytest.fixture
def contexts():
    return _contexts
