"""Keeping a paired-replay run in the repository: the files the manifest recorded, without this
machine's paths, readable by the pooled verdict as the run's own folder is."""
import json

import pytest

from analysis import keep
from analysis.pooled_verdicts import pooled
from tests.worldenv_core.imagination.test_verdict import _row
from worldenv_core.errors import ArtefactError, ConfigError
from worldenv_core.manifest import Manifest, StageRecord


def _record(manifest: Manifest, stage: str, files: dict[str, str]) -> StageRecord:
    out = manifest.root / stage / "run"
    out.mkdir(parents=True)
    rec = StageRecord(stage=stage, tags={"task": "tiny"}, config={}, config_hash="h")
    for name, text in files.items():
        (out / name).write_text(text)
        rec.outputs.append(manifest.artefact(out / name, kind="report"))
    return manifest.append(rec)


def test_a_paired_replay_run_is_kept_without_machine_paths(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the checkout: its data/ and outputs/ are where paths point
    manifest = Manifest(tmp_path / "outputs" / "exp")
    start = tmp_path / "data" / "tiny" / "task00" / "expert_0001.mcap"
    rows = [dict(_row([0, 0.9], first=8, context=0), start=f"{start}@12"), _row([0, 0.2], first=None, context=1)]
    policy = f"{tmp_path}/checkpoints/tiny/sft@1"
    summary = {"headline_policy": policy, "eta": 0.5, "judges": {}}
    rec = _record(manifest, "evaluate_imagination", {"fidelity.json": json.dumps(summary),
                                                     "pairs.json": json.dumps({policy: {"rows": rows}}, indent=1)})
    (kept,) = keep.main([str(manifest.root), rec.id, "--into", "results/tiny"])
    assert kept.resolve() == tmp_path / "results" / "tiny" / rec.id
    for name in ("fidelity.json", "pairs.json"):
        assert str(tmp_path) not in (kept / name).read_text()
    fidelity = json.loads((kept / "fidelity.json").read_text())
    assert fidelity["record"] == rec.id and fidelity["headline_policy"] == "checkpoints/tiny/sft@1"
    pairs = json.loads((kept / "pairs.json").read_text())["checkpoints/tiny/sft@1"]["rows"]
    assert pairs[0]["start"] == "data/tiny/task00/expert_0001.mcap@12"
    # read back as the run's own folder would be: the same verdict (compared as text: NaN is not NaN)
    verdict = [json.dumps(pooled([f])["headline"], sort_keys=True, default=str)
               for f in (kept, manifest.root / "evaluate_imagination" / "run")]
    assert verdict[0] == verdict[1] and json.loads(verdict[0])["rollouts"] == 2


def test_a_changed_report_or_another_stage_is_refused(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    manifest = Manifest(tmp_path / "exp")
    rec = _record(manifest, "evaluate_imagination", {"fidelity.json": "{}", "pairs.json": "{}"})
    (manifest.root / "evaluate_imagination" / "run" / "pairs.json").write_text('{"edited": 1}')
    with pytest.raises(ArtefactError, match="stale"):
        keep.main([str(manifest.root), rec.id, "--into", "kept"])
    other = _record(manifest, "train_reflector", {"metrics.json": "{}"})
    with pytest.raises(ConfigError, match="only evaluate and evaluate_imagination"):
        keep.main([str(manifest.root), other.id, "--into", "kept"])
    assert not (tmp_path / "kept").exists()
