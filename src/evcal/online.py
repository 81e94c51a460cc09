"""OnEI's public names, where callers have always imported them from (the code is the
package :mod:`evcal.onei`; its ``__all__`` lists the same names)."""

from __future__ import annotations

from .onei import MAX_SOLVE_THREADS as MAX_SOLVE_THREADS
from .onei import PENDING_SLOTS as PENDING_SLOTS
from .onei import PIXELS_PER_THREAD as PIXELS_PER_THREAD
from .onei import RANGES_PER_THREAD as RANGES_PER_THREAD
from .onei import STATE_FORMAT as STATE_FORMAT
from .onei import LowPassEstimate as LowPassEstimate
from .onei import OnEIConfig as OnEIConfig
from .onei import OnEIExecutor as OnEIExecutor
from .onei import OnlineCalibrator as OnlineCalibrator
from .onei import onei as onei
from .onei import usable_cores as usable_cores
