"""OnEI: online events + intensity calibration with an event-count-driven buffer.

The stream is cut at frame times into frame intervals. Consecutive intervals are merged into a
*small buffer* until it holds at least ``n_small`` events; a closed small buffer is one equation
per pixel (the OffEI equation with the residual correction, :mod:`evcal.lsq`) between the frame
that opened it and the frame that closed it. The *large buffer* is the sliding set of small
buffers holding at most ``n_large`` events; when it overflows the oldest small buffer leaves.

Reading of the paper: it drops the oldest *frame interval* and re-splits the large buffer. We
drop whole small buffers instead: every equation is then fixed once formed, so the per-pixel
normal equations are updated exactly in O(events) (:class:`~evcal.lsq.NormalEquations`,
``add``/``sign=-1``) instead of re-solved from stored frames, and memory is bounded by
``n_large`` sparse entries plus a handful of maps, whatever the frame rate. For
``n_small << n_large`` the two coincide.

After every closed small buffer the per-pixel system is re-solved and the estimate low-pass
filtered: ``est <- (1 - smoothing) est + smoothing new`` on pixels whose new solution is valid
(the first valid solution of a pixel is taken as is).

Streaming contract: :meth:`OnlineCalibrator.feed_events` takes sorted chunks, time never going
back across chunks; frames may arrive late with respect to events (events after the latest
frame wait in a bounded pending buffer until the frame that closes their interval arrives).
"""

from __future__ import annotations

import json
from collections import deque
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from .accumulate import Accumulator
from .calibration import DEFAULT_BIAS, DEFAULT_CONTRAST, Calibration, Reason, Special
from .events import EVENTS_DTYPE, EventError, SensorSize, validate_events
from .lsq import (
    NormalEquations,
    SolveLimits,
    correction_lambda,
    log_intensity,
    solve_normal_equations,
    usable,
)
from .recording import Recording
from .special import classify


@dataclass(frozen=True, kw_only=True)
class OnEIConfig:
    """OnEI parameters. ``None`` sizes scale with the sensor as in the paper at 240x180
    (200 k and 1.7 M events for 43,200 pixels)."""

    n_small: int | None = None
    n_large: int | None = None
    smoothing: float = 0.2
    log_offset: float = 30.0
    residual_correction: str | float = "auto"
    saturation_dn: tuple[float, float] = (0.0, 255.0)
    max_pending_events: int = 20_000_000
    limits: SolveLimits = field(default_factory=lambda: SolveLimits(min_events=10,
                                                                    min_equations=3.0))

    def __post_init__(self) -> None:
        if not 0 < self.smoothing <= 1:
            raise ValueError(f"smoothing={self.smoothing} must be in (0, 1]")
        if self.log_offset < 0:
            raise ValueError(f"log_offset={self.log_offset} must be >= 0")
        for name in ("n_small", "n_large"):
            v = getattr(self, name)
            if v is not None and v < 1:
                raise ValueError(f"{name}={v} must be >= 1")
        if self.n_small and self.n_large and self.n_large < self.n_small:
            raise ValueError(f"n_large={self.n_large} must be >= n_small={self.n_small}")

    def sizes(self, sensor: SensorSize) -> tuple[int, int]:
        n_small = self.n_small or max(1000, int(round(200_000 / 43_200 * sensor.n_pixels)))
        n_large = self.n_large or max(n_small, int(round(1_700_000 / 43_200 * sensor.n_pixels)))
        return n_small, n_large

    def to_json(self) -> str:
        d = asdict(self)
        return json.dumps(d)

    @classmethod
    def from_json(cls, text: str) -> OnEIConfig:
        d = json.loads(text)
        d["saturation_dn"] = tuple(d["saturation_dn"])
        d["limits"] = SolveLimits(**d["limits"])
        return cls(**d)


