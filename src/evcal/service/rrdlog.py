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
    cameras/<cam>/maps/noise_rate_hz DepthImage: an events-only camera's events/s per pixel
                                     (in its tab, in place of the reference frame); its
                                     ``events`` and ``recon/calibrated``, ``recon/di`` are
                                     the events between two of its map logs, integrated
                                     with c P + b E and with 0.1 P (no frames)
    cameras/<cam>/series/<name>      Scalars: event_rate_hz, latency_ms, valid_fraction,
                                     psnr_calibrated_db, psnr_di_db, psnr_gain_db, errors,
                                     c_mae and b_mae (with the truth); each in a view of its
                                     own scale (rates, latencies, fractions, dB, errors)
    cameras/<cam>/log                TextLog: discovery, rejected inputs (rate-limited)

Timelines: ``sensor_time`` (the camera's t_us as a duration), ``sensor_clock`` (the same as
an absolute timestamp, for cameras whose t_us is Unix time, as ROS stamps are) and
``wall_time``. Sinks: the file, plus a gRPC server a viewer connects to (``serve_port``) or
a running viewer (``connect_url``).

The file is always a valid ``.rrd``: rerun's file sink writes into a pipe, and
:class:`RrdFile` appends what comes out to the file in whole messages (rerun's own sink,
writing to a full disk or past ``RLIMIT_FSIZE``, leaves the file cut mid-message and without
its footer, which ``rerun rrd verify`` refuses). Before each call, :class:`RrdLogger` checks
that the bytes the call may log, what rerun still holds and the footer (rerun's manifest of
every chunk) fit under the file-size limit and in the free space; when they do not, it stops
recording and lets rerun end the stream into the room it kept. That room is held on the disk
by an unlinked reserve file, so that another process filling the disk cannot take it.

File growth is bounded: maps and reconstructions at most once per ``map_period_s`` /
``recon_period_s`` of sensor time, and no more images once ``max_image_bytes`` were logged
(a warning says so in the file); scalars at most every ``scalar_period_s`` (tens of bytes
each). A blueprint with one tab per camera is stored in the file and re-sent when a camera
appears.
"""

from __future__ import annotations

import logging
import resource
import signal
import threading
import time
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from ..calibration import SPECIAL_LEGEND, Calibration, Special
from ..reconstruct import Reconstruction, StreamingEvaluator
from ..recording import Recording
from .rrdfile import RrdFile, StopReason, disk_free, free_path

log = logging.getLogger("evcal.service.rrdlog")

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


def camera_blueprint(camera: str, *, truth: bool = False, events_only: bool = False) -> Any:
    """One camera's tab. An events-only camera (calibrated by OffE) has no reference frame:
    its noise-rate map takes that view's place."""
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
        (rrb.Spatial2DView(origin=f"{base}/maps/noise_rate_hz",
                           name="noise rate (events/s per pixel)") if events_only
         else rrb.Spatial2DView(origin=f"{base}/recon/frame", name="reference frame")),
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


def make_blueprint(cameras: list[str], truth: Collection[str] | None = None,
                   events_only: Collection[str] = ()) -> Any:
    if not cameras:
        return rrb.Blueprint(rrb.TextLogView(origin="/service", name="service"),
                             collapse_panels=False)
    return rrb.Blueprint(rrb.Tabs(*[camera_blueprint(c, truth=c in (truth or ()),
                                                     events_only=c in events_only)
                                    for c in cameras]), collapse_panels=False)


@dataclass
class _CameraLog:
    shape: tuple[int, int]
    evaluator: StreamingEvaluator
    last_map_t_us: int | None = None
    last_scalar_t_us: int | None = None
    last_events_t_us: int | None = None  # the last events image
    method: str | None = None  # of the last calibration logged (offe, then onei)
    event_counts: np.ndarray | None = None  # [2, pixels] ON, OFF of the open interval


