"""What the experiment report's sections share. The report (`<experiment>/report/report.md`,
assembled by `stages/report.py`) is the sum of the stages' sections: each stage's
`evaluation.section(ctx)` renders its part from the manifest alone, through a `ReportContext`
(the manifest's records read once, the report folder, the artefacts a record wrote), and builds
its tables with `markdown_table`. What a section needs to know about another stage's run is in
that run's manifest tags and metrics, never in its config."""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from worldenv_core.manifest import ArtefactError, Manifest, StageRecord

log = logging.getLogger(__name__)

TERMINATIONS = ("oracle", "fixed", "reflector")
POLICIES = ("sft", "post_trained")


def markdown_table(header: list[str], rows: list[list]) -> list[str]:
    """A GitHub markdown table: header, separator, one line per row (cells as given, str()'d)."""
    return ["| " + " | ".join(map(str, header)) + " |", "|" + "---|" * len(header),
            *("| " + " | ".join(map(str, row)) + " |" for row in rows)]


def short_run(path: str) -> str:
    """<stage>/<work dir> of a checkpoint path: which run it came from, without machine paths."""
    parts = Path(path).parts
    return "/".join(parts[-3:-1]) if len(parts) >= 3 else str(path)


def newest(records: list[StageRecord], **tags) -> StageRecord | None:
    found = [r for r in records if all(r.tags.get(k) == v for k, v in tags.items())]
    return found[-1] if found else None


@dataclass
class ReportContext:
    """One report's view of an experiment: its manifest (records read once), the task reported
    on, and the report folder sections copy pictures into."""

    manifest: Manifest
    task: str
    out: Path
    records: list[StageRecord] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.records = self.records or self.manifest.records()
        self.by_id = {r.id: r for r in self.records}

    def find(self, stage: str, **tags) -> list[StageRecord]:
        """This task's records of `stage` with these tags, oldest first."""
        tags = {"task": self.task, **tags}
        return [r for r in self.records if r.stage == stage and all(r.tags.get(k) == v for k, v in tags.items())]

    def report_json(self, record: StageRecord | None, name: str, strict: bool = False) -> dict | None:
        """A JSON report (`kind="report"` output named `name`) a record wrote, if it is still there
        and still what the record wrote (its sha256): a file another run overwrote is never read
        as this record's. A changed file is left out with a warning naming it (`strict`: an error)."""
        if record is None:
            return None
        for art in record.files("report"):
            if Path(art.path).name == name:
                path = self.manifest.root / art.path
                if not path.exists():
                    return None
                try:
                    return json.loads(art.verify(self.manifest.root).read_text())
                except ArtefactError as e:
                    if strict:
                        raise ArtefactError(f"{e}: it is not what record {record.id} wrote") from None
                    log.warning("%s; left out of the report (record %s)", e, record.id)
                    return None
        return None

    def copy(self, path: str, name: str | None = None, folder: str = "videos") -> str | None:
        """Copy an artefact (a path relative to the experiment) beside the report, so the report
        folder stands on its own; returns its path relative to the report, None if it is gone."""
        src = self.manifest.root / path
        if not src.exists():
            return None
        dst = self.out / folder / (name or src.name)
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(src, dst)
        return f"{folder}/{dst.name}"

    def history(self, record: StageRecord) -> list[dict]:
        """A training run's history: the JSON written beside its curves plot."""
        for art in record.files("plot"):
            path = (self.manifest.root / art.path).with_suffix(".json")
            if path.exists():
                return json.loads(path.read_text())
        return []

    def input(self, record: StageRecord | None, stage: str) -> StageRecord | None:
        """The record of `stage` that `record` read."""
        if record is None:
            return None
        return next((self.by_id[i] for i in record.inputs if i in self.by_id and self.by_id[i].stage == stage), None)

    def input_tags(self, record: StageRecord | None, stage: str) -> dict:
        found = self.input(record, stage)
        return found.tags if found else {}


def titled(title: str, lines: list[str]) -> list[str]:
    """A report section: its heading, then its lines; nothing when it has nothing to show."""
    return ["", f"## {title}", "", *lines] if lines else []
