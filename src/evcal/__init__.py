"""evcal: per-pixel contrast-threshold and bias calibration of event cameras.

The public API, at package level::

    rec = evcal.open_recording("road.aedat4")          # AEDAT4, ECD folder, evcal MCAP, npz
    cal = evcal.offei(rec)                              # or onei, offe, brandli
    cal = evcal.calibrate(rec, "onei", n_small=8000)    # any method of evcal.ESTIMATORS
    evcal.save_calibration(cal, "cal.npz")
    result = evcal.evaluate(rec, cal, frames_per_image=5)   # reconstruction vs DI

    live = evcal.OnlineCalibrator(rec.sensor)           # streaming OnEI
    live.feed_events(chunk); live.feed_frame(t_us, image); live.calibration()

    sim = evcal.simulate(...)                           # an event camera with real effects
    gap = evcal.run_gap(rec)                            # the model-gap workflow

Every input error derives from :class:`EvcalError` (a ``ValueError``) and carries an
:class:`ErrorReason`. The live service (``evcal.service``) and its clients
(``evcal.clients``) need the ``service`` extra; this package and its core modules never
import zenoh, rerun or matplotlib.
"""

from importlib.metadata import PackageNotFoundError, version
from typing import TYPE_CHECKING

from .brandli import BrandliConfig, brandli
from .calibration import (
    CALIBRATION_MAPS,
    Calibration,
    CalibrationDataError,
    Diagnostics,
    Reason,
    Special,
)
from .errors import (
    CalibrationError,
    ConfigError,
    ErrorReason,
    EvcalError,
    StateError,
)
from .estimators import ESTIMATORS, calibrate
from .events import EVENTS_DTYPE, EventError, SensorSize, empty_events, make_events, validate_events
from .fusion import with_event_timing
from .gap.workflow import GapConfig, run_gap
from .io import (
    CalibrationFileError,
    WireError,
    load_calibration,
    open_recording,
    save_calibration,
    write_recording,
)
from .offe import OffEConfig, offe
from .offline import OffEIConfig, estimate_log_offset, offei
from .onei import OnEIConfig, OnEIExecutor, OnlineCalibrator
from .posterior import posterior_maps

if TYPE_CHECKING:  # the function; at run time the package itself, callable as the function
    from .onei import onei
from .reconstruct import EvaluationError, EvaluationResult, StreamingEvaluator, evaluate
from .recording import Frames, Recording, RecordingError
from .sim import simulate
from .sim.ideal import SimConfig, simulate_ideal
from .stream import StreamError, StreamGuard, frame_cuts, frame_intervals

try:
    __version__ = version("evcal")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0+unknown"

__all__ = [
    "CALIBRATION_MAPS",
    "ESTIMATORS",
    "EVENTS_DTYPE",
    "BrandliConfig",
    "Calibration",
    "CalibrationDataError",
    "CalibrationError",
    "CalibrationFileError",
    "ConfigError",
    "Diagnostics",
    "ErrorReason",
    "EvaluationError",
    "EvaluationResult",
    "EvcalError",
    "EventError",
    "Frames",
    "GapConfig",
    "OffEConfig",
    "OffEIConfig",
    "OnEIConfig",
    "OnEIExecutor",
    "OnlineCalibrator",
    "Reason",
    "Recording",
    "RecordingError",
    "SensorSize",
    "SimConfig",
    "Special",
    "StateError",
    "StreamError",
    "StreamGuard",
    "StreamingEvaluator",
    "WireError",
    "brandli",
    "calibrate",
    "empty_events",
    "estimate_log_offset",
    "evaluate",
    "frame_cuts",
    "frame_intervals",
    "load_calibration",
    "make_events",
    "offe",
    "offei",
    "onei",
    "open_recording",
    "posterior_maps",
    "run_gap",
    "save_calibration",
    "simulate",
    "simulate_ideal",
    "validate_events",
    "with_event_timing",
    "write_recording",
]
