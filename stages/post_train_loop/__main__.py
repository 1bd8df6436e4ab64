"""python -m stages.post_train_loop +task=<suite> [eta=0.5] [rl.n_rollouts=8]"""
import hydra
from omegaconf import DictConfig

from stages.post_train_loop.run import run
from worldenv_core.cli import launch, user_errors


@hydra.main(config_path="../../conf", config_name="post_train_loop", version_base="1.3")
def main(cfg: DictConfig) -> None:
    with user_errors():
        run(cfg)


if __name__ == "__main__":
    launch(main)
