"""train_worldsim on the tiny task: manifest inputs, checkpoint, fidelity report, resume, errors."""
import json

import numpy as np

import pytest

from stages.train_worldsim.run import run as train_worldsim
from worldenv_core.data.mcap_io import read_episode
from worldenv_core.data.selection import MissingEpisodesError
from worldenv_core.manifest import Manifest
from worldenv_core.models.checkpoint import load_checkpoint
from worldenv_core.stage import compose_config

pytestmark = [pytest.mark.sim, pytest.mark.slow]
SMALL = ["ae.steps=20", "flow.steps=20", "ae.batch_size=4", "flow.batch_size=4", "holdout_every=2", "log_every=5",
         "checkpoint_every=10", "worldsim.ae_widths=[8,16]", "worldsim.width=16", "worldsim.map_channels=4",
         "fidelity.horizons=[8,16]", "fidelity.starts_per_episode=1", "fidelity.videos=1", "worldsim.sampling_steps=2"]


def cfg(exp, *overrides):
    return compose_config("train_worldsim", ["+task=tiny", "scale=tiny", f"experiment_dir={exp}", *SMALL, *overrides])


def test_train_worldsim_without_policy_rollouts_names_the_missing_step(demo_experiment):
    with pytest.raises(MissingEpisodesError, match="source=policy.*expert_only=true"):
        train_worldsim(cfg(demo_experiment))


def test_train_worldsim_records_checkpoint_fidelity_and_resumes(demo_experiment, contract):
    exp = demo_experiment
    metrics = train_worldsim(cfg(exp, "expert_only=true"))
    m = Manifest(exp)
    rec = m.latest("train_worldsim", task="tiny", data="expert")
    assert rec.inputs == [m.latest("collect", task="tiny", source="expert").id]
    files = {p.name: p for p in m.resolve(rec)}
    assert {"model.safetensors", "config.json", "fidelity.json", "fidelity.md", "losses.png"} <= set(files)
    assert any(name.startswith("real_vs_imagined") for name in files)
    # the held-out episodes replayed by the world model, the real ones beside them (Foxglove)
    replays = [m.root / f.path for f in rec.files("imagined")]
    assert replays and all(p.name.startswith("heldout_") for p in replays)
    imagined, real = read_episode(replays[0]), read_episode(replays[0], prefix="/real")
    assert imagined.meta.source == "imagined" and real.meta.source == "expert"
    assert np.array_equal(imagined.actions, real.actions) and imagined.num_frames == real.num_frames
    assert np.array_equal(imagined.images["agentview"][0], real.images["agentview"][0])  # the same start
    tb = next((p for p in files.values() if p.name == "model.safetensors")).parent.parent / "tensorboard"
    assert list(tb.glob("events.out.tfevents.*")), "training curves go to TensorBoard by default"
    report = json.loads(files["fidelity.json"].read_text())
    assert set(report["fidelity"]) == {"8", "16"} and report["fidelity"]["8"]["n"] == 1
    for key in ("model_psnr", "copy_psnr", "model_ssim", "copy_ssim", "plain_psnr", "plain_ssim"):  # detail transfer on
        assert 0 < report["fidelity"]["8"][key] < 100
    assert report["kinematics_1step"]["pos_mm_median"] < 5  # fitted on one episode, checked on the other
    model, meta = load_checkpoint(files["model.safetensors"].parent, "worldsim", contract())
    assert model.sampling_steps == 2 and model.detail_gate == 0.3 and set(meta["cameras"]) == {"0"}
    assert metrics["held_out"] == 1 and metrics["episodes"] == 1

    again = train_worldsim(cfg(exp, "expert_only=true"))  # same settings and inputs, outputs intact: not run again
    assert again["train_wall_s"] == metrics["train_wall_s"]
    assert Manifest(exp).latest("train_worldsim", task="tiny", data="expert").repeats == rec.id
    files["fidelity.md"].unlink()  # an output gone: it runs again, resuming at the end (trains nothing)
    again = train_worldsim(cfg(exp, "expert_only=true"))
    assert again["train_wall_s"] < 5 and not Manifest(exp).latest("train_worldsim", task="tiny", data="expert").repeats


