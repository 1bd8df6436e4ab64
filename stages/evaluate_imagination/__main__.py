"""python -m stages.evaluate_imagination +task=<suite> [policies=[sft]] [noise_scales=[1.0]]"""
import hydra
from omegaconf import DictConfig

from stages.evaluate_imagination.run import run
from worldenv_core.cli import launch, user_errors


@hydra.main(config_path="../../conf", config_name="evaluate_imagination", version_base="1.3")
def main(cfg: DictConfig) -> None:
    with user_errors():
        run(cfg)


if __name__ == "__main__":
    launch(main)