_NO_LIMIT = 1 << 62
_NO_LIMIT = 1 << 62
# Bounds of what rerun writes, measured on rerun-sdk 0.41 (1 to 24 cameras) with margins of
# 2x or more: the footer (its manifest has columns per entity and component) holds ~140 KiB
# per camera plus ~100 bytes per message and ~26 more per camera; a camera logs about 30
# entities (at most one pending message each when the stream ends); a row costs at most
# 3.7 KiB beyond its arrays' bytes (alone in its message, three timelines); the blueprint,
# re-sent when a camera appears, ~70 KiB per camera.
_FOOTER_BYTES = 64 << 10
_FOOTER_BYTES_PER_CAMERA = 256 << 10
_FOOTER_BYTES_PER_MESSAGE = 256
_FOOTER_BYTES_PER_MESSAGE_CAMERA = 64
_BLUEPRINT_BYTES_PER_CAMERA = 128 << 10
_ENTITIES_PER_CAMERA = 32
_ROW_BYTES = 8 << 10




def _file_size_limit() -> int:
    """The process's RLIMIT_FSIZE in bytes (a huge number when unlimited); read at each
    check, since ``prlimit`` can change it while the service runs."""
    soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    return _NO_LIMIT if soft == resource.RLIM_INFINITY or soft < 0 else int(soft)


def _ignore_sigxfsz() -> None:
    """Make a write past RLIMIT_FSIZE fail with EFBIG instead of killing the process. CPython
    ignores SIGXFSZ at start-up; a program embedding it may not, and only the main thread
    may change it."""
    sig = getattr(signal, "SIGXFSZ", None)
    if sig is None or signal.getsignal(sig) == signal.SIG_IGN:
        return
    if threading.current_thread() is not threading.main_thread():
        log.warning("SIGXFSZ is not ignored and the recorder was made outside the main thread: "
                    "a write past the file-size limit would kill the process")
        return
    signal.signal(sig, signal.SIG_IGN)


