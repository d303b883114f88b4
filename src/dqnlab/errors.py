"""Errors that end a command with one clear line instead of a traceback."""

from __future__ import annotations


class DqnlabError(Exception):
    """A problem the user can fix: the message says what was wrong and what is accepted."""


class ConfigError(DqnlabError):
    """A setting, preset or override is not valid."""


class EnvError(DqnlabError):
    """The environment cannot be used: unknown id or game, or unsupported spaces."""


class ResourceError(DqnlabError):
    """Not enough memory or disk for what the configuration asks."""
