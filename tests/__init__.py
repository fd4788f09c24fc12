"""fimnav's tests, a regular package: every test module and helper is imported as
``tests.<directory>.<module>``, by pytest and by the scripts run with ``python -m tests.…``.

pymavlink chooses MAVLink 1 or 2 when it is first imported, from ``MAVLINK20`` in the
environment: it is set here, before any test module or test script can import pymavlink.
"""

import os

os.environ["MAVLINK20"] = "1"
