"""A stage's command line: an error the user can fix is one line on stderr and exit status 2,
no traceback; a real bug keeps its traceback."""

import subprocess
import sys
from pathlib import Path

import pytest

from worldenv_core.cli import EXIT_USER_ERROR, user_errors
from worldenv_core.stage import ConfigError

REPO = Path(__file__).resolve().parents[2]


def stage(*args: str, tmp_path: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *args, f"experiment_dir={tmp_path}/exp"], cwd=REPO,
                          capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("args, needle", [
    (("stages.evaluate",), "no task selected: add +task=<name>"),
    (("stages.collect", "+task=suite"), "task.suite has no value"),
    (("stages.collect", "+task=suite", "task.suite=libero_nope"), "libero_goal_swap"),  # lists the registered ones
    (("stages.train_policy", "+task=tiny", "scale=tiny", "train.steps=0"), "train.steps must be an integer > 0"),
    (("stages.evaluate", "+task=tiny", "scale=tiny", "eval_suite=libero_mine", "task.task_ids=[5]"), "task id 5"),
])
def test_a_bad_setting_is_one_line_and_exit_status_2(tmp_path, args, needle):
    out = stage(*args, tmp_path=tmp_path)
    lines = out.stderr.strip().splitlines()
    assert out.returncode == EXIT_USER_ERROR, out.stderr
    assert len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0], out.stderr
    assert "Traceback" not in out.stderr


def test_a_real_bug_keeps_its_traceback_and_user_errors_can_show_theirs(monkeypatch):
    with pytest.raises(ZeroDivisionError):
        with user_errors():
            1 / 0
    monkeypatch.setenv("WORLDENV_TRACEBACK", "1")
    with pytest.raises(ConfigError):
        with user_errors():
            raise ConfigError("shown with its traceback")
