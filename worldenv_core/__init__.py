"""worldenv's shared core: environments, data, models, RL and the stage plumbing."""

import logging as _logging


class _RobosuiteMacroNotice(_logging.Filter):
    """robosuite warns at every import (so in every worker) that it has no private macro file and
    how to create one. worldenv needs none: its settings go through the env constructors. Drop
    the three lines; any other robosuite message passes."""

    def filter(self, record: _logging.LogRecord) -> bool:
        msg = record.getMessage()
        return "macro file" not in msg and "setup_macros.py" not in msg


# Installed before robosuite is imported anywhere: robosuite's logger keeps filters set on it.
_logging.getLogger("robosuite_logs").addFilter(_RobosuiteMacroNotice())
