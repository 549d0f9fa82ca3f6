"""``python -m kftune`` — the same as the ``kftune`` command."""

import sys

from kftune.cli import main

sys.exit(main())
