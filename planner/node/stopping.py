"""What a planner tells its vehicle when it stops early (docs/in-the-field.md, "When fimnav
stops"): the mission's ``on_stop`` state, commanded and confirmed within a bounded wait.

A planner stops early on Ctrl-C, SIGTERM or SIGHUP (however the command caught the signal: the
node only sees the exception it raised), on a fatal error, or when ``fimnav launch`` stops it.
Its vehicle is then told the mission's ``on_stop``: ``hold`` (the autopilot's pilot-friendly
hold: ArduPilot LOITER, PX4 AUTO.LOITER), ``land`` (LAND, AUTO.LAND) or ``rtl`` (RTL,
AUTO.RTL), and the planner waits up to :data:`ON_STOP_TIMEOUT_S` for the heartbeat that
confirms it. Nothing is commanded to a vehicle a pilot flies (taken over), to a disarmed one,
or over a lost link (the autopilot's own failsafe keeps control). SIGKILL leaves no such
chance: the autopilot's own failsafe acts (ArduPilot GUID_TIMEOUT, PX4's offboard loss).
"""

from __future__ import annotations

import logging
import time
from typing import Literal

from comms.mavlink_client import LinkError, VehicleLink
from planner.node.io import NodeIO
from planner.node.takeover import TakeoverWatch

log = logging.getLogger("fimnav.plan")

#: The mission's ``on_stop`` values.
OnStop = Literal["hold", "land", "rtl"]

#: Wall seconds a stopping planner waits for its vehicle to acknowledge the on_stop mode (half)
#: and to show it in a heartbeat (half): inside the 5 s a signalled ``fimnav`` command has for
#: its clean-up, and the 5 s ``fimnav launch`` gives its children before SIGKILL.
ON_STOP_TIMEOUT_S: float = 4.0


def stop_reason(exc: BaseException) -> str:
    """Why the planner stops, for the log: the signal (``SIGINT`` for KeyboardInterrupt, the
    name a SIGTERM/SIGHUP exception carries) or the error's message."""
    if isinstance(exc, KeyboardInterrupt):
        return "SIGINT"
    text = str(exc)
    return text if text.startswith("SIG") else f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def on_stop_mode(link: VehicleLink, action: OnStop) -> str:
    """The mode that carries ``action`` on the link's autopilot (its profile's hold, land or
    RTL mode: LOITER/AUTO.LOITER, LAND/AUTO.LAND, RTL/AUTO.RTL)."""
    profile = link.profile
    custom = {"hold": profile.hold_mode, "land": profile.land_mode, "rtl": profile.rtl_mode}[action]
    return profile.require_mode(custom).qualified_name


def command_on_stop(io: NodeIO, takeover: TakeoverWatch, action: OnStop, reason: str, timeout_s: float = ON_STOP_TIMEOUT_S) -> dict[str, object]:
    """Tell the vehicle the mission's ``on_stop`` state and wait (at most ``timeout_s`` wall s)
    for its heartbeat in that mode; log the outcome in one line and return it
    (``{"action", "commanded", "confirmed", "mode"?, "reason"?}``). Never raises for a
    vehicle that refuses or does not answer: the planner is stopping anyway."""
    uav = io.config.uav
    link = io.link
    outcome: dict[str, object] = {"action": action, "commanded": False, "confirmed": False}
    why_not = None
    if link is None or link.telemetry.heartbeats == 0:
        why_not = "no vehicle heard"
    elif link.lost:
        why_not = (
            f"the vehicle link is lost (no heartbeat for {link.link_age_s():.1f} s); its failsafe keeps control: {link.profile.link_loss_failsafe}"
        )
    elif takeover.active:
        why_not = f"taken over ({link.mode_name()}): left to the pilot"
    elif not link.telemetry.armed:
        why_not = f"the vehicle is disarmed ({link.mode_name()})"
    if why_not is not None or link is None:
        outcome["reason"] = why_not
        quiet = link is None or link.telemetry.heartbeats == 0 or not link.telemetry.armed
        (log.info if quiet else log.warning)("uav %d: stopping (%s): on_stop %s not commanded: %s", uav, reason, action, why_not)
        return outcome
    mode = on_stop_mode(link, action)
    t0 = time.monotonic()
    try:
        pos = link.telemetry.position_enu_m
        if pos is not None and link.streaming:
            # Until the vehicle confirms, hold where it is (PX4 leaves OFFBOARD on a gap).
            hold = pos.astype(float)
            link.set_stream(lambda _t: (hold, None))
        outcome["commanded"] = True
        link.set_mode(mode, timeout_s=timeout_s / 2, ack_timeout_s=timeout_s / 2)
    except (LinkError, OSError) as exc:
        outcome["reason"] = str(exc)
        log.error("uav %d: stopping (%s): told the vehicle %s (on_stop %s), not confirmed within %g s: %s", uav, reason, mode, action, timeout_s, exc)
        return outcome
    finally:
        link.set_stream(None)
    outcome.update(confirmed=True, mode=mode)
    log.warning(
        "uav %d: stopping (%s): the vehicle is in %s (on_stop %s), confirmed %.2f s after the command",
        uav,
        reason,
        mode,
        action,
        time.monotonic() - t0,
    )
    return outcome
