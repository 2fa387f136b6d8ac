"""The arm's serial wire protocol, mirrored from ``firmware/src/protocol.h`` (see docs/robot.md).

A frame is ``A5 5A LEN SEQ CMD PAYLOAD[LEN] CRC_LO CRC_HI`` with CRC-16/CCITT-FALSE over
``LEN SEQ CMD PAYLOAD``; integers are little-endian. The board answers every frame it sees with a reply
echoing SEQ whose CMD is ``cmd | 0x80``, or with ``CMD_ERROR`` carrying ``(code, offending cmd)``.
Pure functions only: encoding, incremental decoding and payload (un)packing, so the firmware's behaviour
can be mirrored by the fake board and checked by tests without I/O.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum, IntFlag

SOF = b"\xa5\x5a"
MAX_PAYLOAD = 40
FRAME_OVERHEAD = 7
MAX_FRAME = MAX_PAYLOAD + FRAME_OVERHEAD
N_CHANNELS = 7
PROTOCOL_VERSION = 1
REPLY_FLAG = 0x80
# Same defaults and bounds as firmware/src/config.h.
PULSE_ABS_MIN_US = 500
PULSE_ABS_MAX_US = 2500
PULSE_DEFAULT_LIMITS = (1000, 2000, 1500)
SPEED_CEILING_US_S = 6000
WATCHDOG_RANGE_MS = (50, 10000)


class Cmd(IntEnum):
    PING = 0x01
    SET_TARGETS = 0x02
    GET_STATE = 0x03
    HOME = 0x04
    ESTOP = 0x05
    CLEAR_ESTOP = 0x06
    SET_CONFIG = 0x07
    GET_CONFIG = 0x08
    SET_LIMITS = 0x09
    GET_LIMITS = 0x0A
    ERROR = 0x7F


class ErrorCode(IntEnum):
    CRC = 1
    LENGTH = 2
    UNKNOWN_CMD = 3
    PAYLOAD = 4
    LIMIT = 5
    ESTOP = 6
    TIMEOUT = 7
    STATE = 8


class StateFlag(IntFlag):
    ESTOP = 0x01
    WATCHDOG = 0x02
    MOVING = 0x04
    EEPROM_DEFAULTS = 0x08


class ProtocolError(ValueError):
    """A reply could not be decoded or did not match its request."""


def crc16(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF), as computed by the firmware."""
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


def encode_frame(seq: int, cmd: int, payload: bytes = b"") -> bytes:
    if len(payload) > MAX_PAYLOAD:
        raise ProtocolError(f"payload of {len(payload)} bytes exceeds the protocol maximum {MAX_PAYLOAD}")
    body = bytes([len(payload), seq & 0xFF, cmd & 0xFF]) + payload
    return SOF + body + struct.pack("<H", crc16(body))


@dataclass(frozen=True)
class Frame:
    seq: int
    cmd: int
    payload: bytes


