"""Exceptions the library raises for bad input; jobs turn them into one-line messages and a non-zero exit."""


class ToggleIdError(Exception):
    """Base class: a problem the user can fix (bad data, bad configuration, bad checkpoint)."""


class DataError(ToggleIdError, ValueError):
    """A record (CSV or arrays) that cannot be used: missing columns, NaN, unsorted time, wrong units, ..."""


class ConfigError(ToggleIdError, ValueError):
    """A configuration value that cannot be used: inverted bounds, population < 2, probability outside [0, 1], ..."""


class CheckpointError(ToggleIdError):
    """A checkpoint that is missing, truncated, tampered with or from an incompatible run."""
