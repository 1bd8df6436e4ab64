"""What a stage's command line does with errors the user can fix: one line on stderr naming the
key or file and the fix, exit status 2, no traceback. A real bug still shows its traceback, and
`WORLDENV_TRACEBACK=1` shows one for every error."""

from __future__ import annotations

import os
import shutil
import signal
import sys
from contextlib import contextmanager
from pathlib import Path

from hydra.types import RunMode
from omegaconf.errors import MissingMandatoryValue

from worldenv_core.data.mcap_io import CorruptEpisodeError
from worldenv_core.envs.tasks import UnknownTaskError
from worldenv_core.manifest import ArtefactError
from worldenv_core.models.checkpoint import CheckpointError
from worldenv_core.contract import ContractError
from worldenv_core.errors import ConfigError, Interrupted, request_stop

# Bad settings and bad or missing artefacts: each message names what is wrong and how to fix it.
USER_ERRORS = (ConfigError, UnknownTaskError, ArtefactError, CheckpointError, ContractError, CorruptEpisodeError)
EXIT_USER_ERROR = 2


def one_line(error: BaseException) -> str:
    if isinstance(error, MissingMandatoryValue):
        key = error.full_key or "a key"
        return f"{key} has no value: add {key}=<value> to the command"
    return " ".join(str(error).split())


@contextmanager
def user_errors():
    """Around a stage's `run(cfg)`: a user error becomes `error: <message>` and exit status 2."""
    try:
        yield
    except (*USER_ERRORS, MissingMandatoryValue) as e:
        if os.environ.get("WORLDENV_TRACEBACK"):
            raise
        print(f"error: {one_line(e)}", file=sys.stderr, flush=True)
        _remove_empty_run_dir()
        raise SystemExit(EXIT_USER_ERROR) from None
    except KeyboardInterrupt as e:  # Ctrl-C, or SIGTERM (`terminate_as_interrupt`): the user's own action
        if os.environ.get("WORLDENV_TRACEBACK"):
            raise
        where = getattr(e, "where", "")
        print(f"interrupted{' ' + where if where else ''}: the same command resumes", file=sys.stderr, flush=True)
        _remove_empty_run_dir()
        raise SystemExit(128 + getattr(e, "signum", signal.SIGINT)) from None


def terminate_as_interrupt() -> None:
    """SIGTERM (a scheduler's or `kill`'s stop) ends the run as Ctrl-C does: the same line, the
    same clean-up, exit status 143."""
    def stop(signum, frame):
        request_stop(signum)  # kept: the interrupt below can be swallowed by a library's bare except
        raise Interrupted(signum)

    request_stop(None)
    signal.signal(signal.SIGTERM, stop)
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # Ctrl-C the same way; an ignored SIGINT stays so
        signal.signal(signal.SIGINT, stop)


def stage_of_main() -> str | None:
    """The stage `python -m stages.<stage>` runs (None when run some other way)."""
    spec = getattr(sys.modules.get("__main__"), "__spec__", None)
    parts = (spec.name if spec else "").split(".")
    return parts[1] if len(parts) == 3 and parts[0] == "stages" and parts[2] == "__main__" else None


def check_outputs_writable(stage: str | None, overrides: list[str]) -> None:
    """Before Hydra makes its run folder inside `experiment_dir`: the folders the stage writes can
    be written (else one line, exit 2, nothing created). Sweeps and overrides Hydra itself will
    refuse are left to Hydra."""
    if stage is None or any(a in MULTIRUN_FLAGS for a in overrides):
        return
    from worldenv_core.stage import check_writable, compose_config

    try:
        cfg = compose_config(stage, [a for a in overrides if not a.startswith("-")])
        targets = {"experiment_dir": cfg.experiment_dir, **({"data_dir": cfg.data_dir} if stage == "collect" else {})}
    except Exception:  # noqa: BLE001 - a bad override: Hydra's own message names it
        return
    for key, path in targets.items():
        check_writable(key, path)


def _remove_empty_run_dir() -> None:
    """A run refused before it did anything leaves no Hydra run folder behind (one holding only
    Hydra's own `.hydra/` and log), nor the parents that were made only for it."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized() or HydraConfig.get().mode == RunMode.MULTIRUN:
        return
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    if not run_dir.is_dir() or any(p.name != ".hydra" and p.suffix != ".log" for p in run_dir.iterdir()):
        return
    shutil.rmtree(run_dir, ignore_errors=True)
    for parent in list(run_dir.parents)[:3]:  # hydra/<stage>/, hydra/, the experiment dir: each only if empty
        try:
            parent.rmdir()
        except OSError:
            break


MULTIRUN_FLAGS = ("-m", "--multirun")


def multirun_flag_first(argv: list[str]) -> list[str]:
    """Hydra's argument parser takes `-m` only before the overrides (`... +task=x -m a=1,2` fails
    with "unrecognized arguments"); move it to the front so it works anywhere on the line."""
    flags = [a for a in argv[1:] if a in MULTIRUN_FLAGS]
    return [argv[0], *flags[:1], *(a for a in argv[1:] if a not in MULTIRUN_FLAGS)]


def launch(main) -> None:
    """A stage's `if __name__ == "__main__":` body: the Hydra main with `-m` accepted anywhere,
    SIGTERM handled as Ctrl-C, and the output folders checked writable before Hydra writes there."""
    sys.argv = multirun_flag_first(sys.argv)
    terminate_as_interrupt()
    with user_errors():
        check_outputs_writable(stage_of_main(), sys.argv[1:])
    main()
