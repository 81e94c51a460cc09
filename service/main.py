"""Run the evcal calibration service from a checkout: ``python service/main.py [ARGS]``.

The service's code is the package :mod:`evcal.service` (``src/evcal/service``); this launcher is
the same as ``evcal serve`` or ``python -m evcal.service`` once evcal is installed. The
container image (``docker/``) runs the installed ``evcal serve``.
"""

import sys

from evcal.service.cli import main

if __name__ == "__main__":
    sys.exit(main())
