"""python -m stages.collect +task=<suite> source=expert episodes_per_task=5"""
import hydra
from omegaconf import DictConfig

from stages.collect.run import run
from worldenv_core.cli import launch, user_errors


@hydra.main(config_path="../../conf", config_name="collect", version_base="1.3")
def main(cfg: DictConfig) -> None:
    with user_errors():
        run(cfg)


if __name__ == "__main__":
    launch(main)
