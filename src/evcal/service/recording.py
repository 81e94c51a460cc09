"""Rerun recording of a service run (``evcal serve --rrd PATH``): the only module importing rerun.

Entities, per camera (``<cam>`` is the camera id, which may have several chunks)::

    cameras/<cam>/maps/contrast      DepthImage, viridis, robust range      (at most every
    cameras/<cam>/maps/bias          DepthImage, cyan-to-yellow              map_period_s of
    cameras/<cam>/maps/special       SegmentationImage + legend              sensor time)
    cameras/<cam>/hist/contrast      BarChart of valid pixels' c
    cameras/<cam>/hist/bias          BarChart of valid pixels' b
    cameras/<cam>/recon/calibrated   Image: events integrated with the live calibration
    cameras/<cam>/recon/di           Image: the same with direct integration (c=0.1, b=0)
    cameras/<cam>/recon/frame        Image: the reference frame at the end of the window
    cameras/<cam>/series/<name>      Scalars: event_rate_hz, latency_ms, valid_fraction,
                                     psnr_calibrated_db, psnr_di_db, psnr_gain_db, errors
    cameras/<cam>/log                TextLog: discovery, rejected inputs (rate-limited)

Timelines: ``sensor_time`` (the camera's t_us as a duration) and ``wall_time``.

File growth is bounded: maps and reconstructions at most once per ``map_period_s`` /
``recon_period_s`` of sensor time, and no more images once ``max_image_bytes`` were logged
(a warning says so in the file); scalars at most every ``scalar_period_s`` (tens of bytes
each). A blueprint with one tab per camera is stored in the file and re-sent when a camera
appears.
"""

from __future__ import annotations

import itertools
import logging
import shutil
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from ..calibration import SPECIAL_LEGEND, Calibration, Special
from ..reconstruct import Reconstruction, StreamingEvaluator

log = logging.getLogger("evcal.service.recording")

APP_ID = "evcal-service"
_SPECIAL_COLORS = {
    Special.UNOBSERVED: (40, 40, 40),
    Special.NORMAL: (150, 150, 150),
    Special.HOT: (230, 60, 40),
    Special.COLD: (60, 120, 230),
    Special.WARM: (240, 170, 30),
    Special.COOL: (40, 200, 200),
}
SERIES = ("event_rate_hz", "latency_ms", "valid_fraction", "psnr_calibrated_db", "psnr_di_db",
          "psnr_gain_db", "errors_total")


def entity(camera: str, *parts: str) -> str:
    return "/".join(("cameras", camera, *parts))


def camera_blueprint(camera: str) -> Any:
    base = "/" + entity(camera)
    maps = rrb.Grid(
        rrb.Spatial2DView(origin=f"{base}/maps/contrast", name="contrast c"),
        rrb.Spatial2DView(origin=f"{base}/maps/bias", name="bias b"),
        rrb.Spatial2DView(origin=f"{base}/maps/special", name="special pixels"),
        rrb.Spatial2DView(origin=f"{base}/recon/calibrated", name="calibrated reconstruction"),
        rrb.Spatial2DView(origin=f"{base}/recon/di", name="DI reconstruction"),
        rrb.Spatial2DView(origin=f"{base}/recon/frame", name="reference frame"),
        grid_columns=3,
    )
    hists = rrb.Horizontal(
        rrb.BarChartView(origin=f"{base}/hist/contrast", name="histogram of c"),
        rrb.BarChartView(origin=f"{base}/hist/bias", name="histogram of b"),
    )
    series = rrb.Horizontal(
        rrb.TimeSeriesView(origin=f"{base}/series", name="rates and latency",
                           contents=[f"{base}/series/event_rate_hz",
                                     f"{base}/series/latency_ms",
                                     f"{base}/series/errors_total"]),
        rrb.TimeSeriesView(origin=f"{base}/series", name="PSNR (dB)",
                           contents=[f"{base}/series/psnr_calibrated_db",
                                     f"{base}/series/psnr_di_db",
                                     f"{base}/series/psnr_gain_db"]),
    )
    return rrb.Vertical(maps, hists, series, rrb.TextLogView(origin=f"{base}/log", name="log"),
                        row_shares=[3, 1.2, 1.2, 0.6], name=camera)


