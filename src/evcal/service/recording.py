"""Rerun recording of a service run (``evcal serve --rrd PATH``): the only module importing rerun.

Entities, per camera (``<cam>`` is the camera id, which may have several chunks)::

    cameras/<cam>/maps/contrast      DepthImage, viridis, robust range      (at most every
    cameras/<cam>/maps/bias          DepthImage, cyan-to-yellow              map_period_s of
    cameras/<cam>/maps/special       SegmentationImage + legend              sensor time)
    cameras/<cam>/maps/<m>/invalid   SegmentationImage over each map: pixels without a
                                     trusted solution drawn grey, not as data
    cameras/<cam>/maps/stderr_contrast, stderr_bias   DepthImage of the standard errors
    cameras/<cam>/maps/contrast_error, bias_error     |estimate - truth| when the truth is
                                     known (demo, simulations: ``truth=``)
    cameras/<cam>/events             Image: ON (red) / OFF (blue) counts of one frame
                                     interval, at most every map_period_s
    cameras/<cam>/hist/contrast      BarChart of valid pixels' c
    cameras/<cam>/hist/bias          BarChart of valid pixels' b
    cameras/<cam>/recon/calibrated   Image: events integrated with the live calibration
    cameras/<cam>/recon/di           Image: the same with direct integration (c=0.1, b=0)
    cameras/<cam>/recon/frame        Image: the reference frame at the end of the window
    cameras/<cam>/series/<name>      Scalars: event_rate_hz, latency_ms, valid_fraction,
                                     psnr_calibrated_db, psnr_di_db, psnr_gain_db, errors,
                                     c_mae and b_mae (with the truth); each in a view of its
                                     own scale (rates, latencies, fractions, dB, errors)
    cameras/<cam>/log                TextLog: discovery, rejected inputs (rate-limited)

Timelines: ``sensor_time`` (the camera's t_us as a duration), ``sensor_clock`` (the same as
an absolute timestamp, for cameras whose t_us is Unix time, as ROS stamps are) and
``wall_time``. Sinks: the file, plus a gRPC server a viewer connects to (``serve_port``) or
a running viewer (``connect_url``).

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
from collections.abc import Callable, Collection
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from ..calibration import SPECIAL_LEGEND, Calibration, Special
from ..reconstruct import Reconstruction, StreamingEvaluator
from ..recording import Recording

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
          "psnr_gain_db", "errors_total", "c_mae", "b_mae")
# the views of the series, one scale each: every series is in exactly one
SERIES_VIEWS = (("event rate (Hz)", ("event_rate_hz",)),
                ("frame to calibration latency (ms)", ("latency_ms",)),
                ("valid fraction", ("valid_fraction",)),
                ("PSNR (dB)", ("psnr_calibrated_db", "psnr_di_db", "psnr_gain_db")),
                ("input errors (total)", ("errors_total",)),
                ("error vs truth", ("c_mae", "b_mae")))
MAPS_WITH_MASK = ("contrast", "bias", "stderr_contrast", "stderr_bias", "contrast_error",
                  "bias_error")
ABSOLUTE_T_US = 946_684_800_000_000  # 2000-01-01 in Unix µs: later t_us are clock times


def entity(camera: str, *parts: str) -> str:
    return "/".join(("cameras", camera, *parts))


def camera_blueprint(camera: str, *, truth: bool = False) -> Any:
    base = "/" + entity(camera)
    views = [
        rrb.Spatial2DView(origin=f"{base}/maps/contrast", name="contrast c"),
        rrb.Spatial2DView(origin=f"{base}/maps/bias", name="bias b"),
        rrb.Spatial2DView(origin=f"{base}/maps/special", name="special pixels"),
        rrb.Spatial2DView(origin=f"{base}/maps/stderr_contrast", name="std. error of c"),
        rrb.Spatial2DView(origin=f"{base}/maps/stderr_bias", name="std. error of b"),
        rrb.Spatial2DView(origin=f"{base}/events", name="events ON/OFF (one interval)"),
        rrb.Spatial2DView(origin=f"{base}/recon/calibrated", name="calibrated reconstruction"),
        rrb.Spatial2DView(origin=f"{base}/recon/di", name="DI reconstruction"),
        rrb.Spatial2DView(origin=f"{base}/recon/frame", name="reference frame"),
    ]
    if truth:
        views += [rrb.Spatial2DView(origin=f"{base}/maps/contrast_error", name="|c - true c|"),
                  rrb.Spatial2DView(origin=f"{base}/maps/bias_error", name="|b - true b|")]
    maps = rrb.Grid(*views, grid_columns=3)
    hists = rrb.Horizontal(
        rrb.BarChartView(origin=f"{base}/hist/contrast", name="histogram of c"),
        rrb.BarChartView(origin=f"{base}/hist/bias", name="histogram of b"),
    )
    series = rrb.Grid(*[
        rrb.TimeSeriesView(origin=f"{base}/series", name=name,
                           contents=[f"{base}/series/{n}" for n in names])
        for name, names in SERIES_VIEWS if truth or names[0] != "c_mae"], grid_columns=3)
    return rrb.Vertical(maps, hists, series, rrb.TextLogView(origin=f"{base}/log", name="log"),
                        row_shares=[4, 1.2, 2, 0.6], name=camera)


def make_blueprint(cameras: list[str], truth: Collection[str] | None = None) -> Any:
    if not cameras:
        return rrb.Blueprint(rrb.TextLogView(origin="/service", name="service"),
                             collapse_panels=False)
    return rrb.Blueprint(rrb.Tabs(*[camera_blueprint(c, truth=c in (truth or ()))
                                    for c in cameras]), collapse_panels=False)


@dataclass
class _CameraLog:
    shape: tuple[int, int]
    evaluator: StreamingEvaluator
    last_map_t_us: int | None = None
    last_scalar_t_us: int | None = None
    last_events_t_us: int | None = None  # the last events image
    event_counts: np.ndarray | None = None  # [2, pixels] ON, OFF of the open interval


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
                 disk_free: Callable[[Path], int] = _disk_free,
                 truth: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
                 serve_port: int | None = None, connect_url: str | None = None,
                 app_id: str = APP_ID, started: str = "evcal service started"):
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
        # camera -> (true c, true b) maps: error maps and c/b MAE curves are logged for them
        self.truth = {k: (np.asarray(c, np.float64), np.asarray(b, np.float64))
                      for k, (c, b) in (truth or {}).items()}
        self.rec = rr.RecordingStream(app_id, recording_id=recording_id)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        sinks: list[Any] = [rr.FileSink(str(self.path))]
        if serve_port is not None:  # a viewer connects: rerun --connect rerun+http://...
            sinks.append(rr.GrpcServerSink(port=int(serve_port)))
        if connect_url is not None:  # a running viewer
            sinks.append(rr.GrpcSink(connect_url))
        self.serve_port = serve_port
        self.rec.set_sinks(*sinks, default_blueprint=make_blueprint([]))
        self._set_time(None)
        self.rec.log("service", rr.TextLog(started, level="INFO"))
        self._closed = False

    # -- helpers ---------------------------------------------------------------------------

    def _set_time(self, t_us: int | None) -> None:
        if t_us is not None:
            self.rec.set_time("sensor_time", duration=t_us * 1e-6)
            if t_us >= ABSOLUTE_T_US:  # a clock time (ROS stamps, jAER/Prophesee wall time)
                self.rec.set_time("sensor_clock", timestamp=t_us * 1e-6)
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
            self.rec.send_blueprint(make_blueprint(names, self.truth), make_active=True,
                                    make_default=True)
            self.rec.log(entity(camera, "log"), rr.TextLog(
                f"camera {camera}: {shape[1]}x{shape[0]} sensor", level="INFO"))
        return cl

    def _log_static(self, camera: str) -> None:
        self.rec.log(entity(camera, "maps", "special"), rr.AnnotationContext([
            rr.AnnotationInfo(id=int(k), label=SPECIAL_LEGEND[int(k)], color=c)
            for k, c in _SPECIAL_COLORS.items()]), static=True)
        mask = rr.AnnotationContext([
            rr.AnnotationInfo(id=0, label="trusted", color=(0, 0, 0, 0)),
            rr.AnnotationInfo(id=1, label="invalid (no trusted solution)",
                              color=(90, 90, 90, 255))])
        for name in MAPS_WITH_MASK:
            self.rec.log(entity(camera, "maps", name, "invalid"), mask, static=True)

    # -- Observer --------------------------------------------------------------------------

    def events(self, camera: str, events: np.ndarray) -> None:
        self._guard(self._events, camera, events)

    def _events(self, camera: str, events: np.ndarray) -> None:
        cl = self._cams.get(camera)
        if cl is not None:
            cl.evaluator.events(events)
            if cl.event_counts is not None and events.size:
                w = cl.shape[1]
                flat = events["y"].astype(np.int64) * w + events["x"]
                n = cl.shape[0] * w
                on = events["p"] > 0
                cl.event_counts[0] += np.bincount(flat[on], minlength=n)
                cl.event_counts[1] += np.bincount(flat[~on], minlength=n)

    def frame(self, camera: str, t_us: int, image: np.ndarray) -> None:
        self._guard(self._frame, camera, t_us, image)

    def _frame(self, camera: str, t_us: int, image: np.ndarray) -> None:
        cl = self._cams.get(camera)
        if cl is None:
            return
        if self._images_stopped:
            cl.evaluator.discard()
        self._events_image(camera, cl, t_us)
        result = cl.evaluator.frame(t_us, image)
        if result is not None:
            self._log_reconstruction(camera, result)

    def _events_image(self, camera: str, cl: _CameraLog, t_us: int) -> None:
        """At a frame: log the ON/OFF counts of the interval it closes (when one was being
        counted), and start counting the next one when a map period has passed."""
        if cl.event_counts is not None:
            counts, cl.event_counts = cl.event_counts, None
            h, w = cl.shape
            if self._image_budget(3 * h * w, camera):
                busy = counts[counts > 0]
                scale = max(1.0, float(np.percentile(busy, 99))) if busy.size else 1.0
                rgb = np.zeros((h, w, 3), np.uint8)
                rgb[..., 0] = np.clip(counts[0] * (255.0 / scale), 0, 255).reshape(h, w)
                rgb[..., 2] = np.clip(counts[1] * (255.0 / scale), 0, 255).reshape(h, w)
                self._set_time(t_us)
                self.rec.log(entity(camera, "events"), rr.Image(rgb))
            cl.last_events_t_us = t_us
            return
        if not self._images_stopped and (cl.last_events_t_us is None
                                         or t_us - cl.last_events_t_us >= self.map_period_us):
            cl.event_counts = np.zeros((2, cl.shape[0] * cl.shape[1]), np.int64)

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
                      "errors_total": status.get("errors_total"),
                      **self._truth_errors(camera, cal)}
            for name, v in values.items():
                if v is not None:
                    self.rec.log(entity(camera, "series", name), rr.Scalars([float(v)]))
        if cl.last_map_t_us is not None and t_us - cl.last_map_t_us < self.map_period_us:
            return
        n_maps = 4 + 2 * (camera in self.truth)  # c, b, their errors (and vs truth)
        if not self._image_budget(n_maps * (cal.contrast.size * 5) + cal.special.nbytes,
                                  camera):  # each a float32 map and a uint8 mask
            return
        cl.last_map_t_us = t_us
        self._log_maps(camera, cal)

    def _truth_errors(self, camera: str, cal: Calibration) -> dict[str, float]:
        """c and b mean absolute errors over the valid pixels, when the truth is known."""
        t = self.truth.get(camera)
        v = cal.valid
        if t is None or t[0].shape != cal.shape or not v.any():
            return {}
        return {"c_mae": float(np.mean(np.abs(cal.contrast[v] - t[0][v]))),
                "b_mae": float(np.mean(np.abs(cal.bias[v] - t[1][v])))}

    def _log_map(self, camera: str, name: str, values: np.ndarray, invalid: np.ndarray,
                 colormap: str, depth_range: tuple[float, float]) -> None:
        """One map and its mask of invalid pixels (drawn grey over it, not as data)."""
        self.rec.log(entity(camera, "maps", name), rr.DepthImage(
            np.where(invalid, np.float32(0), values).astype(np.float32), colormap=colormap,
            depth_range=depth_range))
        self.rec.log(entity(camera, "maps", name, "invalid"),
                     rr.SegmentationImage(invalid.astype(np.uint8), draw_order=10.0))

    def _log_maps(self, camera: str, cal: Calibration) -> None:
        v = cal.valid
        c_lo, c_hi = (np.percentile(cal.contrast[v], [2, 98]) if v.any() else (0.0, 0.5))
        b_abs = float(np.percentile(np.abs(cal.bias[v]), 98)) if v.any() else 0.1
        c_hi = max(float(c_hi), float(c_lo) + 1e-3)
        b_abs = max(b_abs, 1e-3)
        invalid = ~v
        self._log_map(camera, "contrast", cal.contrast, invalid, "viridis",
                      (float(c_lo), c_hi))
        self._log_map(camera, "bias", cal.bias, invalid, "cyantoyellow", (-b_abs, b_abs))
        for name, se in (("stderr_contrast", cal.stderr_contrast),
                         ("stderr_bias", cal.stderr_bias)):
            bad = invalid | ~np.isfinite(se)
            hi = float(np.percentile(se[~bad], 98)) if (~bad).any() else 1.0
            self._log_map(camera, name, np.where(bad, 0, se), bad, "magma",
                          (0.0, max(hi, 1e-6)))
        t = self.truth.get(camera)
        if t is not None and t[0].shape == cal.shape:
            for name, est, true in (("contrast_error", cal.contrast, t[0]),
                                    ("bias_error", cal.bias, t[1])):
                err = np.abs(est - true)
                hi = float(np.percentile(err[v], 98)) if v.any() else 0.05
                self._log_map(camera, name, err, invalid, "magma", (0.0, max(hi, 1e-6)))
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


def write_review(path: str | Path, rec: Recording, cal: Calibration, *,
                 camera: str = "recording", truth: tuple[np.ndarray, np.ndarray] | None = None,
                 reconstruct: bool = True, frames_per_image: int = 5,
                 max_image_bytes: int = 300 << 20) -> Path:
    """An offline run's ``.rrd`` (``evcal calibrate --rrd``, ``evcal evaluate --rrd``): the
    calibration's maps, masks, standard errors and histograms (and error maps against
    ``truth``, the true c and b), then, with ``reconstruct``, the recording replayed through
    the service's own reconstruction (events integrated over ``frames_per_image`` frame
    intervals with the calibration and with DI, the reference frames, PSNR series and the
    ON/OFF events of every other interval). Returns the path written (never overwrites)."""
    from ..stream import frame_intervals  # noqa: PLC0415

    logger = RrdLogger(path, map_period_s=0.0, recon_period_s=0.0,
                       recon_frames=frames_per_image, scalar_period_s=0.0,
                       max_image_bytes=max_image_bytes,
                       truth={camera: truth} if truth is not None else None,
                       app_id="evcal-offline", started=f"evcal offline review: {camera}")
    try:
        t0 = (int(rec.frames.t_us[0]) if len(rec.frames)
              else int(rec.events["t_us"][0]) if rec.n_events else 0)
        logger.updated(camera, cal, t0, {})
        if reconstruct and len(rec.frames) >= 2:
            for k, chunk in frame_intervals(rec.events, rec.frames.t_us):
                logger.events(camera, chunk)
                logger.frame(camera, int(rec.frames.t_us[k]), rec.frames.images[k])
    finally:
        logger.close()
    if logger.stopped is not None:
        raise OSError(f"{logger.path}: {logger.stopped}")
    return logger.path


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
