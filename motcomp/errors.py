"""motcomp's exceptions.

Every error that motcomp raises on purpose derives from :class:`MotcompError`, so a caller can
catch the product's errors apart from bugs.  Errors of the libraries underneath (zenoh, python-can,
cantools, mcap) are caught in the adapter that uses them and re-raised from one of these with
``raise ... from``.

::

    MotcompError
     +-- ConfigError(ValueError)      a parameter, model spec, limit or config file is invalid
     +-- DataError(ValueError)        input data (CSV, recording) unusable for identification
     +-- ModelFitError                an identification fit failed or is not trustworthy
     +-- TransportError               zenoh / CAN / file adapters: open, send or decode failed
     |    +-- FrameError(ValueError)  one wire frame is malformed or out of range
     +-- ServiceError                 the running service refused or failed a request
"""

from __future__ import annotations

__all__ = [
    "ConfigError",
    "DataError",
    "FrameError",
    "ModelFitError",
    "MotcompError",
    "ServiceError",
    "TransportError",
]


class MotcompError(Exception):
    """Base class of every error motcomp raises on purpose."""


class ConfigError(MotcompError, ValueError):
    """A parameter, model spec, limit or configuration file is invalid.

    The message names the place (file, key path or argument), the rule and the offending value.
    """


class DataError(MotcompError, ValueError):
    """Input data is unusable (missing column, NaN, non-monotonic time, no excitation, ...).

    The message names the problem and where it is (row, column, value).
    """


class ModelFitError(MotcompError):
    """An identification fit failed to converge or gave an untrustworthy answer."""


class TransportError(MotcompError):
    """Opening, sending on or decoding from a transport (zenoh, CAN, file) failed."""


class NoAnswerError(TransportError):
    """A queryable received a query but did not answer it in time (zenoh's own ``Timeout``
    reply): the request may still be served later."""


class FrameError(TransportError, ValueError):
    """One wire frame is malformed, of the wrong type or out of range.

    ``reason`` is a short machine-readable tag used in counters (``"decode"``, ``"type"``, ...).
    """

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


class ServiceError(MotcompError):
    """The running service refused or failed a request (reload, admin query)."""