def test_fidelity_tool_reproduces_the_recorded_report_and_sweeps_the_detail_gate(demo_experiment):
    from analysis.fidelity_settings import main as fidelity

    train_worldsim(cfg(demo_experiment, "expert_only=true"))  # (resumes the finished run of the test above)
    m = Manifest(demo_experiment)
    rec = m.latest("train_worldsim", task="tiny", data="expert")
    recorded = json.loads(next(p for p in m.resolve(rec) if p.name == "fidelity.json").read_text())["fidelity"]
    rows = fidelity([str(demo_experiment), "--record", rec.id, "--detail-gate", "0", "0.3", "--noise-scale", "1", "0"])
    assert [(r["detail_gate"], r["noise_scale"], r["horizon"]) for r in rows] == [
        (g, n, h) for g in (0.0, 0.3) for n in (1.0, 0.0) for h in (8, 16)]
    mean = {(r["detail_gate"], r["horizon"]): r["model_psnr"] for r in rows if r["noise_scale"] == 0}
    assert all(mean[(r["detail_gate"], r["horizon"])] != r["model_psnr"] for r in rows if r["noise_scale"] == 1)
    for r in (r for r in rows if r["noise_scale"] == 0):  # the default: same seed and episode, the recorded numbers
        v = recorded[str(r["horizon"])]
        want = (v["plain_psnr"], v["plain_ssim"]) if r["detail_gate"] == 0 else (v["model_psnr"], v["model_ssim"])
        assert (r["model_psnr"], r["model_ssim"]) == pytest.approx(want, abs=1e-6)


def test_open_loop_fine_tuning_keeps_the_latent_space_and_held_out_episodes_and_measures_the_start(demo_experiment,
                                                                                                    contract):
    import torch

    from worldenv_core.stage import ConfigError

    exp = demo_experiment
    train_worldsim(cfg(exp, "expert_only=true"))  # (resumes the finished run of the tests above)
    base = Manifest(exp).latest("train_worldsim", task="tiny", data="expert")
    with pytest.raises(ConfigError, match="rollout.steps"):
        train_worldsim(cfg(exp, "expert_only=true", f"init_from={base.id}"))
    metrics = train_worldsim(cfg(exp, "expert_only=true", f"init_from={base.id}", "rollout.steps=6",
                                 "rollout.chunks=2", "log_every=1"))
    m = Manifest(exp)
    tuned = m.latest("train_worldsim", task="tiny", data="expert")
    assert tuned.id != base.id and base.id in tuned.inputs and metrics["steps"] == 6
    folder = lambda rec: next(p for p in m.resolve(rec) if p.name == "model.safetensors").parent  # noqa: E731
    (start, start_meta), (model, meta) = (load_checkpoint(folder(r), "worldsim", contract()) for r in (base, tuned))
    assert meta["held_out"] == start_meta["held_out"] and meta["rollout_steps"] == 6
    assert meta["kinematics"] == start_meta["kinematics"]
    for name, value in start.state_dict().items():  # the latent space stays; the flow model trains
        same = torch.equal(value, model.state_dict()[name])
        assert same if not name.startswith("velocity.") or "num_batches" in name else True, name
    assert any(not torch.equal(v, model.state_dict()[n]) for n, v in start.state_dict().items() if n.startswith("velocity."))
    recorded = json.loads(next(p for p in m.resolve(base) if p.name == "fidelity.json").read_text())["fidelity"]
    report = json.loads(next(p for p in m.resolve(tuned) if p.name == "fidelity.json").read_text())["fidelity"]
    for h, v in report.items():  # the starting model, measured again on the same starts, scores what it recorded
        assert (v["start_psnr"], v["start_ssim"]) == pytest.approx((recorded[h]["model_psnr"], recorded[h]["model_ssim"]),
                                                                   abs=1e-6)


