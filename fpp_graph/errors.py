"""The one exception family of the project.

Every error a user can cause (bad files, bad config, bad graphs, bad images) is an
:class:`FppError`. Messages say *what* was wrong, *where* (file, line, frame, key) and *what to
do*. The CLI prints ``str(error)`` as one line and exits with status 2; no traceback.
"""

from __future__ import annotations


class FppError(Exception):
    """Base class of every user-facing error in fpp-graph and its front-ends."""

    exit_code: int = 2


class ConfigError(FppError):
    """A configuration file or value is invalid (unknown key, wrong type, out of range)."""


class InputDataError(FppError):
    """An input file or array is missing, unreadable, malformed or inconsistent."""


class CalibrationError(InputDataError):
    """A calibration is malformed or does not match the images it is used with."""


class GraphError(FppError):
    """A pose graph is malformed or cannot be optimised (disconnected, unconstrained poses)."""


class RegistrationError(FppError):
    """A pairwise registration cannot be attempted on the given frames."""


class OutputError(FppError):
    """An output location cannot be written (exists, not writable)."""


class Interrupted(FppError):
    """The run was stopped by Ctrl-C (SIGINT) or SIGTERM; what was done is kept for ``--resume``."""

    def __init__(self, message: str, signal_number: int = 2) -> None:
        super().__init__(message)
        self.exit_code = 128 + signal_number  # the shell's convention for a death by signal
