"""python -m stages.train_worldsim +task=<suite> [expert_only=true] [worldsim.sampling_steps=1]"""
import hydra
from omegaconf import DictConfig

from stages.train_worldsim.run import run
from worldenv_core.cli import launch, user_errors


@hydra.main(config_path="../../conf", config_name="train_worldsim", version_base="1.3")
def main(cfg: DictConfig) -> None:
    with user_errors():
        run(cfg)


if __name__ == "__main__":
    launch(main)
