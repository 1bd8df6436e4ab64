"""Fault suite, runs side by side and data that moves: two evaluations of one experiment started
at once (real processes), a record's file overwritten after it was recorded, and the held-out
split of episodes that live elsewhere. Part of `make faults`."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from worldenv_core.data.selection import episode_key, holdout_split
from worldenv_core.manifest import ArtefactError, Manifest, StageRun, sha256_file
from worldenv_core.models.checkpoint import load_weights, save_state
from worldenv_core.report import ReportContext
from worldenv_core.stage import compose_config

pytestmark = pytest.mark.fault
REPO = Path(__file__).resolve().parent.parent
TINY_POLICY = ["train.steps=20", "scale_head.steps=10", "train.log_every=5", "train.checkpoint_every=10",
               "demos_per_task=1", "policy.hidden=32", "policy.backbone.widths=[8,8,8,8]",
               "policy.backbone.keypoints=4"]


def cli(*args, timeout=600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *args], cwd=REPO, capture_output=True, text=True, timeout=timeout)


# ---------------------------------------------------------------- two evaluations at once


@pytest.mark.fault_full
@pytest.mark.sim
@pytest.mark.slow
def test_two_evaluations_started_together_each_record_holds_its_own_policys_results(demo_experiment, tmp_path):
    exp = tmp_path / "exp"
    shutil.copytree(demo_experiment, exp)
    trained = cli("stages.train_policy", "+task=tiny", "scale=tiny", *TINY_POLICY, f"experiment_dir={exp}")
    assert trained.returncode == 0, trained.stderr[-2000:]
    sft = Path(Manifest(exp).resolve(Manifest(exp).latest("train_policy"), kind="checkpoint")[0]).parent
    other = tmp_path / "other_policy"  # a second policy: the same one with its weights moved
    config = json.loads((sft / "config.json").read_text())
    weights = {k: v + 0.05 * torch.randn_like(v) if v.is_floating_point() else v
               for k, v in load_weights(sft / "model.safetensors").items()}
    save_state(other, weights, config["model"], config["meta"])
    args = ["stages.evaluate", "+task=tiny", "scale=tiny", f"experiment_dir={exp}", "init_states=2", "workers=1",
            "videos_per_task=0", "progress=false"]
    procs = {str(p): subprocess.Popen([sys.executable, "-m", *args, f"policy_from={p}"], cwd=REPO,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
             for p in (sft, other)}  # started in the same second: Hydra's run folders are named to the second
    for p in procs.values():
        assert p.wait(timeout=600) == 0, p.stderr.read()[-2000:]
    records = Manifest(exp).find("evaluate")
    assert len(records) == 2
    ctx = ReportContext(Manifest(exp), "tiny", exp / "report")
    seen = set()
    for rec in records:
        summary = ctx.report_json(rec, "results.json", strict=True)
        policy = rec.config["policy_from"]
        assert summary["policy"] == str(Path(policy).resolve())  # its own policy's results, verified by sha256
        seen.add(policy)
    assert seen == set(procs)
    folders = {Path(a.path).parent for rec in records for a in rec.files("report")}
    assert len(folders) == 2, "two runs shared a run folder"


def test_a_record_file_another_run_overwrote_is_never_read_as_its_own(tmp_path, caplog):
    m = Manifest(tmp_path)
    out = tmp_path / "hydra" / "evaluate" / "run"
    out.mkdir(parents=True)
    (out / "results.json").write_text(json.dumps({"policy": "sft", "success_rate": 0.5}))
    with StageRun(m, "evaluate", {"task": "t"}, {}) as run:
        run.add_output(out / "results.json", kind="report")
    (rec,) = m.records()
    ctx = ReportContext(m, "t", tmp_path / "report")
    assert ctx.report_json(rec, "results.json") == {"policy": "sft", "success_rate": 0.5}
    (out / "results.json").write_text(json.dumps({"policy": "post_trained", "success_rate": 0.9}))
    assert ctx.report_json(rec, "results.json") is None and "is stale" in caplog.text
    with pytest.raises(ArtefactError, match=f"not what record {rec.id} wrote"):
        ctx.report_json(rec, "results.json", strict=True)


# ---------------------------------------------------------------- the held-out split of moved data


def _layout(demos: Path, exp: Path, expert_root: Path, policy_root: Path) -> None:
    """An experiment whose expert and policy collections live in two data folders: the tiny demos
    recorded once as the expert collection and once (copied) as a policy collection."""
    files = sorted(demos.glob("data/tiny/expert-*/task00/*.mcap"))
    m = Manifest(exp)
    for source, root in (("expert", expert_root), ("policy", policy_root)):
        folder = root / "tiny" / f"{source}-0000cafe" / "task00"  # collection folders keep their names when moved
        folder.mkdir(parents=True)
        with StageRun(m, "collect", {"task": "tiny", "scale": "tiny", "source": source}, {"source": source}) as run:
            for k, f in enumerate(files):
                run.add_output(shutil.copyfile(f, folder / f"{source}_{k:04d}.mcap"), kind="episodes")


def test_the_split_is_by_identity_whatever_the_folders_are_called(tmp_path):
    names = [f"{src}-0000cafe/task00/{src}_{k:04d}.mcap" for src in ("expert", "policy") for k in range(3)]
    # the same episodes, in one data folder, then with the collections in two whose names sort the other way
    layouts = [[tmp_path / "z" / "tiny" / n for n in names],
               [tmp_path / ("b" if n.startswith("expert") else "a") / "tiny" / n for n in names]]
    held = [{episode_key(p) for p in holdout_split(paths, 4)[1]} for paths in layouts]
    assert held[0] == held[1] == {"policy-0000cafe/task00/policy_0000.mcap"}
    with pytest.raises(ArtefactError, match="named twice"):
        holdout_split(layouts[0] + [tmp_path / "elsewhere" / "tiny" / names[0]], 2)


WORLDSIM = ["expert_only=false", "holdout_every=3", "ae.steps=20", "flow.steps=20", "ae.batch_size=4",
            "flow.batch_size=4", "log_every=5", "checkpoint_every=10", "worldsim.ae_widths=[8,16]", "worldsim.width=16",
            "worldsim.map_channels=4", "fidelity.horizons=[8]", "fidelity.starts_per_episode=1", "fidelity.videos=0"]


@pytest.mark.fault_full
@pytest.mark.sim
@pytest.mark.slow
def test_moved_data_keeps_the_split_the_work_dir_and_the_weights(demo_experiment, tmp_path):
    """The collections recorded again from other folders (bit-identical episodes, their expert and
    policy folders now sorting the other way) and the world model trained again: the same episode
    held out, the same work dir, the same weights; and the same from scratch in a new experiment."""
    from stages.train_worldsim.run import run as train_worldsim

    def trained(exp: Path) -> tuple[list, str, str]:
        train_worldsim(compose_config("train_worldsim", ["+task=tiny", "scale=tiny", f"experiment_dir={exp}",
                                                         *WORLDSIM]))
        model = next(p for p in Manifest(exp).resolve(Manifest(exp).latest("train_worldsim"))
                     if p.name == "model.safetensors")
        meta = json.loads((model.parent / "config.json").read_text())["meta"]
        work = next(p for p in model.parents if p.parent.name == "train_worldsim")
        return meta["held_out"], work.name, sha256_file(model)

    exp = tmp_path / "exp"
    _layout(demo_experiment, exp, tmp_path / "a", tmp_path / "b")
    first = trained(exp)
    _layout(demo_experiment, exp, tmp_path / "c", tmp_path / "a2")  # moved: expert now sorts after policy
    for report in Manifest(exp).latest("train_worldsim").files("report"):  # so that it runs again, not repeats
        (exp / report.path).unlink()
    again = trained(exp)
    fresh = tmp_path / "fresh"
    _layout(demo_experiment, fresh, tmp_path / "f" / "c", tmp_path / "f" / "a")
    scratch = trained(fresh)
    assert len(first[0]) == 1 and first[0] == again[0] == scratch[0]
    assert first[1] == again[1]
    assert first[2] == again[2] == scratch[2]
