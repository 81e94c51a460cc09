"""``evcal keygen`` (a key pair to sign calibrations) and ``evcal forget`` (drop a camera).

``evcal keygen --out service`` writes ``service.key`` (give it to ``evcal serve --sign-key``,
keep it private) and ``service.pub`` (give it to clients: ``evcal query --verify``).

``evcal forget --camera ID`` asks the service instances to drop that camera's state, in memory
and on disk (a camera replaced by another sensor under the same id, a test rig retired). In a
secured deployment only operators may query ``<prefix>/*/forget`` (docs/SECURITY.md).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence

from evcal.service import keys
from evcal.service.signing import SignatureError, generate_keys
from evcal.service.transport import Transport, TransportError, options_from_args

from ..clihelp import HelpFormatter
from .common import add_verbosity, base_parser, camera_arg, fail


def main_keygen(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="evcal keygen", formatter_class=HelpFormatter, description=(
        "Make an Ed25519 key pair: PREFIX.key for `evcal serve --sign-key`, PREFIX.pub for "
        "`evcal query --verify`."))
    p.add_argument("--out", required=True, metavar="PREFIX",
                   help="write PREFIX.key (mode 600) and PREFIX.pub; existing files are kept")
    add_verbosity(p)
    args = p.parse_args(argv)
    try:
        key, pub = generate_keys(args.out)
    except (SignatureError, OSError) as exc:
        return fail("evcal keygen", str(exc))
    if not args.quiet:
        print(f"evcal keygen: private key {key} (keep it secret), public key {pub}",
              file=sys.stderr)
    return 0


def main_forget(argv: Sequence[str] | None = None) -> int:
    p = base_parser("evcal forget", "Ask the service to drop a camera's state (memory and "
                                    "disk).")
    p.add_argument("--camera", required=True, type=camera_arg, help="camera id")
    p.add_argument("--timeout", type=float, default=5.0, metavar="S",
                   help="seconds to wait for the service's answer")
    args = p.parse_args(argv)
    prog = "evcal forget"
    try:
        zopts = options_from_args(args)
    except ValueError as exc:
        return fail(prog, str(exc), 2)
    key = keys.camera_key(args.prefix, args.camera, "forget")
    try:
        with Transport(zopts) as t:
            replies = t.get(key, timeout_s=args.timeout, wait_route=True)
    except TransportError as exc:
        return fail(prog, str(exc))
    answers = [json.loads(r.payload) for r in replies if r.ok]
    if not answers:
        return fail(prog, f"no service answered on {key} within {args.timeout:g} s")
    for a in answers:
        state = "forgotten" if a.get("forgotten") else "not known"
        print(f"{prog}: {a.get('camera')}: {state} by instance {a.get('instance')}",
              file=sys.stderr)
    return 0 if any(a.get("forgotten") for a in answers) else 1
