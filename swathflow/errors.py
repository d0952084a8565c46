"""Exceptions raised for bad input: each names the file or key and the fix."""


class SwathflowWarning(UserWarning):
    """Base class of swathflow's own warnings for a user (mission, plugins, formats): the
    command line prints them as one plain line each (defined here so that it can tell them
    apart without importing the modules that raise them)."""


class SwathflowError(Exception):
    """Base class for problems a user can fix (never a programming error)."""


class FormatError(SwathflowError, ValueError):
    """A file does not follow its format."""


class OutOfRangeError(SwathflowError, ValueError):
    """A request falls outside the data (times outside a trajectory, rays off a DEM...)."""


class ArgumentError(SwathflowError, ValueError):
    """An argument of a Python API call outside the values it accepts (named, with them)."""


class ArgumentTypeError(SwathflowError, TypeError):
    """An argument of a Python API call of a type it does not accept (named, with those it
    does)."""
