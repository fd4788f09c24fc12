"""Real ArduPilot SITL still answers the differential-check ground station as recorded in
tests/data/ardupilot_sitl_4.5.5_transcript.json (the reference that
tests/vehicle_sim/test_vehicle_vs_ardupilot.py holds fimnav's vehicle to).

Needs FIMNAV_SITL_ARDUCOPTER and FIMNAV_SITL_ARDUCOPTER_DEFAULTS; skipped otherwise, and skipped
(naming both versions) when that build is another ArduPilot version than the recorded one: the
transcript is the recording of one release. To refresh the recorded transcript (e.g. for
another ArduPilot release)::

    python -m tests.sitl.record_transcript sitl --speedup 10 --out tests/data/ardupilot_sitl_4.5.5_transcript.json
"""

from __future__ import annotations

import json

import pytest

from tests.sitl import gcs_script
from tests.sitl.record_transcript import REFERENCE, _version, record_sitl
from tests.sitl.sitl import sitl_config

_CFG, _REASON = sitl_config()

pytestmark = [pytest.mark.sitl, pytest.mark.integration, pytest.mark.skipif(_CFG is None, reason=_REASON)]

SPEEDUP = 10.0


def test_sitl_still_matches_the_recorded_transcript() -> None:
    assert _CFG is not None
    ref = json.loads(REFERENCE.read_text(encoding="utf-8"))
    recorded, built = ref["vehicle"]["version"], _version(_CFG.binary)
    if built != recorded:
        pytest.skip(f"the transcript records {recorded}, the SITL build is {built}: another release (record its own transcript to compare)")
    got = record_sitl(SPEEDUP)
    assert got["vehicle"]["version"] == recorded
    assert gcs_script.compare(ref, got) == []
    # SITL's own start-up: GUIDED-ready within 60 s of sim time, the EKF using GPS.
    assert got["readiness"]["guided_accepted_s"] < 60.0
    assert any(e.get("text", "").endswith("is using GPS") for e in got["readiness"]["timeline"])
