"""What a stage's command line does with errors the user can fix: one line on stderr naming the
key or file and the fix, exit status 2, no traceback. A real bug still shows its traceback, and
`WORLDENV_TRACEBACK=1` shows one for every error."""

from __future__ import annotations

import os
import sys
from contextlib import contextmanager

from omegaconf.errors import MissingMandatoryValue

from worldenv_core.data.mcap_io import CorruptEpisodeError
from worldenv_core.envs.tasks import UnknownTaskError
from worldenv_core.manifest import ArtefactError
from worldenv_core.models.checkpoint import CheckpointError
from worldenv_core.stage import ConfigError

# Bad settings and bad or missing artefacts: each message names what is wrong and how to fix it.
USER_ERRORS = (ConfigError, UnknownTaskError, ArtefactError, CheckpointError, CorruptEpisodeError)
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
        raise SystemExit(EXIT_USER_ERROR) from None
