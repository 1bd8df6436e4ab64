import json

import pytest

from worldenv_core.manifest import ArtefactError, Manifest, StageRun, config_hash


def _stage(manifest, tmp_path, name, tags, content=b"x"):
    f = tmp_path / f"{name}-{len(manifest.records())}.bin"
    f.write_bytes(content)
    with StageRun(manifest, name, tags, {"lr": 1e-3, "task": tags.get("task")}) as run:
        run.add_output(f, kind="episodes")
        run.metrics["n"] = 1
    return run.record, f


def test_records_are_found_by_stage_and_tags_newest_first(tmp_path):
    m = Manifest(tmp_path / "exp")
    r1, _ = _stage(m, tmp_path, "collect", {"task": "goal", "source": "expert"})
    r2, f2 = _stage(m, tmp_path, "collect", {"task": "goal", "source": "expert"}, b"y")
    _stage(m, tmp_path, "collect", {"task": "object", "source": "expert"})
    latest = m.latest("collect", task="goal", source="expert")
    assert latest.id == r2.id != r1.id
    assert m.resolve(latest, kind="episodes") == [f2.resolve()]
    rec = json.loads(m.path.read_text().splitlines()[0])
    for key in ("config", "config_hash", "git_rev", "packages", "inputs", "outputs", "metrics", "wall_time_s", "started"):
        assert key in rec
    assert rec["outputs"][0]["sha256"] and rec["outputs"][0]["size"] == 1
    assert rec["packages"]["mujoco"] == "3.3.7"


def test_missing_artefact_error_lists_what_exists(tmp_path):
    m = Manifest(tmp_path / "exp")
    _stage(m, tmp_path, "collect", {"task": "goal"})
    with pytest.raises(ArtefactError, match=r"(?s)no .train_policy. artefact.*run that stage first.*collect"):
        m.latest("train_policy", task="goal")


def test_stale_and_deleted_artefacts_are_refused(tmp_path):
    m = Manifest(tmp_path / "exp")
    rec, f = _stage(m, tmp_path, "collect", {"task": "goal"})
    f.write_bytes(b"z")  # same size, other content
    with pytest.raises(ArtefactError, match="stale"):
        m.resolve(rec)
    f.unlink()
    with pytest.raises(ArtefactError, match="missing on disk"):
        m.resolve(rec)


def test_a_failed_stage_records_nothing(tmp_path):
    m = Manifest(tmp_path / "exp")
    with pytest.raises(RuntimeError):
        with StageRun(m, "collect", {}, {}):
            raise RuntimeError("boom")
    assert m.records() == []


def test_config_hash_ignores_key_order():
    assert config_hash({"a": 1, "b": {"c": 2}}) == config_hash({"b": {"c": 2}, "a": 1})
    assert config_hash({"a": 1}) != config_hash({"a": 2})


def test_a_stage_records_the_artefacts_it_used(tmp_path):
    m = Manifest(tmp_path / "exp")
    demos, f = _stage(m, tmp_path, "collect", {"task": "goal"})
    ckpt = tmp_path / "policy.safetensors"
    ckpt.write_bytes(b"weights")
    with StageRun(m, "train_policy", {"task": "goal"}, {}) as run:
        assert run.use(m.latest("collect", task="goal"), kind="episodes") == [f.resolve()]
        run.add_output(ckpt, kind="checkpoint")
    rec = m.latest("train_policy", task="goal")
    assert rec.inputs == [demos.id]
    assert [a.sha256 for a in rec.input_files] == [a.sha256 for a in demos.outputs]


def test_a_rerun_that_hands_on_the_same_files_names_the_same_work(tmp_path):
    """Work dirs are named after their inputs; a re-run of an upstream stage that changed nothing
    is a new record, but a consumer's work_inputs() names the first record with those files."""
    m = Manifest(tmp_path / "exp")
    first, _ = _stage(m, tmp_path, "collect", {"task": "goal"}, b"demos")
    other, _ = _stage(m, tmp_path, "collect", {"task": "goal"}, b"other demos")
    rerun, _ = _stage(m, tmp_path, "collect", {"task": "goal"}, b"demos")  # same content, new record
    names = {}
    for upstream in (first, other, rerun):
        with StageRun(m, "train_policy", {"task": "goal"}, {}) as run:
            run.use(upstream, kind="episodes")
            names[upstream.id] = run.work_inputs()
        assert run.record.inputs == [upstream.id]  # the record still names what it read
    assert names[rerun.id] == names[first.id] == [first.id] and names[other.id] == [other.id]


def test_a_finished_run_is_found_by_settings_inputs_and_intact_outputs(tmp_path):
    m = Manifest(tmp_path / "exp")
    _stage(m, tmp_path, "collect", {"task": "goal"})

    def train(config, content=b"w"):
        """A stage that reads the collection and, unless it finished before, writes `content`;
        its record (the newest), and the run's that produced its outputs."""
        with StageRun(m, "train", {"task": "goal"}, config) as run:
            run.use(m.latest("collect"))
            if run.finished_before() is None:
                f = tmp_path / "weights.bin"
                f.write_bytes(content)
                run.add_output(f, kind="checkpoint")
        rec = m.latest("train")
        return rec, rec.repeats or rec.id

    first, _ = train({"lr": 1})
    repeat, producer = train({"lr": 1})  # repeated: its record hands on the first one's outputs
    assert repeat.id != first.id and producer == first.id and repeat.outputs == first.outputs
    assert repeat.metrics == first.metrics and repeat.tags == first.tags
    assert train({"lr": 2})[1] != first.id  # other settings
    assert train({"lr": 1})[1] == first.id  # the newest again, for `latest`
    (tmp_path / "weights.bin").write_bytes(b"v")  # an output changed: the run is done again
    redone, producer = train({"lr": 1}, b"v")
    assert producer == redone.id != first.id
    assert train({"lr": 1}, b"v")[1] == redone.id  # and that one is found next time
    _stage(m, tmp_path, "collect", {"task": "goal"}, b"other")  # other input content
    other, producer = train({"lr": 1}, b"v")
    assert producer == other.id != redone.id
