"""Helpers shared by the clients: argument groups and camera-id checks."""

from __future__ import annotations

import argparse
import sys

from evcal.service import keys
from evcal.service.transport import add_zenoh_arguments

from ..clihelp import HelpFormatter


class _Verbosity(argparse.Action):
    """-v / -q of the clients: stderr logging is set as the flag is parsed, so every client
    honours it without code of its own."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: object, option_string: str | None = None) -> None:
        from evcal.service.cli import setup_logging

        if self.dest == "quiet":
            namespace.quiet = True
        else:
            namespace.verbose = (getattr(namespace, "verbose", 0) or 0) + 1
        setup_logging(getattr(namespace, "verbose", 0) or 0, getattr(namespace, "quiet", False))


def add_verbosity(p: argparse.ArgumentParser) -> None:
    p.add_argument("-v", "--verbose", action=_Verbosity, nargs=0, default=0,
                   help="more detail on stderr (-vv: debug)")
    p.add_argument("-q", "--quiet", action=_Verbosity, nargs=0, default=False,
                   help="errors only on stderr")


def base_parser(prog: str, description: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description=description,
                                formatter_class=HelpFormatter)
    add_zenoh_arguments(p)
    p.add_argument("--prefix", default="evcal", help="key prefix (default: evcal)")
    add_verbosity(p)
    return p


def fail(prog: str, message: str, code: int = 1) -> int:
    print(f"{prog}: {message}", file=sys.stderr)
    return code


def camera_arg(value: str) -> str:
    try:
        return keys.check_camera_id(value.strip("/"))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
