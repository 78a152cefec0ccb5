"""MAVLink 2 signing helpers shared by the bridge node and the simulator's emulated autopilot
(no rclpy): the key file format and a stricter signature check than pymavlink's.

MAVLink 2 signing (mavlink.io "Message signing"): a signed packet sets incompat_flags bit 0x01
and ends with link_id (1 byte), timestamp (6 bytes, 10 µs units since 2015-01-01) and
signature = SHA-256(secret_key + header + payload + CRC + link_id + timestamp)[:6].
"""

from __future__ import annotations

import hashlib

from deckland_common.params import ParameterError


def load_signing_key(path: str) -> bytes:
    """The 32-byte MAVLink 2 signing secret from ``path`` (32 raw bytes, or 64 hex characters
    with optional surrounding whitespace); ParameterError naming ``signing_key_file`` if not.

    The same key must be provisioned on the autopilot (see the package README, "Signing"):
    with a key, the bridge signs everything it sends *and* drops every unsigned or wrongly
    signed message it receives (pymavlink without ``allow_unsigned_callback``).
    """
    try:
        with open(path, 'rb') as f:
            raw = f.read()
    except OSError as exc:
        raise ParameterError(f"parameter 'signing_key_file': cannot read {path!r}: {exc}") \
            from exc
    if len(raw) == 32:
        return raw   # raw bytes are never stripped: 0x09-0x0d and 0x20 are valid key bytes
    text = raw.strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text.decode('ascii'))
        except ValueError:
            pass
    raise ParameterError("parameter 'signing_key_file': need 32 raw bytes or 64 hex "
                         f'characters, got {len(raw)} bytes')


def verify_signature_first(mav) -> None:
    """Make ``mav`` (a pymavlink ``MAVLink`` object with a signing key) check the signature
    *before* its replay protection records the packet's timestamp.

    pymavlink's ``check_signature`` stores a new (link id, system, component) stream's
    timestamp and only then compares the hash, so one forged packet with a far-future
    timestamp makes every genuine packet of that stream "old" until the clock catches up
    (denial of service from anyone on the link). With this wrapper a packet whose
    SHA-256(key + packet[:-6])[:6] does not match is refused without touching the stream
    state; genuine packets go through pymavlink's own check unchanged (timestamps, replay).
    """
    original = mav.check_signature

    def check_signature(msgbuf, src_system, src_component):
        key = mav.signing.secret_key
        if key is None or len(msgbuf) < 13:
            return False
        if hashlib.sha256(bytes(key) + bytes(msgbuf[:-6])).digest()[:6] != bytes(msgbuf[-6:]):
            return False
        return original(msgbuf, src_system, src_component)

    mav.check_signature = check_signature


__all__ = ['load_signing_key', 'verify_signature_first']
