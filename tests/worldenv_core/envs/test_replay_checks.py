"""Replay checks kept between sittings (no simulator: the kept answers are all a resumed run reads)."""
import json
import os

from worldenv_core.envs.replay import RealStart, unreplayable
from worldenv_core.envs.replay_checks import MISSING, ReplayChecks


def starts(tmp_path, n=3):
    out = []
    for k in range(n):
        f = tmp_path / f"ep{k}.mcap"
        f.write_bytes(b"x" * (k + 1))
        out.append(RealStart(task_id=0, seed=k, episode=str(f), frame=40))
    return out


def test_kept_answers_come_back_until_the_file_or_the_simulator_changes(tmp_path):
    s = starts(tmp_path)
    path = tmp_path / "cache" / "replay_checks.json"
    kept = ReplayChecks(path, versions="mujoco==1")
    assert kept.get(s[0]) is MISSING
    kept.put([{"start": s[0], "error": None}, {"start": s[1], "error": "state off by 0.2"}])
    again = ReplayChecks(path, versions="mujoco==1")
    assert again.get(s[0]) is None and again.get(s[1]) == "state off by 0.2" and again.get(s[2]) is MISSING
    assert ReplayChecks(path, versions="mujoco==2").get(s[0]) is MISSING  # another simulator: checked again
    st = os.stat(s[0].episode)
    os.utime(s[0].episode, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # the episode rewritten
    assert ReplayChecks(path, versions="mujoco==1").get(s[0]) is MISSING
    # two runs sharing the file: each one's new answers are merged with what the other wrote
    a, b = ReplayChecks(path, versions="mujoco==1"), ReplayChecks(path, versions="mujoco==1")
    a.put([{"start": s[2], "error": None}])
    b.put([{"start": s[1], "error": None}])
    final = ReplayChecks(path, versions="mujoco==1")
    assert final.get(s[2]) is None and final.get(s[1]) is None
    path.write_text("{not json")
    assert ReplayChecks(path, versions="mujoco==1").get(s[1]) is MISSING  # unreadable: every start checked again
    assert ReplayChecks(None).get(s[1]) is MISSING


def test_a_resumed_run_replays_nothing_its_kept_checks_answer(tmp_path, contract):
    s = starts(tmp_path)
    path = tmp_path / "replay_checks.json"
    ReplayChecks(path).put([{"start": s[0], "error": None}, {"start": s[1], "error": "does not replay"},
                            {"start": s[2], "error": None}])
    # every start answered: no job is run (this test has no simulator), the kept error named by its key
    assert unreplayable(contract(), s, cache=path, workers=1, progress=False) == {s[1].key: "does not replay"}
    assert json.loads(path.read_text())["records"][s[1].key]["error"] == "does not replay"
