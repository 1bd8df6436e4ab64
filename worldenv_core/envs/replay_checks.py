"""Replay checks kept between sittings: whether a recorded episode's prefix replays to its recorded state.

`replay.unreplayable` replays every mid-episode start before a run uses it. The answer is a fact of the episode
file and the simulator, and 200 keyframes cost about 8 minutes of physics on one core, paid again each time a
campaign resumes. A record keeps its file's size and modification time and the simulator's versions; a record
that no longer matches (the file rewritten, MuJoCo or robosuite upgraded) is checked again. The file is rewritten
whole (temporary name, then rename) and merged with what is on disk, so two runs sharing it lose nothing worse
than a check to redo."""

from __future__ import annotations

import json
import os
from pathlib import Path

from worldenv_core.files import write_text_atomic

MISSING = object()  # `ReplayChecks.get`: no valid record


def replay_checks_file(cfg) -> Path:
    """An experiment's kept replay checks (every stage that drops unreplayable starts shares them)."""
    return Path(cfg.experiment_dir) / "cache" / "replay_checks.json"


def simulator_versions(also: tuple[str, ...] = ()) -> str:
    """What a replay's outcome depends on besides the file: the physics and the robot's controllers (and the
    packages `also` names), as `name==version` joined by commas, `?` for one not installed."""
    from importlib.metadata import PackageNotFoundError, version

    out = []
    for name in ("mujoco", "robosuite", *also):
        try:
            out.append(f"{name}=={version(name)}")
        except PackageNotFoundError:
            out.append(f"{name}==?")
    return ",".join(out)


def _stamp(episode: str) -> list[int] | None:
    try:
        st = os.stat(episode)
    except OSError:
        return None
    return [st.st_size, st.st_mtime_ns]


class ReplayChecks:
    """start key (`RealStart.key`: episode path @ frame) -> the replay's error, or None where it replays."""

    def __init__(self, path: str | Path | None, versions: str | None = None):
        self.path = Path(path) if path else None
        self.versions = versions or simulator_versions()
        self.records = self._read() if self.path else {}

    def _read(self) -> dict:
        try:
            data = json.loads(self.path.read_text())
        except (OSError, ValueError):  # none yet, or unreadable: every start is checked again
            return {}
        return data.get("records", {}) if data.get("versions") == self.versions else {}

    def get(self, start):
        """The kept error (None: it replays) of `start`, or MISSING."""
        rec = self.records.get(start.key)
        if rec is None or rec.get("stamp") != _stamp(start.episode):
            return MISSING
        return rec["error"]

    def put(self, results: list[dict]) -> None:
        """`replays` results (start, error) kept, merged with the file's records."""
        if self.path is None or not results:
            return
        self.records = {**self._read(), **self.records}
        for r in results:
            self.records[r["start"].key] = {"error": r["error"], "stamp": _stamp(r["start"].episode)}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(self.path, json.dumps({"versions": self.versions, "records": self.records}))
