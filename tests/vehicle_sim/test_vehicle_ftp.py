"""MAVLink FTP is not simulated, but every request is answered at once (MAVLink FTP spec:
NAK = opcode 129 with the error code in data[0]; ACK = 128) so ground stations fall back to the
parameter protocol without waiting for their FTP timeout."""

from __future__ import annotations

from tests.vehicle_sim.memlink import decode_all, gcs_encoder, memory_vehicle


def _request(opcode: int, seq: int = 7, session: int = 3) -> list[int]:
    body = seq.to_bytes(2, "little") + bytes([session, opcode, 0, 0, 0, 0]) + bytes(4)
    return list(body + bytes(251 - len(body)))


def test_ftp_requests_get_nak_or_ack():
    v, mem = memory_vehicle()
    enc, sink = gcs_encoder()
    for opcode in (4, 2, 9):  # OpenFileRO, ResetSessions, CalcFileCRC32
        enc.file_transfer_protocol_send(0, 1, 1, _request(opcode))
    for f in sink.frames:
        mem.inject(f)
    mem.outbox.clear()
    v.advance_to(0.0)
    replies = [m for m in decode_all(mem.outbox) if m.get_type() == "FILE_TRANSFER_PROTOCOL"]
    assert len(replies) == 3
    got = [(bytes(r.payload)[3], bytes(r.payload)[5], bytes(r.payload)[12], int.from_bytes(bytes(r.payload)[0:2], "little"))
           for r in replies]
    assert got[0] == (129, 4, 10, 8)  # NAK FileNotFound, seq + 1
    assert got[1][:2] == (128, 2)  # ACK
    assert got[2][:3] == (129, 9, 7)  # NAK UnknownCommand
    assert all(r.target_system == 255 for r in replies)
