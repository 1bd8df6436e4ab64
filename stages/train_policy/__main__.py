"""python -m stages.train_policy +task=<suite> [demos_per_task=5]"""
import hydra
from omegaconf import DictConfig

from stages.train_policy.run import run
from worldenv_core.cli import launch, user_errors


@hydra.main(config_path="../../conf", config_name="train_policy", version_base="1.3")
def main(cfg: DictConfig) -> None:
    with user_errors():
        run(cfg)


if __name__ == "__main__":
    launch(main)
