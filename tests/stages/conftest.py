"""What the stages that imagine share: a tiny task experiment with an SFT policy, a world
simulator and a reflector trained for a few steps on its 2 expert demos (`tiny_models`)."""
import pytest

from tests.conftest import shared_root
from worldenv_core.stage import compose_config

REFLECTOR = ["expert_only=true", "train.steps=2", "train.batch_size=2", "holdout_every=2", "reflector.d_model=16",
             "reflector.layers=1", "reflector.heads=2", "reflector.frame_encoder.widths=[8,16]",
             "reflector.frame_encoder.keypoints=4", "plots=1", "imagined.enabled=false", "eta_folds=0"]


def stage_cfg(stage, exp, *overrides):
    return compose_config(stage, ["+task=tiny", "scale=tiny", f"experiment_dir={exp}", *overrides])


@pytest.fixture(scope="session")
def _tiny_models(_tiny_demos, tmp_path_factory):
    """Trained once for all pytest-xdist workers, as `_tiny_demos` is collected once."""
    import shutil

    from filelock import FileLock

    from stages.train_policy.run import run as train_policy
    from stages.train_reflector.run import run as train_reflector
    from stages.train_worldsim.run import run as train_worldsim

    root = shared_root(tmp_path_factory)
    exp = root / "tiny-models"
    with FileLock(str(root / "tiny-models.lock")):
        if (root / "tiny-models.done").exists():
            return exp
        shutil.rmtree(exp, ignore_errors=True)  # a worker killed part way: start again
        shutil.copytree(_tiny_demos, exp)
        train_policy(stage_cfg("train_policy", exp, "train.steps=10", "scale_head.steps=4", "demos_per_task=1",
                               "policy.hidden=32", "policy.backbone.widths=[8,8,8,8]", "policy.backbone.keypoints=4"))
        train_worldsim(stage_cfg("train_worldsim", exp, "expert_only=true", "ae.steps=4", "flow.steps=4", "ae.batch_size=2",
                                 "flow.batch_size=2", "holdout_every=2", "worldsim.ae_widths=[8,16]", "worldsim.width=16",
                                 "worldsim.map_channels=4", "fidelity.horizons=[8]", "fidelity.starts_per_episode=1",
                                 "fidelity.videos=0", "worldsim.sampling_steps=1"))
        train_reflector(stage_cfg("train_reflector", exp, *REFLECTOR))
        (root / "tiny-models.done").touch()
    return exp


@pytest.fixture(scope="module")
def tiny_models(_tiny_models, tmp_path_factory):
    """A fresh copy of the demo experiment with train_policy, train_worldsim and train_reflector
    records (both hold out the same one of the 2 demos), for one test module to add runs to."""
    import shutil

    exp = tmp_path_factory.mktemp("models") / "experiment"
    shutil.copytree(_tiny_models, exp)
    return exp
