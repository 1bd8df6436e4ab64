"""The learning-curve summary: validation against real episodes consumed, throughput, the table."""
import json

import pytest

from analysis.rl_curves import main, markdown, read_history, summarise


def _history():
    h = [{"step": 0, "validation_success": 0.5, "validation_episodes": 100}]
    for it in range(1, 5):
        h.append({"step": it, "mean_reward": 0.4 + 0.05 * it, "kept_groups": 0.5, "exact_kl": 0.04, "direction_cosine": 0.1,
                  "action_shift_rms": 0.01, "ppo_steps": 3, "seconds": 600.0, "update_seconds": 60.0,
                  "rollout_total_seconds": 1000.0, "rollout_reset_seconds": 200.0, "rollout_render_seconds": 300.0,
                  "rollout_physics_seconds": 400.0, "rollout_policy_seconds": 100.0, "rollout_env_build_seconds": 0.0})
    h[2].update(validation_success=0.6, validation_episodes=100)
    for e, (sig, noise) in zip(h[1:], ((30.0, 400.0), (-10.0, 500.0), (10.0, 450.0), (10.0, 450.0))):
        e.update(gradient_signal_sq=sig, gradient_noise_sq=noise)
    return h


def test_summary_counts_real_episodes_and_splits_the_time():
    s = summarise(_history(), rollouts_per_iteration=128)
    assert s["iterations"] == 4 and s["real_rl_episodes"] == 512
    assert s["validation"] == [(0, 0.5), (256, 0.6)]  # x: real RL episodes consumed when it was measured
    t = s["throughput"]
    assert t["episodes_per_hour"] == pytest.approx(512 / 2400 * 3600) and t["iteration_seconds"] == 600
    assert t["rollout_share"]["physics"] == pytest.approx(0.4) and t["update_share_of_wall"] == pytest.approx(0.1)
    g = s["gradient_signal"]  # pooled: |s|^2 10, sigma^2 450 -> 4.26 x 45 groups
    assert (g["signal_sq"], g["noise_sq"]) == (10.0, 450.0) and g["groups_for_cos_0.9"] == pytest.approx(0.81 / 0.19 * 45)
    assert "| r | 4 | 512 | 0: 0.50, 256: 0.60 | 0.0400 | 0.100 | 192 | 768 |" in markdown({"r": s})
    s["direction_cosine"][1] = (2, float("nan"))  # an iteration with nothing to compare is skipped, not a blank mean
    assert "| 0.0400 | 0.100 | 192 |" in markdown({"r": s})


def test_an_imagined_run_counts_only_its_real_episodes_the_guards_replays():
    h = _history()
    for e in h[1:]:  # imagination: no training rollout is real; the guard replayed 32 after each step but the third
        e.update(train_episodes=0.0, guard_episodes=0.0 if e["step"] == 3 else 32.0)
    s = summarise(h, rollouts_per_iteration=256)
    assert s["real_rl_episodes"] == 96 and s["validation"] == [(0, 0.5), (64, 0.6)]
    assert s["throughput"]["episodes_per_hour"] == pytest.approx(4 * 256 / 2400 * 3600)  # rollouts, imagined ones too


def test_the_cli_reads_a_work_dir_and_keeps_the_curve(tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    (work / "training.json").write_text(json.dumps(_history()))
    (work / "run_config.json").write_text(json.dumps({"rl": {"contexts_per_iteration": 16, "n_rollouts": 8}}))
    runs = main(["--run", f"a={work}", "--json", str(tmp_path / "kept"), "--figure", str(tmp_path / "c.png"),
                 "--markdown", str(tmp_path / "c.md")])
    assert runs["a"]["real_rl_episodes"] == 512 and (tmp_path / "c.png").stat().st_size > 0
    assert json.loads((tmp_path / "kept" / "a.json").read_text())["validation"] == [[0, 0.5], [256, 0.6]]
    # an ES run: both members of each pair from every context
    (work / "run_config.json").write_text(json.dumps({"rl": {"contexts_per_iteration": 16, "n_rollouts": 8,
                                                             "policy_update": "es", "es_pairs": 8}}))
    (work / "es_ledger").mkdir()  # its ledger: each iteration's pair differences on even against odd starts
    for it, flip in ((1, 1), (2, 0)):
        success = [[1, 0, 1, 0], [1, 0, 0, 1], [1, 0, 1, 0], [1, 0, flip, 1 - flip]]  # 4 starts x 2 pairs
        (work / "es_ledger" / f"iter_{it:04d}.json").write_text(json.dumps(
            {"iteration": it, "success": success, "steps": [[1] * 4] * 4, "es_discount": 1.0}))
    es_run = main(["--run", f"es={work}"])["es"]
    assert es_run["real_rl_episodes"] == 4 * 256
    assert es_run["direction_cosine"] == [(1, pytest.approx(1 / 2 ** 0.5)), (2, 0.0)]  # d_even (1, 1); d_odd (1, 0), (1, -1)
    assert es_run["es_half_cosine_pooled"] == pytest.approx(1 / 12 ** 0.5)
    # the same run from its ledger kept in the repository (export_ledger: iter files + the history), no work dir
    kept = tmp_path / "kept_ledger"
    kept.mkdir()
    for f in (work / "es_ledger").iterdir():
        (kept / f.name).write_text(f.read_text())
    (kept / "history.json").write_text(json.dumps(_history()[:3]))
    from_ledger = main(["--run", f"es={kept}"])["es"]
    assert from_ledger["real_rl_episodes"] == 2 * 16 and from_ledger["validation"] == [(0, 0.5), (32, 0.6)]
    assert from_ledger["direction_cosine"] == es_run["direction_cosine"]
    # ES runs alone: per-task validation in place of the PPO panels (each task at the first and the last point)
    es_only = [{k: v for k, v in h.items() if k not in ("exact_kl", "action_shift_rms")} for h in _history()[:3]]
    es_only[0].update(validation_task0=0.4, validation_task1=0.9)
    es_only[2].update(validation_task0=0.7, validation_task1=0.8)
    (kept / "history.json").write_text(json.dumps(es_only))
    per_task = main(["--run", f"es={kept}", "--figure", str(tmp_path / "es.png")])["es"]["validation_tasks"]
    assert per_task == {0: [(0, 0.4), (32, 0.7)], 1: [(0, 0.9), (32, 0.8)]} and (tmp_path / "es.png").stat().st_size > 0
    with pytest.raises(FileNotFoundError, match="neither training.json nor a checkpoint"):
        read_history(tmp_path)
    with pytest.raises(SystemExit):
        main(["--run", str(work)])  # no NAME=
