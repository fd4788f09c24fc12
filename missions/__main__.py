"""``python -m missions`` runs the ``fimnav`` command line."""

import sys

from missions.cli import main

sys.exit(main())
