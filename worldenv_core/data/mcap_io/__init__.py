"""One episode per MCAP file: lossless, self-describing, and viewable in Foxglove.

File layout (schema_version 1):
  /camera/<name>  foxglove.CompressedImage (protobuf), PNG, frame_id = camera name   T+1 msgs
  /state          JSON {frame, proprio[7], joint_pos[7], success}                   T+1 msgs
  /sim_state      JSON {frame, sim_state[S]}                                        T+1 msgs
  /action         JSON {frame, action[7], extras: {name: nested list}}              T msgs
  metadata "episode": every EpisodeMeta field as a string, plus schema_version, length, dtypes,
                      shapes.
Every message carries log_time = publish_time = frame / fps (ns) and sequence = frame index;
the reader places messages by `sequence`, so rounding in the timestamps can never shuffle frames.

Why JSON for numbers: Foxglove plots JSON fields directly, and Python writes a float64 with the
shortest repr that parses back to the same bits, so float32 (widened to float64) and float64 both
round-trip bit-exactly. NaN/Infinity are written as the non-standard tokens Python's json accepts.

Why messages are grouped by channel (all /state, then /action, ..., each camera last) with a
chunk boundary between channels: MCAP's chunk index then lets a reader that asks for /state only
skip every image chunk, so loading proprio/actions for statistics does not decode a single PNG.
Foxglove reads through the index, so playback order is unaffected.
"""

from .format import (
    JSON_SCHEMAS, REAL_PREFIX, REFLECTOR_SCHEMA, SCHEMA_VERSION, SUFFIX, CorruptEpisodeError, EpisodeInfo,
)
from .png import decode_png, encode_png
from .read import (glob_episode_files, iter_episodes, list_episode_files, read_episode, read_info, read_meta,
                   read_reflector_scores)
from .write import write_episode, write_imagined_episode

__all__ = [
    "JSON_SCHEMAS", "REAL_PREFIX", "REFLECTOR_SCHEMA", "SCHEMA_VERSION", "SUFFIX",
    "CorruptEpisodeError", "EpisodeInfo", "decode_png", "encode_png", "glob_episode_files",
    "iter_episodes", "list_episode_files",
    "read_episode", "read_info", "read_meta", "read_reflector_scores", "write_episode", "write_imagined_episode",
]