class RrdStream:
    """The ``.rrd`` of one run as rerun writes it, kept whole and within limits.

    It never overwrites a file (a restart writes ``run.1.rrd`` beside ``run.rrd``) and never
    fails the service. Before each call that logs (:meth:`_guard`), it checks that what the
    call may log, what rerun still holds and the footer fit under the process's file-size
    limit and in the free space (keeping ``min_free_bytes`` free); when they do not, or
    rerun raises, it logs why, finishes the file (a valid ``.rrd``, footer included) and
    stops recording: ``state()`` says why (``reason``). Finishing never takes longer than
    ``finish_timeout_s``. What is logged is its subclass's (:class:`RrdLogger`).
    """

    def __init__(self, path: str | Path, *, recording_id: str | None, min_free_bytes: int,
                 disk_free: Callable[[Path], int], max_unflushed_bytes: int,
                 finish_timeout_s: float, serve_port: int | None, connect_url: str | None,
                 app_id: str, started: str, default_blueprint: Any) -> None:
        self.requested_path = Path(path)
        self.path = free_path(self.requested_path)
        if self.path != self.requested_path:
            log.warning("%s exists: this run records to %s", self.requested_path, self.path)
        self.min_free_bytes = int(min_free_bytes)
        self._disk_free = disk_free
        # bytes logged since rerun was last flushed (an upper bound), and rerun's output then
        self.max_unflushed_bytes = int(max_unflushed_bytes)
        self._unflushed = 0
        self._flushed_at = 0
        self.finish_timeout_s = float(finish_timeout_s)
        self.stopped: str | None = None  # why recording stopped, None while it records
        self.reason: StopReason | None = None
        self.errors = 0
        self._finish_lock = threading.Lock()
        self._finished = False
        self._closed = False
        _ignore_sigxfsz()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = RrdFile(self.path)
        self.rec = rr.RecordingStream(app_id, recording_id=recording_id)
        sinks: list[Any] = [rr.FileSink(self._file.sink_path)]
        if serve_port is not None:  # a viewer connects: rerun --connect rerun+http://...
            sinks.append(rr.GrpcServerSink(port=int(serve_port)))
        if connect_url is not None:  # a running viewer
            sinks.append(rr.GrpcSink(connect_url))
        self.serve_port = serve_port
        try:
            self.rec.set_sinks(*sinks, default_blueprint=default_blueprint)
        except BaseException:
            self._file.sink_opened()
            self._file.wait(self.finish_timeout_s)
            self._file.close()
            if self._file.written == 0:
                self.path.unlink(missing_ok=True)
            raise
        self._file.sink_opened()
        if self._room_for(len(started) + _ROW_BYTES):
            self._set_time(None)
            self.rec.log("service", rr.TextLog(started, level="INFO"))

    def _n_cameras(self) -> int:
        """The cameras logged so far (the footer grows with each)."""
        return 0


    def _set_time(self, t_us: int | None) -> None:
        if t_us is not None:
            self.rec.set_time("sensor_time", duration=t_us * 1e-6)
            if t_us >= ABSOLUTE_T_US:  # a clock time (ROS stamps, jAER/Prophesee wall time)
                self.rec.set_time("sensor_clock", timestamp=t_us * 1e-6)
        self.rec.set_time("wall_time", timestamp=time.time())

    def state(self) -> dict[str, Any]:
        """Where and whether it records (for the service's ``cameras`` reply): ``reason`` is
        a :class:`StopReason` code once stopped, ``bytes`` the file's size, ``complete``
        whether the file has its footer (after the stop or the close)."""
        return {"path": str(self.path), "recording": self.stopped is None,
                "stopped": self.stopped,
                "reason": str(self.reason) if self.reason is not None else None,
                "errors": self.errors, "bytes": self._file.written, "complete": self._file.complete}

    def _footer_bytes(self, cameras: int) -> int:
        """An upper bound of what rerun writes when the stream of ``cameras`` cameras ends:
        the messages it may still batch (one per entity), the end message and the footer."""
        messages = self._file.messages + _ENTITIES_PER_CAMERA * (cameras + 1)
        per_message = _FOOTER_BYTES_PER_MESSAGE + _FOOTER_BYTES_PER_MESSAGE_CAMERA * cameras
        return _FOOTER_BYTES + _FOOTER_BYTES_PER_CAMERA * cameras + per_message * messages

    def _room_for(self, nbytes: int, *, new_camera: bool = False) -> bool:
        """Whether a call logging at most ``nbytes`` fits, with everything rerun may
        still write after it, under the file-size limit and in the free space (keeping
        ``min_free_bytes``), and the disk space for it is reserved; otherwise recording stops.
        Near the limit rerun is flushed first, so that only its real backlog counts. A new
        camera widens the footer of every message already written."""
        f = self._file
        if f.failure is not None:
            self.errors += 1
            self.stop(*f.failure)
            return False
        need = nbytes
        if self._held() + need > self.max_unflushed_bytes and not self._flush():
            return False
        while True:
            promised = (f.pending() + self._held() + need
                        + self._footer_bytes(self._n_cameras() + new_camera))
            limit = _file_size_limit()
            if f.received + promised > limit:
                why = (StopReason.FILE_SIZE_LIMIT,
                       f"{self.path} would pass the file-size limit of {limit} bytes "
                       f"(RLIMIT_FSIZE; {f.written} written): recording stopped, the file is "
                       "finished and readable")
            else:
                free = self._disk_free(self.path.parent)
                # min_free_bytes stay free once all that is promised is written; the reserve is
                # ours, and follows the promise (a disk others filled stops recording at once)
                if (free + f.reserved - promised >= self.min_free_bytes
                        and f.reserve(promised)):
                    self._unflushed += need
                    return True
                why = (StopReason.DISK_FULL,
                       f"the disk holding {self.path} has {max(0, free) >> 20} MiB free (and "
                       f"{f.reserved >> 10} KiB this recorder reserved), and recording on "
                       f"needs {promised >> 10} KiB while keeping "
                       f"{self.min_free_bytes >> 20} MiB free: recording stopped, the file is "
                       "finished and readable")
            if self._held() == 0:
                break
            if not self._flush():  # what rerun really holds, then judge again
                return False
        self.stop(*why)
        return False

    def _held(self) -> int:
        """An upper bound of the bytes rerun holds: those logged since the last flush less
        what it wrote since (in order: all of it came from those calls)."""
        f = self._file
        return max(0, self._unflushed - (f.received + f.pending() - self._flushed_at))

    def _flush(self) -> bool:
        """Flush rerun's batches into the file (bounded); a timeout stops recording."""
        try:
            self.rec.flush(timeout_sec=self.finish_timeout_s)
        except Exception as exc:  # noqa: BLE001 - rerun's timeout error has no public type
            self.errors += 1
            self.stop(StopReason.RERUN_ERROR, f"rerun did not flush within "
                      f"{self.finish_timeout_s:g} s ({exc}): recording stopped")
            return False
        self._unflushed = 0
        self._flushed_at = self._file.received + self._file.pending()
        return True

    def stop(self, reason: StopReason, message: str) -> None:
        """Stop recording for good, finishing the file (never raises)."""
        with self._finish_lock:
            if self.stopped is not None:
                return
            self.stopped, self.reason = message, reason
        log.error("rerun recording: %s", message)
        if self._file.failure is None:  # the file still takes messages: say why it ends
            try:
                self._set_time(None)
                self.rec.log("service", rr.TextLog(message, level="ERROR"))
            except Exception:  # noqa: BLE001, S110 - stopping anyway
                pass
        self._finish()

    def _finish(self) -> None:
        """Let rerun end the stream (its last batches, then the footer) and wait for that to
        reach the file, ``finish_timeout_s`` at most: shutdown never waits on a stuck disk."""
        with self._finish_lock:
            if self._finished:
                return
            self._finished = True
        deadline = time.monotonic() + self.finish_timeout_s

        def end() -> None:
            try:
                self.rec.flush(timeout_sec=self.finish_timeout_s)
                self.rec.disconnect()  # drops the file sink: it writes the footer and closes
            except Exception as exc:  # noqa: BLE001 - reported, the file is what it is
                self.errors += 1
                log.error("rerun recording: cannot finish %s: %s", self.path, exc)

        ender = threading.Thread(target=end, name="evcal-rrd-finish", daemon=True)
        ender.start()
        ender.join(self.finish_timeout_s)
        if not self._file.wait(deadline - time.monotonic()):
            self.errors += 1
            log.error("rerun recording: %s not finished within %g s; it ends at its last "
                      "whole message, without rerun's footer", self.path, self.finish_timeout_s)
        elif not self._file.complete and self._file.failure is None:
            self.errors += 1
            log.error("rerun recording: rerun ended %s without its footer", self.path)
        self._file.close()

    def _guard(self, nbytes: int | None, fn: Callable[..., None], *args: Any,
               new_camera: bool = False) -> None:
        """Run one observer call that logs at most ``nbytes`` (None: logs nothing)
        unless stopped or out of room; a failure stops recording, never the service."""
        if self.stopped is not None or self._closed:
            return
        if nbytes is None:
            if self._file.failure is not None:
                self.errors += 1
                self.stop(*self._file.failure)
                return
        elif not self._room_for(nbytes, new_camera=new_camera):
            return
        try:
            fn(*args)
        except Exception as exc:  # noqa: BLE001 - rerun errors
            self.errors += 1
            self.stop(StopReason.RERUN_ERROR,
                      f"recording failed ({type(exc).__name__}: {exc}); stopped")

    def close(self) -> None:
        """Flush and finish the file (footer included): the ``.rrd`` is complete after this,
        within ``finish_timeout_s``. Never raises."""
        if self._closed:
            return
        self._closed = True
        if self.stopped is not None:
            return  # already finished
        if self._file.failure is None:  # its room is in the footer's reserve
            try:
                self._set_time(None)
                self.rec.log("service", rr.TextLog("evcal service stopped", level="INFO"))
            except Exception:  # noqa: BLE001
                self.errors += 1
        self._finish()
        if self._file.failure is not None:
            self.stopped, self.reason = self._file.failure[1], self._file.failure[0]