def make_blueprint(cameras: list[str]) -> Any:
    if not cameras:
        return rrb.Blueprint(rrb.TextLogView(origin="/service", name="service"),
                             collapse_panels=False)
    return rrb.Blueprint(rrb.Tabs(*[camera_blueprint(c) for c in cameras]),
                         collapse_panels=False)


@dataclass
class _CameraLog:
    shape: tuple[int, int]
    evaluator: StreamingEvaluator
    last_map_t_us: int | None = None
    last_scalar_t_us: int | None = None


def free_path(path: Path) -> Path:
    """``path``, or the first of ``stem.1.rrd``, ``stem.2.rrd``... that does not exist: a
    restarted service never overwrites the previous run's recording."""
    if not path.exists():
        return path
    for i in itertools.count(1):
        p = path.with_name(f"{path.stem}.{i}{path.suffix}")
        if not p.exists():
            return p
    raise AssertionError("unreachable")


def _disk_free(path: Path) -> int:
    return int(shutil.disk_usage(path).free)


class RrdLogger:
    """Writes one ``.rrd`` per service run; implements :class:`evcal.service.core.Observer`.

    It never overwrites a file (a restart writes ``run.1.rrd`` beside ``run.rrd``) and never
    fails the service: when the disk gets short (less than ``min_free_bytes`` free) or rerun
    raises, it logs why, finishes the file so that what was written stays readable, and
    stops recording (``state()`` says so, the service's ``cameras`` reply shows it).
    """

    def __init__(self, path: str | Path, *, map_period_s: float = 2.0,
                 recon_period_s: float = 2.0, recon_frames: int = 5,
                 scalar_period_s: float = 0.2, max_image_bytes: int = 300 << 20,
                 max_recon_events: int = 5_000_000, recording_id: str | None = None,
                 min_free_bytes: int = 64 << 20,
                 disk_free: Callable[[Path], int] = _disk_free):
        self.requested_path = Path(path)
        self.path = free_path(self.requested_path)
        if self.path != self.requested_path:
            log.warning("%s exists: this run records to %s", self.requested_path, self.path)
        self.min_free_bytes = int(min_free_bytes)
        self._disk_free = disk_free
        self._next_disk_check = 0.0
        self.stopped: str | None = None  # why recording stopped, None while it records
        self.errors = 0
        self.map_period_us = int(map_period_s * 1e6)
        self.recon_period_us = int(recon_period_s * 1e6)
        self.recon_frames = int(recon_frames)
        self.scalar_period_us = int(scalar_period_s * 1e6)
        self.max_image_bytes = int(max_image_bytes)
        self.max_recon_events = int(max_recon_events)
        self.image_bytes = 0
        self._images_stopped = False
        self._cams: dict[str, _CameraLog] = {}
        self._lock = threading.Lock()
        self.rec = rr.RecordingStream(APP_ID, recording_id=recording_id)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.rec.save(self.path, default_blueprint=make_blueprint([]))
        self._set_time(None)
        self.rec.log("service", rr.TextLog("evcal service started", level="INFO"))
        self._closed = False

    # -- helpers ---------------------------------------------------------------------------

    def _set_time(self, t_us: int | None) -> None:
        if t_us is not None:
            self.rec.set_time("sensor_time", duration=t_us * 1e-6)
        self.rec.set_time("wall_time", timestamp=time.time())

    def state(self) -> dict[str, Any]:
        """Where and whether it records (for the service's ``cameras`` reply)."""
        return {"path": str(self.path), "recording": self.stopped is None,
                "stopped": self.stopped, "errors": self.errors,
                "image_bytes": self.image_bytes}

    def _disk_ok(self) -> bool:
        """False (and recording stopped) when the disk is nearly full; checked at most once
        a second."""
        now = time.monotonic()
        if now < self._next_disk_check:
            return True
        self._next_disk_check = now + 1.0
        free = self._disk_free(self.path.parent)
        if free < self.min_free_bytes:
            self.stop(f"the disk holding {self.path} has {free >> 20} MiB free, less than "
                      f"{self.min_free_bytes >> 20} MiB: recording stopped, the file so far is "
                      "complete")
            return False
        return True

    def stop(self, reason: str) -> None:
        """Stop recording for good, finishing the file (never raises)."""
        if self.stopped is not None:
            return
        self.stopped = reason
        log.error("rerun recording: %s", reason)
        try:
            self._set_time(None)
            self.rec.log("service", rr.TextLog(reason, level="ERROR"))
        except Exception:  # noqa: BLE001 - stopping anyway
            pass
        self._finish()

    def _finish(self) -> None:
        try:
            self.rec.flush()
            self.rec.disconnect()
        except Exception as exc:  # noqa: BLE001 - the file so far is what it is
            self.errors += 1
            log.error("rerun recording: cannot finish %s: %s", self.path, exc)

    def _guard(self, fn: Callable[..., None], *args: Any) -> None:
        """Run one observer call unless stopped; a failure stops recording, never the
        service."""
        if self.stopped is not None or self._closed or not self._disk_ok():
            return
        try:
            fn(*args)
        except Exception as exc:  # noqa: BLE001 - disk full, rerun errors
            self.errors += 1
            self.stop(f"recording failed ({type(exc).__name__}: {exc}); stopped")

    def _image_budget(self, nbytes: int, camera: str) -> bool:
        with self._lock:
            if self.image_bytes + nbytes > self.max_image_bytes:
                if not self._images_stopped:
                    self._images_stopped = True
                    self.rec.log("service", rr.TextLog(
                        f"image budget of {self.max_image_bytes >> 20} MiB reached: no more "
                        "maps or reconstructions in this file (scalars continue)",
                        level="WARN"))
                return False
            self.image_bytes += nbytes
            return True

    def _camera(self, camera: str, shape: tuple[int, int]) -> _CameraLog:
        cl = self._cams.get(camera)
        if cl is None:
            with self._lock:
                cl = self._cams[camera] = _CameraLog(shape, StreamingEvaluator(
                    shape, period_us=self.recon_period_us, window_frames=self.recon_frames,
                    max_events=self.max_recon_events))
                names = sorted(self._cams)
            self._log_static(camera)
            self.rec.send_blueprint(make_blueprint(names), make_active=True, make_default=True)
            self.rec.log(entity(camera, "log"), rr.TextLog(
                f"camera {camera}: {shape[1]}x{shape[0]} sensor", level="INFO"))
        return cl

    def _log_static(self, camera: str) -> None:
        self.rec.log(entity(camera, "maps", "special"), rr.AnnotationContext([
            rr.AnnotationInfo(id=int(k), label=SPECIAL_LEGEND[int(k)], color=c)
            for k, c in _SPECIAL_COLORS.items()]), static=True)

    # -- Observer --------------------------------------------------------------------------

    def events(self, camera: str, events: np.ndarray) -> None:
        self._guard(self._events, camera, events)

    def _events(self, camera: str, events: np.ndarray) -> None:
        cl = self._cams.get(camera)
        if cl is not None:
            cl.evaluator.events(events)

    def frame(self, camera: str, t_us: int, image: np.ndarray) -> None:
        self._guard(self._frame, camera, t_us, image)

    def _frame(self, camera: str, t_us: int, image: np.ndarray) -> None:
        cl = self._cams.get(camera)
        if cl is None:
            return
        if self._images_stopped:
            cl.evaluator.discard()
        result = cl.evaluator.frame(t_us, image)
        if result is not None:
            self._log_reconstruction(camera, result)

    def _log_reconstruction(self, camera: str, r: Reconstruction) -> None:
        """Log what the core's :class:`~evcal.reconstruct.StreamingEvaluator` computed."""
        self._set_time(r.t_end_us)
        if self._image_budget(3 * r.reference.size, camera):
            for name, img in (("calibrated", r.calibrated), ("di", r.di),
                              ("frame", r.reference)):
                self.rec.log(entity(camera, "recon", name),
                             rr.Image(np.clip(np.rint(img), 0, 255).astype(np.uint8)))
        for name, v in (("psnr_calibrated_db", r.psnr_calibrated_db),
                        ("psnr_di_db", r.psnr_di_db), ("psnr_gain_db", r.psnr_gain_db)):
            if np.isfinite(v):
                self.rec.log(entity(camera, "series", name), rr.Scalars([float(v)]))

    def updated(self, camera: str, cal: Calibration, t_us: int, status: dict[str, Any]
                ) -> None:
        self._guard(self._updated, camera, cal, t_us, status)

    def _updated(self, camera: str, cal: Calibration, t_us: int, status: dict[str, Any]
                 ) -> None:
        cl = self._camera(camera, cal.shape)
        cl.evaluator.calibration(cal)
        self._set_time(t_us)
        if cl.last_scalar_t_us is None or t_us - cl.last_scalar_t_us >= self.scalar_period_us:
            cl.last_scalar_t_us = t_us
            lat = status.get("latency_ms", {}).get("last")
            values = {"event_rate_hz": status.get("event_rate_hz"), "latency_ms": lat,
                      "valid_fraction": cal.valid_fraction,
                      "errors_total": status.get("errors_total")}
            for name, v in values.items():
                if v is not None:
                    self.rec.log(entity(camera, "series", name), rr.Scalars([float(v)]))
        if cl.last_map_t_us is not None and t_us - cl.last_map_t_us < self.map_period_us:
            return
        if not self._image_budget(cal.contrast.nbytes * 2 + cal.special.nbytes, camera):
            return
        cl.last_map_t_us = t_us
        self._log_maps(camera, cal)

    def _log_maps(self, camera: str, cal: Calibration) -> None:
        v = cal.valid
        c_lo, c_hi = (np.percentile(cal.contrast[v], [2, 98]) if v.any() else (0.0, 0.5))
        b_abs = float(np.percentile(np.abs(cal.bias[v]), 98)) if v.any() else 0.1
        c_hi = max(float(c_hi), float(c_lo) + 1e-3)
        b_abs = max(b_abs, 1e-3)
        self.rec.log(entity(camera, "maps", "contrast"), rr.DepthImage(
            cal.contrast, colormap="viridis", depth_range=(float(c_lo), c_hi)))
        self.rec.log(entity(camera, "maps", "bias"), rr.DepthImage(
            cal.bias, colormap="cyantoyellow", depth_range=(-b_abs, b_abs)))
        self.rec.log(entity(camera, "maps", "special"), rr.SegmentationImage(cal.special))
        for name, values, rng in (("contrast", cal.contrast[v], (float(c_lo), c_hi)),
                                  ("bias", cal.bias[v], (-b_abs, b_abs))):
            if values.size == 0:
                continue
            lo, hi = rng
            pad = 0.25 * (hi - lo)
            counts, edges = np.histogram(values, bins=50, range=(lo - pad, hi + pad))
            self.rec.log(entity(camera, "hist", name), rr.BarChart(
                counts.astype(np.float64), abscissa=0.5 * (edges[:-1] + edges[1:])))

    def discard(self, camera: str, dropped: int) -> None:
        """The service dropped ``dropped`` calls of ``camera`` (this recorder fell behind): an
        open reconstruction window misses events, so it is abandoned."""
        cl = self._cams.get(camera)
        if cl is not None:
            cl.evaluator.discard()
        self.note(camera, f"the recorder fell behind: {dropped} call(s) dropped (maps, "
                          "frames or events); the open reconstruction was abandoned")

    def note(self, camera: str, text: str, level: str = "WARN") -> None:
        self._guard(self._note, camera, text, level)

    def _note(self, camera: str, text: str, level: str) -> None:
        if camera in self._cams:
            self._set_time(None)
            self.rec.log(entity(camera, "log"), rr.TextLog(text, level=level))

    def close(self) -> None:
        """Flush and finish the file (footer included): the ``.rrd`` is complete after this.
        Never raises."""
        if self._closed:
            return
        self._closed = True
        if self.stopped is not None:
            return  # already finished
        try:
            self._set_time(None)
            self.rec.log("service", rr.TextLog("evcal service stopped", level="INFO"))
        except Exception:  # noqa: BLE001
            self.errors += 1
        self._finish()


def read_entities(path: str | Path) -> dict[str, int]:
    """``{entity_path: rows}`` of a ``.rrd`` (for tests and the demo's summary)."""
    from rerun.chunk import RrdReader

    counts: dict[str, int] = {}
    reader = RrdReader(str(path))
    for store in reader.recordings():
        for chunk in reader.stream(store=store).collect().stream():
            p = str(chunk.entity_path)
            counts[p] = counts.get(p, 0) + int(chunk.num_rows)
    return counts
