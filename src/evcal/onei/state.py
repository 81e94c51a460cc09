"""OnEI's state format (``evcal.onei.v2``): everything a calibrator needs to resume, as numpy
arrays (``np.savez``-able), and back.

The arrays: ``format``; ``scalars`` (JSON: the sensor, the configuration, the stream's times,
:data:`SCALARS` and the offset's ``offset_info``); the open interval as ``Accumulator``'s maps
(``acc_on``, ``acc_off``, ``acc_last_p``); ``counts``; the estimate's maps
(:attr:`LowPassEstimate.ARRAYS`); the ``pending`` events; the buffered frames (``fr_images``,
``fr_last_p``, ``fr_meta`` rows ``t_us, cum_events, n_sparse, opens, closes_at``) and their
intervals, sparse (``fr_idx``, ``fr_on``, ``fr_off``); the normal equations (``ne_*``) and,
with a history, ``hist_m`` and ``hist_counts``. States of earlier versions lack some scalars
(:data:`OPTIONAL_SCALARS`) and load.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import StateError
from ..events import EVENTS_DTYPE, SensorSize
from ..jsonable import to_jsonable
from ..solver import NormalEquations
from .buffer import Frame
from .config import OnEIConfig
from .estimate import load_into
from .executor import OnEIExecutor

if TYPE_CHECKING:
    from .calibrator import OnlineCalibrator

STATE_FORMAT = "evcal.onei.v2"


def _opt_int(v: Any) -> int | None:
    return None if v is None else int(v)


# the scalars besides sensor, config and the stream's times: JSON key -> (the part of the
# calibrator that holds it, its attribute there, its type); the order is the format's
SCALARS: dict[str, tuple[str, str, Callable[[Any], Any]]] = {
    "lam": ("", "lam", float), "n_updates": ("", "n_updates", int),
    "n_events": ("", "n_events", int), "n_frames": ("", "n_frames", int),
    "n_equations": ("buffer", "n_equations", int), "n_gaps": ("", "n_gaps", int),
    "gap": ("buffer", "gap", bool), "n_folded_late": ("", "n_folded_late", int),
    "n_refolds": ("", "n_refolds", int), "n_late_events": ("", "n_late_events", int),
    "n_sessions": ("", "n_sessions", int), "base": ("buffer", "base", int),
    "next_open": ("buffer", "next_open", int), "cum_events": ("buffer", "cum_events", int),
    "removals": ("sums", "removals", int), "since_resolve": ("buffer", "since_resolve", int),
    "frame_cap": ("buffer", "frame_cap", _opt_int),
    "log_offset": ("offset", "log_offset", float),
    "next_offset_check": ("offset", "next_check", int),
    "holds_all": ("buffer", "holds_all", bool), "hist_ref": ("sums", "hist_ref", int)}
# absent from the states of earlier versions
OPTIONAL_SCALARS = frozenset({"n_sessions", "log_offset", "next_offset_check", "holds_all",
                              "hist_ref", "n_refolds"})


def _part(cal: OnlineCalibrator, name: str) -> Any:
    if name == "buffer":
        return cal.buffer
    if name == "sums":
        return cal.buffer.sums
    if name == "offset":
        return cal.offset
    return cal


def state_dict(cal: OnlineCalibrator) -> dict[str, np.ndarray]:
    """Everything needed to resume ``cal``, as numpy arrays (copies)."""
    buffer = cal.buffer
    sums = buffer.sums
    frames = list(buffer.frames)
    n = cal.sensor.n_pixels
    sparse = [f.sparse() for f in frames]  # the format's intervals are sparse

    def cat(i: int) -> np.ndarray:
        if not frames:
            return np.zeros(0, np.int32)
        return np.concatenate([sp[i] for sp in sparse]).astype(np.int32)

    waiting = buffer.intake.waiting()  # the events folded ahead wait again
    pending = np.concatenate(waiting) if waiting else np.zeros(0, EVENTS_DTYPE)
    scalars = {"height": cal.sensor.height, "width": cal.sensor.width,
               "config": cal.config.to_json(),
               "last_event_t_us": cal.last_event_t_us,
               "last_frame_t_us": cal.last_frame_t_us}
    scalars.update({key: getattr(_part(cal, part), attr)
                    for key, (part, attr, _) in SCALARS.items()})
    if cal.offset.job is not None:  # its result is not saved: check again on restore
        scalars["next_offset_check"] = cal.n_frames
    scalars["offset_info"] = to_jsonable(cal.offset.info)
    img_dtype = frames[0].image.dtype if frames else np.dtype(np.uint8)
    out: dict[str, np.ndarray] = {
        "format": np.array(STATE_FORMAT),
        "scalars": np.array(json.dumps(scalars)),
        **buffer.intake.open_interval_maps(),
        "counts": sums.counts, **cal.estimate.state(),
        "pending": pending, "fr_images": (np.stack([f.image for f in frames]) if frames
                      else np.zeros((0, n), img_dtype)),
        "fr_last_p": (np.stack([f.last_p for f in frames]) if frames
                      else np.zeros((0, n), np.int8)),
        "fr_meta": np.array([[f.t_us, f.cum_events, sp[0].size, int(f.opens), f.closes_at]
                             for f, sp in zip(frames, sparse, strict=True)],
                            np.int64).reshape(-1, 5),
        "fr_idx": cat(0), "fr_on": cat(1), "fr_off": cat(2),
    }
    for k, v in sums.normal_equations().arrays().items():
        out[f"ne_{k}"] = v
    if sums.hist is not None and sums.hist_counts is not None:
        out["hist_m"] = sums.rows(sums.hist)  # stored weights, with hist_ref
        out["hist_counts"] = sums.hist_counts[:n]
    return {k: np.array(v, copy=True) for k, v in out.items()}


def from_state(cls: type[OnlineCalibrator], state: dict[str, np.ndarray],
               executor: OnEIExecutor | None) -> OnlineCalibrator:
    """A calibrator of class ``cls`` rebuilt from :func:`state_dict` (raises
    :class:`~evcal.errors.StateError` if the state is not one or is inconsistent)."""
    try:
        if str(state["format"]) != STATE_FORMAT:
            raise StateError(f"unknown OnEI state format {state['format']!s} "
                             f"(this version reads {STATE_FORMAT})")
        s = json.loads(str(state["scalars"]))
        sensor = SensorSize(int(s["height"]), int(s["width"]))
        cal = cls(sensor, OnEIConfig.from_json(s["config"]), executor=executor)
        _load_arrays(cal, state)
        for key, (part, attr, conv) in SCALARS.items():
            if key in s or key not in OPTIONAL_SCALARS:
                setattr(_part(cal, part), attr, conv(s[key]))
        if isinstance(s.get("offset_info"), dict):
            cal.offset.info = s["offset_info"]
        if cal.config.log_offset == "auto" and not math.isnan(cal.log_offset):
            cal.offset.state = "restored from a saved state"
        base = cal.buffer.base
        cal.buffer.win_range = [[base, base], [base, base]]
        cal._last_event_t_us = s["last_event_t_us"]
        cal._last_frame_t_us = s["last_frame_t_us"]
    except KeyError as exc:
        raise StateError(f"OnEI state lacks {exc.args[0]!r}") from None
    return cal


def _load_arrays(cal: OnlineCalibrator, state: dict[str, np.ndarray]) -> None:
    """The state's arrays into a new calibrator ``cal`` (shapes checked)."""
    n = cal.sensor.n_pixels
    intake, sums = cal.buffer.intake, cal.buffer.sums
    load_into(intake.spill[0], state["acc_on"], "acc_on")  # as spilled counts
    load_into(intake.spill[1], state["acc_off"], "acc_off")
    intake.spilled = bool(intake.spill.any())
    load_into(intake.last_p, state["acc_last_p"], "acc_last_p")
    load_into(sums.counts, state["counts"], "counts")
    cal.estimate.load(state)
    pending = np.asarray(state["pending"])
    if pending.dtype != EVENTS_DTYPE:
        raise StateError("state pending events have the wrong dtype")
    if pending.size:
        intake.pending.append(pending)
    intake.n_pending = int(pending.size)
    ne = NormalEquations.from_arrays({k[3:]: v for k, v in state.items()
                                      if k.startswith("ne_")})
    if ne.n_pixels != n:
        raise StateError(f"state normal equations have {ne.n_pixels} pixels, expected {n}")
    sums.blocked(ne.m, sums.m)
    if sums.hist is not None and sums.hist_counts is not None and "hist_m" in state:
        hist_m = np.asarray(state["hist_m"], np.float64)
        if hist_m.shape != (16, n):
            raise StateError(f"state hist_m has shape {hist_m.shape}, expected (16, {n})")
        sums.blocked(hist_m, sums.hist)
        load_into(sums.hist_counts[:n], state["hist_counts"], "hist_counts")
    meta = np.asarray(state["fr_meta"], np.int64).reshape(-1, 5)
    images, last_p = state["fr_images"], state["fr_last_p"]
    if images.shape != (len(meta), n) or last_p.shape != (len(meta), n):
        raise StateError(f"state frames have shapes {images.shape} and {last_p.shape}, "
                         f"expected ({len(meta)}, {n})")
    bounds = np.concatenate([[0], np.cumsum(meta[:, 2])])
    if bounds[-1] != state["fr_idx"].size:
        raise StateError("state interval counts do not add up")
    for i, (t_us, cum, _, opens, closes_at) in enumerate(meta):
        sl = slice(int(bounds[i]), int(bounds[i + 1]))
        cal.buffer.frames.append(Frame(
            int(t_us), np.array(images[i]), np.array(last_p[i], np.int8), int(cum),
            np.array(state["fr_idx"][sl], np.int32), np.array(state["fr_on"][sl], np.int32),
            np.array(state["fr_off"][sl], np.int32), bool(opens), int(closes_at)))
    if cal.buffer.frames:
        intake.has_frames = True
