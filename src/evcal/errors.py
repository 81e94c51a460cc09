"""One base for every error evcal raises on bad input, and the reason codes they carry.

Every specific error (:class:`~evcal.events.EventError`, :class:`~evcal.recording.
RecordingError`, :class:`~evcal.io.wire.WireError`, ...) derives from :class:`EvcalError`,
which is a ``ValueError``: ``except evcal.EvcalError`` catches all of evcal's input errors
and nothing else. An error carries a :class:`ErrorReason` code, so that a caller (the service
counting rejected inputs, a client printing a summary) branches on the code, never on the
message text. The codes are part of the wire protocol (``docs/WIRE.md``): their values never
change.
"""

from __future__ import annotations

from enum import Enum


class ErrorReason(str, Enum):
    """Why an input was refused (the ``reason`` of service errors; stable strings)."""

    NOT_MSGPACK = "not_msgpack"  # not a msgpack map (random bytes, empty, trailing data)
    MALFORMED = "malformed"  # missing, unknown or mistyped field; wrong dtype or shape
    VERSION = "version"  # an envelope version this reader does not know
    TRUNCATED = "truncated"  # an array shorter or longer than its count says
    OUT_OF_RANGE = "out_of_range"  # a header value out of range (size 0, negative exposure)
    OUT_OF_SENSOR = "out_of_sensor"  # an event outside W x H
    UNSORTED = "unsorted"  # timestamps decrease inside one chunk
    BAD_POLARITY = "bad_polarity"  # p not +1 / -1
    BAD_VALUES = "bad_values"  # NaN or infinite values where numbers are needed
    TIME_BACKWARDS = "time_backwards"  # a chunk starts before the previous one ended
    TIME_JUMP = "time_jump"  # time jumps far (a glitch, or a new time base not yet confirmed)
    DUPLICATE = "duplicate"  # an exact copy of a recently accepted message (same seq, times)
    SENSOR_CHANGED = "sensor_changed"  # a message for another sensor size than the stream's
    SENSOR_TOO_LARGE = "sensor_too_large"  # more pixels than the configured limit
    TOO_LARGE = "too_large"  # a payload above the configured size limit
    TOO_MANY_CAMERAS = "too_many_cameras"  # a new camera beyond the configured limit
    REJECTED = "rejected"  # the estimator refused it (e.g. a frame of the wrong shape)
    BAD_QUERY = "bad_query"  # a query with an unknown field, format or estimate
    NO_CALIBRATION = "no_calibration"  # a query before the first update
    INTERNAL = "internal"  # an unexpected exception (a bug), counted, never fatal

    def __str__(self) -> str:
        return self.value


class EvcalError(ValueError):
    """Base of evcal's input errors: a message saying what was wrong, and a reason code."""

    default_reason = ErrorReason.MALFORMED

    def __init__(self, message: str, reason: ErrorReason | None = None) -> None:
        super().__init__(message)
        self.reason: ErrorReason = reason if reason is not None else self.default_reason


def reraise_as(exc: EvcalError, cls: type[EvcalError], message: str | None = None
               ) -> EvcalError:
    """``exc`` converted to ``cls`` (keeping its reason), to raise ``from None``."""
    return cls(str(exc) if message is None else message, exc.reason)


class CalibrationError(EvcalError):
    """The data cannot support the requested calibration (too few frames, no events, ...)."""

    default_reason = ErrorReason.REJECTED


class ConfigError(EvcalError):
    """A parameter out of its range (an estimator's, the simulator's or the service's)."""

    default_reason = ErrorReason.OUT_OF_RANGE


class StateError(EvcalError):
    """A saved state (an OnEI state, a service snapshot) that cannot be restored."""
