"""``evcal query``: fetch a camera's current calibration (or status, or the camera list).

``--out CALIB.npz`` writes the same ``.npz`` layout as ``evcal calibrate`` (checked by
:func:`evcal.io.load_calibration` before it replaces the file). When several service
instances answer, the newest calibration (largest ``t_us``) wins.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from evcal.calibration import Calibration
from evcal.io import load_calibration
from evcal.io.calibfile import CalibrationFileError
from evcal.service import keys
from evcal.service.signing import SignatureError, Verifier, read_attachment
from evcal.service.transport import Reply, Transport, TransportError, options_from_args

from ..jsonable import strict_dumps
from .common import base_parser, camera_arg, fail


class QueryError(RuntimeError):
    """No service answered, or it answered with an error."""


def _errors(replies: list[Reply]) -> str:
    msgs = []
    for r in replies:
        if not r.ok:
            try:
                msgs.append(json.loads(r.payload)["message"])
            except (ValueError, KeyError, TypeError):
                msgs.append(r.payload.decode(errors="replace"))
    return "; ".join(msgs)


def _nobody(t: Transport, prefix: str, camera: str, key: str, timeout_s: float) -> str:
    """Why nothing answered: no service reachable, or services that do not know the camera."""
    try:
        alive = t.alive(keys.service_token_key(prefix), timeout_s=min(timeout_s, 2.0))
    except Exception:  # noqa: BLE001 - a diagnosis only
        alive = []
    if not alive:
        return (f"no service answered on {key} within {timeout_s:g} s and none is reachable "
                f"under {prefix!r} (is `evcal serve` running, with the same --prefix?)")
    names = ", ".join(sorted(a.rsplit("/", 1)[-1] for a in alive))
    return (f"{len(alive)} service instance(s) are running ({names}) but none has camera "
            f"{camera!r} (see `evcal query --list`)")


def fetch_calibration_npz(t: Transport, camera: str, *, prefix: str = "evcal",
                          timeout_s: float = 5.0, verifier: Verifier | None = None,
                          instance: str | None = None) -> tuple[bytes, dict[str, Any]]:
    """The ``.npz`` bytes of ``camera``'s calibration and its params (``t_us``, ...).

    Every answer names the service instance that sent it (the reply's attachment). With a
    ``verifier`` only answers signed with its key count (:mod:`evcal.service.signing`);
    with ``instance`` only that instance's. Answers of several instances that disagree are
    refused (:class:`QueryError`) unless ``instance`` says which to trust: a rogue
    queryable cannot win by claiming a newer calibration.
    """
    import io

    import numpy as np

    key = keys.camera_key(prefix, camera, "calibration")
    replies = t.get(f"{key}?format=npz", timeout_s=timeout_s)
    answers: dict[str, tuple[int, bytes, dict[str, Any]]] = {}
    refused: list[str] = []
    for r in replies:
        if not r.ok:
            continue
        if verifier is not None:
            try:
                who = verifier.verify(r.key, r.payload, r.attachment)
            except SignatureError as exc:
                refused.append(str(exc))
                continue
        else:
            who = str(read_attachment(r.attachment).get("instance", "?"))
        if instance is not None and who != instance:
            refused.append(f"an answer from instance {who!r}, not {instance!r}")
            continue
        try:
            with np.load(io.BytesIO(r.payload), allow_pickle=False) as z:
                params = json.loads(str(z["params_json"]))
        except Exception as exc:  # noqa: BLE001 - a malformed answer: refused, said why
            refused.append(f"a malformed answer from instance {who!r} ({exc})")
            continue
        params["instance"] = who
        t_us = int(params.get("t_us", -1))
        if who not in answers or t_us > answers[who][0]:
            answers[who] = (t_us, r.payload, params)
    if not answers:
        why = "; ".join(refused) or _errors(replies) or _nobody(t, prefix, camera, key,
                                                                 timeout_s)
        raise QueryError(why)
    if len(answers) > 1 and len({a[1] for a in answers.values()}) > 1:
        raise QueryError(f"{len(answers)} instances answer for {camera!r} with different "
                         f"calibrations ({', '.join(sorted(answers))}); pass --instance NAME "
                         "to say which to trust (and --verify KEY.pub to check it)")
    best = max(answers.values(), key=lambda a: a[0])
    return best[1], best[2]


def fetch_calibration(t: Transport, camera: str, *, prefix: str = "evcal",
                      timeout_s: float = 5.0, verifier: Verifier | None = None,
                      instance: str | None = None) -> Calibration:
    payload, _ = fetch_calibration_npz(t, camera, prefix=prefix, timeout_s=timeout_s,
                                       verifier=verifier, instance=instance)
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "calibration.npz"
        p.write_bytes(payload)
        return load_calibration(p)


def fetch_json(t: Transport, selector: str, *, timeout_s: float = 5.0) -> list[dict[str, Any]]:
    replies = t.get(selector, timeout_s=timeout_s)
    return [json.loads(r.payload) for r in replies if r.ok]


def save_npz_bytes(payload: bytes, out: Path) -> Calibration:
    """Check ``payload`` loads as a calibration, then atomically put it at ``out``."""
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=out.name + ".", suffix=".tmp.npz", dir=out.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(payload)
        cal = load_calibration(tmp)
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return cal


def build_parser():
    p = base_parser("evcal query", "Fetch a camera's current calibration from the service.")
    p.add_argument("--camera", type=camera_arg, help="camera id, e.g. lab/rig1/cam0")
    p.add_argument("--out", metavar="CALIB.npz", help="write the calibration here")
    p.add_argument("--status", action="store_true", help="print the camera's status (JSON)")
    p.add_argument("--list", action="store_true", help="list the cameras of every instance")
    p.add_argument("--timeout", type=float, default=5.0, metavar="S")
    p.add_argument("--verify", metavar="KEY.pub",
                   help="accept only calibrations signed with this Ed25519 public key "
                        "(the service's --sign-key); unsigned or forged answers are refused")
    p.add_argument("--instance", metavar="NAME",
                   help="accept only answers of this service instance (needed when several "
                        "instances disagree)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    prog = "evcal query"
    if not (args.list or (args.camera and (args.out or args.status))):
        return fail(prog, "give --camera ID with --out CALIB.npz and/or --status, or --list", 2)
    try:
        zopts = options_from_args(args)
        verifier = Verifier(args.verify) if args.verify else None
    except ValueError as exc:
        return fail(prog, str(exc), 2)
    try:
        with Transport(zopts) as t:
            if args.list:
                for info in fetch_json(t, keys.cameras_key(args.prefix), timeout_s=args.timeout):
                    print(strict_dumps(info, indent=2))
            if args.camera and args.status:
                key = keys.camera_key(args.prefix, args.camera, "status")
                found = fetch_json(t, key, timeout_s=args.timeout)
                if not found:
                    return fail(prog, f"no status on {key} within {args.timeout:g} s")
                for st in found:
                    print(strict_dumps(st, indent=2))
            if args.camera and args.out:
                payload, params = fetch_calibration_npz(t, args.camera, prefix=args.prefix,
                                                        timeout_s=args.timeout,
                                                        verifier=verifier,
                                                        instance=args.instance)
                cal = save_npz_bytes(payload, Path(args.out))
                print(f"{prog}: {args.camera}: {cal.shape[1]}x{cal.shape[0]} {cal.method} "
                      f"calibration at t_us={params.get('t_us')} from instance "
                      f"{params.get('instance')}{' (signature verified)' if verifier else ''}, "
                      f"{100 * cal.valid_fraction:.1f}% valid pixels -> {args.out}",
                      file=sys.stderr)
    except (QueryError, TransportError, CalibrationFileError) as exc:
        return fail(prog, str(exc))
    return 0


if __name__ == "__main__":
    sys.exit(main())
