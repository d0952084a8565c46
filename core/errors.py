"""Exceptions raised for bad input: each names the file or key and the fix."""


class SwathflowError(Exception):
    """Base class for problems a user can fix (never a programming error)."""


class FormatError(SwathflowError, ValueError):
    """A file does not follow its format."""


class OutOfRangeError(SwathflowError, ValueError):
    """A request falls outside the data (times outside a trajectory, rays off a DEM...)."""
