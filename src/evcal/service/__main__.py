"""``python -m evcal.service ...`` is ``evcal serve ...``."""

import sys

from .cli import main_serve

if __name__ == "__main__":
    sys.exit(main_serve(sys.argv[1:]))
