"""Exceptions raised by symsbl."""

__all__ = ["SymsblError", "DataError", "LibraryError", "SimulationError", "MissingExtraError"]


class SymsblError(ValueError):
    """Base class of symsbl's user-facing errors (a ``ValueError``)."""


class DataError(SymsblError):
    """Input data is malformed: bad columns, non-uniform time, NaN, too few samples."""


class LibraryError(SymsblError):
    """A candidate library is malformed or does not fit the data."""


class SimulationError(SymsblError):
    """A simulation could not be set up."""


class MissingExtraError(SymsblError, ImportError):
    """An optional dependency is not installed; the message names the extra to install."""
