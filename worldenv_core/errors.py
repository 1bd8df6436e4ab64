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


# The signal that asked this run to stop, kept beside the interrupt it raised: LIBERO builds its scenes inside bare
# `except: continue` blocks, and an interrupt raised there is swallowed (a collection went on for minutes after a
# SIGTERM). Loops that run episodes ask `raise_if_stopped` between steps and jobs, so the stop is not lost.
_stop_signal: int | None = None


def request_stop(signum: int | None) -> None:
    """Record that the user asked the run to stop (None: forget it, as a fresh run starts)."""
    global _stop_signal
    _stop_signal = None if signum is None else int(signum)


def raise_if_stopped(where: str = "") -> None:
    """Raise `Interrupted` if a stop was asked for, even if the interrupt it raised was swallowed."""
    if _stop_signal is not None:
        raise Interrupted(_stop_signal, where)
