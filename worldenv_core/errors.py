"""The error a user fixes in their settings. It lives at the bottom of the package so every layer
can raise it; the command line turns it into one line (`worldenv_core.cli`)."""


class ConfigError(ValueError):
    """An invalid or incomplete stage configuration."""
