"""Record a PX4 ground-station transcript (tests/sitl/gcs_script_px4.py) of real PX4 SITL (SIH)
or of ``fimnav vehicle --flavour px4``, and print the vehicle's differences from the recorded
PX4 transcript.

    FIMNAV_SITL_PX4=.../bin/px4 FIMNAV_SITL_PX4_ETC=.../etc \\
        python -m tests.sitl.record_transcript_px4 px4 --speedup 5 --out tests/data/px4_sitl_1.15_transcript.json
    python -m tests.sitl.record_transcript_px4 vehicle --out /tmp/vehicle.json

Both run on loopback, in a temporary directory, and stop what they started.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

from tests.sitl import gcs_script_px4
from tests.sitl.px4 import px4_config, start_px4
from tests.support.proc import Proc

ROOT = Path(__file__).resolve().parents[2]

#: The recorded PX4 transcript (test data: a measurement, not PX4's code).
REFERENCE = ROOT / "tests" / "data" / "px4_sitl_1.15_transcript.json"
#: Home of the recording: ArduPilot's CMAC field, fimnav's default origin (lat, lon deg, m AMSL).
CMAC = (-35.363261, 149.165230, 584.0)
#: fimnav vehicle: not ready for this long (sim s), as PX4 SIH is for about 37 s.
VEHICLE_READY_AFTER_S = 35.0


def record_px4(speedup: float, log: Any = None) -> dict[str, Any]:
    """Start PX4 SIH (environment variables), fly the sequence, stop PX4; the transcript."""
    cfg, reason = px4_config()
    if cfg is None:
        raise SystemExit(reason)
    with tempfile.TemporaryDirectory(prefix="fimnav-px4-") as tmp, start_px4(cfg, Path(tmp) / "px4", home=CMAC, speed=speedup) as inst:
        try:
            return gcs_script_px4.run_sequence(inst.offboard, speedup=speedup, log=log, vehicle={
                "kind": "px4_sitl", "version": "PX4 1.15 (release/1.15, SIH, airframe 10040 sihsim_quadx)",
                "home": "CMAC -35.363261,149.165230,584", "link": "offboard (Onboard mode, 14580+N -> 14540+N)"})
        except gcs_script_px4.SequenceError as exc:
            raise RuntimeError(f"{exc}\nPX4 console:\n{inst.log_tail()}") from exc


def vehicle_argv(speedup: float) -> list[str]:
    """``fimnav vehicle`` as the differential check runs it (PX4 flavour, CMAC origin, not
    ready for :data:`VEHICLE_READY_AFTER_S`, ephemeral loopback UDP port)."""
    return [sys.executable, "-m", "missions.cli.main", "vehicle", "--flavour", "px4", "--sysid", "1", "--mavlink", "udpin:127.0.0.1:0",
            "--speedup", f"{speedup:g}", "--ready-after", f"{VEHICLE_READY_AFTER_S:g}", "--log-level", "WARNING"]


def record_vehicle(speedup: float, log: Any = None) -> dict[str, Any]:
    """Start ``fimnav vehicle --flavour px4``, fly the sequence, stop it; the transcript."""
    p = Proc(vehicle_argv(speedup), cwd=str(ROOT))
    try:
        m = p.expect(r'"mavlink": "udpin:127\.0\.0\.1:(\d+)"', timeout_s=30)
        return gcs_script_px4.run_sequence(f"udpout:127.0.0.1:{m.group(1)}", speedup=speedup, log=log,
                                           vehicle={"kind": "fimnav_vehicle", "flavour": "px4"})
    finally:
        p.stop()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("target", choices=["px4", "vehicle"])
    ap.add_argument("--speedup", type=float, default=5.0)
    ap.add_argument("--out", default="-")
    a = ap.parse_args(argv)

    def log(s: str) -> None:
        print(s, file=sys.stderr, flush=True)

    tr = record_px4(a.speedup, log) if a.target == "px4" else record_vehicle(a.speedup, log)
    text = json.dumps(tr, indent=1, sort_keys=True) + "\n"
    if a.out == "-":
        sys.stdout.write(text)
    else:
        Path(a.out).write_text(text, encoding="utf-8")
    if REFERENCE.exists() and a.target == "vehicle":
        for d in gcs_script_px4.compare(json.loads(REFERENCE.read_text()), tr):
            print("DIFF", d, file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
