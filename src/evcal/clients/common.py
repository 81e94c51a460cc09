"""Helpers shared by the clients: argument groups and camera-id checks."""

from __future__ import annotations

import argparse
import sys

from evcal.service import keys
from evcal.service.transport import add_zenoh_arguments


def base_parser(prog: str, description: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description=description)
    add_zenoh_arguments(p)
    p.add_argument("--prefix", default="evcal", help="key prefix (default: evcal)")
    return p


def fail(prog: str, message: str, code: int = 1) -> int:
    print(f"{prog}: {message}", file=sys.stderr)
    return code


def camera_arg(value: str) -> str:
    try:
        return keys.check_camera_id(value.strip("/"))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
