"""``evcal query``: fetch a camera's current calibration (or status, or the camera list).

``--out CALIB.npz`` writes the same ``.npz`` layout as ``evcal calibrate`` (checked by
:func:`evcal.io.load_calibration` before it replaces the file).

Which answers count (docs/SECURITY.md): with ``--verify KEY.pub`` those signed with that key;
by default, trust on first use: the first signed answer accepted pins its key for the prefix
(:class:`~evcal.service.signing.KnownServices`, ``--known-keys``), unsigned answers are
ignored when a signed one comes or a key is pinned, and an answer signed with another key
than the pinned one fails the query. Only a service that never signed (no ``--sign-key``, no
pin) is taken unsigned, and ``--insecure`` takes unsigned answers whatever was pinned. Answers
that disagree are refused unless ``--instance`` says which to trust.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from evcal.calibration import Calibration
from evcal.io import load_calibration
from evcal.io.calibfile import CalibrationFileError
from evcal.posterior import estimate_of
from evcal.service import keys
from evcal.service.signing import (
    KnownServices,
    SignatureError,
    Verifier,
    read_attachment,
)
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


@dataclass(frozen=True)
class _Answer:
    instance: str
    key_id: str | None  # the key that signed it (checked), None: unsigned
    payload: bytes
    params: dict[str, Any]


def fetch_calibration_npz(t: Transport, camera: str, *, prefix: str = "evcal",
                          timeout_s: float = 5.0, verifier: Verifier | None = None,
                          instance: str | None = None, known: KnownServices | None = None,
                          estimate: str | None = None) -> tuple[bytes, dict[str, Any]]:
    """The ``.npz`` bytes of ``camera``'s calibration and its params (``t_us``,
    ``instance``, and ``trust``: how the answer was checked).

    Every answer names the service instance that sent it (the reply's attachment). With a
    ``verifier`` only answers signed with its key count (:mod:`evcal.service.signing`).
    With ``known`` (and no ``verifier``) trust on first use: a key pinned for ``prefix``
    acts as the verifier, and an answer signed with any other key fails the query (someone
    else signs in the service's name, or its key was replaced); with nothing pinned, signed
    answers (checked against the key they carry) outrank unsigned ones, which are then
    ignored, and their key is pinned. With ``instance`` only that instance's answers count.
    ``estimate``: ``"raw"`` or ``"posterior"`` maps (None: those the service publishes).
    Answers that disagree are refused (:class:`QueryError`): a rogue queryable cannot win
    by claiming a newer calibration, nor by naming the genuine instance.
    """
    import io

    import numpy as np

    key = keys.camera_key(prefix, camera, "calibration")
    selector = f"{key}?format=npz" + (f";estimate={estimate}" if estimate else "")
    replies = t.get(selector, timeout_s=timeout_s, wait_route=True)
    pinned = known.get(prefix) if known is not None and verifier is None else None
    check = verifier or pinned
    answers: list[_Answer] = []
    refused: list[str] = []
    foreign: list[str] = []  # signed with another key than the pinned one
    first_use: dict[str, Verifier] = {}  # nothing pinned: the keys the answers carry
    for r in replies:
        if not r.ok:
            continue
        body = read_attachment(r.attachment)
        who, signed_by = str(body.get("instance", "?")), None
        if check is not None:
            try:
                who = check.verify(r.key, r.payload, r.attachment)
            except SignatureError as exc:
                refused.append(str(exc))
                if pinned is not None and isinstance(body.get("sig"), bytes) and \
                        body.get("key_id") != pinned.key_id:
                    foreign.append(f"{exc} (from instance {who!r})")
                continue
            signed_by = check.key_id
        elif known is not None and isinstance(body.get("sig"), bytes):
            if not isinstance(body.get("pub"), bytes):
                refused.append(f"the answer on {r.key} from instance {who!r} is signed but "
                               "carries no public key to pin (a service older than this "
                               "client): pass --verify KEY.pub")
                continue
            try:
                own = Verifier.from_raw(body["pub"])
                who = own.verify(r.key, r.payload, r.attachment)
            except SignatureError as exc:
                refused.append(str(exc))
                continue
            first_use[own.key_id] = own
            signed_by = own.key_id
        if instance is not None and who != instance:
            refused.append(f"an answer from instance {who!r}, not {instance!r}")
            continue
        try:
            with np.load(io.BytesIO(r.payload), allow_pickle=False) as z:
                params = json.loads(str(z["params_json"]))
        except Exception as exc:  # noqa: BLE001 - a malformed answer: refused, said why
            refused.append(f"a malformed answer from instance {who!r} ({exc})")
            continue
        answers.append(_Answer(who, signed_by, r.payload, params))
    if foreign and known is not None and pinned is not None:
        raise QueryError(
            f"{'; '.join(foreign)}: key {pinned.key_id} is pinned for prefix {prefix!r} in "
            f"{known.path}. Someone else answers in the service's name, or its key was "
            f"replaced: if you replaced it, delete the entry for {prefix!r} from that file "
            "(or pass --verify NEW.pub)")
    if first_use:
        if len(first_use) > 1:
            raise QueryError(f"answers for {camera!r} are signed with {len(first_use)} "
                             f"different keys ({', '.join(sorted(first_use))}) and none is "
                             f"pinned for prefix {prefix!r} yet: pass --verify KEY.pub with "
                             "the service's public key (its --sign-key's .pub)")
        unsigned = [a for a in answers if a.key_id is None]
        refused += [f"an unsigned answer from instance {a.instance!r} (the service signs)"
                    for a in unsigned]
        answers = [a for a in answers if a.key_id is not None]
    if not answers:
        why = "; ".join(refused) or _errors(replies) or _nobody(t, prefix, camera, key,
                                                                 timeout_s)
        if refused and pinned is not None and known is not None:
            why += (f" (key {pinned.key_id} is pinned for prefix {prefix!r} in {known.path}; "
                    "--insecure takes unsigned answers)")
        raise QueryError(why)
    by_instance: dict[str, _Answer] = {}
    for a in answers:
        seen = by_instance.setdefault(a.instance, a)
        if seen.payload != a.payload:
            raise QueryError(f"two answers claim instance {a.instance!r} for {camera!r} with "
                             "different calibrations: someone answers in its name; pass "
                             "--verify KEY.pub (the service's --sign-key) to tell them apart")
    if len(by_instance) > 1 and len({a.payload for a in answers}) > 1:
        raise QueryError(f"{len(by_instance)} instances answer for {camera!r} with different "
                         f"calibrations ({', '.join(sorted(by_instance))}); pass --instance "
                         "NAME to say which to trust (and --verify KEY.pub to check it)")
    best = max(answers, key=lambda a: int(a.params.get("t_us", -1)))
    params = {**best.params, "instance": best.instance}
    if verifier is not None:
        params["trust"] = f"signature verified (key {verifier.key_id})"
    elif pinned is not None:
        params["trust"] = f"signed with the key pinned for {prefix!r} ({pinned.key_id})"
    elif best.key_id is not None and known is not None:
        known.pin(prefix, first_use[best.key_id], best.instance)
        params["trust"] = (f"signed; key {best.key_id} pinned for {prefix!r} on first use in "
                           f"{known.path}")
    else:
        params["trust"] = "unsigned: anyone on the network could have sent it"
    return best.payload, params


def fetch_calibration(t: Transport, camera: str, *, prefix: str = "evcal",
                      timeout_s: float = 5.0, verifier: Verifier | None = None,
                      instance: str | None = None, known: KnownServices | None = None
                      ) -> Calibration:
    payload, _ = fetch_calibration_npz(t, camera, prefix=prefix, timeout_s=timeout_s,
                                       verifier=verifier, instance=instance, known=known)
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "calibration.npz"
        p.write_bytes(payload)
        return load_calibration(p)


def fetch_json(t: Transport, selector: str, *, timeout_s: float = 5.0,
               wait_route: bool = True) -> list[dict[str, Any]]:
    """The JSON replies on ``selector``; ``wait_route``: a session that has just connected
    first waits until it knows a queryable there (:meth:`Transport.wait_route`)."""
    replies = t.get(selector, timeout_s=timeout_s, wait_route=wait_route)
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


def format_instances(infos: list[dict[str, Any]]) -> str:
    """The replies on ``<prefix>/cameras`` as a short table: a row per camera (an instance
    without cameras, a supervisor of workers, gets one row of its own), with its sensor,
    updates, events and the sensor time of its last calibration."""
    head = ("instance", "pid", "camera", "sensor", "updates", "events", "last calibration t_us")
    rows: list[tuple[str, ...]] = []
    for info in sorted(infos, key=lambda d: (not d.get("supervisor"), str(d.get("instance")))):
        name = str(info.get("instance", "?"))
        if info.get("supervisor"):
            name += " (supervisor)"
        elif info.get("shard"):
            name += f" (shard {info['shard']})"
        pid = str(info.get("pid", "?"))
        cams = info.get("cameras") or []
        if not cams:
            rows.append((name, pid, "-", "", "", "", ""))
        for c in cams:
            t = c.get("last_update_t_us")
            rows.append((name, pid, str(c.get("id")), str(c.get("sensor") or "-"),
                         str(c.get("updates", "")), f"{c.get('events', 0):,}",
                         "-" if t is None else str(t)))
    widths = [max(len(r[i]) for r in (head, *rows)) for i in range(len(head))]
    lines = ["  ".join(v.ljust(w) for v, w in zip(r, widths, strict=True)).rstrip()
             for r in (head, *rows)]
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    p = base_parser("evcal query", "Fetch a camera's current calibration from the service.")
    p.add_argument("--camera", type=camera_arg, help="camera id, e.g. lab/rig1/cam0")
    p.add_argument("--out", metavar="CALIB.npz", help="write the calibration here")
    p.add_argument("--estimate", choices=("raw", "posterior"), default=None,
                   help="with --out: each pixel's own estimate (raw) or the posterior maps, "
                        "pulled toward the sensor's population (default: whichever the "
                        "service publishes; serve --posterior publishes the posterior)")
    p.add_argument("--status", action="store_true", help="print the camera's status (JSON)")
    p.add_argument("--list", action="store_true",
                   help="a table of every instance and its cameras (--json: the whole replies)")
    p.add_argument("--json", action="store_true",
                   help="with --list: print every instance's reply as JSON (its counters too)")
    p.add_argument("--timeout", type=float, default=5.0, metavar="S",
                   help="seconds to wait for the answers")
    trust = p.add_mutually_exclusive_group()
    trust.add_argument("--verify", metavar="KEY.pub",
                       help="accept only calibrations signed with this Ed25519 public key "
                            "(the service's --sign-key); unsigned or forged answers are "
                            "refused")
    trust.add_argument("--known-keys", metavar="FILE",
                       help="the service keys pinned on first use (default: "
                            "$XDG_STATE_HOME/evcal/known_services): once a signed answer "
                            "was accepted, only answers signed with its key count")
    trust.add_argument("--insecure", action="store_true",
                       help="accept unsigned answers even from a service whose key is "
                            "pinned (and pin nothing)")
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
        known = None if args.verify or args.insecure else KnownServices(args.known_keys)
    except ValueError as exc:
        return fail(prog, str(exc), 2)
    try:
        with Transport(zopts) as t:
            if args.list:
                infos = fetch_json(t, keys.cameras_key(args.prefix), timeout_s=args.timeout)
                if args.json:
                    for info in infos:
                        print(strict_dumps(info, indent=2))
                elif infos:
                    print(format_instances(infos))
                else:
                    return fail(prog, f"no service answered on "
                                      f"{keys.cameras_key(args.prefix)} within "
                                      f"{args.timeout:g} s")
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
                                                        instance=args.instance, known=known,
                                                        estimate=args.estimate)
                cal = save_npz_bytes(payload, Path(args.out))
                print(f"{prog}: {args.camera}: {cal.shape[1]}x{cal.shape[0]} {cal.method} "
                      f"({estimate_of(cal)} maps) "
                      f"calibration at t_us={params.get('t_us')} from instance "
                      f"{params.get('instance')} ({params['trust']}), "
                      f"{100 * cal.valid_fraction:.1f}% valid pixels -> {args.out}",
                      file=sys.stderr)
    except (QueryError, TransportError, CalibrationFileError, SignatureError) as exc:
        return fail(prog, str(exc))
    return 0


if __name__ == "__main__":
    sys.exit(main())