@dataclass
class _Equation:
    """One closed small buffer: sparse per-pixel terms at the pixels that had events."""

    idx: np.ndarray  # int32 flat pixel indices
    p: np.ndarray
    e: np.ndarray
    q: np.ndarray
    a: np.ndarray
    dl: np.ndarray
    w: np.ndarray
    n_events: int
    t0_us: int
    t1_us: int


class OnlineCalibrator:
    """Per-camera OnEI state: feed events and frames in time order, read the calibration."""

    def __init__(self, sensor: SensorSize, config: OnEIConfig | None = None):
        self.sensor = sensor
        self.config = config or OnEIConfig()
        self.n_small, self.n_large = self.config.sizes(sensor)
        n = sensor.n_pixels
        self._acc = Accumulator(sensor)  # counts since the current small buffer opened
        self._ne = NormalEquations(n)
        self._counts = np.zeros(n, np.int64)  # events per pixel inside the large buffer
        self._eqs: deque[_Equation] = deque()
        self._buffer_events = 0  # events inside the large buffer
        self._pending: list[np.ndarray] = []
        self._n_pending = 0
        self._start_l: np.ndarray | None = None  # log frame that opened the small buffer
        self._start_ok: np.ndarray | None = None
        self._start_q = np.zeros(n, np.int8)
        self._start_t_us = 0
        self._small_events = 0
        # smoothed estimate
        self._c = np.full(n, DEFAULT_CONTRAST)
        self._b = np.full(n, DEFAULT_BIAS)
        self._se_c = np.full(n, np.inf)
        self._se_b = np.full(n, np.inf)
        self._seen = np.zeros(n, bool)
        self._reason = np.full(n, Reason.NO_EVENTS, np.uint8)
        self.lam = 0.0
        self.n_updates = 0
        self.n_events = 0
        self.n_frames = 0
        self.n_folded_late = 0  # events folded without their frame (pending overflow)
        self.last_event_t_us: int | None = None
        self.last_frame_t_us: int | None = None

    # -- input ------------------------------------------------------------------------------

    def feed_events(self, events: np.ndarray) -> None:
        """Add a sorted chunk of events (validated; raises :class:`EventError`)."""
        validate_events(events, self.sensor, where="events", after_t_us=self.last_event_t_us)
        if events.size == 0:
            return
        self.last_event_t_us = int(events["t_us"][-1])
        self.n_events += int(events.size)
        self._pending.append(events)
        self._n_pending += int(events.size)
        while self._n_pending > self.config.max_pending_events and len(self._pending) > 1:
            old = self._pending.pop(0)
            self._n_pending -= int(old.size)
            self._fold(old)
            self.n_folded_late += int(old.size)

    def feed_frame(self, t_us: int, image: np.ndarray, exposure_us: int = 0) -> bool:
        """Close the frame interval ending at ``t_us``; True when the estimate was re-solved."""
        t_us = int(t_us)
        img = np.asarray(image)
        if img.shape != self.sensor.shape:
            h, w = img.shape[:2] if img.ndim >= 2 else (0, 0)
            raise ValueError(
                f"frame at t_us={t_us} has shape {img.shape}, the camera is {self.sensor} "
                f"(expected {self.sensor.shape})"
            )
        if img.dtype.kind == "f" and not np.isfinite(img).all():
            raise ValueError(f"frame at t_us={t_us} contains NaN or infinite values")
        if self.last_frame_t_us is not None and t_us <= self.last_frame_t_us:
            raise ValueError(
                f"frame time goes backwards: t_us={t_us} after t_us={self.last_frame_t_us}"
            )
        # events before the frame belong to the interval it closes
        if self._pending:
            pending = np.concatenate(self._pending) if len(self._pending) > 1 else self._pending[0]
            cut = int(np.searchsorted(pending["t_us"], t_us, side="left"))
            self._fold(pending[:cut])
            rest = pending[cut:]
            self._pending = [rest] if rest.size else []
            self._n_pending = int(rest.size)
        self.last_frame_t_us = t_us
        self.n_frames += 1
        flat = img.ravel()
        l_now = log_intensity(flat, self.config.log_offset)
        ok_now = usable(flat, self.config.saturation_dn)
        if self._start_l is None:
            self._open(l_now, ok_now, t_us)
            return False
        if self._small_events < self.n_small:
            return False
        self._close(l_now, ok_now, t_us)
        self._open(l_now, ok_now, t_us)
        self._resolve()
        return True

    # -- internals ---------------------------------------------------------------------------

    def _fold(self, events: np.ndarray) -> None:
        if events.size and self._start_l is not None:
            self._acc.add(events)
            self._small_events += int(events.size)
        elif events.size:
            # before the first frame: only the last polarity matters
            self._acc.add(events)
            self._acc.reset_counts()

    def _open(self, l_now: np.ndarray, ok_now: np.ndarray, t_us: int) -> None:
        self._start_l = l_now
        self._start_ok = ok_now
        self._start_q = self._acc.last_p.copy()
        self._start_t_us = t_us
        self._acc.reset_counts()
        self._small_events = 0

    def _close(self, l_now: np.ndarray, ok_now: np.ndarray, t_us: int) -> None:
        assert self._start_l is not None and self._start_ok is not None
        on, off = self._acc.on, self._acc.off
        idx = np.flatnonzero((on | off) != 0).astype(np.int32)
        p = (on[idx] - off[idx]).astype(np.float64)
        e = (on[idx] + off[idx]).astype(np.float64)
        qn = self._acc.last_p[idx].astype(np.float64)
        qs = self._start_q[idx].astype(np.float64)
        eq = _Equation(
            idx=idx, p=p, e=e, q=qn - qs, a=np.abs(qn) - np.abs(qs),
            dl=l_now[idx] - self._start_l[idx],
            w=(ok_now[idx] & self._start_ok[idx]).astype(np.float64),
            n_events=self._small_events, t0_us=self._start_t_us, t1_us=t_us,
        )
        self._apply(eq, +1.0)
        self._eqs.append(eq)
        while self._buffer_events > self.n_large and len(self._eqs) > 1:
            self._apply(self._eqs.popleft(), -1.0)

    def _apply(self, eq: _Equation, sign: float) -> None:
        self._ne.add(eq.p, eq.e, eq.q, eq.a, eq.dl, eq.w, idx=eq.idx, sign=sign)
        self._counts[eq.idx] += (sign * eq.e).astype(np.int64)
        self._buffer_events += int(sign) * eq.n_events

    def _resolve(self) -> None:
        cfg = self.config
        self.lam = correction_lambda(self._ne, cfg.residual_correction, cfg.limits, self._counts)
        new = solve_normal_equations(
            self._ne, self._counts, (self.sensor.n_pixels, 1), limits=cfg.limits,
            overlap=1.0, log_offset=cfg.log_offset, method="onei", residual_lambda=self.lam,
        )
        ok = new.valid.ravel()
        c_new = new.contrast.ravel().astype(np.float64)
        b_new = new.bias.ravel().astype(np.float64)
        first = ok & ~self._seen
        again = ok & self._seen
        a = cfg.smoothing
        self._c[first] = c_new[first]
        self._b[first] = b_new[first]
        self._c[again] = (1 - a) * self._c[again] + a * c_new[again]
        self._b[again] = (1 - a) * self._b[again] + a * b_new[again]
        self._se_c[ok] = new.stderr_contrast.ravel()[ok]
        self._se_b[ok] = new.stderr_bias.ravel()[ok]
        self._seen |= ok
        r = new.reason.ravel()
        self._reason = np.where(self._seen, np.uint8(Reason.VALID), r).astype(np.uint8)
        self.n_updates += 1

    # -- output ------------------------------------------------------------------------------

    def calibration(self) -> Calibration:
        """The current smoothed estimate (defaults where no valid solution was seen yet)."""
        shape = self.sensor.shape
        valid = self._seen
        special = classify(self._c, self._b, self._se_c, self._se_b, valid)
        special = np.where(valid, special, np.uint8(Special.UNOBSERVED))
        return Calibration(
            contrast=self._c.reshape(shape),
            bias=self._b.reshape(shape),
            valid=valid.reshape(shape),
            reason=self._reason.reshape(shape),
            stderr_contrast=np.where(valid, self._se_c, np.inf).reshape(shape),
            stderr_bias=np.where(valid, self._se_b, np.inf).reshape(shape),
            special=special.reshape(shape),
            log_offset=self.config.log_offset,
            method="onei",
            n_events=self._counts.reshape(shape),
            params=self.status() | {"config": json.loads(self.config.to_json())},
        )

    def status(self) -> dict[str, Any]:
        return {
            "n_updates": self.n_updates,
            "n_events": self.n_events,
            "n_frames": self.n_frames,
            "buffer_events": self._buffer_events,
            "buffer_equations": len(self._eqs),
            "pending_events": self._n_pending,
            "folded_late_events": self.n_folded_late,
            "residual_lambda": self.lam,
            "n_small": self.n_small,
            "n_large": self.n_large,
            "last_frame_t_us": self.last_frame_t_us,
        }

    # -- persistence -------------------------------------------------------------------------

    def state_dict(self) -> dict[str, np.ndarray]:
        """Everything needed to resume, as numpy arrays (``np.savez``-able)."""
        eqs = list(self._eqs)
        lens = np.array([eq.idx.size for eq in eqs], np.int64)

        def cat(name: str, dtype: Any) -> np.ndarray:
            if not eqs:
                return np.zeros(0, dtype)
            return np.concatenate([getattr(eq, name) for eq in eqs]).astype(dtype)

        pending = (np.concatenate(self._pending) if self._pending
                   else np.zeros(0, EVENTS_DTYPE))
        scalars = {
            "height": self.sensor.height, "width": self.sensor.width,
            "config": self.config.to_json(), "lam": self.lam, "n_updates": self.n_updates,
            "n_events": self.n_events, "n_frames": self.n_frames,
            "n_folded_late": self.n_folded_late, "last_event_t_us": self.last_event_t_us,
            "last_frame_t_us": self.last_frame_t_us, "buffer_events": self._buffer_events,
            "small_events": self._small_events, "start_t_us": self._start_t_us,
        }
        out: dict[str, np.ndarray] = {
            "format": np.array("evcal.onei.v1"),
            "scalars": np.array(json.dumps(scalars)),
            "acc_on": self._acc.on, "acc_off": self._acc.off, "acc_last_p": self._acc.last_p,
            "counts": self._counts, "start_q": self._start_q,
            "start_l": self._start_l if self._start_l is not None else np.zeros(0),
            "start_ok": self._start_ok if self._start_ok is not None else np.zeros(0, bool),
            "c": self._c, "b": self._b, "se_c": self._se_c, "se_b": self._se_b,
            "seen": self._seen, "reason": self._reason, "pending": pending,
            "eq_len": lens, "eq_meta": np.array([[eq.n_events, eq.t0_us, eq.t1_us] for eq in eqs],
                                                 np.int64).reshape(-1, 3),
            "eq_idx": cat("idx", np.int32),
        }
        for name in ("p", "e", "q", "a", "dl", "w"):
            out[f"eq_{name}"] = cat(name, np.float64)
        for k, v in self._ne.arrays().items():
            out[f"ne_{k}"] = v
        return {k: np.array(v, copy=True) for k, v in out.items()}

    @classmethod
    def from_state(cls, state: dict[str, np.ndarray]) -> OnlineCalibrator:
        """Rebuild a calibrator from :meth:`state_dict` (raises ValueError if inconsistent)."""
        try:
            if str(state["format"]) != "evcal.onei.v1":
                raise ValueError(f"unknown OnEI state format {state['format']!s}")
            s = json.loads(str(state["scalars"]))
            sensor = SensorSize(int(s["height"]), int(s["width"]))
            self = cls(sensor, OnEIConfig.from_json(s["config"]))
            n = sensor.n_pixels
            for name in ("acc_on", "acc_off", "acc_last_p", "counts", "start_q", "c", "b",
                         "se_c", "se_b", "seen", "reason"):
                if state[name].shape != (n,):
                    raise ValueError(f"state {name} has shape {state[name].shape}, expected ({n},)")
            self._acc.on[:] = state["acc_on"]
            self._acc.off[:] = state["acc_off"]
            self._acc.last_p[:] = state["acc_last_p"]
            self._counts[:] = state["counts"]
            self._start_q[:] = state["start_q"]
            if state["start_l"].size:
                self._start_l = np.array(state["start_l"], np.float64)
                self._start_ok = np.array(state["start_ok"], bool)
            self._c[:] = state["c"]
            self._b[:] = state["b"]
            self._se_c[:] = state["se_c"]
            self._se_b[:] = state["se_b"]
            self._seen[:] = state["seen"]
            self._reason[:] = state["reason"]
            pending = np.asarray(state["pending"])
            if pending.dtype != EVENTS_DTYPE:
                raise ValueError("state pending events have the wrong dtype")
            self._pending = [pending] if pending.size else []
            self._n_pending = int(pending.size)
            self._ne = NormalEquations.from_arrays({k[3:]: v for k, v in state.items()
                                                    if k.startswith("ne_")})
            bounds = np.concatenate([[0], np.cumsum(state["eq_len"])])
            for i, meta in enumerate(state["eq_meta"]):
                sl = slice(int(bounds[i]), int(bounds[i + 1]))
                self._eqs.append(_Equation(
                    idx=state["eq_idx"][sl], p=state["eq_p"][sl], e=state["eq_e"][sl],
                    q=state["eq_q"][sl], a=state["eq_a"][sl], dl=state["eq_dl"][sl],
                    w=state["eq_w"][sl], n_events=int(meta[0]), t0_us=int(meta[1]),
                    t1_us=int(meta[2]),
                ))
            self.lam = float(s["lam"])
            self.n_updates = int(s["n_updates"])
            self.n_events = int(s["n_events"])
            self.n_frames = int(s["n_frames"])
            self.n_folded_late = int(s["n_folded_late"])
            self.last_event_t_us = s["last_event_t_us"]
            self.last_frame_t_us = s["last_frame_t_us"]
            self._buffer_events = int(s["buffer_events"])
            self._small_events = int(s["small_events"])
            self._start_t_us = int(s["start_t_us"])
        except KeyError as exc:
            raise ValueError(f"OnEI state lacks {exc.args[0]!r}") from None
        return self


def onei(rec: Recording, config: OnEIConfig | None = None, *,
         history_every: int = 0) -> Calibration:
    """Run :class:`OnlineCalibrator` over a recording (the path the service uses).

    With ``history_every = n > 0`` the calibration after every n-th update is kept in
    ``params["history"]`` as ``(t_us, contrast, bias, valid)`` tuples (for convergence plots).
    """
    assert rec.frames is not None
    if len(rec.frames) < 2:
        raise EventError(f"OnEI needs frames: the recording has {len(rec.frames)}")
    cal_state = OnlineCalibrator(rec.sensor, config)
    t_ev = rec.events["t_us"]
    prev = 0
    history = []
    for k in range(len(rec.frames)):
        t = int(rec.frames.t_us[k])
        end = int(np.searchsorted(t_ev, t, side="left"))
        if end > prev:
            cal_state.feed_events(rec.events[prev:end])
            prev = end
        updated = cal_state.feed_frame(t, rec.frames.images[k])
        if updated and history_every and cal_state.n_updates % history_every == 0:
            cur = cal_state.calibration()
            history.append((t, cur.contrast.copy(), cur.bias.copy(), cur.valid.copy()))
    cal = cal_state.calibration()
    if history_every:
        cal.params["history"] = history
    return cal