def expert_only_model(exp):
    """The expert-only world model's checkpoint folder (its run resumes, finished, from the tests above)."""
    train_worldsim(cfg(exp, "expert_only=true"))
    m = Manifest(exp)
    return next(p for p in m.resolve(m.latest("train_worldsim", task="tiny", data="expert"))
                if p.name == "model.safetensors").parent


def test_latent_pack_trains_open_loop_off_the_episodes_and_refuses_another_autoencoder(demo_experiment, contract,
                                                                                          tmp_path):
    """The GPU route of phase 3, as settings of the stage: `latents_to=` packs the model's training
    episodes as its latents here; `latents_from=` trains on them in an experiment with no episode (a
    GPU host) into a checkpoint like `init_from`'s: resumable, snapshots, the pack recorded by content."""
    import shutil

    import torch
    from safetensors.torch import load_file, save_file

    from worldenv_core.models.checkpoint import CheckpointError
    from worldenv_core.models.latent_pack import read_latent_pack

    exp = demo_experiment
    base = expert_only_model(exp)
    start, start_meta = load_checkpoint(base, "worldsim", contract())
    records = len(Manifest(exp).records())
    packed = train_worldsim(cfg(exp, "expert_only=true", f"init_from={base}", f"latents_to={tmp_path / 'pack.st'}"))
    pack = read_latent_pack(tmp_path / "pack.st", base)
    assert packed["episodes"] == len(pack.keys) == 1 and pack.keys[0] not in start_meta["held_out"]  # 2 demos, 1 held out
    assert len(Manifest(exp).records()) == records  # an export: no record a later stage could take for a model
    real = read_episode(next((exp / "data").rglob(pack.keys[0].split("/")[-1])), cameras=["agentview"])
    assert np.array_equal(pack.episodes[0].actions, real.actions) and len(pack.latents[0]) == real.num_frames
    with torch.no_grad():
        want = start.autoencoder.encode(torch.from_numpy(real.images["agentview"]).permute(0, 3, 1, 2))
    assert torch.allclose(pack.latents[0], want, atol=2e-3 * float(want.abs().max()))  # stored as fp16

    gpu = tmp_path / "gpu"  # an experiment with no collection: the pack is all the data there is
    there = ["expert_only=true", f"init_from={base}", f"latents_from={tmp_path / 'pack.st'}", "rollout.steps=4",
             "snapshots=2", "rollout.chunks=2", "rollout.batch_size=4", "log_every=1", "checkpoint_every=2"]
    metrics = train_worldsim(cfg(gpu, *there))
    rec = Manifest(gpu).latest("train_worldsim", task="tiny")
    final = next(p for p in Manifest(gpu).resolve(rec) if p.name == "model.safetensors").parent
    assert metrics["steps"] == 4 and "fidelity" not in metrics  # no held-out episode on that host
    assert any(f.kind == "latent_pack" for f in rec.input_files)
    model, meta = load_checkpoint(final, "worldsim", contract())
    assert meta["held_out"] == start_meta["held_out"] and meta["kinematics"] == start_meta["kinematics"]
    assert meta["rollout_steps"] == 4 and meta["episodes"] == 1 and meta["trained_from"]["every"] == 1
    tuned = model.state_dict()
    assert all(torch.equal(v, tuned[n]) for n, v in start.state_dict().items() if not n.startswith("velocity."))
    assert any(not torch.equal(v, tuned[n]) for n, v in start.state_dict().items() if n.startswith("velocity."))
    assert load_checkpoint(final.parent / "snapshot_2", "worldsim", contract())[1]["rollout_steps"] == 2
    assert list((final.parent / "tensorboard").glob("events.*"))
    again = train_worldsim(cfg(gpu, *there))  # the same command again: finished before, nothing trained
    assert again["train_wall_s"] == metrics["train_wall_s"]
    # a model trained on from the packed one keeps its autoencoder, so the pack still serves it ...
    assert read_latent_pack(tmp_path / "pack.st", final).keys == pack.keys
    # ... but one with another autoencoder would read the pack's latents as its own: refused
    other = tmp_path / "other"
    shutil.copytree(base, other)
    state = load_file(str(other / "model.safetensors"))
    name = next(k for k in state if k.startswith("autoencoder.") and state[k].is_floating_point())
    state[name] = state[name] + 1e-3
    save_file(state, str(other / "model.safetensors"))
    with pytest.raises(CheckpointError, match="another autoencoder"):
        train_worldsim(cfg(tmp_path / "gpu2", *[o for o in there if not o.startswith("init_from")], f"init_from={other}"))


