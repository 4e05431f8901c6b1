"""Exception hierarchy: one root, one subclass per area.

The CLI turns any ``VtrError`` into a one-line message and exit code 1; anything else is a bug
and keeps its traceback.
"""


class VtrError(Exception):
    """Root of every error the library raises on purpose."""


class ConfigError(VtrError):
    """A configuration file or value is invalid."""


class DataError(VtrError):
    """Input data is missing, malformed or inconsistent (names the file and the problem)."""


class CalibrationError(DataError):
    """Calibration is missing, malformed, or does not match the images."""


class MapError(VtrError):
    """A map on disk is missing, corrupt, of another format version, or misused."""


class EstimationError(VtrError):
    """An estimator received invalid input (NaN pose, non-SE(3) matrix, non-PSD covariance...)."""


class OutputError(VtrError):
    """An output path cannot be written (exists as a file, parent not writable...); raised before work starts."""
