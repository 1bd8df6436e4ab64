"""The errors a user fixes: in their settings, or in the artefacts a run needs. They live at the
bottom of the package so every layer can raise them; the command line turns them into one line
(`worldenv_core.cli`)."""


class ConfigError(ValueError):
    """An invalid or incomplete stage configuration."""


class ArtefactError(RuntimeError):
    """A required artefact is missing from the manifest, missing on disk, or stale."""


class Interrupted(KeyboardInterrupt):
    """The user stopped the run (SIGINT: Ctrl-C, or SIGTERM). `signum` sets the exit status (128 +
    signum, as a shell reports a signal); `where` says how far the run got, for the one line the
    command line prints instead of a traceback."""

    def __init__(self, signum: int = 2, where: str = ""):
        super().__init__(where)
        self.signum, self.where = int(signum), where
