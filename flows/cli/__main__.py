"""``python -m flows.cli``: the ``weldrecon`` command line."""

import sys

from flows.cli import main

sys.exit(main())