def test_from_a_latent_pack_a_fresh_flow_network_of_another_width_and_a_deadline(demo_experiment, contract, tmp_path):
    """The world model's model-size curve: `fresh_width=` swaps in a new flow network and keeps the
    latent space; `minutes=` plans the steps from timed ones and stops, saved, at the deadline, with
    no record claiming a finished run (the same command goes on)."""
    import torch

    from worldenv_core.models.checkpoint import read_config
    from worldenv_core.stage import ConfigError

    exp = demo_experiment
    base = expert_only_model(exp)
    start, _ = load_checkpoint(base, "worldsim", contract())
    train_worldsim(cfg(exp, "expert_only=true", f"init_from={base}", f"latents_to={tmp_path / 'p.st'}"))
    width = start.velocity.width // 2
    there = ["expert_only=true", f"init_from={base}", f"latents_from={tmp_path / 'p.st'}", "rollout.chunks=0",
             "rollout.batch_size=4"]
    train_worldsim(cfg(tmp_path / "gpu", *there, "rollout.steps=2", f"fresh_width={width}"))
    m = Manifest(tmp_path / "gpu")
    final = next(p for p in m.resolve(m.latest("train_worldsim", task="tiny")) if p.name == "model.safetensors").parent
    model, meta = load_checkpoint(final, "worldsim", contract())
    assert read_config(final)["model"]["width"] == model.velocity.width == width
    assert meta["rollout_steps"] == 2 and meta["trained_from"]["fresh_width"] == width and meta["init_from_step"] is None
    fresh = model.state_dict()
    assert all(torch.equal(v, fresh[n]) for n, v in start.state_dict().items() if not n.startswith("velocity."))
    assert sum(p.numel() for p in model.velocity.parameters()) < sum(p.numel() for p in start.velocity.parameters())
    # a fresh flow network conditioned on maps that draw the arm, from the pack's joints and arms
    train_worldsim(cfg(tmp_path / "gpu_arm", *there, "rollout.steps=2", f"fresh_width={width}", "worldsim.arm_map=true"))
    m = Manifest(tmp_path / "gpu_arm")
    final = next(p for p in m.resolve(m.latest("train_worldsim", task="tiny")) if p.name == "model.safetensors").parent
    model, meta = load_checkpoint(final, "worldsim", contract())
    assert model.arm_map and read_config(final)["model"]["arm_map"] and set(meta["arms"]) == set(meta["cameras"])
    assert not start.arm_map

    timed = train_worldsim(cfg(tmp_path / "gpu3", *there, "minutes=0.001"))  # the plan and the deadline: ~60 ms
    plan = json.loads(next((tmp_path / "gpu3" / "train_worldsim").glob("*/plan.json")).read_text())
    assert plan["minutes"] == 0.001 and 1 <= timed["steps"] <= plan["steps"]
    if timed["steps"] < plan["steps"]:  # stopped at the deadline: saved, not recorded as finished
        assert not Manifest(tmp_path / "gpu3").find("train_worldsim")
    for override, match in (("latents_every=0", "latents_every"), ("fresh_width=4", "fresh_width")):
        with pytest.raises(ConfigError, match=match):
            train_worldsim(cfg(tmp_path / "gpu4", *there, "rollout.steps=1", override))
    with pytest.raises(ConfigError, match="init_from"):
        train_worldsim(cfg(tmp_path / "gpu4", f"latents_from={tmp_path / 'p.st'}"))


