"""Stage tests share one real expert collection of the tiny task (collecting costs ~1 min): 2 demos
that go on for 8 steps after the oracle's success (the reflector's positive frames)."""
import shutil

import pytest
from worldenv_core.stage import compose_config


@pytest.fixture(scope="session")
def _tiny_demos(tmp_path_factory):
    from stages.collect.run import run as collect

    exp = tmp_path_factory.mktemp("demos")
    collect(compose_config("collect", ["+task=tiny", "scale=tiny", f"experiment_dir={exp}", f"data_dir={exp / 'data'}",
                                       "episodes_per_task=2", "post_success_steps=8", "workers=1", "progress=false", "lerobot_export=false"]))
    return exp


@pytest.fixture(scope="module")
def demo_experiment(_tiny_demos, tmp_path_factory):
    """A fresh experiment dir holding a manifest with 2 expert demos of the tiny task."""
    exp = tmp_path_factory.mktemp("exp") / "experiment"
    shutil.copytree(_tiny_demos, exp)
    return exp
