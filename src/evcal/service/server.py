"""The running service: :class:`~evcal.service.core.Service` wired to a zenoh session.

:func:`run` opens the session, restores snapshots, declares the subscribers, queryables and
the liveliness token, then ticks (status, snapshots) until ``stop`` is set; on the way out it
drains the camera queues, publishes a last status, writes the snapshots and finishes the
``.rrd``. Every resource is closed by a ``with`` block or ``finally``.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..errors import ErrorReason, EvcalError
from ..jsonable import strict_dumps
from . import keys
from .core import Service, ServiceConfig
from .gcpolicy import GcPolicy
from .outputs import error_reply
from .ros2 import (
    NODE_NAME,
    DistroDetector,
    DistroMismatch,
    Ros2Options,
    RosNode,
    RosRouter,
    distro,
    subscription_keys,
)
from .ros2out import RosCalibrationPublisher
from .signing import Signer
from .state import StateStore
from .transport import Request, Transport, ZenohOptions, intersects

log = logging.getLogger("evcal.service")


def _reply_error(req: Request, exc: EvcalError) -> None:
    req.reply_err(error_reply(exc))


def _publish_restored_images(service: Service, ros_out: RosCalibrationPublisher) -> None:
    """The restored calibrations as TRANSIENT_LOCAL images, for late ROS 2 subscribers."""
    for cam in list(service.cameras.values()):
        with cam.lock:
            cal, t_us = cam.state.current_calibration(), cam.state.calibration_t_us
        if cal is None:
            continue
        try:
            ros_out.publish_calibration(cam.id, cal, int(t_us or 0))
        except Exception as exc:  # a transport hiccup: counted, the start goes on
            service.publish_errors += 1
            log.warning("camera %s: cannot publish its restored images: %s", cam.id, exc)


def run(
    zenoh: ZenohOptions,
    config: ServiceConfig,
    *,
    stop: threading.Event,
    state_dir: str | Path | None = None,
    rrd: str | Path | None = None,
    rrd_options: dict[str, Any] | None = None,
    ready: Callable[[Service], None] | None = None,
    tick_s: float = 0.1,
    sign_key: str | Path | None = None,
    ros2: Ros2Options | None = None,
) -> Service:
    """Serve until ``stop`` is set; returns the (closed) service for its counters.

    With ``ros2`` the service is also a ROS 2 node over rmw_zenoh (:mod:`.ros2`): it takes
    EventPacket and Image topics as camera input and publishes each update as Images.

    Each camera's last calibration reaches late joiners: it is put on
    ``<prefix>/<camera>/calibration`` through a latched publisher (zenoh's advanced publisher
    cache; an advanced subscriber with history gets it when it joins, as ``evcal record``
    does), restored calibrations included, and its ROS 2 images are TRANSIENT_LOCAL.
    """
    store = StateStore(state_dir, max_pixels=config.max_pixels) if state_dir else None
    observer = None
    if rrd:
        from .rrdlog import RrdLogger  # rerun only when asked for

        observer = RrdLogger(rrd, **(rrd_options or {}))
    prefix = config.prefix.strip("/")
    try:
        with Transport(zenoh) as t:
            instance = config.instance or t.zid
            signer = Signer.from_file(instance, sign_key)
            node = ros_out = detector = None
            shard = config.shard
            if ros2 is not None:
                # the workers of `serve --workers N` are nodes /evcal_w0, /evcal_w1, ...
                node = RosNode(zid=t.zid, domain=ros2.domain,
                               name=(NODE_NAME if shard is None else f"{NODE_NAME}_w{shard[0]}"))
                if ros2.distro == "auto":
                    detector = DistroDetector(own_zid=t.zid)
                    profiles = detector.active
                else:
                    fixed = (distro(ros2.distro),)
                    profiles = lambda: fixed  # noqa: E731
                ros_out = RosCalibrationPublisher(node, t.put, t.token, session=t,
                                                  distros=profiles)

            def publish(key: str, payload: bytes, encoding: str, *,
                        attachment: bytes | None = None) -> None:
                # calibrations are latched: a subscriber with history joining later gets the
                # last one of each camera
                parsed = keys.split_camera_key(prefix, key)
                t.put(key, payload, encoding, attachment=attachment,
                      latest=parsed is not None and parsed[1] == "calibration")

            service = Service(config, publish, match=intersects, observer=observer,
                              store=store, instance=instance, signer=signer,
                              on_update=ros_out.publish if ros_out is not None else None)
            service.shm = t.shm
            restored = service.restore()
            claim = f"{prefix}/{config.cameras}"
            if restored:
                log.info("restored %d camera(s) from %s: %s", len(restored), state_dir,
                         ", ".join(restored))
                try:  # their calibrations into the latched publishers, for late joiners
                    for key, payload, enc in service.query_calibration(
                            f"{claim}/calibration", {}):
                        service.publish(key, payload, enc,
                                        attachment=service.attachment(key, payload))
                except EvcalError:
                    pass  # no restored camera had a calibration yet
                if ros_out is not None:
                    _publish_restored_images(service, ros_out)

            def on_calibration(req: Request) -> None:
                try:
                    replies = service.query_calibration(req.key, req.parameters)
                except EvcalError as exc:
                    _reply_error(req, exc)
                    return
                for key, payload, enc in replies:
                    req.reply(key, payload, enc, attachment=service.attachment(key, payload))

            def on_status(req: Request) -> None:
                for key, payload, enc in service.query_status(req.key):
                    req.reply(key, payload, enc)

            def on_cameras(req: Request) -> None:
                req.reply(keys.cameras_key(prefix), strict_dumps(service.cameras_info()).encode(),
                          keys.ENC_CAMERAS)

            def on_forget(req: Request) -> None:
                parsed = keys.split_camera_key(prefix, req.key)
                if parsed is None or parsed[1] != "forget":
                    req.reply_err(strict_dumps(
                        {"reason": str(ErrorReason.BAD_QUERY),
                         "message": "forget one camera: <prefix>/<camera>/forget"}))
                    return
                if not service.owns(parsed[0]):
                    return  # another shard's camera: its owner answers (and removes the file)
                found = service.forget(parsed[0])
                # nor do late joiners get its last calibration any more
                t.drop_latest(service.key(parsed[0], "calibration"))
                if ros_out is not None:
                    ros_out.forget(parsed[0])
                req.reply(req.key, strict_dumps({"camera": parsed[0], "forgotten": found,
                                                 "instance": service.instance}).encode(),
                          keys.ENC_STATUS)

            # a shard answers for some cameras of these keys only: not "complete", so that
            # a query with zenoh's default target reaches every shard
            complete = shard is None
            t.queryable(f"{claim}/calibration", on_calibration, complete=complete)
            t.queryable(f"{claim}/status", on_status, complete=complete)
            t.queryable(f"{claim}/forget", on_forget, complete=complete)
            t.queryable(keys.cameras_key(prefix), on_cameras, complete=complete)
            accept = service.accepts_key if shard is not None else None
            for kind in keys.INPUT_KINDS:
                t.subscribe(f"{claim}/{kind}", service.on_sample, accept=accept)
            router = None
            if ros2 is not None and node is not None:
                router = RosRouter(node, service.deliver, ros2.topic_map,
                                   owns=service.owns if shard is not None else None,
                                   detector=detector,
                                   distro=None if detector is not None else fixed[0])
                for key in subscription_keys(ros2.domain):
                    t.subscribe(key, router.on_sample, attachment=True,
                                accept=router.accepts if shard is not None else None)
                # auto: the tokens choose the profiles; an explicit distro: a warning when
                # the domain speaks the other style only
                watcher = (detector if detector is not None
                           else DistroMismatch(fixed[0], own_zid=t.zid))

                def on_token(key: str, alive: bool) -> None:
                    if alive:
                        watcher.seen_token(key)

                t.watch_alive(f"@ros2_lv/{ros2.domain}/**", on_token)
                t.token(node.node_token())
                log.info("ROS 2 node /%s in domain %d: EventPacket and Image topics in, "
                         "calibration images out (rmw_zenoh of %s)", node.name, ros2.domain,
                         ros2.distro if detector is None else "the tokens and samples seen")
            t.token(keys.service_token_key(prefix, instance.replace("/", "_")))
            log.info("evcal service %s up: prefix %s, cameras %s%s, on_full=%s", instance,
                     prefix, config.cameras,
                     f" (shard {shard[0]}/{shard[1]})" if shard is not None else "",
                     config.on_full)
            service.tick(force=True)
            gcp = GcPolicy()
            gcp.install()
            service.gc = gcp
            gcp.freeze()  # what start-up made lives as long as the process (see .gcpolicy)
            frozen_for: set[str] = set()
            if ready is not None:
                ready(service)
            try:
                while not stop.wait(tick_s):
                    service.tick()
                    # a camera's first update loaded its kernels and allocated its state
                    updated = {c.id for c in list(service.cameras.values())
                               if c.counters.updates}
                    if updated - frozen_for:
                        frozen_for |= updated
                        gcp.freeze()
                    if router is not None:
                        try:  # subscription tokens of new ROS 2 topics (never fatal)
                            router.declare_pending(t.token)
                        except Exception:
                            service.tick_errors += 1
                            log.exception("declaring ROS 2 subscription tokens failed")
            finally:
                log.info("shutting down: draining queues, saving state")
                gcp.uninstall()
                service.close()
    finally:
        if observer is not None:
            observer.close()
    return service
