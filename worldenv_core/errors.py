"""The errors a user fixes: in their settings, or in the artefacts a run needs. They live at the
bottom of the package so every layer can raise them; the command line turns them into one line
(`worldenv_core.cli`)."""


class ConfigError(ValueError):
    """An invalid or incomplete stage configuration."""


class ArtefactError(RuntimeError):
    """A required artefact is missing from the manifest, missing on disk, or stale."""
