"""Episode data: the in-memory Episode, its MCAP files, torch datasets and LeRobot export/import.

The LeRobot functions live in `worldenv_core.data.lerobot_io` and are not imported here: lerobot
is a heavy import that most consumers of episodes do not need.
"""

from .dataset import EpisodeDataset
from .episode import ACTION_DIM, JOINT_DIM, PROPRIO_DIM, Episode, EpisodeMeta, episode_differences
from .mcap_io import (
    CorruptEpisodeError,
    EpisodeInfo,
    iter_episodes,
    list_episode_files,
    read_episode,
    read_info,
    read_meta,
    write_episode,
)

__all__ = [
    "ACTION_DIM", "JOINT_DIM", "PROPRIO_DIM",
    "CorruptEpisodeError", "Episode", "EpisodeDataset", "EpisodeInfo", "EpisodeMeta",
    "episode_differences", "iter_episodes", "list_episode_files", "read_episode", "read_info",
    "read_meta", "write_episode",
]
