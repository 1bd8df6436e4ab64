"""LOOP's rollouts in the real simulator (the `env=real` reference): the reward is the oracle's
verdict on exactly the actions the batch holds, the batch has the shapes PPO expects, and the
same seed draws the same rollouts."""
import numpy as np
import pytest
import torch

from tests.worldenv_core.imagination.test_recording import tiny_policy
from worldenv_core.data.mcap_io import read_episode
from worldenv_core.envs.recording import cached_env
from worldenv_core.envs.replay import RealStart, execute
from worldenv_core.models.checkpoint import save_model
from worldenv_core.rl.loop import ppo_update
from worldenv_core.rl.real_rollouts import collect_real_rollouts

pytestmark = pytest.mark.sim
POLICY_CONFIG = {"_target_": "worldenv_core.models.policy.LaplacePolicy", "cameras": ["agentview"], "chunk": 4,
                 "hidden": 32, "instruction_dim": 16,
                 "backbone": {"_target_": "worldenv_core.models.backbones.SmallConvBackbone", "cameras": ["agentview"],
                              "cond_dim": 16, "widths": [8, 8], "keypoints": 4}}


def encoder(texts):
    return torch.stack([torch.full((16,), float(len(t))) for t in texts])


@pytest.fixture(scope="module")
def demo(demo_experiment):
    path = sorted((demo_experiment / "data").rglob("*.mcap"))[0]
    return path, read_episode(path)


