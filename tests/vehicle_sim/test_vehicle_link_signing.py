"""MavlinkLink signing state and .tlog filtering, in memory (no sockets).

The reference is the MAVLink 2 signing rule written out here independently of the link: a
frame is accepted when its SHA-256 signature matches the key and its timestamp is newer
than the last one accepted for its stream (link id, system, component) on this link — from
whichever peer socket it came — or, for a new stream, at most one minute old.
"""

from __future__ import annotations

import struct
import time
from pathlib import Path
from typing import Any

from vehicle_sim.link import MavlinkLink, mavlink_module, signing_timestamp_now

from tests.vehicle_sim.memlink import MemoryTransport, Sink

KEY = bytes(range(100, 132))
MINUTE = 60 * 100_000  # signing timestamp units (10 µs)


def signed_frame(key: bytes, timestamp: int, *, sysid: int = 250, link_id: int = 0, mode: int = 4) -> bytes:
    """A COMMAND_LONG DO_SET_MODE frame signed with ``key`` at ``timestamp``."""
    m = mavlink_module()
    sink = Sink()
    enc = m.MAVLink(sink, srcSystem=sysid, srcComponent=190)
    enc.signing.secret_key = key
    enc.signing.sign_outgoing = True
    enc.signing.link_id = link_id
    enc.signing.timestamp = timestamp
    enc.command_long_send(1, 1, m.MAV_CMD_DO_SET_MODE, 0, 1, mode, 0, 0, 0, 0, 0)
    (frame,) = sink.frames
    return frame


def forge(frame: bytes, timestamp: int) -> bytes:
    """``frame`` with its signature timestamp replaced (the signature no longer matches)."""
    return frame[:-12] + timestamp.to_bytes(6, "little") + frame[-6:]


def link(tlog: Path | None = None) -> tuple[MavlinkLink, MemoryTransport]:
    t = MemoryTransport()
    return MavlinkLink(t, 1, 1, signing_key=KEY, tlog_path=None if tlog is None else str(tlog)), t


def accepted(lk: MavlinkLink, frame: bytes, peer: object) -> list[Any]:
    return [m for m in lk.parse(peer, frame) if m.get_type() == "COMMAND_LONG"]


def test_a_signed_frame_is_accepted_once_per_link_whatever_the_peer() -> None:
    lk, _ = link()
    now = signing_timestamp_now()
    first = signed_frame(KEY, now)
    assert len(accepted(lk, first, ("127.0.0.1", 40000))) == 1
    for peer in (("127.0.0.1", 40000), ("127.0.0.1", 40001), ("10.0.0.9", 40000), 7):
        assert accepted(lk, first, peer) == [], f"replay from {peer} accepted"
    # the genuine sender goes on, from its port or another one (its timestamps increase)
    assert len(accepted(lk, signed_frame(KEY, now + 1), ("127.0.0.1", 40001))) == 1
    assert len(accepted(lk, signed_frame(KEY, now + 2), ("127.0.0.1", 40000))) == 1
    # another stream (link id or system) has its own timestamps
    assert len(accepted(lk, signed_frame(KEY, now, link_id=3), ("127.0.0.1", 40002))) == 1
    assert len(accepted(lk, signed_frame(KEY, now, sysid=251), ("127.0.0.1", 40002))) == 1
    lk.close()


def test_a_forged_future_timestamp_does_not_lock_the_sender_out() -> None:
    """Without the key, a frame claiming a far-future timestamp is refused and not recorded
    (pymavlink 2.4.50 records the timestamp before checking the signature)."""
    lk, _ = link()
    now = signing_timestamp_now()
    genuine = signed_frame(KEY, now)
    assert accepted(lk, forge(genuine, now + 10**9), ("10.6.6.6", 666)) == []
    assert accepted(lk, signed_frame(bytes(32), now + 10**9), ("10.6.6.6", 667)) == []  # wrong key
    assert len(accepted(lk, genuine, ("127.0.0.1", 40000))) == 1
    assert lk.rx_signing.badsig_count == 2 and lk.rx_signing.goodsig_count == 1
    lk.close()


def test_a_new_stream_may_lag_one_minute_not_more() -> None:
    lk, _ = link()
    now = signing_timestamp_now()
    assert len(accepted(lk, signed_frame(KEY, now - MINUTE + 2 * 100_000, sysid=10), "a")) == 1  # 58 s old
    assert accepted(lk, signed_frame(KEY, now - MINUTE - 10 * 100_000, sysid=11), "a") == []  # 70 s old
    lk.close()


def test_our_timestamp_follows_the_newest_valid_one_received() -> None:
    lk, t = link()
    ahead = signing_timestamp_now() + 5 * MINUTE  # a ground station whose clock is ahead
    assert len(accepted(lk, signed_frame(KEY, ahead), "a")) == 1
    m = mavlink_module()
    lk.send(m.MAVLink_heartbeat_message(2, 3, 0, 0, 0, 3))
    sent = t.outbox[-1]
    assert int.from_bytes(sent[-12:-6], "little") >= ahead


def test_setup_signing_is_never_written_to_the_tlog(tmp_path: Path) -> None:
    tlog = tmp_path / "v.tlog"
    lk, _ = link(tlog)
    m = mavlink_module()
    sink = Sink()
    enc = m.MAVLink(sink, srcSystem=250, srcComponent=190)
    enc.signing.secret_key = KEY
    enc.signing.sign_outgoing = True
    enc.signing.timestamp = signing_timestamp_now()
    enc.setup_signing_send(1, 1, list(KEY), 0)
    enc.command_long_send(1, 1, m.MAV_CMD_DO_SET_MODE, 0, 1, 4, 0, 0, 0, 0, 0)
    got = [x.get_type() for f in sink.frames for x in lk.parse("gcs", f)]
    assert got == ["SETUP_SIGNING", "COMMAND_LONG"]  # the vehicle still receives it
    lk.send(m.MAVLink_setup_signing_message(250, 190, list(KEY), 0))  # and never logs what it sends
    lk.send(m.MAVLink_heartbeat_message(2, 3, 0, 0, 0, 3))
    lk.close()
    data = tlog.read_bytes()
    assert KEY not in data and KEY.hex().encode() not in data
    assert lk.frames_not_logged == 2
    # the reference: the other frames are in the log, as 8-byte time stamp + frame
    ids = []
    pos = 0
    parser = m.MAVLink(None)
    parser.signing.secret_key = KEY
    while pos < len(data):
        usec = struct.unpack(">Q", data[pos:pos + 8])[0]
        assert abs(usec / 1e6 - time.time()) < 600
        length = data[pos + 9]
        sig = 13 if data[pos + 10] & 1 else 0
        frame = data[pos + 8: pos + 8 + 12 + length + sig]
        ids.append(parser.decode(bytearray(frame)).get_type())
        pos += 8 + len(frame)
    assert ids == ["COMMAND_LONG", "HEARTBEAT"]
