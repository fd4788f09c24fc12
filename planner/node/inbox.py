"""The planner node's Zenoh inbox: messages from Zenoh's callback threads handed to the node's
single thread through a queue, with a self-pipe that wakes its select(); and the checks every
message passes before the node sees it (decoding, sender id against the key expression)."""

from __future__ import annotations

import logging
import os
import queue
from collections import Counter
from typing import Any

from comms import keys
from comms.messages import MessageError, MessageKind, decode

log = logging.getLogger("fimnav.plan")


class Inbox:
    """Messages from Zenoh callbacks, handed to the node's single thread through a queue."""

    def __init__(self, mission_id: str, count: int) -> None:
        self.mission_id = mission_id
        self.count = count
        #: (kind, key expression, payload): kind "data", or "alive"/"gone" for a liveliness
        #: change (no payload: b"").
        self.queue: queue.SimpleQueue[tuple[str, str, bytes]] = queue.SimpleQueue()
        self.dropped: Counter[str] = Counter()
        # Self-pipe: a callback makes it readable so the node's select() wakes at once.
        self.wake_r, self.wake_w = os.pipe()
        os.set_blocking(self.wake_r, False)
        os.set_blocking(self.wake_w, False)

    def _put(self, item: tuple[str, str, bytes]) -> None:
        self.queue.put(item)
        try:
            os.write(self.wake_w, b"z")
        except (BlockingIOError, OSError):
            pass  # already readable (or closing)

    def on_sample(self, sample: Any) -> None:
        self._put(("data", str(sample.key_expr), bytes(sample.payload.to_bytes())))

    def on_liveliness(self, sample: Any) -> None:
        self._put(("alive" if str(sample.kind).endswith("PUT") else "gone", str(sample.key_expr), b""))

    def clear_wake(self) -> None:
        try:
            while os.read(self.wake_r, 4096):
                pass
        except (BlockingIOError, OSError):
            pass

    def close(self) -> None:
        for fd in (self.wake_r, self.wake_w):
            try:
                os.close(fd)
            except OSError:
                pass

    def decode(self, key: str, data: bytes) -> Any | None:
        """The message, or None (counted, warned) if it is invalid or spoofed."""
        try:
            header, msg = decode(data, self.mission_id, self.count)
        except MessageError as exc:
            reason = str(exc).split(":")[0][:60]
            self.dropped[reason] += 1
            log.warning("dropped message on %s: %s", key, exc)
            return None
        key_uav = keys.uav_of(key)
        sender = getattr(msg, "sender", None)
        if sender is not None and key_uav is not None and key_uav != sender:
            self.dropped["sender id does not match the key"] += 1
            log.warning("dropped message on %s: sender %s does not match the key expression", key, sender)
            return None
        if header.kind == MessageKind.MEASUREMENT and "/measurement/" not in key:
            self.dropped["measurement on a record key"] += 1
            return None
        if header.kind == MessageKind.RECORD and "/record/" not in key:
            self.dropped["record on another key"] += 1
            return None
        return msg
