"""User-facing errors: the CLI turns these into one line on stderr and exit code 2.

Messages say what is wrong ("exists", "is a device"); the CLI adds how to fix it where that
depends on its flags (``OutputExists`` gets "; use --force to overwrite").
"""


class FusionlogError(Exception):
    """Bad usage or bad input. The message names the file and the problem."""


class ValidationError(FusionlogError):
    """A scenario or model definition is inconsistent (shape, symmetry, definiteness, key)."""


class OutputError(FusionlogError):
    """An output cannot be written: the target is unsuitable or the write failed (disk full,
    read-only folder). The message names the path and the OS error."""


class OutputExists(OutputError):
    """An output exists (or appeared while we were writing) and overwriting was not asked for."""


class DamagedFile(FusionlogError):
    """An input file is damaged (truncated, changed bytes). ``path`` is the file;
    ``recoverable`` says `fusionlog inspect --recover` reads what is left of it (an MCAP file;
    not a recording or a ROS bag, whose damage the CLI then does not send the user there for)."""

    def __init__(self, message: str, path: object = None, *, recoverable: bool = True) -> None:
        super().__init__(message)
        self.path = path
        self.recoverable = recoverable


class NumericalError(FusionlogError):
    """The numbers of an accepted definition cannot be computed with (singular, overflow)."""
