"""MAVLink 2 signing on the planner's link: reading the key file, and telling the user what a
signing mismatch looks like (a vehicle with another key, or one that signs while we do not)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from comms.errors import UsageError
from comms.session import check_secret_file

#: A vehicle whose frames all fail our signature check for this long (wall s) and at least
#: :data:`WRONG_KEY_MIN_FRAMES` of them was set up with another key: refused at once.
WRONG_KEY_AFTER_S = 3.0
WRONG_KEY_MIN_FRAMES = 5


def read_signing_key(path: str | Path) -> bytes:
    """Read a MAVLink 2 signing key file: 32 raw bytes, or 64 hex digits (text).

    The key is a secret: a file that its group or others may read or write is refused
    (``chmod 600 FILE``), and the key itself never appears in a message.

    Raises:
        UsageError: missing or unreadable file, permissions too open, wrong length/content.
    """
    p = Path(path)
    check_secret_file(p, "signing key")
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise UsageError(f"signing key {str(p)!r}: {exc.strerror or exc}") from None
    if len(data) == 32:
        return data
    text = data.strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    raise UsageError(f"signing key {str(p)!r}: expected 32 raw bytes or 64 hex digits, found {len(data)} bytes")


def rejects_our_key(signing: Any) -> bool:
    """pymavlink's signing state (``mav.signing``) says the vehicle signs with another key: at
    least :data:`WRONG_KEY_MIN_FRAMES` frames failed our signature check, and none passed it."""
    return bool(signing.badsig_count >= WRONG_KEY_MIN_FRAMES and signing.goodsig_count == 0)


def wrong_key_message(target_system: int, elapsed_s: float, signing: Any) -> str:
    """Why vehicle ``target_system`` is refused: every frame for ``elapsed_s`` wall seconds
    carried a signature that does not match our key."""
    return (
        f"vehicle {target_system}: every frame from it for {elapsed_s:.0f} s "
        f"({signing.badsig_count} frames) carried a signature that does not match our signing key: "
        "the vehicle was set up with another key (check --signing-key / signing_key_file)"
    )


def signing_hint(have_key: bool, signing: Any, signed_seen: bool) -> str:
    """What a timeout's message adds about signing (empty: nothing to add): with our key, the
    vehicle's frames whose signature did not match; without one, that the vehicle signs.

    Args:
        have_key: we sign with a key.
        signing: pymavlink's signing state (``mav.signing``).
        signed_seen: a frame with a signature block was received.
    """
    if have_key and signing.badsig_count:
        return (
            f" ({signing.badsig_count} frames from the vehicle carried a signature that does not "
            "match our signing key: check that both use the same key)"
        )
    if not have_key and (signed_seen or signing.sig_count):
        return (
            " (the vehicle signs its messages: it probably refuses our unsigned ones; give the "
            "signing key with --signing-key or vehicles.overrides[i].signing_key_file)"
        )
    return ""
