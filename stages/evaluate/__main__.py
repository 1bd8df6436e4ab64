"""python -m stages.evaluate +task=<suite> [policy=<artefact>] [termination=oracle|fixed]"""
import hydra
from omegaconf import DictConfig

from stages.evaluate.run import run
from worldenv_core.cli import launch, user_errors


@hydra.main(config_path="../../conf", config_name="evaluate", version_base="1.3")
def main(cfg: DictConfig) -> None:
    with user_errors():
        run(cfg)


if __name__ == "__main__":
    launch(main)