class RrdLogger(RrdStream):
    """What a service run logs to its ``.rrd`` (the entities of the module docstring);
    implements :class:`evcal.service.core.Observer`. The file, its limits and its end are
    :class:`RrdStream`'s; the service's ``cameras`` reply shows :meth:`state`."""

    def __init__(self, path: str | Path, *, map_period_s: float = 2.0,
                 recon_period_s: float = 2.0, recon_frames: int = 5,
                 scalar_period_s: float = 0.2, max_image_bytes: int = 300 << 20,
                 max_recon_events: int = 5_000_000, recording_id: str | None = None,
                 min_free_bytes: int = 64 << 20,
                 disk_free: Callable[[Path], int] = disk_free,
                 max_unflushed_bytes: int = 4 << 20, finish_timeout_s: float = 3.0,
                 truth: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
                 serve_port: int | None = None, connect_url: str | None = None,
                 app_id: str = APP_ID, started: str = "evcal service started"):
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
        super().__init__(path, recording_id=recording_id, min_free_bytes=min_free_bytes,
                         disk_free=disk_free, max_unflushed_bytes=max_unflushed_bytes,
                         finish_timeout_s=finish_timeout_s, serve_port=serve_port,
                         connect_url=connect_url, app_id=app_id, started=started,
                         default_blueprint=make_blueprint([]))

    def _n_cameras(self) -> int:
        return len(self._cams)

    def state(self) -> dict[str, Any]:
        return super().state() | {"image_bytes": self.image_bytes}


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
            self._log_static(camera)
            self._send_blueprint()
            self.rec.log(entity(camera, "log"), rr.TextLog(
                f"camera {camera}: {shape[1]}x{shape[0]} sensor", level="INFO"))
        return cl

    def _send_blueprint(self) -> None:
        with self._lock:
            names = sorted(self._cams)
            events_only = {c for c, cl in self._cams.items() if cl.method == "offe"}
        self.rec.send_blueprint(make_blueprint(names, self.truth, events_only),
                                make_active=True, make_default=True)

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
        self._guard(None, self._events, camera, events)  # counted, logged at a frame

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
        cl = self._cams.get(camera)
        # at most the ON/OFF image (RGB), three reconstructions (uint8), three PSNRs, a warning
        nbytes = (None if cl is None else 3 * cl.shape[0] * cl.shape[1] + 3 * int(image.size)
                  + 8 * _ROW_BYTES)
        self._guard(nbytes, self._frame, camera, t_us, image)

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
                self._set_time(t_us)
                self._log_counts(camera, cl.shape, counts)
            cl.last_events_t_us = t_us
            return
        if not self._images_stopped and (cl.last_events_t_us is None
                                         or t_us - cl.last_events_t_us >= self.map_period_us):
            cl.event_counts = np.zeros((2, cl.shape[0] * cl.shape[1]), np.int64)

    def _log_counts(self, camera: str, shape: tuple[int, int], counts: np.ndarray) -> None:
        """The ON (red) / OFF (blue) counts ``[2, pixels]`` of an interval as one image."""
        h, w = shape
        busy = counts[counts > 0]
        scale = max(1.0, float(np.percentile(busy, 99))) if busy.size else 1.0
        rgb = np.zeros((h, w, 3), np.uint8)
        rgb[..., 0] = np.clip(counts[0] * (255.0 / scale), 0, 255).reshape(h, w)
        rgb[..., 2] = np.clip(counts[1] * (255.0 / scale), 0, 255).reshape(h, w)
        self.rec.log(entity(camera, "events"), rr.Image(rgb))

    def _events_only_review(self, camera: str, cl: _CameraLog, cal: Calibration) -> None:
        """An events-only camera (no frames to integrate between): the events since its
        previous maps, their ON/OFF image and their integration, with the calibration (the
        OffE model's log-intensity change ``c P + b E``, ``P`` the polarity sum and ``E`` the
        count of each pixel) and with DI (``0.1 P``), both on one scale around mid-grey; then
        counting starts again."""
        counts, cl.event_counts = cl.event_counts, np.zeros((2, cal.contrast.size), np.int64)
        if counts is None or not counts.any():
            return
        p = (counts[0] - counts[1]).reshape(cal.shape).astype(np.float64)
        e = (counts[0] + counts[1]).reshape(cal.shape).astype(np.float64)
        calibrated = cal.contrast * p + cal.bias * e
        di = 0.1 * p
        scale = max(float(np.percentile(np.abs(calibrated), 99)),
                    float(np.percentile(np.abs(di), 99)), 1e-6)
        self._log_counts(camera, cl.shape, counts)
        for name, img in (("calibrated", calibrated), ("di", di)):
            self.rec.log(entity(camera, "recon", name), rr.Image(
                np.clip(np.rint(127.5 + 127.5 * img / scale), 0, 255).astype(np.uint8)))

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

    def updated(self, camera: str, cal: Calibration, t_us: int, status: dict[str, Any],
                extra_maps: Mapping[str, np.ndarray] | None = None) -> None:
        # at most 6 series and a warning; when maps are due 6 float32 maps, their uint8 masks,
        # the special map, the extra maps (float32) and 2 histograms; for a new camera, or a
        # camera whose method changed, the blueprint (and a new camera's static rows)
        cl = self._cams.get(camera)
        extra = dict(extra_maps or {})
        maps = (cl is None or cl.last_map_t_us is None
                or t_us - cl.last_map_t_us >= self.map_period_us)
        events_only = status.get("method") == "offe"  # its events' image and integrations
        nbytes = ((7 + (15 + len(extra) + 3 * events_only) * maps) * _ROW_BYTES
                  + (31 + 4 * len(extra) + 5 * events_only) * int(cal.contrast.size) * maps)
        if cl is None:
            nbytes += 9 * _ROW_BYTES
        if cl is None or cl.method != status.get("method"):
            # a new events-only camera: the new camera's blueprint, then its method's
            nbytes += (_BLUEPRINT_BYTES_PER_CAMERA * (len(self._cams) + 1)
                       * (1 + (cl is None and status.get("method") == "offe")))
        self._guard(nbytes, self._updated, camera, cal, t_us, status, extra,
                    new_camera=cl is None)

    def _updated(self, camera: str, cal: Calibration, t_us: int, status: dict[str, Any],
                 extra_maps: dict[str, np.ndarray]) -> None:
        cl = self._camera(camera, cal.shape)
        cl.evaluator.calibration(cal)
        self._set_time(t_us)
        method = status.get("method")
        if isinstance(method, str) and method != cl.method:
            # an events-only camera is calibrated by OffE (c relative to its median) until
            # its first frame moves it to OnEI: the review must say which maps it sees
            if cl.method is not None or method != "onei":
                self.rec.log(entity(camera, "log"), rr.TextLog(
                    f"calibration by {method}" + (" (events only: c relative, median 0.1)"
                                                  if method == "offe" else ""),
                    level="INFO"))
            new_view = (method == "offe") != (cl.method == "offe")
            if cl.method == "offe":
                cl.event_counts = None  # counted for the events-only review: frames came
            cl.method = method
            if new_view:  # the noise-rate view replaces the reference frame's, or leaves
                self._send_blueprint()
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
        events_only = method == "offe"  # and its events: an RGB image, two uint8 images
        if not self._image_budget(n_maps * (cal.contrast.size * 5) + cal.special.nbytes
                                  + (4 * len(extra_maps) + 5 * events_only)
                                  * cal.contrast.size,
                                  camera):  # each a float32 map and a uint8 mask
            return
        cl.last_map_t_us = t_us
        self._log_maps(camera, cal)
        if events_only:
            self._events_only_review(camera, cl, cal)
        noise = extra_maps.get("noise_rate_hz")
        if noise is not None and noise.shape == cal.shape:
            # events/s per pixel: on a still scene the noise rate; the scale stops at the
            # 99th percentile, or a few hot pixels would leave the rest black
            hi = float(np.percentile(noise, 99)) if noise.size else 1.0
            self.rec.log(entity(camera, "maps", "noise_rate_hz"), rr.DepthImage(
                noise.astype(np.float32), colormap="inferno",
                depth_range=(0.0, max(hi, 1e-3))))

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
            # each bar as wide as its bin, on the map's own axis (without widths the viewer
            # draws every bar 1 unit wide: bins 0.007 apart overlap into one block)
            self.rec.log(entity(camera, "hist", name), rr.BarChart(
                counts.astype(np.float64), abscissa=0.5 * (edges[:-1] + edges[1:]),
                widths=np.diff(edges).astype(np.float32)))

    def discard(self, camera: str, dropped: int) -> None:
        """The service dropped ``dropped`` calls of ``camera`` (this recorder fell behind): an
        open reconstruction window misses events, so it is abandoned."""
        cl = self._cams.get(camera)
        if cl is not None:
            cl.evaluator.discard()
        self.note(camera, f"the recorder fell behind: {dropped} call(s) dropped (maps, "
                          "frames or events); the open reconstruction was abandoned")

    def note(self, camera: str, text: str, level: str = "WARN") -> None:
        # a TextLog row when the camera is known, nothing otherwise
        nbytes = 4 * len(text) + _ROW_BYTES if camera in self._cams else None
        self._guard(nbytes, self._note, camera, text, level)

    def _note(self, camera: str, text: str, level: str) -> None:
        if camera in self._cams:
            self._set_time(None)
            self.rec.log(entity(camera, "log"), rr.TextLog(text, level=level))



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