def test_refit_kinematics_keeps_the_weights_and_scores_the_fit_on_held_out_episodes(demo_experiment, contract,
                                                                                   tmp_path):
    from analysis import refit_kinematics
    from worldenv_core.kinematics.next_state import NextStateModel

    exp = demo_experiment
    base = expert_only_model(exp)
    episodes = str(exp / "data" / "*" / "*" / "*" / "*.mcap")
    out = refit_kinematics.main([str(base), episodes, "--out", str(tmp_path / "refit")])
    assert (tmp_path / "refit" / "model.safetensors").read_bytes() == (base / "model.safetensors").read_bytes()
    _, meta = load_checkpoint(tmp_path / "refit", "worldsim", contract())
    _, base_meta = load_checkpoint(base, "worldsim", contract())
    assert meta["kinematics"] == out["kinematics"] and NextStateModel(**meta["kinematics"]).grip_lag is not None
    assert meta["held_out"] == base_meta["held_out"] and meta["kinematics_refit"]["episodes"] == 1  # the other is held out
    assert [r["horizon"] for r in out["errors"]["after"]] == list(refit_kinematics.HORIZONS)
    with pytest.raises(ValueError, match="held-out"):  # only the held-out episode: nothing to fit on
        held = [p for p in (exp / "data").glob("*/*/*/*.mcap") if "/".join(p.parts[-3:]) in base_meta["held_out"]]
        refit_kinematics.main([str(base), *map(str, held), "--out", str(tmp_path / "none")])


def test_the_arm_refiner_trains_on_imagined_frames_and_keeps_everything_else(demo_experiment, contract, tmp_path):
    """`init_from=<model> refine.steps=N`: a refiner after the decoder learns from imagined chunks; the
    autoencoder, flow model, held-out episodes and kinematics stay the starting model's, and the
    report measures the starting model on the same starts."""
    import torch

    from worldenv_core.stage import ConfigError

    exp = demo_experiment
    base = expert_only_model(exp)
    with pytest.raises(ConfigError, match="refine.steps.*init_from"):
        train_worldsim(cfg(tmp_path / "none", "expert_only=true", "refine.steps=2"))
    with pytest.raises(ConfigError, match="refine.arm_weight"):
        train_worldsim(cfg(exp, "expert_only=true", f"init_from={base}", "refine.steps=2", "refine.arm_weight=-1"))
    metrics = train_worldsim(cfg(exp, "expert_only=true", f"init_from={base}", "refine.steps=4", "refine.chunks=1",
                                 "refine.batch_size=2", "refine.width=8", "log_every=1"))
    assert metrics["steps"] == 4
    m = Manifest(exp)
    refined = m.latest("train_worldsim", task="tiny", data="expert")
    folder = next(p for p in m.resolve(refined) if p.name == "model.safetensors").parent
    (start, start_meta), (model, meta) = (load_checkpoint(f, "worldsim", contract()) for f in (base, folder))
    assert model.refiner is not None and start.refiner is None and meta["refine_steps"] == 4
    assert meta["held_out"] == start_meta["held_out"] and meta["kinematics"] == start_meta["kinematics"]
    state = model.state_dict()
    assert all(torch.equal(v, state[n]) for n, v in start.state_dict().items())  # only the refiner trained
    assert any(state[n].abs().sum() > 0 for n in state if n.startswith("refiner.out"))  # it left its zero start
    report = json.loads(next(p for p in m.resolve(refined) if p.name == "fidelity.json").read_text())["fidelity"]
    assert all("start_ssim_gripper" in v and "model_ssim_gripper" in v for v in report.values())


def test_demo_share_is_checked_before_any_work(tmp_path):
    from worldenv_core.stage import ConfigError

    with pytest.raises(ConfigError, match="demo_share must be a number strictly between 0 and 1"):
        train_worldsim(cfg(tmp_path / "none", "demo_share=1.5"))
    with pytest.raises(ConfigError, match="demo_share weighs the demos.*expert_only=true"):
        train_worldsim(cfg(tmp_path / "none", "demo_share=0.5", "expert_only=true"))