def test_real_rollouts_are_rewarded_by_the_oracle_on_the_actions_they_hold(demo, contract, tmp_path):
    path, ep = demo
    c = contract(chunk=4, image_size=32)
    policy = tiny_policy()
    saved = save_model(tmp_path / "behaviour", policy, POLICY_CONFIG, {"kind": "policy"})
    first = int(np.flatnonzero(ep.success)[0])
    # two contexts: the episode's start (the policy is untrained: no success in 12 steps) and two
    # steps before its recorded success (the object already on its way: the oracle fires soon)
    starts = [RealStart(task_id=ep.meta.task_id, episode=str(path), frame=0),
              RealStart(task_id=ep.meta.task_id, episode=str(path), frame=first - 2)]
    batch = collect_real_rollouts(policy, saved, c, starts, [ep.meta.instruction] * 2, 2, encoder, horizon=10,
                                  generator=torch.Generator().manual_seed(0), workers=1)
    assert batch.frames.shape[:2] == batch.actions.shape[:2] == batch.mask.shape[:2] == (4, 3)  # 10 steps: 3 chunks of 4
    assert batch.actions.shape[2:] == (4, 7) and batch.frames.dtype == torch.uint8
    assert batch.rewards.tolist()[:2] == [0.0, 0.0] and batch.by_reflector.tolist()[:2] == [False, False]
    assert batch.t_end.tolist()[:2] == [12, 12]  # the horizon rounded up to whole chunks, as in imagination
    assert batch.rewards.tolist()[2:] == [1.0, 1.0]
    assert torch.equal(batch.advantages, torch.zeros(4))  # every group agrees: RLOO gives no signal
    assert torch.equal(batch.t_end, batch.mask.sum((1, 2)).long())
    env = cached_env(c.suite, ep.meta.task_id, c.cameras, c.image_size)
    for i in range(4):
        # the actions the batch holds, executed again, give the reward and the observations it holds
        steps = int(batch.t_end[i])
        actions = policy.unnormalize_actions(batch.actions[i]).flatten(0, 1)[:steps].detach().numpy()
        out = execute(env, starts[i // 2], actions, every=4, camera="agentview")
        assert out["success"] == bool(batch.rewards[i])
        assert out["success"] is False or out["first_success"] == steps  # it stopped at the first success
        for k in range(int((batch.mask[i, :, 0] > 0).sum())):
            diff = np.abs(out["frames"][4 * k].astype(int) - batch.frames[i, k].permute(1, 2, 0).numpy())
            assert diff.max() <= 1
    assert torch.isfinite(batch.logp_old).all() and (batch.logp_old[batch.mask == 0] == 0).all()
    again = collect_real_rollouts(policy, saved, c, starts, [ep.meta.instruction] * 2, 2, encoder, horizon=10,
                                  generator=torch.Generator().manual_seed(0), workers=1)
    assert torch.equal(again.actions, batch.actions) and torch.equal(again.frames, batch.frames)
    # the behaviour log-probabilities are the policy's own: PPO's first ratio is exactly 1
    stats = ppo_update(policy, torch.optim.SGD(policy.parameters(), lr=0.0), batch, 1, 0.1, 4)
    assert stats["ratio_mean"] == pytest.approx(1.0, abs=1e-5) and stats["approx_kl"] == pytest.approx(0.0, abs=1e-6)


def test_an_interrupted_collection_resumes_with_the_rollouts_it_had_finished(demo, contract, tmp_path, monkeypatch):
    from worldenv_core.rl import real_rollouts

    path, ep = demo
    c = contract(chunk=4, image_size=32)
    policy = tiny_policy()
    saved = save_model(tmp_path / "behaviour", policy, POLICY_CONFIG, {"kind": "policy"})
    starts = [RealStart(task_id=ep.meta.task_id, episode=str(path), frame=f) for f in (0, 3)]
    journal = tmp_path / "journal"
    (journal / "0123456789abcdef").mkdir(parents=True)  # an older iteration's journal: finished, removed
    real, ran = real_rollouts.real_rollout, []

    def counted(job, stop_after=None):
        if stop_after is not None and len(ran) == stop_after:
            raise KeyboardInterrupt  # the session ends in the middle of the iteration
        ran.append(job.index)
        return real(job)

    def collect(seed=0):
        return collect_real_rollouts(policy, saved, c, starts, [ep.meta.instruction] * 2, 2, encoder, horizon=8,
                                     generator=torch.Generator().manual_seed(seed), workers=1, journal=journal)

    monkeypatch.setattr(real_rollouts, "real_rollout", lambda job: counted(job, stop_after=3))
    with pytest.raises(KeyboardInterrupt):
        collect()
    assert ran == [0, 1, 2] and not (journal / "0123456789abcdef").exists()
    (book,) = journal.iterdir()
    (book / "00001.rollout").write_bytes(b"torn")  # a file cut short is run again, not trusted
    monkeypatch.setattr(real_rollouts, "real_rollout", counted)
    ran.clear()
    resumed = collect()
    assert ran == [1, 3]  # only what was missing or torn
    fresh = collect_real_rollouts(policy, saved, c, starts, [ep.meta.instruction] * 2, 2, encoder, horizon=8,
                                  generator=torch.Generator().manual_seed(0), workers=1)
    for name in ("frames", "actions", "mask", "rewards", "logp_old"):
        assert torch.equal(getattr(resumed, name), getattr(fresh, name)), name
    ran.clear()
    collect(seed=1)  # other seeds: other rollouts, none taken from the journal
    assert sorted(ran) == [0, 1, 2, 3]


def test_a_kept_journal_moves_finished_iterations_beside_their_behaviour_policy(tmp_path):
    """RolloutJournal(keep=...): the iterations before this one are moved into `keep` instead of
    removed, and this iteration's behaviour policy is copied there once (`<digest>_behaviour`)."""
    from worldenv_core.manifest import sha256_file
    from worldenv_core.rl.real_rollouts import RolloutJournal, retire

    saved = save_model(tmp_path / "behaviour", tiny_policy(), POLICY_CONFIG, {"kind": "policy"})
    digest = sha256_file(saved / "model.safetensors")[:16]
    journal, kept = tmp_path / "journal", tmp_path / "kept"
    (journal / "0123456789abcdef").mkdir(parents=True)
    (journal / "0123456789abcdef" / "00000.rollout").write_bytes(b"an older iteration's rollout")
    book = RolloutJournal(journal, saved, keep=kept)
    assert [p.name for p in journal.iterdir()] == [digest] and book.folder == journal / digest
    assert (kept / "0123456789abcdef" / "00000.rollout").read_bytes() == b"an older iteration's rollout"
    assert (kept / f"{digest}_behaviour" / "model.safetensors").exists() and not list(kept.glob("*.tmp"))
    retire(book.folder, kept)  # the run's end: this iteration's rollouts join the others
    assert sorted(p.name for p in kept.iterdir()) == sorted(["0123456789abcdef", digest, f"{digest}_behaviour"])
    (journal / digest).mkdir()
    retire(journal / digest, kept)  # a resumed run's copy of an iteration already kept: removed, the kept one stays
    assert not (journal / digest).exists() and (kept / digest).exists()
    RolloutJournal(journal, saved)  # without keep, as before: the older iterations are removed
    assert (journal / digest).exists()


def test_a_journal_tells_a_chunk_held_draw_from_a_per_step_one_and_keeps_the_older_keys():
    """A rollout is taken back only for the same exploration; per-step jobs keep the key journals
    written before rl.exploration existed had, so a running campaign resumes with its rollouts."""
    import dataclasses

    from worldenv_core.rl.real_rollouts import RealRolloutJob, RolloutJournal

    start = RealStart(task_id=2, seed=11)
    job = RealRolloutJob(None, start, "behaviour", 7, np.zeros(4, dtype=np.float32), 16, 1.6, index=3)
    assert RolloutJournal._job_key(job) == (3, 7, start.key, 16, 1.6)
    held = RolloutJournal._job_key(dataclasses.replace(job, exploration="chunk"))
    assert held != RolloutJournal._job_key(job) and held[-1] == "chunk"


def test_an_es_journals_outcomes_travel_as_json_and_are_taken_back_by_the_same_jobs_only(tmp_path):
    """`journal_outcomes` -> JSON -> `restore_outcomes` on another machine's empty journal: the same job under the
    same behaviour weights gets its outcome back; a rollout that kept frames (PPO's) is not exported, and a job
    of another member or start is run afresh."""
    import dataclasses
    import json

    from worldenv_core.rl.real_rollouts import RealRolloutJob, RolloutJournal, journal_outcomes, restore_outcomes

    saved = save_model(tmp_path / "behaviour", tiny_policy(), POLICY_CONFIG, {"kind": "policy"})
    lang = np.zeros(16, dtype=np.float32)
    member = RealRolloutJob(None, RealStart(task_id=3, seed=2**40 + 7), str(saved), 0, lang, 224, 0.0, index=5,
                            perturbation=(3969543146641149120, -0.05), keep_frames=False)
    ppo = RealRolloutJob(None, RealStart(task_id=1, seed=9), str(saved), 4, lang, 224, 1.0, index=6)
    book = RolloutJournal(tmp_path / "journal", saved)
    outcome = {"index": 5, "start": member.start, "seed": 0, "frames": [], "proprio": [], "actions": [],
               "executed": [8] * 21, "first_success": 168, "error": None, "seconds": {"physics": 1.23456}, "steps": 168}
    book.add(member, outcome)
    book.add(ppo, {**outcome, "index": 6, "frames": [np.zeros((2, 2, 3), np.uint8)], "actions": [np.zeros((4, 7))]})
    records = json.loads(json.dumps(journal_outcomes(tmp_path / "journal")))
    assert [r["index"] for r in records] == [5]  # only the outcome-only rollout
    assert restore_outcomes(tmp_path / "elsewhere", records) == 1
    back = RolloutJournal(tmp_path / "elsewhere", saved).get(member)
    assert back["first_success"] == 168 and back["steps"] == 168 and back["error"] is None
    assert back["start"] == member.start and back["seconds"] == {"physics": 1.235}
    assert RolloutJournal(tmp_path / "elsewhere", saved).get(dataclasses.replace(member, perturbation=(1, -0.05))) is None
    moved = tiny_policy()
    with torch.no_grad():
        next(moved.parameters()).add_(1.0)
    other = save_model(tmp_path / "other", moved, POLICY_CONFIG, {"kind": "policy"})
    assert RolloutJournal(tmp_path / "elsewhere", other).get(member) is None  # another behaviour: its folder retired


def test_jobs_over_several_tasks_run_one_task_after_another_and_come_back_in_index_order(tmp_path, monkeypatch):
    """ES members over starts of several tasks are indexed member-major, so in index order a worker's consecutive
    jobs cycle through the tasks (an env and a scene rebuilt for each). The journal's jobs still to run go out grouped
    by task, in index order within one, the finished one is not run again, and the results return in index order."""
    import worldenv_core.parallel as parallel
    from worldenv_core.rl.real_rollouts import RealRolloutJob, RolloutJournal, run_journaled

    saved = save_model(tmp_path / "behaviour", tiny_policy(), POLICY_CONFIG, {"kind": "policy"})
    lang = np.zeros(16, dtype=np.float32)
    starts = [RealStart(task_id=t, seed=s) for t, s in ((2, 11), (0, 12), (1, 13))]
    jobs = [RealRolloutJob(None, starts[c], str(saved), 0, lang, 16, 0.0, index=m * 3 + c, perturbation=(m, 0.05),
                           keep_frames=False) for m in range(3) for c in range(3)]

    def outcome(job):
        return {"index": job.index, "start": job.start, "seed": 0, "frames": [], "proprio": [], "actions": [],
                "executed": [16], "first_success": None, "error": None, "seconds": {"total": 0.0}, "steps": 16}

    RolloutJournal(tmp_path / "journal", saved).add(jobs[4], outcome(jobs[4]))
    sent = []

    def run_jobs(fn, todo, **kwargs):
        sent.extend(j.index for j in todo)
        return (outcome(j) for j in reversed(todo))  # completion order is any order

    monkeypatch.setattr(parallel, "run_jobs", run_jobs)
    runs = run_journaled(jobs, saved, tmp_path / "journal")
    assert sent == [1, 7, 2, 5, 8, 0, 3, 6]  # task 0, task 1 (job 4 came from the journal), task 2
    assert [r["index"] for r in runs] == list(range(9))
