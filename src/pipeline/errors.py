"""The project's input errors.

Every error caused by what a user gives -- files, folders, config values, models --
derives from :class:`InputError`, and its message names the file (or setting) and the
problem. ``gcgs`` prints exactly these as one line; any other exception is a bug and
keeps its traceback.
"""
from __future__ import annotations

import sys


class InputError(ValueError):
    """Bad input a user can act on; the message names the file or setting and the problem."""


class MissingInputError(InputError, FileNotFoundError):
    """A named input file or folder does not exist (also a ``FileNotFoundError``)."""


class ConfigError(InputError):
    """A config value (params.yaml, conf/ or a command-line override) that cannot be used."""


class OutputError(InputError):
    """An output path that cannot be written, or whose writing would destroy data gcgs did
    not write (an input, the current folder, a user's folder)."""


class DegenerateResultError(InputError):
    """A run whose result is empty or degenerate (too few surfels, an empty mesh), nearly
    always from too little or bad input; nothing is written."""


class Interrupted(Exception):
    """The user stopped a run (Ctrl-C); the message says what was kept and how to go on."""


def print_warning(message: str) -> None:
    """A warning for the user (the result may not be what they meant): one line on stderr."""
    print(f"gcgs: warning: {message}", file=sys.stderr)
