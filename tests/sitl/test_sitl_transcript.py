"""Real ArduPilot SITL still answers the differential-check ground station as recorded in
tests/data/ardupilot_sitl_4.5.5_transcript.json (the reference that
tests/vehicle_sim/test_vehicle_vs_ardupilot.py holds fimnav's vehicle to).

Needs FIMNAV_SITL_ARDUCOPTER and FIMNAV_SITL_ARDUCOPTER_DEFAULTS; skipped otherwise. To refresh
the recorded transcript (e.g. for another ArduPilot release)::

    python -m tests.sitl.record_transcript sitl --speedup 10 --out tests/data/ardupilot_sitl_4.5.5_transcript.json
"""

from __future__ import annotations

import json

import pytest

from tests.sitl import gcs_script
from tests.sitl.record_transcript import REFERENCE, record_sitl
from tests.sitl.sitl import sitl_config

_CFG, _REASON = sitl_config()

pytestmark = [pytest.mark.sitl, pytest.mark.integration, pytest.mark.skipif(_CFG is None, reason=_REASON)]

SPEEDUP = 10.0


def test_sitl_still_matches_the_recorded_transcript() -> None:
    ref = json.loads(REFERENCE.read_text(encoding="utf-8"))
    got = record_sitl(SPEEDUP)
    assert got["vehicle"]["version"] == ref["vehicle"]["version"], "another ArduPilot build: refresh the transcript"
    assert gcs_script.compare(ref, got) == []
    # SITL's own start-up: GUIDED-ready within 60 s of sim time, the EKF using GPS.
    assert got["readiness"]["guided_accepted_s"] < 60.0
    assert any(e.get("text", "").endswith("is using GPS") for e in got["readiness"]["timeline"])
