"""CMUcam5 Pixy (v1) block protocol: incremental parser and encoder (pure, no rclpy).

The Pixy v1 "data out" words (16-bit little-endian, over UART or one frame per UDP datagram
from the simulator): a frame is ``SYNC block+`` or ``SYNC ZERO ZERO``, a block ``SYNC checksum
sig x y w h`` (``SYNC_CC`` + angle for colour codes), checksum the 16-bit sum of the fields.
Pixel coordinates are delivered unaltered (x right 0..319, y down 0..199: the ``x_cam``,
``y_cam`` of (29)-(30)). On a stream a frame is complete only when the next double sync
arrives (one frame period late); each frame carries ``end_offset`` for arrival stamping
(:mod:`pixy_driver.arrival`). Wire format, resync and latency: the package README.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
import math
import struct

from deckland_common.contract import PixyBlock

__all__ = [
    'ANGLE_MAX_DEG',
    'ANGLE_MIN_DEG',
    'HEIGHT_MAX_PX',
    'MAX_CC_SIGNATURE',
    'MAX_SIGNATURE',
    'SYNC',
    'SYNC_CC',
    'SYNC_X',
    'WIDTH_MAX_PX',
    'X_MAX_PX',
    'Y_MAX_PX',
    'ParserParams',
    'PixyBlock',
    'PixyFrame',
    'PixyParser',
    'block_checksum',
    'block_in_range',
    'encode_block',
    'encode_frame',
]

SYNC = 0xAA55
SYNC_CC = 0xAA56
SYNC_X = 0x55AA  # a sync word read one byte out of step
X_MAX_PX = 319
Y_MAX_PX = 199
WIDTH_MAX_PX = 320
HEIGHT_MAX_PX = 200
MAX_SIGNATURE = 7  # normal blocks: signatures 1..7
MAX_CC_SIGNATURE = 0o77777  # colour codes: 2..5 octal digits, each 1..7
ANGLE_MIN_DEG = -180
ANGLE_MAX_DEG = 180

_SYNC_BYTES = b'\x55\xaa'
_SYNC_WORD = struct.pack('<H', SYNC)
_SYNC_CC_WORD = struct.pack('<H', SYNC_CC)
_NO_DATA = b'\x00\x00\x00\x00'
_BODY = struct.Struct('<6H')  # checksum, signature, x, y, width, height
_BODY_CC = struct.Struct('<7H')  # ... + angle (two's complement)
_NORMAL_LEN = _BODY.size  # 12 bytes after the sync word
_CC_LEN = _BODY_CC.size  # 14 bytes after the sync word

# parser states
_HUNT = 0  # searching for the byte pair 55 aa
_GOT_SYNC = 1  # one sync word consumed: frame marker or a block's sync, decided by the next word
_BODY_N = 2  # a normal block body follows
_BODY_C = 3  # a colour-code block body follows
_EXPECT = 4  # between blocks (or idle): a sync word or a no-data marker must follow


@dataclass(frozen=True, slots=True)
class ParserParams:
    """Parser limits.

    max_blocks_per_frame: blocks kept per frame; further ones are counted in ``overflow``
        (the Pixy Arduino library keeps at most 130).
    """

    max_blocks_per_frame: int = 130

    def __post_init__(self) -> None:
        v = self.max_blocks_per_frame
        if not isinstance(v, int) or isinstance(v, bool) or not 1 <= v <= 10_000:
            raise ValueError(f'ParserParams.max_blocks_per_frame must be an int in '
                             f'[1, 10000], got {v!r}')


@dataclass(frozen=True, slots=True)
class PixyFrame:
    """One Pixy frame as parsed.

    seq: frames emitted by this parser before this one (0, 1, 2, ...).
    blocks: accepted blocks in wire order (checksum-valid and in range).
    angles_deg: per block, the colour-code angle in degrees, or None for a normal block.
    end_offset: stream offset (bytes fed since construction) just past the frame's last byte.
    closed_by: 'next_frame' (the next double sync), 'no_data' (two zero words) or 'flush'.
    """

    seq: int
    blocks: tuple[PixyBlock, ...]
    angles_deg: tuple[int | None, ...]
    end_offset: int
    closed_by: str


def block_checksum(signature: int, x: int, y: int, width: int, height: int,
                   angle_deg: int | None = None) -> int:
    """16-bit wrapping sum of the block's words (the angle as its two's-complement word)."""
    s = signature + x + y + width + height
    if angle_deg is not None:
        s += angle_deg & 0xFFFF
    return s & 0xFFFF


def _cc_signature_ok(sig: int) -> bool:
    if not 0o11 <= sig <= MAX_CC_SIGNATURE:
        return False
    while sig:
        if sig & 7 == 0:
            return False
        sig >>= 3
    return True


def block_in_range(signature: int, x: int, y: int, width: int, height: int,
                   angle_deg: int | None = None) -> bool:
    """Field ranges of a Pixy v1 block (x 0..319, y 0..199, w 1..320, h 1..200).

    Normal blocks have signature 1..7; colour codes have 2..5 octal digits each 1..7 and an
    angle in [-180, 180] degrees.
    """
    if not (0 <= x <= X_MAX_PX and 0 <= y <= Y_MAX_PX and 1 <= width <= WIDTH_MAX_PX
            and 1 <= height <= HEIGHT_MAX_PX):
        return False
    if angle_deg is None:
        return 1 <= signature <= MAX_SIGNATURE
    return ANGLE_MIN_DEG <= angle_deg <= ANGLE_MAX_DEG and _cc_signature_ok(signature)


def encode_block(signature: int, x: int, y: int, width: int, height: int,
                 angle_deg: int | None = None, *, checksum: int | None = None) -> bytes:
    """Bytes of one block including its sync word, unchecked (fault injection welcome).

    ``checksum`` overrides the correct one. Fields are taken modulo 2**16.
    """
    if checksum is None:
        checksum = block_checksum(signature, x, y, width, height, angle_deg)
    words = [checksum & 0xFFFF, signature & 0xFFFF, x & 0xFFFF, y & 0xFFFF, width & 0xFFFF,
             height & 0xFFFF]
    if angle_deg is None:
        return _SYNC_WORD + _BODY.pack(*words)
    return _SYNC_CC_WORD + _BODY_CC.pack(*words, angle_deg & 0xFFFF)


def _block_fields(block) -> tuple[int, int, int, int, int, int | None]:
    if isinstance(block, (tuple, list)):
        if len(block) not in (5, 6):
            raise ValueError(f'a block tuple is (sig, x, y, w, h[, angle_deg]), got {block!r}')
        angle = block[5] if len(block) == 6 else None
        sig, x, y, w, h = block[:5]
    else:
        sig, x, y, w, h = (block.signature, block.x_px, block.y_px, block.width_px,
                           block.height_px)
        angle = getattr(block, 'angle_deg', None)
    try:
        out = tuple(math.floor(v + 0.5) for v in (sig, x, y, w, h))
        return (*out, None if angle is None else math.floor(angle + 0.5))
    except (OverflowError, ValueError, TypeError) as exc:
        raise ValueError(f'block fields must be finite numbers, got {block!r}') from exc


def encode_frame(blocks: Iterable, *, end_marker: bool = False) -> bytes:
    """The byte stream a Pixy sends for one frame.

    ``blocks`` holds tuples ``(sig, x, y, w, h)`` (normal) or ``(sig, x, y, w, h, angle_deg)``
    (colour code), or objects with ``signature, x_px, y_px, width_px, height_px`` (and
    optionally ``angle_deg``); coordinates are rounded to whole pixels. The result is the frame
    marker followed by each block with its sync word (so a non-empty frame starts with a double
    sync). An empty frame is the frame marker followed by the no-data marker (two zero words).
    ``end_marker=True`` appends the no-data marker to a non-empty frame too, so that a stream
    parser closes the frame without waiting for the next one.

    Raises ValueError when a block is out of range (the parser would drop it).
    """
    parts = [_SYNC_WORD]
    n = 0
    for block in blocks:
        fields = _block_fields(block)
        if not block_in_range(*fields):
            raise ValueError(f'block out of Pixy range (sig, x, y, w, h, angle) = {fields}')
        parts.append(encode_block(*fields))
        n += 1
    if n == 0 or end_marker:
        parts.append(_NO_DATA)
    return b''.join(parts)


class PixyParser:
    """Incremental Pixy v1 stream parser: bytes in any split, frames out.

    Guarantees: never raises from :meth:`feed`/:meth:`flush` (a non-bytes argument is counted
    in ``rejected['bad_input']``); every emitted block passed its checksum and the range check;
    memory is bounded (at most 15 buffered bytes between calls and ``max_blocks_per_frame``
    blocks in the open frame); the output does not depend on how the stream was split.

    Counters (ints): ``frames`` (emitted), ``blocks`` (accepted into frames), ``checksum_errors``,
    ``out_of_range`` (checksum-valid blocks with a field out of range), ``resyncs`` (times an
    unexpected word forced a search for the next sync word, e.g. 0x55aa), ``bytes_dropped``
    (bytes skipped while searching, including the body of a rejected block and leading
    garbage), ``orphan_blocks`` (valid blocks seen while no frame was open), ``overflow_blocks``
    (beyond ``max_blocks_per_frame``), ``bytes_in``.
    """

    def __init__(self, params: ParserParams | None = None) -> None:
        self.params = params if params is not None else ParserParams()
        self._max_blocks = self.params.max_blocks_per_frame
        self.frames = 0
        self.blocks = 0
        self.checksum_errors = 0
        self.out_of_range = 0
        self.resyncs = 0
        self.bytes_dropped = 0
        self.orphan_blocks = 0
        self.overflow_blocks = 0
        self.bad_input = 0
        self.bytes_in = 0
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget any partial data and the open frame (counters are kept)."""
        self._buf = bytearray()
        self._base = self.bytes_in  # stream offset of _buf[0]
        self._state = _HUNT
        self._frame: list | None = None  # open frame: list of PixyBlock
        self._angles: list = []
        self._frame_end = 0

    @property
    def buffered_bytes(self) -> int:
        """Bytes held back for the next call (bounded)."""
        return len(self._buf)

    @property
    def open_frame_blocks(self) -> int:
        """Blocks of the frame not yet emitted (0 when no frame is open)."""
        return 0 if self._frame is None else len(self._frame)

    @property
    def rejected(self) -> dict[str, int]:
        """What was thrown away, by reason."""
        return {'checksum': self.checksum_errors, 'out_of_range': self.out_of_range,
                'orphan': self.orphan_blocks, 'overflow': self.overflow_blocks,
                'bad_input': self.bad_input}

    def stats(self) -> dict[str, int]:
        """Every counter, for diagnostics."""
        return {'frames': self.frames, 'blocks': self.blocks,
                'checksum_errors': self.checksum_errors, 'out_of_range': self.out_of_range,
                'resyncs': self.resyncs, 'bytes_dropped': self.bytes_dropped,
                'orphan_blocks': self.orphan_blocks, 'overflow_blocks': self.overflow_blocks,
                'bad_input': self.bad_input, 'bytes_in': self.bytes_in}

    # ------------------------------------------------------------------ frames
    def _close(self, out: list, closed_by: str) -> None:
        if self._frame is None:
            return
        out.append(PixyFrame(self.frames, tuple(self._frame), tuple(self._angles),
                             self._frame_end, closed_by))
        self.frames += 1
        self._frame = None

    def _open(self, out: list, end: int) -> None:
        self._close(out, 'next_frame')
        self._frame = []
        self._angles = []
        self._frame_end = end

    # ------------------------------------------------------------------ input
    def feed(self, data: bytes) -> list[PixyFrame]:
        """Consume ``data``; return the frames completed by it (possibly none)."""
        if not isinstance(data, (bytes, bytearray, memoryview)):
            self.bad_input += 1
            return []
        out: list[PixyFrame] = []
        if not data:
            return out
        buf = self._buf
        buf += data
        self.bytes_in += len(data)
        n = len(buf)
        pos = 0
        state = self._state
        while True:
            if state == _EXPECT:
                if n - pos < 2:
                    break
                w = buf[pos] | (buf[pos + 1] << 8)
                if w == SYNC:
                    pos += 2
                    state = _GOT_SYNC
                elif w == SYNC_CC:
                    pos += 2
                    state = _BODY_C
                elif w == 0:
                    if n - pos < 4:
                        break
                    if buf[pos + 2] == 0 and buf[pos + 3] == 0:  # no data: frame over
                        pos += 4
                        self._close(out, 'no_data')
                    else:
                        self.resyncs += 1
                        self.bytes_dropped += 1
                        pos += 1
                        state = _HUNT
                else:  # e.g. 0x55aa: out of step; drop a byte and look for the sync pair
                    self.resyncs += 1
                    self.bytes_dropped += 1
                    pos += 1
                    state = _HUNT
            elif state == _BODY_N:
                if n - pos < _NORMAL_LEN:
                    break
                cs, sig, x, y, w, h = _BODY.unpack_from(buf, pos)
                if (sig + x + y + w + h) & 0xFFFF != cs:
                    self.checksum_errors += 1
                    state = _HUNT  # re-scan the body: a lost byte may have eaten a sync
                    continue
                pos += _NORMAL_LEN
                state = _EXPECT
                if (sig < 1 or sig > MAX_SIGNATURE or x > X_MAX_PX or y > Y_MAX_PX or w < 1
                        or w > WIDTH_MAX_PX or h < 1 or h > HEIGHT_MAX_PX):
                    self.out_of_range += 1
                    continue
                self._accept(PixyBlock(signature=sig, x_px=float(x), y_px=float(y),
                                        width_px=float(w), height_px=float(h)),
                             None, self._base + pos)
            elif state == _GOT_SYNC:
                if n - pos < 2:
                    break
                w = buf[pos] | (buf[pos + 1] << 8)
                if w == SYNC:  # double sync: the previous word was a frame marker
                    pos += 2
                    self._open(out, self._base + pos - 2)
                elif w == SYNC_CC:
                    pos += 2
                    self._open(out, self._base + pos - 2)
                    state = _BODY_C
                elif w == 0:
                    if n - pos < 4:
                        break
                    if buf[pos + 2] == 0 and buf[pos + 3] == 0:  # marker + no data: empty
                        self._close(out, 'next_frame')
                        self._frame = []
                        self._angles = []
                        self._frame_end = self._base + pos
                        pos += 4
                        self._close(out, 'no_data')
                        state = _EXPECT
                    else:
                        state = _BODY_N
                else:
                    state = _BODY_N
            elif state == _BODY_C:
                if n - pos < _CC_LEN:
                    break
                cs, sig, x, y, w, h, a = _BODY_CC.unpack_from(buf, pos)
                if (sig + x + y + w + h + a) & 0xFFFF != cs:
                    self.checksum_errors += 1
                    state = _HUNT
                    continue
                pos += _CC_LEN
                state = _EXPECT
                if a >= 0x8000:
                    a -= 0x10000
                if not block_in_range(sig, x, y, w, h, a):
                    self.out_of_range += 1
                    continue
                self._accept(PixyBlock(signature=sig, x_px=float(x), y_px=float(y),
                                        width_px=float(w), height_px=float(h)),
                             a, self._base + pos)
            else:  # _HUNT
                i = buf.find(_SYNC_BYTES, pos)
                if i < 0:
                    keep = n - 1 if (n > pos and buf[n - 1] == 0x55) else n
                    self.bytes_dropped += keep - pos
                    pos = keep
                    break
                self.bytes_dropped += i - pos
                pos = i + 2
                state = _GOT_SYNC
        self._state = state
        if pos:
            del buf[:pos]
            self._base += pos
        return out

    def _accept(self, block: PixyBlock, angle: int | None, end: int) -> None:
        frame = self._frame
        if frame is None:
            self.orphan_blocks += 1
        elif len(frame) >= self._max_blocks:
            self.overflow_blocks += 1
        else:
            frame.append(block)
            self._angles.append(angle)
            self._frame_end = end
            self.blocks += 1

    def flush(self) -> list[PixyFrame]:
        """End of stream (or of a datagram): emit the open frame, drop partial bytes.

        Returns at most one frame (closed_by 'flush'). The next bytes are parsed as a fresh
        stream: a frame must start with a double sync again.
        """
        out: list[PixyFrame] = []
        self._close(out, 'flush')
        self.bytes_dropped += len(self._buf)
        if self._state == _GOT_SYNC:  # a lone sync word at the end: nothing to build
            self.bytes_dropped += 2
        self._base += len(self._buf)
        self._buf = bytearray()
        self._state = _HUNT
        return out

    def feed_datagram(self, data: bytes) -> list[PixyFrame]:
        """One datagram = one frame (the simulator over UDP): feed, then :meth:`flush`."""
        out = self.feed(data)
        out.extend(self.flush())
        return out
