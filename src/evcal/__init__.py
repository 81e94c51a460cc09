"""evcal: per-pixel contrast-threshold and bias calibration of event cameras."""

from .calibration import Calibration, Reason, Special
from .events import EVENTS_DTYPE, EventError, SensorSize, empty_events, make_events, validate_events
from .recording import Frames, Recording, RecordingError

__all__ = [
    "EVENTS_DTYPE",
    "Calibration",
    "EventError",
    "Frames",
    "Reason",
    "Recording",
    "RecordingError",
    "SensorSize",
    "Special",
    "empty_events",
    "make_events",
    "validate_events",
]
__version__ = "0.1.0"
