"""Which collected episodes a model stage trains on, and which it holds out.

The world simulator and the reflector read the same episodes (expert demos plus the policy's
Laplace-perturbed rollouts) and split them by the same rule, so with the same `holdout_every`
they hold out the same episodes: imagined evaluation then replays episodes neither model saw.
`set_aside_damaged` checks the episodes a resumed collection would skip, so a damaged one is
collected again.
"""

from __future__ import annotations

import glob
import logging
import os
import time
from collections.abc import Iterable
from pathlib import Path

from worldenv_core.data.mcap_io import CorruptEpisodeError, read_episode
from worldenv_core.manifest import ArtefactError, Manifest, StageRun, sha256_file

log = logging.getLogger(__name__)


class MissingEpisodesError(ArtefactError):
    """A stage needs a collection the experiment does not have yet."""


POLICY_COLLECTIONS = ("latest", "all")  # the `policy_collections` setting of the stages that read collections


def collected_episodes(manifest: Manifest, stage: StageRun, task: str, scale: str, expert_only: bool,
                       policy_collections: str = "latest") -> list[Path]:
    """The latest expert collection of this task and scale, plus policy rollouts unless `expert_only`
    (the paper's "w/o extra data" ablation); sorted paths. `policy_collections`: "latest", the newest
    policy collection; "all", the newest record of every policy collection folder (each policy and noise
    scale collects into its own: the SFT policy's rollouts and, after a refit round, the improved
    policy's, or exploration data at several noise scales), every one recorded as an input.

    Newest per folder, not every record: collections with the same seed and policy hold the same
    rollouts (episode seeds depend on seed, task and index only; a rerun with `post_success_steps` only
    extends them), so a union would count episodes twice and put copies on both sides of the held-out
    split. More rollouts come from a larger `episodes_per_task` into the same collection."""
    if policy_collections not in POLICY_COLLECTIONS:
        raise ValueError(f"policy_collections must be one of {list(POLICY_COLLECTIONS)}, got {policy_collections!r}")
    tags = {"task": task, "scale": scale}
    paths = stage.use(manifest.latest("collect", source="expert", **tags), kind="episodes")
    if not expert_only:
        records = manifest.find("collect", source="policy", **tags)
        if not records:
            raise MissingEpisodesError(
                f"no policy rollouts of task {task} at scale {scale} in {manifest.path}; collect them first "
                f"(`python -m stages.collect +task={task} source=policy`) or use expert data only with "
                "expert_only=true")
        for record in newest_per_folder(records) if policy_collections == "all" else records[-1:]:
            paths += stage.use(record, kind="episodes")
    return sorted(paths)


def newest_per_folder(records: list) -> list:
    """The newest record of each collection folder (records oldest first)."""
    newest = {}
    for r in records:  # a later record of a folder replaces the earlier one
        for a in r.files("episodes"):
            newest[Path(a.path).parts[-3]] = r  # <collection>/taskNN/<file>
    return list({r.id: r for r in newest.values()}.values())


def holdout_split(paths: list[Path], every: int) -> tuple[list[Path], list[Path]]:
    """Every `every`-th episode in the order of their identities (`episode_key`) is held out; at
    least one is. By identity, not by path: the same episodes under another data_dir, copied or
    re-rooted, hold out the same ones (sorted absolute paths interleave two collections by where
    they live). Returns (train, held out), each in that order."""
    order = sorted(paths, key=lambda p: (episode_key(p), str(p)))
    keys = [episode_key(p) for p in order]
    if len(set(keys)) != len(keys):
        twice = sorted({k for k in keys if keys.count(k) > 1})
        raise ArtefactError(f"{len(twice)} episode(s) are named twice among the collections read, e.g. {twice[0]}: "
                            "one collection per source, please")
    held = set(order[every - 1::every]) or {order[-1]}
    return [p for p in order if p not in held], [p for p in order if p in held]


def episode_key(path: str | Path) -> str:
    """A machine-independent name for a collected episode: <collection>/<task>/<file>. The
    collection folder is named by the settings that made it (`stages.collect.episodes.episode_dir`),
    the file by its index, so the key is the episode's identity wherever the data lives."""
    return "/".join(Path(path).parts[-3:])


def expand_episode_paths(patterns: Iterable[str]) -> list[Path]:
    """Episode files named or matched by glob patterns, sorted and once each (the CLIs' argument);
    a name that matches nothing and is no file is an error naming it."""
    paths = sorted({Path(q) for pattern in patterns for q in (glob.glob(pattern) or [pattern])})
    missing = [str(q) for q in paths if not q.is_file()]
    if missing:
        raise FileNotFoundError(f"episode files not found: {missing[:3]}")
    return paths


def load_split(paths: list[Path], holdout_every: int, camera: str,
               held_out: Iterable[str] | None = None) -> tuple[list[Path], list[Path], list, list]:
    """What the world-simulator and reflector stages start from: `paths` (`collected_episodes`)
    split by `holdout_every` (or, given `held_out` episode keys, e.g. a model's that is trained
    further, exactly those) and read with `camera` only. Returns (train paths, held-out paths,
    train episodes, held-out episodes); nothing left to train on is an error naming the count."""
    if held_out is None:
        train, held = holdout_split(paths, holdout_every)
    else:
        keys = set(held_out)
        train, held = [p for p in paths if episode_key(p) not in keys], [p for p in paths if episode_key(p) in keys]
    if not train:
        raise MissingEpisodesError(f"only {len(paths)} episodes: none left for training after holding out {len(held)}; "
                                   "collect more (episodes_per_task=N) or raise holdout_every")
    read = lambda ps: [read_episode(p, cameras=[camera]) for p in ps]  # noqa: E731
    return train, held, read(train), read(held)


def set_aside_damaged(manifest, paths: Iterable[str | os.PathLike]) -> int:
    """Before a collection resumes: every existing episode file it would skip is checked, against
    the sha256 a manifest record holds for it (any change is damage), or, if no record names it
    yet (a run killed before recording), by reading it whole. A damaged file is moved aside
    (`<name>.damaged-<time>`, kept for inspection) so the collection writes it again with the
    same seed. Returns how many were set aside."""
    recorded = {}
    for record in manifest.records():
        if record.stage == "collect":
            for art in record.files("episodes"):
                recorded[str((manifest.root / art.path).resolve())] = art.sha256
    stamp = time.strftime("%Y%m%dT%H%M%S")
    moved = 0
    for path in map(Path, paths):
        if not path.exists():
            continue
        sha = recorded.get(str(path.resolve()))
        if sha is not None:
            problem = None if sha256_file(path) == sha else "its content changed after the manifest recorded it"
        else:
            try:
                read_episode(path)
                problem = None
            except CorruptEpisodeError as e:
                problem = e.reason
        if problem:
            aside = path.with_name(f"{path.name}.damaged-{stamp}")
            os.replace(path, aside)
            log.warning("%s is damaged (%s): moved to %s; collecting it again with the same seed", path, problem,
                        aside.name)
            moved += 1
    return moved
