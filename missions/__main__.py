"""``python -m missions`` runs the ``fimnav`` command line."""

import sys

from missions.cli.main import main

sys.exit(main())
