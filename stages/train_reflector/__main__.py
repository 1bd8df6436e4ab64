"""python -m stages.train_reflector +task=<suite> [eta=0.5] [expert_only=true]"""
import hydra
from omegaconf import DictConfig

from stages.train_reflector.run import run
from worldenv_core.cli import launch, user_errors


@hydra.main(config_path="../../conf", config_name="train_reflector", version_base="1.3")
def main(cfg: DictConfig) -> None:
    with user_errors():
        run(cfg)


if __name__ == "__main__":
    launch(main)
