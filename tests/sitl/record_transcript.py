"""Record a ground-station transcript (tests/sitl/gcs_script.py) of real ArduPilot SITL or of
``fimnav vehicle``, and print its differences from the recorded SITL transcript.

    FIMNAV_SITL_ARDUCOPTER=.../arducopter FIMNAV_SITL_ARDUCOPTER_DEFAULTS=.../copter.parm \\
        python -m tests.sitl.record_transcript sitl --speedup 10 --out tests/data/ardupilot_sitl_4.5.5_transcript.json
    python -m tests.sitl.record_transcript vehicle --out /tmp/vehicle.json

Both run on loopback, on free ports, in a temporary directory, and stop what they started.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

from tests.sitl import gcs_script
from tests.sitl.sitl import sitl_config, start_sitl
from tests.support.proc import Proc

ROOT = Path(__file__).resolve().parents[2]

#: The recorded SITL transcript (test data: a measurement, not ArduPilot's code).
REFERENCE = ROOT / "tests" / "data" / "ardupilot_sitl_4.5.5_transcript.json"
#: fimnav vehicle: not ready for this long (sim s), as SITL is for about 40 s.
VEHICLE_READY_AFTER_S = 30.0


def record_sitl(speedup: float, log: Any = None) -> dict[str, Any]:
    """Start SITL (environment variables), fly the sequence, stop SITL; the transcript."""
    cfg, reason = sitl_config()
    if cfg is None:
        raise SystemExit(reason)
    with tempfile.TemporaryDirectory(prefix="fimnav-sitl-") as tmp, start_sitl(cfg, Path(tmp), speedup=speedup) as inst:
        version = _version(cfg.binary)
        try:
            return gcs_script.run_sequence(inst.address, speedup=speedup, log=log, vehicle={
                "kind": "ardupilot_sitl", "version": version, "model": "+", "defaults": cfg.defaults.name,
                "home": "CMAC -35.363261,149.165230,584,353"})
        except gcs_script.SequenceError as exc:
            raise RuntimeError(f"{exc}\nSITL console:\n{inst.log_tail()}") from exc


def _version(binary: Path) -> str:
    """ArduCopter's version string from the binary (``ArduCopter V4.5.5``), or ``unknown``."""
    data = binary.read_bytes()
    i = data.find(b"ArduCopter V")
    if i < 0:
        return "unknown"
    j = i
    while j < len(data) and 32 <= data[j] < 127:
        j += 1
    return data[i:j].decode("ascii").split(" (")[0]


def vehicle_argv(speedup: float) -> list[str]:
    """``fimnav vehicle`` as the differential check runs it (ArduPilot flavour, CMAC origin,
    not ready for :data:`VEHICLE_READY_AFTER_S`, ephemeral loopback TCP port)."""
    return [sys.executable, "-m", "missions.cli.main", "vehicle", "--sysid", "1", "--mavlink", "tcpin:127.0.0.1:0",
            "--speedup", f"{speedup:g}", "--ready-after", f"{VEHICLE_READY_AFTER_S:g}", "--log-level", "WARNING"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("target", choices=["sitl", "vehicle"])
    ap.add_argument("--speedup", type=float, default=10.0)
    ap.add_argument("--out", default="-")
    a = ap.parse_args(argv)

    def log(s: str) -> None:
        print(s, file=sys.stderr, flush=True)

    if a.target == "sitl":
        tr = record_sitl(a.speedup, log)
    else:
        p = Proc(vehicle_argv(a.speedup), cwd=str(ROOT))
        try:
            m = p.expect(r'"mavlink": "tcpin:127\.0\.0\.1:(\d+)"', timeout_s=30)
            tr = gcs_script.run_sequence(f"tcp:127.0.0.1:{m.group(1)}", speedup=a.speedup, log=log,
                                         vehicle={"kind": "fimnav_vehicle", "flavour": "ardupilot"})
        finally:
            p.stop()
    text = json.dumps(tr, indent=1, sort_keys=True) + "\n"
    if a.out == "-":
        sys.stdout.write(text)
    else:
        Path(a.out).write_text(text, encoding="utf-8")
    if REFERENCE.exists() and a.target == "vehicle":
        for d in gcs_script.compare(json.loads(REFERENCE.read_text()), tr):
            print("DIFF", d, file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
