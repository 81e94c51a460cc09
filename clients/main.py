"""Run an evcal client from a checkout: ``python clients/main.py replay|query|record|demo ARGS``.

The clients' code is the package :mod:`evcal.clients` (``src/evcal/clients``); this launcher is
the same as ``evcal replay|query|record|demo`` once evcal is installed.
"""

import sys

from evcal.cli import main

if __name__ == "__main__":
    if len(sys.argv) < 2 or sys.argv[1] not in ("replay", "query", "record", "demo"):
        print("usage: python clients/main.py replay|query|record|demo [ARGS]", file=sys.stderr)
        sys.exit(2)
    sys.exit(main(sys.argv[1:]))
