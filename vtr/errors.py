"""Exception hierarchy: one root, one subclass per area.

The CLI turns any ``VtrError`` into a one-line message and exit code 1; anything else is a bug
and keeps its traceback.
"""

from __future__ import annotations


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


class UnfinishedRouteError(MapError):
    """A repeat refused because the map's teach run did not finish (its route may be cut short); ``reason`` says
    which run and how it ended, ``vertices`` how many it holds. The caller names its own way to allow it (the
    library's ``allow_partial``, the command line's ``--allow-partial``)."""

    def __init__(self, reason: str, vertices: int, allow: str = "allow_partial=True"):
        self.reason, self.vertices, self.allow = reason, int(vertices), allow
        super().__init__(
            f"{reason}: its route may be incomplete; refusing to repeat it ({allow} to use its "
            f"{self.vertices} vertices anyway)"
        )

    def __reduce__(self) -> tuple[type, tuple[str, int, str]]:  # pickled whole (a batch's worker hands it back)
        return type(self), (self.reason, self.vertices, self.allow)

    def allowed_by(self, allow: str) -> UnfinishedRouteError:
        """The same refusal naming another way to allow it."""
        return UnfinishedRouteError(self.reason, self.vertices, allow)


class TeachFailedError(DataError):
    """A teach whose odometry failed on too many frames (``odometry.teach_max_failed_fraction``): no route."""


class EstimationError(VtrError):
    """An estimator received invalid input (NaN pose, non-SE(3) matrix, non-PSD covariance...)."""


class NotLocalizedError(EstimationError):
    """A controller asked for a state the estimator cannot give yet: no repeat frame has been localized (or
    processed) up to that time. Typed so that a control loop can wait for the first localization."""


class Terminated(BaseException):  # noqa: N818 - a signal, named like KeyboardInterrupt
    """SIGTERM turned into an exception by the ``vtr`` command: an orderly exit, like ``KeyboardInterrupt``
    (not an ``Exception``, so no ``except Exception`` swallows it); runs in progress end ``aborted``."""


def interruption(exc: BaseException) -> KeyboardInterrupt | Terminated | None:
    """The ``KeyboardInterrupt`` or ``Terminated`` that ``exc`` is, or that directly caused it, else None.

    A signal handler that raises while compiled code (a numba kernel) is returning surfaces as a
    ``SystemError`` ("returned a result with an exception set") whose ``__cause__`` chain holds the
    signal's exception; Ctrl-C and SIGTERM must still end a run in order, not as a crash.
    """
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt | Terminated):
            return e
        if not isinstance(e, SystemError):
            return None
        seen.add(id(e))
        e = e.__cause__
    return None


class OutputError(VtrError):
    """An output path cannot be written (exists as a file, parent not writable...); raised before work starts."""
