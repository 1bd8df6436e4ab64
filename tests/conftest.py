"""Shared fixtures: real components at small sizes."""
import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

# Each pytest-xdist worker takes its share of the cores (unless OMP_NUM_THREADS says otherwise):
# torch's default, a thread per core in every worker, puts two workers' threads on each core.
_XDIST_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
if _XDIST_WORKERS > 1 and "OMP_NUM_THREADS" not in os.environ:
    from worldenv_core.parallel import default_workers, limit_threads

    limit_threads(max(1, default_workers() // _XDIST_WORKERS))

import numpy as np  # noqa: E402
import pytest  # noqa: E402

# The CI task: libero_object task 0 ("pick the alphabet soup and place it in the basket").
TINY_SUITE, TINY_TASK = "libero_object", 0


@pytest.fixture(scope="session")
def tiny_env():
    """One real LIBERO env for the whole session (building one costs seconds)."""
    from worldenv_core.envs.libero_env import LiberoEnv

    env = LiberoEnv(TINY_SUITE, TINY_TASK, cameras=["agentview", "robot0_eye_in_hand"], image_size=64)
    yield env
    env.close()


def synthetic_episode(rng, size=16, length=24, colour=0, succeed_at=None):
    """A noisy video where a square of `colour` (the instruction: 'red' or 'blue') appears at
    `succeed_at`; a square of the other colour is a distractor that never counts."""
    from worldenv_core.data.episode import Episode, EpisodeMeta

    imgs = rng.integers(0, 60, (length + 1, size, size, 3), dtype=np.uint8)
    distractor_at = int(rng.integers(2, length))
    imgs[distractor_at:, 2:6, 2:6, 1 - colour] = 255
    success = np.zeros(length + 1, dtype=bool)
    if succeed_at is not None:
        imgs[succeed_at:, 9:14, 9:14, colour] = 255
        success[succeed_at:] = True
    meta = EpisodeMeta(suite="libero_object", task_id=colour, task_name="t", instruction=["red", "blue"][colour],
                       init_state_index=-1, seed=0, source="policy", success=success[-1], cameras=["agentview"])
    z = np.zeros((length + 1, 7))
    return Episode(meta=meta, images={"agentview": imgs}, proprio=z, joint_pos=z, sim_state=np.zeros((length + 1, 0)),
                   success=success, actions=np.zeros((length, 7)))


def _synthetic_episodes(seed, n):
    rng = np.random.default_rng(seed)
    return [synthetic_episode(rng, colour=i % 2, succeed_at=int(rng.integers(6, 24)) if i % 3 else None)
            for i in range(n)]


@pytest.fixture
def synthetic_episodes():
    """(seed, n) -> n synthetic 'red'/'blue' square episodes, two thirds of them succeeding."""
    return _synthetic_episodes


# Stage and fault tests share one real expert collection of the tiny task (collecting costs ~1 min):
# 2 demos that go on for 8 steps after the oracle's success (the reflector's positive frames). The
# pytest-xdist workers share it too: the first to get the lock collects, the others wait and read it
# (every user copies it before writing).
def shared_root(tmp_path_factory):
    """The folder every pytest-xdist worker's base temp is in (the base temp itself without workers)."""
    root = tmp_path_factory.getbasetemp()
    return root.parent if os.environ.get("PYTEST_XDIST_WORKER") else root


@pytest.fixture(scope="session")
def _tiny_demos(tmp_path_factory):
    from filelock import FileLock

    from stages.collect.run import run as collect
    from worldenv_core.stage import compose_config

    root = shared_root(tmp_path_factory)
    exp = root / "tiny-demos"
    with FileLock(str(root / "tiny-demos.lock")):
        if not (root / "tiny-demos.done").exists():
            collect(compose_config("collect", ["+task=tiny", "scale=tiny", f"experiment_dir={exp}", f"data_dir={exp / 'data'}",
                                               "episodes_per_task=2", "post_success_steps=8", "workers=1", "progress=false",
                                               "lerobot_export=false"]))
            (root / "tiny-demos.done").touch()  # complete: a worker killed mid-collection leaves none
    return exp


@pytest.fixture(scope="module")
def demo_experiment(_tiny_demos, tmp_path_factory):
    """A fresh experiment dir holding a manifest with 2 expert demos of the tiny task."""
    import shutil

    exp = tmp_path_factory.mktemp("exp") / "experiment"
    shutil.copytree(_tiny_demos, exp)
    return exp



# ---- `make faults`: the fault matrix as a table ------------------------------------------------


def pytest_addoption(parser):
    parser.addoption("--fault-matrix", action="store_true", help="print the fault suite as a table")


def pytest_terminal_summary(terminalreporter, config):
    if not config.getoption("--fault-matrix"):
        return
    rows = [r for outcome in ("passed", "failed", "skipped") for r in terminalreporter.stats.get(outcome, [])
            if r.when == "call" and "/test_faults" in "/" + r.nodeid]
    terminalreporter.write_line("")
    terminalreporter.write_line("| fault case | outcome | seconds |")
    terminalreporter.write_line("|---|---|---|")
    for r in sorted(rows, key=lambda r: r.nodeid):
        name, _, param = r.nodeid.split("::", 1)[1].partition("[")
        case = name.removeprefix("test_").replace("_", " ") + (f" [{param}" if param else "")
        terminalreporter.write_line(f"| {case} | {r.outcome} | {r.duration:.1f} |")


@pytest.fixture
def contract():
    """A task contract with the tiny task's shapes; keyword arguments change fields:
    `contract(image_size=16, chunk=4)`."""
    from worldenv_core.contract import TaskContract

    def make(**fields) -> TaskContract:
        base = dict(name="tiny", suite="libero_object", task_ids=(0,), cameras=("agentview",), image_size=64, chunk=8,
                    action_dim=7, proprio_dim=7, max_steps=280, control_freq=20.0)
        return TaskContract(**{**base, **fields})
    return make
