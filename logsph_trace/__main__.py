"""``python -m logsph_trace ...`` is the ``logsph-trace`` command (see :mod:`logsph_trace.cli`)."""

import sys

from .cli import main

if __name__ == "__main__":
    sys.exit(main())
