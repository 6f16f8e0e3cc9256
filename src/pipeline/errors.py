"""The project's input errors.

Every error caused by what a user gives -- files, folders, config values, models --
derives from :class:`InputError`, and its message names the file (or setting) and the
problem. ``gcgs`` prints exactly these as one line; any other exception is a bug and
keeps its traceback.
"""
from __future__ import annotations


class InputError(ValueError):
    """Bad input a user can act on; the message names the file or setting and the problem."""


class MissingInputError(InputError, FileNotFoundError):
    """A named input file or folder does not exist (also a ``FileNotFoundError``)."""


class ConfigError(InputError):
    """A config value (params.yaml, conf/ or a command-line override) that cannot be used."""
