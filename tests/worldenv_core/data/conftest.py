"""Small synthetic episodes (2 cameras, 32x32, 10 steps) shared by the data-layer tests."""

import numpy as np
import pytest

from worldenv_core.data.episode import Episode, EpisodeMeta


def make_episode(T: int = 10, cameras=("agentview", "wrist"), size: int = 32, seed: int = 0,
                 extras: bool = True, sim_dim: int = 9, task_id: int = 3,
                 special_floats: bool = False) -> Episode:
    rng = np.random.default_rng(seed)
    n = T + 1
    meta = EpisodeMeta(
        suite="libero_object", task_id=task_id, task_name=f"task_{task_id}",
        instruction=f"pick up the alphabet soup and place it in the basket ({seed})",
        init_state_index=seed % 50, seed=1000 + seed, source="policy", success=True, attempts=2,
        fps=20.0, cameras=list(cameras), extra={"policy_ckpt": "ckpt/123", "unicode": "é✓"},
    )
    images = {c: rng.integers(0, 256, (n, size, size, 3), dtype=np.uint8) for c in cameras}
    proprio = rng.standard_normal((n, 7)).astype(np.float32)
    joint = rng.standard_normal((n, 7))
    sim = rng.standard_normal((n, sim_dim))
    actions = rng.uniform(-1, 1, (T, 7)).astype(np.float32)
    if special_floats and T >= 2:
        # values that a lossy float path would get wrong: -0.0, float32 subnormal/max, 1/3, inf, nan
        proprio[0, :6] = [-0.0, 1e-45, np.finfo(np.float32).max, 1 / 3, np.inf, np.nan]
        joint[1, :4] = [-0.0, 5e-324, 1 / 3, -np.inf]
        actions[0, :3] = [-0.0, np.float32(0.1), np.finfo(np.float32).tiny]
    success = np.zeros(n, bool)
    success[-1] = True
    step_extras = {}
    if extras:
        step_extras = {"mu": rng.standard_normal((T, 7)).astype(np.float32),
                       "beta": rng.standard_normal((T, 7)).astype(np.float32),
                       "chunk_logp": rng.standard_normal((T, 2, 3)).astype(np.float32)}
    return Episode(meta=meta, images=images, proprio=proprio, joint_pos=joint, sim_state=sim,
                   success=success, actions=actions, step_extras=step_extras)


@pytest.fixture
def episode() -> Episode:
    """10 steps, with -0.0 / subnormal / inf / nan planted to catch lossy float paths."""
    return make_episode(special_floats=True)


@pytest.fixture
def episode_dir(tmp_path):
    """Three episode files of different lengths (10, 5, 1 steps)."""
    from worldenv_core.data.mcap_io import write_episode

    d = tmp_path / "episodes"
    for i, T in enumerate((10, 5, 1)):
        write_episode(d / f"ep_{i:03d}.mcap", make_episode(T=T, seed=i))
    return d


@pytest.fixture
def make_ep():
    """The factory itself (tests import nothing from conftest: other test folders have their own)."""
    return make_episode
