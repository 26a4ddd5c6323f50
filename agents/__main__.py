"""``python -m agents`` is the ``wiremap`` command."""

import sys

from agents.cli import main

sys.exit(main())
