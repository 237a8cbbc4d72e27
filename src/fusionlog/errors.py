"""User-facing errors: the CLI turns these into one line on stderr and exit code 2."""


class FusionlogError(Exception):
    """Bad usage or bad input. The message names the file and the problem."""


class ValidationError(FusionlogError):
    """A scenario or model definition is inconsistent (shape, symmetry, definiteness, key)."""