class FrameDecoder:
    """Incremental decoder: ``feed(bytes)`` returns the frames completed so far.

    Frames with a bad CRC or an impossible length are dropped (counted in ``errors``); the decoder
    resynchronises on the next start-of-frame, like the firmware's parser.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.errors = 0

    def feed(self, data: bytes) -> list[Frame]:
        self._buf += data
        frames = []
        while True:
            start = self._buf.find(SOF)
            if start < 0:
                # Keep a trailing 0xA5: it may be the first half of the next start-of-frame.
                del self._buf[: max(0, len(self._buf) - 1) if self._buf.endswith(SOF[:1]) else len(self._buf)]
                return frames
            del self._buf[:start]
            if len(self._buf) < 3:
                return frames
            length = self._buf[2]
            if length > MAX_PAYLOAD:
                self.errors += 1
                del self._buf[:2]
                continue
            total = length + FRAME_OVERHEAD
            if len(self._buf) < total:
                return frames
            body = bytes(self._buf[2 : total - 2])
            (crc,) = struct.unpack("<H", self._buf[total - 2 : total])
            if crc != crc16(body):
                self.errors += 1
                del self._buf[:2]
                continue
            frames.append(Frame(seq=body[1], cmd=body[2], payload=body[3:]))
            del self._buf[:total]

    def pending(self) -> int:
        return len(self._buf)


@dataclass(frozen=True)
class BoardInfo:
    protocol: int
    firmware: str
    channels: int
    driver: str
    rx_buffer: int
    max_payload: int


@dataclass(frozen=True)
class BoardState:
    flags: StateFlag
    pulses_us: tuple[int, ...]
    targets_us: tuple[int, ...]
    uptime_ms: int
    error_count: int

    @property
    def estop(self) -> bool:
        return bool(self.flags & StateFlag.ESTOP)

    @property
    def watchdog(self) -> bool:
        return bool(self.flags & StateFlag.WATCHDOG)

    @property
    def moving(self) -> bool:
        return bool(self.flags & StateFlag.MOVING)


@dataclass(frozen=True)
class BoardConfig:
    watchdog_ms: int
    default_speed: int
    max_speed: int
    accel: int


@dataclass(frozen=True)
class ChannelLimits:
    channel: int
    min_us: int
    max_us: int
    home_us: int


STATE_FORMAT = f"<B{N_CHANNELS}H{N_CHANNELS}HIH"
STATE_SIZE = struct.calcsize(STATE_FORMAT)
DRIVERS = {0: "timer1", 1: "pca9685"}


def _check_size(payload: bytes, size: int, what: str) -> None:
    if len(payload) != size:
        raise ProtocolError(f"{what} reply has {len(payload)} payload bytes, expected {size}")


def pack_targets(pulses_us: list[int] | tuple[int, ...], speed_us_s: int = 0) -> bytes:
    if len(pulses_us) != N_CHANNELS:
        raise ProtocolError(f"need {N_CHANNELS} pulse widths, got {len(pulses_us)}")
    return struct.pack(f"<H{N_CHANNELS}H", int(speed_us_s), *(int(p) for p in pulses_us))


def unpack_targets(payload: bytes) -> tuple[int, tuple[int, ...]]:
    values = struct.unpack(f"<H{N_CHANNELS}H", payload)
    return values[0], tuple(values[1:])


def pack_state(state: BoardState) -> bytes:
    return struct.pack(STATE_FORMAT, int(state.flags), *state.pulses_us, *state.targets_us,
                       state.uptime_ms & 0xFFFFFFFF, state.error_count & 0xFFFF)


def unpack_state(payload: bytes) -> BoardState:
    _check_size(payload, STATE_SIZE, "state")
    v = struct.unpack(STATE_FORMAT, payload)
    n = N_CHANNELS
    return BoardState(StateFlag(v[0]), tuple(v[1 : 1 + n]), tuple(v[1 + n : 1 + 2 * n]), v[1 + 2 * n], v[2 + 2 * n])


def unpack_info(payload: bytes) -> BoardInfo:
    _check_size(payload, 8, "ping")
    proto, major, minor, patch, channels, driver, rx, maxp = payload
    return BoardInfo(proto, f"{major}.{minor}.{patch}", channels, DRIVERS.get(driver, f"unknown({driver})"), rx, maxp)


def pack_config(cfg: BoardConfig) -> bytes:
    return struct.pack("<4H", cfg.watchdog_ms, cfg.default_speed, cfg.max_speed, cfg.accel)


def unpack_config(payload: bytes) -> BoardConfig:
    _check_size(payload, 8, "config")
    return BoardConfig(*struct.unpack("<4H", payload))


def pack_limits(lim: ChannelLimits) -> bytes:
    return struct.pack("<B3H", lim.channel, lim.min_us, lim.max_us, lim.home_us)


def unpack_limits(payload: bytes) -> ChannelLimits:
    _check_size(payload, 7, "limits")
    return ChannelLimits(*struct.unpack("<B3H", payload))
